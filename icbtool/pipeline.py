"""The ICB loop in one process: a client moving along a camera path, a cloud with a cache.

:func:`run_loop` is a thin driver over the system's objects (:mod:`icbtool.system`): a
:class:`~icbtool.system.Client` asks an in-process :class:`~icbtool.system.Cloud` (its
:class:`~icbtool.system.GISource`) for GI. For every client frame at time ``t`` (docs/design.md
section 6, without the network yet):

1. The client rasterizes its WRT-buffer (DL, albedo, normals, depth) at its camera ``c(t)``.
2. The cloud answers the request the client sent ``T_IL`` earlier: from the client's camera and
   velocities at ``t - T_IL`` it predicts the prefetch camera (wider, pulled back;
   :func:`icbtool.prefetch.prefetch_camera`), looks it up in the octree cache (a similar camera
   whose FOV covers it is a hit) and otherwise renders a CRT-buffer there (raster G-buffers,
   path-traced GI, optionally denoised) and stores it.
3. The client warps the reference GI to ``c(t)`` with its own depth (backward warp, hole mask by
   cause), combines it with the previous reference, and inpaints what is left.
4. The final frame is ``DL + w * GI``.

Every stage is timed; on some frames the truth (a high-sample trace at ``c(t)``) is rendered to
score the frame (SSIM on the display scale).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.camera import CameraPath
from icbtool.system.client import ClientConfig
from icbtool.system.cloud import CloudConfig


@dataclass(frozen=True)
class PathConfig:
    """Which camera path a client follows, how many frames, at what image size (the part of a
    client's settings that :class:`LoopConfig` and the desktop app's viewer share)."""

    path: str = "test"
    """Name of the scene's camera path the client follows."""
    frames: int = 24
    """Client frames, evenly spaced in time along the path."""
    height: int = 128
    """Client image height (pixels)."""
    width: int = 128
    """Client image width (pixels)."""

    def __post_init__(self) -> None:
        for k in ("frames", "height", "width"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{type(self).__name__}.{k} must be an integer >= 1, got {v!r}")


#: Fields of the nested cloud and client configs that :class:`LoopConfig` still accepts (and
#: reads) flat, as before they were nested: ``LoopConfig(spp=4)`` is
#: ``LoopConfig(cloud=CloudConfig(spp=4))``, ``cfg.spp`` is ``cfg.cloud.spp``.
_NESTED_FLAT = {
    **{f.name: "cloud" for f in dataclasses.fields(CloudConfig)},
    **{f.name: "client" for f in dataclasses.fields(ClientConfig)},
}


@dataclass(frozen=True)
class LoopConfig(PathConfig):
    """How :func:`run_loop` drives the client and the cloud: the client's path and size, the
    cloud's settings (:class:`~icbtool.system.CloudConfig`), the client's
    (:class:`~icbtool.system.ClientConfig`), and the scoring against the truth.

    The fields of ``cloud`` and ``client`` are also accepted as keywords (``LoopConfig(spp=4,
    inpaint=False)``) and readable as attributes (``cfg.spp``), as before they were nested."""

    cloud: CloudConfig = field(default_factory=CloudConfig)
    """The cloud's settings: prefetch, T_IL (``latency_s``), spp, denoising, cache thresholds,
    seed (the truth's seeds follow it too)."""
    client: ClientConfig = field(default_factory=ClientConfig)
    """The client's settings: combining with the previous reference, inpainting, GI weight."""
    truth_every: int = 6
    """Render the ground truth every this many frames (0: never)."""
    truth_spp: int = 128
    """Samples per pixel of the ground truth."""
    generator: str | None = None
    """A trained GAN run directory (:func:`icbtool.gan.train`) or world-space radiance run
    (:func:`icbtool.radiance.train`): the client makes its GI with it (the paper's rule) and asks
    the cloud only when it cannot answer (:class:`icbtool.system.GeneratorSource`). None: every
    GI map comes from the cloud."""
    compare_cloud: bool = True
    """With a generator: on the frames that get a truth, also ask the cloud for its (warped) GI
    and write cloud GI | generated GI | truth GI side by side (``frames/NNN_gi.png``; the SSIM in
    ``ssim_gi_cloud``). Those extra cloud answers are counted apart (``comparison_renders``)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not isinstance(self.cloud, CloudConfig) or not isinstance(self.client, ClientConfig):
            raise TypeError("LoopConfig.cloud/.client must be a CloudConfig / ClientConfig")
        v = self.truth_spp
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(f"LoopConfig.truth_spp must be an integer >= 1, got {v!r}")
        if self.truth_every < 0:
            raise ValueError(f"LoopConfig.truth_every must be >= 0, got {self.truth_every}")

    def __getattr__(self, name: str) -> Any:  # only called for names that are not fields
        part = _NESTED_FLAT.get(name)
        if part is None:
            raise AttributeError(f"'LoopConfig' object has no attribute {name!r}")
        return getattr(object.__getattribute__(self, part), name)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LoopConfig:
        """The config of a ``config.json``'s ``"loop"`` entry (nested, or flat as written before
        the cloud and client settings were nested); unknown keys are ignored."""
        known = {f.name for f in dataclasses.fields(cls)} | set(_NESTED_FLAT)
        kw = {k: v for k, v in d.items() if k in known and k not in ("cloud", "client")}
        if isinstance(d.get("cloud"), dict):
            kw["cloud"] = CloudConfig(**d["cloud"])
        if isinstance(d.get("client"), dict):
            kw["client"] = ClientConfig(**d["client"])
        return cls(**kw)

    def cloud_config(self) -> CloudConfig:
        """The cloud's part of this configuration (``self.cloud``)."""
        return self.cloud

    def client_config(self) -> ClientConfig:
        """The client's part of this configuration (``self.client``)."""
        return self.client


def _accept_flat_keywords(cls: type) -> type:
    """Let ``cls(**kw)`` take the nested configs' fields flat (see :data:`_NESTED_FLAT`)."""
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self: Any, *args: Any, **kw: Any) -> None:
        nested: dict[str, dict[str, Any]] = {}
        for k in [k for k in kw if k in _NESTED_FLAT]:
            nested.setdefault(_NESTED_FLAT[k], {})[k] = kw.pop(k)
        for part, values in nested.items():
            base = kw.get(part) or (CloudConfig() if part == "cloud" else ClientConfig())
            kw[part] = dataclasses.replace(base, **values)
        init(self, *args, **kw)

    cls.__init__ = __init__  # type: ignore[method-assign]
    return cls


_accept_flat_keywords(LoopConfig)


@dataclass
class FrameStats:
    """What happened in one client frame (times in milliseconds)."""

    index: int
    time_s: float
    cache_hit: bool
    reference_fov_y_deg: float
    raster_ms: float
    lookup_ms: float
    cloud_render_ms: float
    warp_ms: float
    hole_ratio: float
    """Holes after warping the current reference alone."""
    hole_ratio_combined: float
    """Holes left after combining with the previous reference (then inpainted)."""
    ssim_final: float | None = None
    ssim_gi: float | None = None
    ssim_dl_only: float | None = None
    """SSIM of DL alone against the truth: what the client would show without the cloud."""
    mse_final: float | None = None
    """MSE (display scale, 0-255) of the final frame against the truth."""
    mse_dl_only: float | None = None
    """MSE (display scale) of DL alone against the truth."""
    gi_source: str = "cloud"
    """Who made this frame's GI: "cloud" or "generator"."""
    generate_ms: float = 0.0
    """Time of the local generator (0 when the cloud answered)."""
    request_ms: float = 0.0
    """The whole request -> reply time the client waited (in-process: the cloud's call)."""
    queue_ms: float = 0.0
    """Over a network: the request's wait for the server's cloud thread."""
    encode_ms: float = 0.0
    """Over a network: the server's encoding of the reply."""
    transfer_ms: float = 0.0
    """Over a network: both directions on the wire and the server's send queue."""
    decode_ms: float = 0.0
    """Over a network: the client's decoding of the reply."""
    mesh_level: int = -1
    """The client's mesh level (LPM) it rasterized (-1: the full scene, in-process)."""
    rx_bytes: int = 0
    """Bytes the client received during this frame (network sources)."""
    ssim_gi_cloud: float | None = None
    """With a generator and ``compare_cloud``: SSIM of the cloud's warped GI against the truth's
    GI on the same frame (``ssim_gi`` is the generated one's)."""
    stale: bool = False
    """An animated scene: the GI shown was marked stale (rendered under another scene state
    that the change since may alter; docs/dynamic.md)."""


@dataclass
class LoopReport:
    """The result of :func:`run_loop`."""

    scene: str
    config: LoopConfig
    frames: list[FrameStats] = field(default_factory=list)
    cloud_renders: int = 0
    comparison_renders: int = 0
    """Cloud renders made only for ``LoopConfig.compare_cloud`` (not in ``cloud_renders``)."""
    total_s: float = 0.0

    @property
    def hit_rate(self) -> float:
        return float(np.mean([f.cache_hit for f in self.frames])) if self.frames else 0.0

    def summary(self) -> dict[str, Any]:
        """Aggregates: hit rate, mean hole ratios and SSIM/MSE against the truth, and per stage
        the median time and the first call's time apart (the first frame pays one-time costs:
        kernel compilation, shader builds, cache warm-up, which a mean would smear over all)."""

        def mean(key: str) -> float | None:
            vals = [getattr(f, key) for f in self.frames if getattr(f, key) is not None]
            return float(np.mean(vals)) if vals else None

        out: dict[str, Any] = {
            "scene": self.scene,
            "frames": len(self.frames),
            "cloud_renders": self.cloud_renders,
            "cache_hit_rate": self.hit_rate,
            "mean_hole_ratio_single_reference": mean("hole_ratio"),
            "mean_hole_ratio_combined": mean("hole_ratio_combined"),
            "mean_ssim_final_vs_truth": mean("ssim_final"),
            "mean_ssim_gi_vs_truth": mean("ssim_gi"),
            "mean_ssim_dl_only_vs_truth": mean("ssim_dl_only"),
            "mean_mse_final_vs_truth": mean("mse_final"),
            "mean_mse_dl_only_vs_truth": mean("mse_dl_only"),
            "stale_frames": sum(f.stale for f in self.frames),
        }
        misses = [f for f in self.frames if not f.cache_hit]
        for stage, frames in (
            ("raster_ms", self.frames),
            ("lookup_ms", self.frames),
            ("cloud_render_ms", misses),
            ("warp_ms", self.frames),
        ):
            t = timing_summary([getattr(f, stage) for f in frames])
            name = stage.removesuffix("_ms") + ("_on_miss" if stage == "cloud_render_ms" else "")
            out[f"median_{name}_ms"] = t["median"]
            out[f"first_{name}_ms"] = t["first"]
            out[f"median_{name}_ms_after_first"] = t["median_after_first"]
        if any(f.transfer_ms or f.decode_ms for f in self.frames):  # over a network
            remote = [f for f in self.frames if f.gi_source == "cloud"]
            for stage in ("request_ms", "queue_ms", "encode_ms", "transfer_ms", "decode_ms"):
                t = timing_summary([getattr(f, stage) for f in remote])
                out[f"median_{stage.removesuffix('_ms')}_ms"] = t["median"]
            out["rx_bytes"] = int(sum(f.rx_bytes for f in self.frames))
        gen = [f for f in self.frames if f.gi_source == "generator"]
        if self.config.generator is not None or gen:
            out["generated_frames"] = len(gen)
            out["cloud_fallback_frames"] = len(self.frames) - len(gen)
            t = timing_summary([f.generate_ms for f in gen])
            out["median_generate_ms"] = t["median"]
            out["first_generate_ms"] = t["first"]
            out["mean_ssim_gi_cloud_vs_truth"] = mean("ssim_gi_cloud")
            out["comparison_renders"] = self.comparison_renders
        out["total_s"] = self.total_s
        return out


def timing_summary(times_ms: list[float]) -> dict[str, float | None]:
    """Median of all calls, the first call, and the median of the calls after the first.

    Args:
        times_ms: per-call times in call order.

    Returns:
        ``{"median", "first", "median_after_first"}`` (None where there are too few calls).
    """
    if not times_ms:
        return {"median": None, "first": None, "median_after_first": None}
    rest = times_ms[1:]
    return {
        "median": float(np.median(times_ms)),
        "first": float(times_ms[0]),
        "median_after_first": float(np.median(rest)) if rest else None,
    }


def _client_path(scene: Any, cfg: LoopConfig) -> CameraPath:
    if cfg.path not in scene.paths:
        raise ValueError(
            f"scene '{scene.name}' has no camera path {cfg.path!r}; it has {sorted(scene.paths)}"
        )
    p = scene.paths[cfg.path]
    intr = p.intrinsics.resized(cfg.height, cfg.width)
    return p.with_intrinsics(intr)


def run_loop(
    scene: Any,
    config: LoopConfig | None = None,
    out_dir: str | Path | None = None,
    store_dir: str | Path | None = None,
    progress: bool = True,
    *,
    source: Any = None,
    client_scene: Callable[[], tuple[int, Any]] | None = None,
) -> LoopReport:
    """Drive a :class:`~icbtool.system.Client` along a path against an in-process
    :class:`~icbtool.system.Cloud` (see module docstring), or against another GI source.

    Args:
        scene: an :class:`icbtool.scene.Scene` with the named path (and the truth's scene).
        config: :class:`LoopConfig`.
        out_dir: where to write frame images (PNG), ``frames.csv``, ``summary.json`` and
            ``config.json``; None writes nothing.
        store_dir: the cloud's cache (an :func:`icbtool.store.open` directory); default
            ``out_dir / "cache"``, or a temporary directory when ``out_dir`` is None.
        progress: show a progress bar.
        source: a :class:`~icbtool.system.GISource` to ask instead of an in-process cloud (a
            network client); not closed here. ``config.generator`` is then ignored (the source
            decides) and no store is opened.
        client_scene: ``() -> (level, scene)``, asked before every frame: the scene the client
            rasterizes (the finest mesh level it holds); a new level replaces the client's
            rasterizer. None: the client rasterizes ``scene``.

    Returns:
        A :class:`LoopReport`.
    """
    import tempfile

    from icbtool import imageio, metrics, raster, system, trace

    cfg = config or LoopConfig()
    path = _client_path(scene, cfg)
    out = Path(out_dir) if out_dir is not None else None
    tmp = None
    if source is None and store_dir is None:  # a given source needs no store here
        if out is not None:
            store_dir = out / "cache"
        else:
            tmp = tempfile.TemporaryDirectory(prefix="icb-cache-")
            store_dir = tmp.name
    if out is not None:
        (out / "frames").mkdir(parents=True, exist_ok=True)
    times = np.linspace(path.times[0], path.times[-1], cfg.frames)
    report = LoopReport(scene.name, cfg)
    t_start = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.frames, desc=f"icb loop {scene.name}", unit="frame")
    level, client_mesh = (-1, scene) if client_scene is None else client_scene()
    try:
        with contextlib.ExitStack() as stack:
            rz = stack.enter_context(raster.Rasterizer(client_mesh))
            cloud = None
            if source is None:
                cloud = stack.enter_context(
                    system.Cloud(scene, store_dir, cfg.cloud, rasterizer=rz)
                )
                source = stack.enter_context(_gi_source(cfg, cloud))
            client = stack.enter_context(
                system.Client(client_mesh, source, cfg.client, rasterizer=rz)
            )
            cloud_view = (
                stack.enter_context(_comparison_client(cfg, scene, cloud, rz))
                if cloud is not None
                else None
            )
            for k, t in enumerate(times):
                if client_scene is not None:
                    new_level, new_mesh = client_scene()
                    if new_level != level:
                        level = new_level
                        client.use_scene(new_mesh)
                rx0 = sum(getattr(source, "bytes_received", {}).values())
                cam = path.camera_at(float(t))
                # the request the client sent T_IL ago
                t_req = max(float(t) - cfg.cloud.latency_s, float(path.times[0]))
                v_t, v_r = path.velocity_cam(t_req)
                request = system.GIRequest(path.camera_at(t_req), v_t, v_r, t_req, seq=k)
                # an animated scene: the client rasterizes it at the frame's time
                fr = client.frame(cam, request, time_s=float(t) if scene.is_animated else None)
                ref = fr.reply.reference
                fs = FrameStats(
                    index=k,
                    time_s=float(t),
                    cache_hit=fr.reply.cache_hit,
                    reference_fov_y_deg=ref.camera.fov_y_deg,
                    raster_ms=fr.raster_ms,
                    lookup_ms=fr.reply.timings_ms.get("lookup", 0.0),
                    cloud_render_ms=fr.reply.timings_ms.get("render", 0.0),
                    warp_ms=fr.warp_ms,
                    hole_ratio=fr.warped.hole_ratio,
                    hole_ratio_combined=fr.hole_ratio_combined,
                    gi_source=(
                        "generator"
                        if isinstance(fr.reply.reference, system.LocalReference)
                        else "cloud"
                    ),
                    generate_ms=fr.reply.timings_ms.get("generate", 0.0),
                    request_ms=fr.request_ms,
                    queue_ms=fr.reply.timings_ms.get("queue", 0.0),
                    encode_ms=fr.reply.timings_ms.get("encode", 0.0),
                    transfer_ms=fr.reply.timings_ms.get("transfer", 0.0),
                    decode_ms=fr.reply.timings_ms.get("decode", 0.0),
                    mesh_level=level,
                    rx_bytes=sum(getattr(source, "bytes_received", {}).values()) - rx0,
                    stale=fr.stale,
                )
                truth = None
                if cfg.truth_every and k % cfg.truth_every == 0:
                    truth = trace.render(
                        scene.at(float(t)),
                        cam,
                        trace.TraceConfig(
                            spp=cfg.truth_spp,
                            seed=truth_seed(cfg.cloud, k),
                            max_depth=cfg.cloud.max_depth,
                        ),
                    )
                    fs.ssim_final = metrics.ssim(fr.final, truth.full)
                    fs.ssim_gi = metrics.ssim(fr.gi, truth.gi)
                    fs.ssim_dl_only = metrics.ssim(fr.wrt.dl, truth.full)
                    fs.mse_final = metrics.mse(fr.final, truth.full)
                    fs.mse_dl_only = metrics.mse(fr.wrt.dl, truth.full)
                    if cloud_view is not None and fs.gi_source == "generator":
                        before = cloud.renders
                        fc = cloud_view.frame(cam, request)
                        report.comparison_renders += cloud.renders - before
                        fs.ssim_gi_cloud = metrics.ssim(fc.gi, truth.gi)
                        if out is not None:
                            _write_strip(
                                out / "frames" / f"{k:03d}_gi.png",
                                [fc.gi, fr.gi, truth.gi],
                                imageio,
                                ["cloud GI", "generated GI", f"truth GI {cfg.truth_spp}spp"],
                            )
                report.frames.append(fs)
                if out is not None:
                    _write_frame(
                        out / "frames" / f"{k:03d}.png",
                        fr.wrt,
                        fr.combined,
                        fr.final,
                        truth,
                        imageio,
                        cfg.truth_spp,
                    )
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(hit=fs.cache_hit, holes=f"{fs.hole_ratio_combined:.3f}")
            report.cloud_renders = (
                cloud.renders - report.comparison_renders
                if cloud is not None
                else sum(1 for f in report.frames if f.gi_source == "cloud" and not f.cache_hit)
            )
    finally:
        if bar is not None:
            bar.close()
        if tmp is not None:
            tmp.cleanup()
    report.total_s = time.perf_counter() - t_start
    if out is not None:
        _write_report(out, report)
    return report


_EXPOSURE = 1.0


def _gi_source(cfg: LoopConfig, cloud: Any) -> Any:
    """The client's GI source: the cloud, or a generator with the cloud as fallback."""
    from icbtool import system

    if cfg.generator is None:
        return contextlib.nullcontext(cloud)
    return system.GeneratorSource(load_client_model(cfg.generator), fallback=cloud)


def load_client_model(run: str | Path) -> Any:
    """The model a client makes its GI with: a world-space radiance run (it holds
    ``radiance.pt``: :class:`icbtool.radiance.RadianceModel`) or a GAN run
    (:class:`icbtool.gan.Generator`)."""
    p = Path(run)
    if (p / "radiance.pt").is_file() or (p.is_file() and p.name.endswith("radiance.pt")):
        from icbtool.radiance import RadianceModel

        return RadianceModel.load(p)
    from icbtool.gan import Generator

    return Generator.load(p)


def _comparison_client(cfg: LoopConfig, scene: Any, cloud: Any, rz: Any) -> Any:
    """A second client on the cloud for :attr:`LoopConfig.compare_cloud` (else None)."""
    from icbtool import system

    if cfg.generator is None or not cfg.compare_cloud or not cfg.truth_every:
        return contextlib.nullcontext(None)
    return system.Client(scene, cloud, cfg.client, rasterizer=rz)


def truth_seed(cloud: CloudConfig, index: int) -> int:
    """The seed of the truth of frame ``index`` (the desktop app renders the same truths)."""
    return cloud.seed + 5000 + index


def truth_noise_ssim(scene: Any, config: LoopConfig) -> float:
    """SSIM of two truths of the loop's first frame that differ only in their seed: the truth's
    own Monte Carlo noise, the best SSIM any frame can score against a truth at
    ``config.truth_spp`` (a final frame near it is as good as the truth can tell).

    Returns:
        The SSIM in [-1, 1].
    """
    from icbtool import metrics, trace

    path = _client_path(scene, config)
    cam = path.camera_at(float(path.times[0]))  # run_loop's first frame
    a, b = (
        trace.render(
            scene,
            cam,
            trace.TraceConfig(
                spp=config.truth_spp,
                seed=config.cloud.seed + 9000 + k,
                max_depth=config.cloud.max_depth,
            ),
        )  # fmt: skip
        for k in range(2)
    )
    return float(metrics.ssim(a.full, b.full))


#: Height in pixels of the caption band above each panel of a frame strip.
LABEL_HEIGHT = 14


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    """``tile`` (H, W, 3) uint8 under a black band of :data:`LABEL_HEIGHT` pixels holding
    ``text`` in white (clipped to the tile's width)."""
    import cv2

    band = np.zeros((LABEL_HEIGHT, tile.shape[1], 3), np.uint8)
    cv2.putText(band, text, (2, LABEL_HEIGHT - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33,
                (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    return np.concatenate([band, tile], axis=0)


def _write_tiles(
    path: Path, tiles: list[np.ndarray], imageio: Any, labels: list[str] | None = None
) -> None:
    """(H, W_k, 3) uint8 tiles side by side, white 2-pixel gaps, as a PNG; with ``labels``,
    each under a caption band (:func:`_label`)."""
    if labels is not None:
        tiles = [_label(t, text) for t, text in zip(tiles, labels, strict=True)]
    sep = np.full((tiles[0].shape[0], 2, 3), 255, np.uint8)
    strip = tiles[0]
    for t in tiles[1:]:
        strip = np.concatenate([strip, sep, t], axis=1)
    imageio.write_png(path, strip)


def _write_strip(
    path: Path, images: list[np.ndarray], imageio: Any, labels: list[str] | None = None
) -> None:
    """Linear HDR images side by side (display transform), white 2-pixel gaps."""
    _write_tiles(path, [imageio.to_display(a, _EXPOSURE) for a in images], imageio, labels)


def _write_frame(
    path: Path, wrt: Any, w: Any, final: np.ndarray, truth: Any, imageio: Any, truth_spp: int
) -> None:
    """One strip, each panel labelled: DL | warped GI | holes by cause | final | truth (when
    rendered, with its samples per pixel)."""
    from icbtool.warp import HOLE_COLOURS

    holes = np.zeros((*w.holes.shape, 3), np.uint8)
    for cause, colour in HOLE_COLOURS.items():
        holes[getattr(w, cause)] = colour
    tiles = [
        imageio.to_display(wrt.dl, _EXPOSURE),
        imageio.to_display(w.image, _EXPOSURE),
        holes,
        imageio.to_display(final, _EXPOSURE),
    ]
    labels = ["DL (client)", "warped GI", "holes", "final"]
    if truth is not None:
        tiles.append(imageio.to_display(truth.full, _EXPOSURE))
        labels.append(f"truth {truth_spp}spp")
    _write_tiles(path, tiles, imageio, labels)


def _write_report(out: Path, report: LoopReport) -> None:
    import csv

    from icbtool.provenance import run_info, write_json

    write_json(out / "config.json", {"loop": asdict(report.config), "run": run_info()})
    write_json(out / "summary.json", report.summary())
    with open(out / "frames.csv", "w", newline="") as f:
        rows = [asdict(fr) for fr in report.frames]
        if rows:
            wtr = csv.DictWriter(f, fieldnames=list(rows[0]))
            wtr.writeheader()
            wtr.writerows(rows)
    # a plot of holes and SSIM over the path
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fr = report.frames
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot([f.index for f in fr], [100 * f.hole_ratio for f in fr], label="one reference")
    ax[0].plot([f.index for f in fr], [100 * f.hole_ratio_combined for f in fr], label="combined")
    ax[0].scatter(
        [f.index for f in fr if not f.cache_hit],
        [100 * f.hole_ratio for f in fr if not f.cache_hit],
        marker="x",
        color="k",
        label="cloud render (miss)",
    )
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("holes (% of pixels)")
    ax[0].legend()
    sel = [f for f in fr if f.ssim_final is not None]
    if sel:
        ax[1].plot([f.index for f in sel], [f.ssim_final for f in sel], "o-", label="DL + GI")
        ax[1].plot([f.index for f in sel], [f.ssim_dl_only for f in sel], "s--", label="DL only")
        ax[1].set_xlabel("frame")
        ax[1].set_ylabel("SSIM vs path-traced truth")
        ax[1].legend()
    fig.suptitle(f"ICB loop on {report.scene}: hit rate {100 * report.hit_rate:.0f} %")
    fig.tight_layout()
    fig.savefig(out / "loop.png", dpi=110)
    plt.close(fig)
    (out / "README.txt").write_text(
        "frames/NNN.png: DL | warped GI (after combine+inpaint) | holes (red: outside the "
        "reference, yellow: disoccluded, grey: no geometry) | final DL+GI | truth (some frames)\n"
        "summary.json, frames.csv: numbers; loop.png: holes and SSIM along the path\n"
        + json.dumps(report.summary(), indent=2)
        + "\n"
    )
