"""Measure every level of an LPM: size, geometric and uv error, client-side WRT-buffer error,
warping with the client's LPM depth, and time to first frame. Shared by ``icbtool lpm`` and
benchmarks.lpm_levels.

Cameras: ``n_cameras`` spread evenly over the scene's ``test`` path (else its default camera),
at ``height`` x ``width``. The reference of each (where the cloud renders the GI map) is what the
system warps: the prefetch camera (icbtool.prefetch.prefetch_camera, docs/design.md section 4) of
the request the client sent ``latency_s`` earlier on the path, with the path's velocities then
(a scene without a ``test`` path: the client camera pulled back along its view by
``reference_back`` of the scene diagonal). The reference GI is path traced on the FULL mesh
(``gi_spp`` samples per pixel, seeded), its depth rasterized from the full mesh.

Time to first frame of a level: cut it into chunks, (transfer), assemble the Scene from the
chunks, create the rasterizer and render the first DL frame. Transfer time is
``bytes * 8 / bandwidth`` for each bandwidth asked (no latency), reported apart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from icbtool.lpm.build import LPM, Level
from icbtool.lpm.chunks import assemble
from icbtool.lpm.metrics import (
    compare_views,
    geometric_error,
    render_views,
    uv_error,
    warp_error,
)

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera
    from icbtool.raster import RasterConfig
    from icbtool.scene import Scene


@dataclass(frozen=True)
class EvalConfig:
    """What :func:`evaluate` measures.

    Attributes:
        n_cameras: client cameras (spread over the ``test`` path; 1 = the default camera when
            the scene has no such path).
        height, width: their image size.
        latency_s: T_IL: the reference is the prefetch camera of the request sent this long
            before the client camera (on the ``test`` path).
        reference_back: without a ``test`` path, the reference camera is the client camera
            moved back along its view by this fraction of the scene diagonal (0: no warp
            measurement).
        gi_spp: samples per pixel of the reference GI maps (full mesh); 0: skip warping.
        n_samples: surface samples each way for the geometric error.
        uv_samples: samples for the uv error.
        bandwidths_mbit: bandwidths (Mbit/s) at which transfer times are reported.
        seed: every sampling seed.
        raster: raster options (None: defaults).
    """

    n_cameras: int = 3
    height: int = 128
    width: int = 128
    latency_s: float = 0.1
    reference_back: float = 0.03
    gi_spp: int = 16
    n_samples: int = 100_000
    uv_samples: int = 20_000
    bandwidths_mbit: tuple[float, ...] = (10.0, 100.0)
    seed: int = 0
    raster: RasterConfig | None = field(default=None)

    def __post_init__(self) -> None:
        for name in ("n_cameras", "height", "width", "n_samples", "uv_samples"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"EvalConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.height < 11 or self.width < 11:
            raise ValueError("EvalConfig height and width must be >= 11 (SSIM window)")
        if not 0 <= self.reference_back < 1 or self.gi_spp < 0:
            raise ValueError("EvalConfig: reference_back must be in [0, 1), gi_spp >= 0")
        if not (np.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"EvalConfig.latency_s must be finite and >= 0, got {self.latency_s}")


def _path_indices(scene: Scene, cfg: EvalConfig) -> list[int]:
    n = len(scene.paths["test"])
    if cfg.n_cameras > 1:
        return [int(i) for i in np.linspace(0, n - 1, cfg.n_cameras).round().astype(int)]
    return [n // 2]


def client_cameras(scene: Scene, cfg: EvalConfig) -> list[Camera]:
    """The client cameras (see the module docstring)."""

    if "test" in scene.paths:
        cams = [scene.paths["test"][i] for i in _path_indices(scene, cfg)]
    elif scene.default_camera is not None:
        cams = [scene.default_camera]
    else:
        from icbtool.scene.view import default_view

        cams = [default_view(scene, fov_y_deg=45.0)]
    return [c.resized(cfg.height, cfg.width) for c in cams]


def reference_cameras(scene: Scene, cams: list[Camera], cfg: EvalConfig) -> list[Camera]:
    """The reference camera of each client camera (see the module docstring)."""
    if "test" not in scene.paths:
        return [reference_camera(c, cfg.reference_back * scene.diagonal) for c in cams]
    from icbtool import prefetch

    path = scene.paths["test"]
    reqs = []
    for i, cam in zip(_path_indices(scene, cfg), cams):
        t_req = max(float(path.times[i]) - cfg.latency_s, float(path.times[0]))
        reqs.append((path.camera_at(t_req).resized(cam.height, cam.width), t_req))
    out = []
    for (req, t_req), seen in zip(reqs, render_views(scene, [r for r, _ in reqs], cfg.raster)):
        v_t, v_r = path.velocity_cam(t_req)
        try:
            near_far = prefetch.depth_range_from_depth(seen.depth, seen.mask)
        except ValueError:  # the request camera sees nothing: the prefetch default range
            near_far = (0.1, 100.0)
        out.append(prefetch.prefetch_camera(req, v_t, v_r, depth_range=near_far).camera)
    return out


def reference_camera(cam: Camera, back: float) -> Camera:
    """``cam`` moved back along its view direction by ``back`` (scene units)."""
    pose = np.array(cam.world_from_cam)
    pose[:3, 3] -= back * cam.forward
    return cam.with_pose(pose)


def time_to_first_frame(
    level: Level, base: Scene, camera: Camera, cfg: EvalConfig
) -> dict[str, Any]:
    """Seconds to cut ``level`` into chunks, assemble it and rasterize the first DL frame, and
    its bytes (see the module docstring)."""
    from icbtool.raster import Rasterizer

    t0 = time.perf_counter()
    chunks = level.to_chunks()
    t1 = time.perf_counter()
    scene = assemble(chunks, base=base)
    t2 = time.perf_counter()
    with Rasterizer(scene, cfg.raster) as r:
        r.render(camera, ("dl",))
    t3 = time.perf_counter()
    n = sum(len(c[2]) for c in chunks)
    local = (t1 - t0) + (t2 - t1) + (t3 - t2)
    return {
        "bytes": n,
        "chunks": len(chunks),
        "chunks_s": t1 - t0,
        "assemble_s": t2 - t1,
        "first_raster_s": t3 - t2,
        "local_s": local,
        "transfer_s": {f"{b:g}Mbit": n * 8 / (b * 1e6) for b in cfg.bandwidths_mbit},
        "total_s": {f"{b:g}Mbit": local + n * 8 / (b * 1e6) for b in cfg.bandwidths_mbit},
    }


@dataclass
class Evaluation:
    """What :func:`evaluate` measured.

    Attributes:
        rows: one dict per level (stats, errors, time to first frame).
        previews: per level, the DL (H, W, 3) float32 of the first client camera.
        full_preview: the full mesh's DL at that camera.
        exposure: the exposure used for the previews and SSIMs of that camera.
    """

    rows: list[dict[str, Any]]
    previews: list[np.ndarray]
    full_preview: np.ndarray
    exposure: float


def evaluate(lpm: LPM, cfg: EvalConfig = EvalConfig(), progress: bool = False) -> Evaluation:  # noqa: B008
    """Measure every level of ``lpm`` against its full scene (see the module docstring)."""
    from icbtool.imageio import auto_exposure

    full = lpm.source
    cams = client_cameras(full, cfg)
    fv = render_views(full, cams, cfg.raster)
    refs = []
    has_path = "test" in full.paths
    if (cfg.reference_back > 0 or has_path) and cfg.gi_spp > 0:
        from icbtool.trace import render_gi

        rcs = reference_cameras(full, cams, cfg)
        for rc, view in zip(rcs, render_views(full, rcs, cfg.raster)):  # one GL context
            refs.append((render_gi(full, rc, spp=cfg.gi_spp, seed=cfg.seed), view))
    stats = lpm.stats(error=False)
    rows, previews = [], []
    exposure = auto_exposure(fv[0].dl, fv[0].valid)
    it = lpm.levels
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="lpm evaluate", unit="level")
    for lv, st in zip(it, stats):
        lvv = render_views(lv.scene, cams, cfg.raster)
        per_cam = [compare_views(a, b, auto_exposure(b.dl, b.valid)) for a, b in zip(lvv, fv)]
        client = {k: float(np.nanmean([p[k] for p in per_cam])) for k in per_cam[0]}
        row = dict(st)
        row["geometric"] = geometric_error(lv.scene, full, cfg.n_samples, cfg.seed)
        row["uv"] = uv_error(lv.scene, full, cfg.uv_samples, cfg.seed)
        row["client"] = {**client, "per_camera": per_cam}
        if refs:
            row["warp"] = warp_error(lvv, fv, refs)
        row["first_frame"] = time_to_first_frame(lv, full, cams[0], cfg)
        rows.append(row)
        previews.append(lvv[0].dl)
    return Evaluation(rows, previews, fv[0].dl, exposure)


def flat_row(row: dict[str, Any], scene: str = "") -> dict[str, Any]:
    """One CSV row of an evaluation row (the headline numbers)."""
    ff = row["first_frame"]
    out = {
        "scene": scene,
        "level": row["level"],
        "ratio": row["ratio"],
        "triangles": row["triangles"],
        "vertices": row["vertices"],
        "bytes": row["bytes"],
        "bytes_geometry": row["bytes_geometry"],
        "bytes_texture": row["bytes_texture"],
        "build_s": round(row["build_s"], 3),
        "rms": row["geometric"]["rms"],
        "hausdorff": row["geometric"]["hausdorff"],
        "uv_mean_abs_255": row["uv"]["mean_abs_255"],
        "depth_rel_median": row["client"]["depth_rel_median"],
        "depth_rel_p95": row["client"]["depth_rel_p95"],
        "depth_bad_fraction": row["client"]["depth_bad_fraction"],
        "dl_ssim": row["client"]["dl_ssim"],
        "albedo_ssim": row["client"]["albedo_ssim"],
        "warp_ssim": row.get("warp", {}).get("ssim", float("nan")),
        "warp_holes_level": row.get("warp", {}).get("holes_level", float("nan")),
        "warp_holes_full": row.get("warp", {}).get("holes_full", float("nan")),
        "first_frame_local_s": ff["local_s"],
    }
    for k, v in ff["total_s"].items():
        out[f"first_frame_{k}_s"] = v
    return out


__all__ = [
    "EvalConfig",
    "Evaluation",
    "client_cameras",
    "evaluate",
    "flat_row",
    "reference_camera",
    "time_to_first_frame",
]
