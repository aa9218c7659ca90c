"""What the window shows, without Qt: the session, client frames, the prefetch camera, geometry.

Everything here goes through icbtool's public API (``icbtool.scene``, ``icbtool.store``,
``icbtool.system``, ``icbtool.prefetch``, ``icbtool.metrics``, ``icbtool.gan``) and can be used
from a script: the window logs each of its actions as the equivalent call
(:mod:`icbtool_gui.calls`).

The client moves along a camera path of the scene. With ``speed`` s (ViewerConfig) it traverses
the path s times faster than the path's own timing: at frame k it is at path time ``t_k``, its
velocities are s times the path's, and the request it sent ``T_IL`` seconds ago (the cloud's
``latency_s``) was sent at path time ``t_k - s T_IL``. The cloud answers that request at its
prefetch camera (:meth:`Session.prefetch_camera`, the rule of
:meth:`icbtool.system.Cloud.reference_camera`), from its cache or by rendering.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

import icbtool as icb
from icbtool import metrics, prefetch, system
from icbtool.camera import Camera, CameraPath
from icbtool.imageio import HOLE_COLOURS, to_display  # not icbtool.warp's: it imports torch
from icbtool.pipeline import PathConfig, truth_seed
from icbtool.scene import load_scene  # re-exported: SCENE as the command line reads it


@dataclass(frozen=True)
class ViewerConfig(PathConfig):
    """How the window moves the client along its path (path, frames, height and width: the
    loop's :class:`icbtool.pipeline.PathConfig`)."""

    speed: float = 1.0
    """The client traverses the path this many times faster than the path's own timing (its
    velocities, hence the prefetch camera, scale with it)."""
    truth_spp: int = 32
    """Samples per pixel of the path-traced truth of each frame, for the truth panel and the
    SSIM / FLIP heatmaps (0: none). On a demo's store, the demo's (:func:`demo_settings`), so
    that the window scores a frame as the demo's frames.csv does."""
    exposure: float = 1.0
    """Exposure of the display transform (panels and metrics)."""
    play_interval_ms: int = 200
    """Playing: the next frame is asked for this often (when the previous one is done)."""
    leaf_colour: Literal["records", "hits"] = "records"
    """Colour the octree leaves by their number of records or by their records' cache hits
    (as the store has written them: the cloud writes its hits with its next new record)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        v = self.play_interval_ms
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"ViewerConfig.play_interval_ms must be an integer >= 1, got {v!r}")
        if not isinstance(self.truth_spp, int) or self.truth_spp < 0:
            raise ValueError(
                f"ViewerConfig.truth_spp must be an integer >= 0, got {self.truth_spp}"
            )
        if not (math.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"ViewerConfig.speed must be finite and > 0, got {self.speed}")
        if self.leaf_colour not in ("records", "hits"):
            raise ValueError(
                f"ViewerConfig.leaf_colour must be records|hits, got {self.leaf_colour!r}"
            )
        if not (math.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"ViewerConfig.exposure must be finite and > 0, got {self.exposure}")


@dataclass(frozen=True)
class Leaf:
    """One occupied octree leaf of the store.

    Attributes:
        scene_hash: the scene whose octree it belongs to.
        cell: (i, j, k) leaf coordinates.
        bounds: (2, 3) [min, max] corners.
        records: records in the leaf.
        hits: cache hits of those records.
    """

    scene_hash: str
    cell: tuple[int, int, int]
    bounds: np.ndarray
    records: int
    hits: int


@dataclass
class FrameResult:
    """One client frame as the window shows it (images (H, W, 3) float32 linear unless noted).

    Attributes:
        index: frame index along the path.
        time_s: path time of the client camera.
        camera: the client camera.
        request: the GI request answered (sent ``T_IL`` earlier, with the client's depth range).
        prefetch: the camera the cloud looked up / rendered for it (its prefetch camera).
        reference_camera: the camera of the reference GI map that answered.
        cache_hit: the cloud answered from its store.
        dl: the client's direct light.
        cloud_gi: the reference's GI map (at ``reference_camera``, its own size).
        warped_gi: the reference warped to the client camera (holes left black).
        holes: (H, W, 3) uint8 holes by cause (:data:`HOLE_COLOURS`).
        hole_ratio: fraction of hole pixels after the warp.
        gi: the GI the client shows (combined, inpainted).
        final: DL + w GI.
        generated_gi: the generator's GI at the client camera, or None (``generated_note`` says
            why).
        truth: the path-traced full image at the client camera, or None.
        ssim_map: (H - 10, W - 10) per-pixel SSIM of final vs truth ('valid' windows), or None.
        ssim: its mean (= ``icbtool.metrics.ssim(final, truth)``), or None.
        flip_map: (H, W) per-pixel FLIP error of final vs truth, or None.
        flip: its mean (= ``icbtool.metrics.flip(truth, final)``), or None.
        timings_ms: time of each step.
    """

    index: int
    time_s: float
    camera: Camera
    request: Any
    prefetch: Camera
    reference_camera: Camera
    cache_hit: bool
    dl: np.ndarray
    cloud_gi: np.ndarray
    warped_gi: np.ndarray
    holes: np.ndarray
    hole_ratio: float
    gi: np.ndarray
    final: np.ndarray
    generated_gi: np.ndarray | None = None
    generated_note: str = ""
    truth: np.ndarray | None = None
    truth_spp: int = 0
    ssim_map: np.ndarray | None = None
    ssim: float | None = None
    flip_map: np.ndarray | None = None
    flip: float | None = None
    flip_note: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------- the session
class Session:
    """The scene, the store, the path and the settings the window works with.

    Args:
        scene: an :class:`icbtool.scene.Scene`.
        store_dir: the cloud's store (:func:`icbtool.store.open` directory; it must exist).
        run_dir: a GAN run (:func:`icbtool.gan.train`), or None.
        viewer, cloud, client: the settings.

    Raises:
        ValueError: the scene has no such path.
    """

    def __init__(
        self,
        scene: Any,
        store_dir: str | Path,
        run_dir: str | Path | None = None,
        viewer: ViewerConfig | None = None,
        cloud: system.CloudConfig | None = None,
        client: system.ClientConfig | None = None,
    ) -> None:
        self.scene = scene
        self.store_dir = Path(store_dir)
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.viewer = viewer or ViewerConfig()
        self.cloud = cloud or system.CloudConfig()
        self.client = client or system.ClientConfig()
        self._check_path(self.viewer)
        self._store: Any = None

    def _check_path(self, viewer: ViewerConfig) -> None:
        if viewer.path not in self.scene.paths:
            raise ValueError(
                f"scene '{self.scene.name}' has no camera path {viewer.path!r}; it has "
                f"{sorted(self.scene.paths)}"
            )

    def set_viewer(self, viewer: ViewerConfig) -> None:
        self._check_path(viewer)
        self.viewer = viewer

    # -- the store (read-only here; the cloud writes through its own handle)
    @property
    def store(self) -> Any:
        if self._store is None:
            self._store = icb.store.open(
                self.store_dir, icb.store.StoreConfig(readonly=True, record_hits=False)
            )
        return self._store

    def close(self) -> None:
        if self._store is not None:
            self._store.close()
            self._store = None

    def records(self) -> list[Any]:
        """Every record's :class:`icbtool.store.RecordInfo` of this scene, in id order."""
        self.store.refresh()
        return [r for r in self.store if r.meta.scene_hash == self.scene.content_hash]

    def leaves(self, records: list[Any] | None = None) -> list[Leaf]:
        """The occupied leaves of the scene's octree in the store (empty if none)."""
        recs = self.records() if records is None else records
        if not recs:
            return []
        sh = self.scene.content_hash
        try:
            geom = self.store.geometry(sh)
        except KeyError:
            return []
        tree = icb.store.SceneOctree(geom)
        count: dict[tuple[int, int, int], list[int]] = {}
        for r in recs:
            cell = tree.cell_of(r.camera.position)
            count.setdefault(cell, [0, 0])
            count[cell][0] += 1
            count[cell][1] += r.hits
        size = geom.leaf_size
        lo = np.asarray(geom.root_min, np.float64)
        out = []
        for cell, (n, hits) in sorted(count.items()):
            mn = lo + size * np.asarray(cell, np.float64)
            out.append(Leaf(sh, cell, np.stack([mn, mn + size]), n, hits))
        return out

    # -- the path and the client
    @property
    def path(self) -> CameraPath:
        """The client's path at the client's resolution."""
        p = self.scene.paths[self.viewer.path]
        return p.with_intrinsics(p.intrinsics.resized(self.viewer.height, self.viewer.width))

    @property
    def times(self) -> np.ndarray:
        p = self.scene.paths[self.viewer.path]
        return np.linspace(p.times[0], p.times[-1], self.viewer.frames)

    def client_camera(self, k: int) -> Camera:
        """The client camera at frame ``k``."""
        return self.path.camera_at(float(self.times[self._index(k)]))

    def _index(self, k: int) -> int:
        if not 0 <= k < self.viewer.frames:
            raise ValueError(f"frame {k} is outside the path's 0..{self.viewer.frames - 1}")
        return int(k)

    def request(self, k: int, depth_range: tuple[float, float] | None = None) -> system.GIRequest:
        """The request answered at frame ``k``: sent ``latency_s`` (real time) earlier, with the
        velocities scaled by ``speed``."""
        p = self.path
        t = float(self.times[self._index(k)])
        s = self.viewer.speed
        t_req = max(t - s * self.cloud.latency_s, float(p.times[0]))
        v_t, v_r = p.velocity_cam(t_req)
        return system.GIRequest(
            p.camera_at(t_req), s * v_t, s * v_r, time_s=t_req, seq=k, depth_range=depth_range
        )

    def prefetch_camera(self, request: system.GIRequest) -> Camera:
        """The camera the cloud looks up or renders for ``request``: the rule of
        :meth:`icbtool.system.Cloud.reference_camera` (prefetch camera, FOV rounded up)."""
        if not self.cloud.prefetch:
            return request.camera
        cfg = prefetch.PrefetchConfig(latency_s=max(self.cloud.latency_s, 1e-9))
        cam = prefetch.prefetch_camera(
            request.camera,
            request.velocity_t,
            request.velocity_r,
            cfg,
            depth_range=request.depth_range or system.DEFAULT_DEPTH_RANGE,
        ).camera
        return system.round_fov(cam, self.cloud.fov_step_deg, cfg.max_fov_deg)


# ----------------------------------------------------------------------------- frames
class FrameComputer:
    """Computes client frames (:meth:`compute`): an :class:`icbtool.system.Client` against an
    :class:`icbtool.system.Cloud` on the session's store, sharing one rasterizer.

    Create, use and close it in one thread (its OpenGL context belongs to that thread); the
    window runs it in a process of its own (:mod:`icbtool_gui.frames`).
    """

    def __init__(self, session: Session) -> None:
        self.session = session
        self._rz: Any = None
        self._cloud: Any = None
        self._client: Any = None
        self._configs: tuple[Any, Any] | None = None
        self._generator: Any = None
        self._generator_note = "no generator (icbtool gui --run RUN)"
        if session.run_dir is not None:
            try:
                self._generator = icb.gan.Generator.load(session.run_dir)
                self._generator_note = ""
            except (OSError, ValueError, KeyError, ImportError) as e:
                self._generator_note = f"cannot load generator from {session.run_dir}: {e}"

    def _ensure(self) -> None:
        s = self.session
        if self._configs == (s.cloud, s.client):
            return
        self._close_system()
        from icbtool import raster

        if self._rz is None:
            self._rz = raster.Rasterizer(s.scene)
        self._cloud = system.Cloud(s.scene, s.store_dir, s.cloud, rasterizer=self._rz)
        self._client = system.Client(s.scene, self._cloud, s.client, rasterizer=self._rz)
        self._configs = (s.cloud, s.client)

    def _close_system(self) -> None:
        if self._client is not None:
            self._client.close()
        if self._cloud is not None:
            self._cloud.close()
        self._client = self._cloud = None
        self._configs = None

    def close(self) -> None:
        self._close_system()
        if self._rz is not None:
            self._rz.close()
            self._rz = None

    def compute(self, k: int) -> FrameResult:
        """Frame ``k``: raster, GI request (cache or render), warp, blend, then the generator,
        the truth and the heatmaps when enabled."""
        self._ensure()
        s = self.session
        v = s.viewer
        times: dict[str, float] = {}
        cam = s.client_camera(k)
        t0 = time.perf_counter()
        wrt = self._client.rasterize(cam)
        req = s.request(k, system.visible_depth_range(wrt))
        pre = self._cloud.reference_camera(req)
        fr = self._client.frame(cam, req)
        times["frame"] = 1e3 * (time.perf_counter() - t0)
        ref = fr.reply.reference
        w = fr.warped
        warped = np.where(w.holes[..., None], 0.0, w.image).astype(np.float32)
        out = FrameResult(
            index=k,
            time_s=float(s.times[k]),
            camera=cam,
            request=req,
            prefetch=pre,
            reference_camera=ref.camera,
            cache_hit=bool(fr.reply.cache_hit),
            dl=fr.wrt.dl,
            cloud_gi=np.asarray(ref.gi, np.float32),
            warped_gi=warped,
            holes=hole_image(w),
            hole_ratio=float(w.hole_ratio),
            gi=fr.gi,
            final=fr.final,
            generated_note=self._generator_note,
            timings_ms={**times, **fr.reply.timings_ms},
        )
        if self._generator is not None:
            t0 = time.perf_counter()
            try:
                names = tuple(n for n in self._generator.inputs if n != "mask")
                buf = self._rz.render(cam, buffers=names)
                out.generated_gi = self._generator.generate(buf)
                out.generated_note = ""
            except ValueError as e:
                out.generated_note = f"generator: {e}"
            times["generate"] = 1e3 * (time.perf_counter() - t0)
        if v.truth_spp > 0:
            t0 = time.perf_counter()
            truth = icb.trace.render(
                s.scene,
                cam,
                icb.trace.TraceConfig(spp=v.truth_spp, seed=truth_seed(s.cloud, k),
                                      max_depth=s.cloud.max_depth),
            )  # fmt: skip
            out.truth = truth.full
            out.truth_spp = v.truth_spp
            times["truth"] = 1e3 * (time.perf_counter() - t0)
            add_heatmaps(out, v.exposure)
        out.timings_ms.update(times)
        return out


def add_heatmaps(frame: FrameResult, exposure: float = 1.0) -> None:
    """Fill the SSIM and FLIP maps and means of ``frame`` (final vs truth) with
    :mod:`icbtool.metrics` (FLIP only when its optional package is installed)."""
    if frame.truth is None:
        return
    frame.ssim_map = metrics.ssim_map(frame.final, frame.truth, exposure, padding="valid")
    frame.ssim = float(frame.ssim_map.mean(dtype=np.float64))
    try:
        frame.flip_map = metrics.flip_map(frame.truth, frame.final, exposure)
        frame.flip = float(frame.flip_map.mean(dtype=np.float64))
    except ImportError as e:
        frame.flip_note = str(e)


def hole_image(w: Any) -> np.ndarray:
    """(H, W, 3) uint8: the warp's holes coloured by cause (:data:`HOLE_COLOURS`), the warped
    pixels as a dim grey."""
    img = np.full((*w.holes.shape, 3), 90, np.uint8)
    for cause, colour in HOLE_COLOURS.items():
        img[getattr(w, cause)] = colour
    return img


def display(img: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(H, W, 3) uint8 of a linear image (or a uint8 one as it is)."""
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a
    return to_display(a, exposure)


# ----------------------------------------------------------------------------- geometry
def frustum_points(cam: Camera, depth: float) -> np.ndarray:
    """(5, 3) world points: the camera centre, then the image corners (top-left, top-right,
    bottom-right, bottom-left) at view depth ``depth``."""
    uv = np.array(
        [[0.0, 0.0], [cam.width, 0.0], [cam.width, cam.height], [0.0, cam.height]], np.float64
    )
    corners = cam.unproject(uv, np.full(4, float(depth)))
    return np.concatenate([np.asarray(cam.position, np.float64)[None], corners])


def frustum_depth(scene: Any, fraction: float = 0.08) -> float:
    """A frustum length that reads well: ``fraction`` of the scene's bounding-box diagonal."""
    b = np.asarray(scene.bounds, np.float64)
    return float(fraction * np.linalg.norm(b[1] - b[0]))


# ----------------------------------------------------------------------------- defaults
def demo_settings(
    demo_dir: str | Path,
) -> tuple[ViewerConfig, system.CloudConfig, system.ClientConfig] | None:
    """The viewer, cloud and client settings of a ``make demo`` run (its ``config.json``), so
    that stepping along its path meets the references it stored; None without one."""
    p = Path(demo_dir) / "config.json"
    if not p.is_file():
        return None
    cfg = icb.pipeline.LoopConfig.from_dict(json.loads(p.read_text()).get("loop", {}))
    viewer = ViewerConfig(path=cfg.path, frames=cfg.frames, height=cfg.height, width=cfg.width,
                          truth_spp=cfg.truth_spp)  # fmt: skip
    return viewer, cfg.cloud, cfg.client


__all__ = [
    "HOLE_COLOURS",
    "FrameComputer",
    "FrameResult",
    "Leaf",
    "Session",
    "ViewerConfig",
    "add_heatmaps",
    "demo_settings",
    "display",
    "frustum_depth",
    "frustum_points",
    "hole_image",
    "truth_seed",  # icbtool.pipeline's: the demo's truths
    "load_scene",
]
