"""Baking: render the CRT-buffers of every camera of a path into a store (resumable).

For each client camera of the path: choose the cloud camera (``"same"``, or ``"prefetch"``: wider
FOV, pulled back along -forward), skip it if the store already holds exactly that camera for this
scene and light setup with an intact payload, else (a damaged record is re-rendered and
replaced) render G-buffers + DL (raster) and GI (path tracer) and ``put`` them.

The tracer already uses both cores (two Embree threads); the raster runs in this process between
traces (a few tens of ms against seconds of tracing), so the two are not overlapped.

Scale-out: with a ``pool`` (:func:`icbtool.system.workers.open_pool`: render workers on Dask
distributed, docs/protocol.md section Scaling out) every view is one :class:`RenderJob`, a pure
function of the scene (sent to the workers once), the camera and the trace config, run by
:func:`render_job` on a worker; this process stays the store's only writer and puts the records
in path order, so a pool bake writes the same records (same ids, same maps bit for bit) as the
single-process one and stays resumable the same way.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from icbtool.camera import Camera, CameraPath
from icbtool.store.record import CRTBuffer, RecordMeta
from icbtool.trace.tracer import DenoiseQuality, check_denoise_quality

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BakeConfig:
    """How :func:`bake` renders a path."""

    spp: int = 16
    """Path-tracing samples per pixel of the GI maps."""
    seed: int = 0
    """Base seed; view k of the path is traced with seed ``seed + k`` (independent noise)."""
    max_depth: int = 8
    """Longest traced path (segments), as :class:`icbtool.trace.TraceConfig`."""
    denoise: bool = False
    """Denoise GI with OIDN (the stored GI is then the denoised one)."""
    denoise_quality: DenoiseQuality = "high"
    """OIDN quality ('fast': about half the denoising time, see TraceConfig.denoise_quality)."""
    gbuffer: Literal["raster", "trace"] = "raster"
    """Where DL and the G-buffers come from: the OpenGL rasterizer (the system's design), or a
    primary Embree ray cast at pixel centres plus the tracer's direct light (no OpenGL needed)."""
    cloud_camera: Literal["same", "wider", "prefetch"] = "same"
    """The camera baked for a client camera: the same one; "wider": a fixed rule (FOV times
    ``fov_multiplier``, pulled back by ``pullback``); "prefetch":
    ``icbtool.prefetch.prefetch_camera`` with the path's velocities at that camera (docs/design.md
    section 4) and ``prefetch_config``."""
    fov_multiplier: float = 1.5
    """"wider": the vertical FOV is multiplied by this (capped at ``max_fov_deg``)."""
    pullback: float = 0.0
    """"wider": the camera moves this far back along -forward (scene units)."""
    max_fov_deg: float = 120.0
    """"wider": FOV cap (a pinhole camera near 180 degrees is unusable)."""
    prefetch_config: Any = None
    """"prefetch": an ``icbtool.prefetch.PrefetchConfig`` (None: its defaults)."""
    resolution: tuple[int, int] | None = None
    """(height, width) of the baked maps; None: the path's."""
    stride: int = 1
    """Bake every ``stride``-th camera of the path."""
    limit: int | None = None
    """Bake at most this many cameras (after ``stride``)."""
    skip_existing: bool = True
    """Resume: skip cameras already in the store (exact camera, same scene and light hashes) whose
    payload verifies; a damaged one is re-rendered and replaced."""
    progress: bool = True
    """Show a tqdm progress bar."""
    tags: dict[str, Any] = field(default_factory=dict)
    """Extra tags on every record (the path name and camera index are always added)."""

    def __post_init__(self) -> None:
        for k in ("spp", "max_depth", "stride"):
            v = getattr(self, k)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise ValueError(f"BakeConfig.{k} must be an integer >= 1, got {v!r}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"BakeConfig.seed must be an integer >= 0, got {self.seed!r}")
        if self.gbuffer not in ("raster", "trace"):
            raise ValueError(
                f"BakeConfig.gbuffer must be 'raster' or 'trace', got {self.gbuffer!r}"
            )
        check_denoise_quality(self.denoise_quality, "BakeConfig.denoise_quality")
        if self.cloud_camera not in ("same", "wider", "prefetch"):
            raise ValueError(
                "BakeConfig.cloud_camera must be 'same', 'wider' or 'prefetch', "
                f"got {self.cloud_camera!r}"
            )
        if not (self.fov_multiplier >= 1.0 and math.isfinite(self.fov_multiplier)):
            raise ValueError(f"BakeConfig.fov_multiplier must be >= 1, got {self.fov_multiplier}")
        if not (self.pullback >= 0 and math.isfinite(self.pullback)):
            raise ValueError(f"BakeConfig.pullback must be >= 0, got {self.pullback}")
        if not (0 < self.max_fov_deg < 180):
            raise ValueError(f"BakeConfig.max_fov_deg must be in (0, 180), got {self.max_fov_deg}")
        if self.resolution is not None:
            h, w = self.resolution
            if int(h) != h or int(w) != w or h < 1 or w < 1:
                raise ValueError(
                    f"BakeConfig.resolution must be (height, width) > 0, got {self.resolution}"
                )
        if self.limit is not None and (int(self.limit) != self.limit or self.limit < 1):
            raise ValueError(f"BakeConfig.limit must be None or >= 1, got {self.limit}")


@dataclass
class BakeReport:
    """What :func:`bake` did.

    Attributes:
        rendered: record ids of the views rendered now, in path order.
        skipped: path indices skipped because the store already had them.
        seconds: wall time.
        seconds_per_view: mean render time of the rendered views.
        replaced: ids of damaged records (payload missing, truncated, checksum) that were
            re-rendered and replaced (their new ids are in ``rendered``).
    """

    rendered: list[int]
    skipped: list[int]
    seconds: float
    seconds_per_view: float
    replaced: list[int] = field(default_factory=list)


def cloud_camera(
    client: Camera,
    config: BakeConfig,
    path: CameraPath | None = None,
    index: int = 0,
    scene: Any = None,
) -> Camera:
    """The cloud camera baked for ``client`` (see :attr:`BakeConfig.cloud_camera`).

    Args:
        client: the client camera (``path[index]``).
        config: the bake config.
        path, index: the path and the camera's index in it ("prefetch" uses its velocities).
        scene: the scene ("prefetch" uses its diagonal as the far depth).

    Raises:
        ValueError: "prefetch" without a path.
    """
    if config.resolution is not None:
        client = client.resized(*config.resolution)
    if config.cloud_camera == "same":
        return client
    if config.cloud_camera == "prefetch":
        from icbtool import prefetch

        if path is None:
            raise ValueError("cloud_camera='prefetch' needs the camera path (for velocities)")
        v_t, v_r = path.velocity_cam(float(path.times[index]))
        far = 100.0 if scene is None else max(1.0, float(scene.diagonal))
        cfg = config.prefetch_config or prefetch.PrefetchConfig()
        return prefetch.prefetch_camera(client, v_t, v_r, cfg, (0.1, far)).camera
    fov = min(client.fov_y_deg * config.fov_multiplier, config.max_fov_deg)
    pose = np.array(client.world_from_cam)
    pose[:3, 3] -= config.pullback * pose[:3, 2]
    return client.with_fov(fov).with_pose(pose)


def _trace_gbuffers(scene: Any, cam: Camera) -> dict[str, np.ndarray]:
    """G-buffers from one primary ray per pixel centre (what a rasterizer would produce)."""
    from icbtool.scene.raycast import EmbreeScene

    es = EmbreeScene.from_scene(scene)
    o, d, dpd = cam.rays()
    h, w = cam.height, cam.width
    hits = es.intersect(o.reshape(-1, 3), d.reshape(-1, 3))
    hit = hits.hit
    t = np.where(hit, hits.t, 0.0).astype(np.float64)
    pos = o.reshape(-1, 3) + t[:, None] * d.reshape(-1, 3)
    f = scene.faces[np.maximum(hits.prim, 0)]
    bu, bv = hits.u.astype(np.float64), hits.v.astype(np.float64)
    n = (
        (1 - bu - bv)[:, None] * scene.normals[f[:, 0]]
        + bu[:, None] * scene.normals[f[:, 1]]
        + bv[:, None] * scene.normals[f[:, 2]]
    )
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    flip = np.sum(n * d.reshape(-1, 3), axis=1) > 0
    n[flip] *= -1
    m = hit[:, None]
    pos, n = np.where(m, pos, 0.0), np.where(m, n, 0.0)
    nv = n @ cam.world_from_cam[:3, :3]
    depth = np.where(hit, t * dpd.reshape(-1), 0.0)
    as32 = lambda a, c: a.reshape(h, w, c).astype(np.float32)  # noqa: E731
    return {
        "position": as32(pos, 3),
        "normal_world": as32(n, 3),
        "normal_view": as32(nv, 3),
        "depth": as32(depth, 1),
        "mask": as32(hit.astype(np.float32), 1),
    }


#: The raster buffers a CRT-buffer holds (docs/design.md section 2); the mask is always included.
CRT_RASTER_BUFFERS: tuple[str, ...] = (
    "dl",
    "albedo",
    "normal_world",
    "normal_view",
    "depth",
    "position",
    "mask",
)


def render_crt_buffer(
    scene: Any,
    cam: Camera,
    trace_config: Any,
    rasterizer: Any = None,
    buffers: tuple[str, ...] = CRT_RASTER_BUFFERS,
    tags: dict[str, Any] | None = None,
) -> CRTBuffer:
    """Render one CRT-buffer: raster G-buffers and DL, path-traced GI, metadata.

    Args:
        scene: an :class:`icbtool.scene.Scene`.
        cam: the cloud camera; a thin lens or an orthographic camera renders as its
            :meth:`~icbtool.camera.Camera.pinhole` (the ICB pipeline's G-buffers, GI and warps
            assume one).
        trace_config: an :class:`icbtool.trace.TraceConfig` for the GI map.
        rasterizer: an open :class:`icbtool.raster.Rasterizer` for ``scene``; None: the
            G-buffers come from a primary Embree ray cast and DL from the tracer (no OpenGL).
        buffers: raster buffers to keep (``mask`` is always kept); ignored without a rasterizer.
        tags: tags of the record's :class:`RecordMeta`.

    Returns:
        A :class:`CRTBuffer` whose ``meta.render_time_s`` covers raster and trace.
    """
    from icbtool import trace

    t0 = time.perf_counter()
    cam = cam.pinhole()
    if rasterizer is not None:
        rb = rasterizer.render(cam, buffers=tuple(b for b in buffers if b != "mask"))
        maps = {n: getattr(rb, n) for n in (*buffers, "mask")}
        # DL comes from the raster: the tracer's `direct` is not kept, so the extra emission
        # samples on emitter edges (which change only `direct`, never `gi`) would be wasted
        tr = trace.render(scene, cam, replace(trace_config, edge_samples=0))
    else:
        tr = trace.render(scene, cam, trace_config)
        maps = _trace_gbuffers(scene, cam)
        maps["dl"] = tr.direct
        maps["albedo"] = tr.albedo
    maps["gi"] = tr.gi
    meta = RecordMeta.for_scene(
        scene,
        spp=int(trace_config.spp),
        render_time_s=time.perf_counter() - t0,
        tags=dict(tags or {}),
    )
    return CRTBuffer(camera=cam, meta=meta, **maps)


@dataclass(frozen=True)
class RenderJob:
    """One CRT-buffer to render: everything but the scene (a render worker's task input).

    Attributes:
        camera: the cloud camera.
        trace_config: the :class:`icbtool.trace.TraceConfig` of the GI map (its seed included).
        gbuffer: "raster" (OpenGL G-buffers and DL) or "trace" (primary ray cast, no OpenGL).
        buffers: raster buffers to keep (see :func:`render_crt_buffer`).
        tags: tags of the record.
    """

    camera: Camera
    trace_config: Any
    gbuffer: Literal["raster", "trace"] = "raster"
    buffers: tuple[str, ...] = CRT_RASTER_BUFFERS
    tags: dict[str, Any] = field(default_factory=dict)


def render_job(scene: Any, job: RenderJob, rasterizer: Any = None) -> CRTBuffer:
    """Render ``job`` (a pure function of the scene and the job: same inputs, same maps).

    Args:
        scene: the :class:`icbtool.scene.Scene`.
        job: the :class:`RenderJob`.
        rasterizer: an open :class:`icbtool.raster.Rasterizer` of ``scene`` for
            ``gbuffer="raster"`` (required then); ignored for "trace".

    Returns:
        The :class:`CRTBuffer`.

    Raises:
        ValueError: ``gbuffer="raster"`` without a rasterizer.
    """
    if job.gbuffer == "raster" and rasterizer is None:
        raise ValueError("render_job: gbuffer='raster' needs an open rasterizer of the scene")
    r = rasterizer if job.gbuffer == "raster" else None
    return render_crt_buffer(scene, job.camera, job.trace_config, r, job.buffers, job.tags)


def bake(
    scene: Any,
    path: CameraPath | str,
    store: Any,
    config: BakeConfig | None = None,
    camera_fn: Callable[[Camera, int], Camera] | None = None,
    pool: Any = None,
) -> BakeReport:
    """Render the CRT-buffers of every camera of ``path`` into ``store`` (resumable).

    Args:
        scene: an :class:`icbtool.scene.Scene`.
        path: a :class:`CameraPath`, or the name of one of ``scene.paths``.
        store: an open writable :class:`icbtool.store.Store`.
        config: :class:`BakeConfig`.
        camera_fn: optional ``(client_camera, index) -> cloud camera`` replacing
            :func:`cloud_camera` (must be deterministic for resuming to work).
        pool: render workers (:func:`icbtool.system.workers.open_pool`, an object with
            ``submit(job) -> concurrent.futures.Future`` and ``capacity``); None renders in this
            process. Either way this process writes the store, in path order.

    Returns:
        :class:`BakeReport`.

    Raises:
        ValueError: unknown path name, bad config.
        RuntimeError: a view failed on the workers (after the pool's retries); the views before
            it are stored, so running the bake again resumes there.
    """

    cfg = config or BakeConfig()
    if isinstance(path, str):
        if path not in scene.paths:
            raise ValueError(
                f"scene '{scene.name}' has no camera path {path!r}; it has {sorted(scene.paths)}"
            )
        path = scene.paths[path]
    indices = list(range(0, len(path), cfg.stride))
    if cfg.limit is not None:
        indices = indices[: cfg.limit]
    sh, lh = scene.content_hash, scene.light_hash
    store.register_scene(scene)
    todo, skipped = [], []
    for i in indices:
        if camera_fn is not None:
            cam = camera_fn(path[i], i)
        else:
            cam = cloud_camera(path[i], cfg, path, i, scene)
        if not cfg.skip_existing:
            todo.append((i, cam, []))
            continue
        ids = store.find_exact_all(cam, sh, lh)
        problems = {rid: store.verify(rid) for rid in ids}
        if any(p is None for p in problems.values()):
            skipped.append(i)  # an intact record of this camera exists
            continue
        for rid, problem in problems.items():
            log.warning(
                "bake %s: view %d's record %d is damaged (%s); re-rendering it",
                path.name,
                i,
                rid,
                problem,
            )
        todo.append((i, cam, list(problems)))
    jobs = [
        (i, _view_job(cfg, path.name, i, cam, camera_fn is None), damaged)
        for i, cam, damaged in todo
    ]
    t0 = time.perf_counter()
    rendered: list[int] = []
    replaced: list[int] = []
    times: list[float] = []
    with contextlib.ExitStack() as stack:
        bar = None
        if cfg.progress:
            from tqdm import tqdm

            bar = stack.enter_context(
                tqdm(
                    total=len(indices), initial=len(skipped), desc=f"bake {path.name}", unit="view"
                )
            )
        if pool is None:
            results = _render_here(scene, [j for _, j, _ in jobs], stack)
        else:
            results = _render_on(pool, [j for _, j, _ in jobs])
        for (_, _, damaged), buf in zip(jobs, results, strict=True):
            dt = buf.meta.render_time_s
            if damaged:  # the new record replaces the damaged ones (never an intact one)
                rid = store.replace_damaged(damaged[0], buf)
                for old in damaged[1:]:
                    if store.verify(old) is not None:
                        store.delete([old])
                replaced.extend(damaged)
            else:
                rid = store.put(buf)
            rendered.append(rid)
            times.append(dt)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(s_per_view=f"{dt:.2f}")
    return BakeReport(
        rendered,
        skipped,
        time.perf_counter() - t0,
        float(np.mean(times)) if times else 0.0,
        replaced,
    )


def _view_job(cfg: BakeConfig, path_name: str, i: int, cam: Camera, own_camera: bool) -> RenderJob:
    """The render job of view ``i`` of a path (seed ``cfg.seed + i``, whoever renders it)."""
    from icbtool import trace

    tcfg = trace.TraceConfig(
        spp=cfg.spp,
        seed=cfg.seed + i,
        max_depth=cfg.max_depth,
        denoise=cfg.denoise,
        denoise_quality=cfg.denoise_quality,
    )
    tags = {
        **cfg.tags,
        "path": path_name,
        "index": i,
        "cloud_camera": cfg.cloud_camera if own_camera else "custom",
    }
    return RenderJob(cam, tcfg, cfg.gbuffer, CRT_RASTER_BUFFERS, tags)


def _render_here(
    scene: Any, jobs: list[RenderJob], stack: contextlib.ExitStack
) -> Iterator[CRTBuffer]:
    """The jobs rendered one after the other in this process (one rasterizer for all)."""
    rasterizer = None
    if any(j.gbuffer == "raster" for j in jobs):
        from icbtool import raster

        rasterizer = raster.Rasterizer(scene, raster.RasterConfig())
        if hasattr(rasterizer, "__enter__"):
            rasterizer = stack.enter_context(rasterizer)
    for job in jobs:
        yield render_job(scene, job, rasterizer)


def _render_on(pool: Any, jobs: list[RenderJob]) -> Iterator[CRTBuffer]:
    """The jobs rendered by ``pool``, yielded in job order; at most ``2 * pool.capacity`` jobs
    are submitted ahead of the one being written (bounded memory on a long path)."""
    window = max(2, 2 * int(pool.capacity))
    futures: collections.deque[Any] = collections.deque()
    it = iter(jobs)
    try:
        for job in itertools.islice(it, window):
            futures.append((job, pool.submit(job)))
        while futures:
            job, fut = futures.popleft()
            try:
                buf = fut.result()
            except Exception as e:
                raise RuntimeError(
                    f"bake: view {job.tags.get('index')} failed on the render workers: {e!r}; "
                    "the views before it are stored: run the bake again to resume"
                ) from e
            nxt = next(it, None)
            if nxt is not None:
                futures.append((nxt, pool.submit(nxt)))
            yield buf
    finally:
        for _, fut in futures:
            fut.cancel()
