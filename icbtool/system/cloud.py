"""The cloud: the full-detail scene, the octree CRT-buffer cache and the path tracer.

For a :class:`~icbtool.system.messages.GIRequest` (docs/design.md sections 3, 4 and 6):

1. predict where the client can be after the latency: the prefetch camera (wider FOV, pulled
   back; :func:`icbtool.prefetch.prefetch_camera`), its FOV rounded up to a step so that a stored
   reference covers the slightly different FOVs of the next requests;
2. look that camera up in the octree cache (a similar camera whose FOV covers it, with at least
   :data:`MIN_DENSITY` of its pixel density, is a hit);
   a hit whose payload is damaged (missing, truncated, checksum) is a miss, logged as a WARNING;
3. on a miss, render a CRT-buffer there (raster G-buffers + path-traced GI, optionally
   denoised) and store it (replacing the damaged record, if that was the miss).

Every step is timed in the reply.

An animated scene (docs/dynamic.md) is answered at the scene time of the request
(``GIRequest.time_s``): records carry the state they were rendered under
(:mod:`icbtool.store.invalidation`), and a record whose state differs from the request's is
judged by the invalidation rule. Under ``invalidation="rule"`` a record the change reaches
serves *marked stale* (``GIReply.stale``) while a cheap render (``cheap_spp``, denoised) at the
current state replaces it; a cheap record met again at the state it was rendered under is
refined (rendered again at ``spp``, replacing it). ``"all"`` (full invalidation) and ``"none"``
(a stale cache) are the baselines.

The steps are also separate methods (:meth:`Cloud.lookup`, :meth:`Cloud.job`,
:meth:`Cloud.store_render`) so that a server can run them on different threads and processes:
lookups on a read-only store (a Cloud over ``StoreConfig(readonly=True)``), renders on render
workers (:mod:`icbtool.system.workers`), the puts on the one writer.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

from icbtool.buffers import WRT_BUFFERS
from icbtool.camera import Camera
from icbtool.store import invalidation
from icbtool.system.messages import GIReply, GIRequest
from icbtool.system.source import GISource
from icbtool.trace.tracer import DenoiseQuality, check_denoise_quality

if TYPE_CHECKING:  # pragma: no cover (types only: the layers stay lazy)
    from icbtool.raster import RasterBuffers, Rasterizer
    from icbtool.scene.types import Scene
    from icbtool.store import Store
    from icbtool.store.record import CRTBuffer


log = logging.getLogger(__name__)

#: The prefetch camera's depth range when the client sent none (it sees no geometry).
DEFAULT_DEPTH_RANGE = (0.1, 100.0)
#: A stored reference answers a request only with at least this fraction of its pixel density
#: (focal length in pixels): a coarser one is a miss.
MIN_DENSITY = 0.95
#: Coarser similar records skipped per lookup before it counts as a miss.
MAX_COARSE_SKIPS = 4


@dataclass(frozen=True)
class CloudConfig:
    """How the :class:`Cloud` answers requests."""

    prefetch: bool = True
    """Render at the prefetch camera (else at the request's camera)."""
    latency_s: float = 0.1
    """Interaction latency T_IL the prefetch camera must cover."""
    fov_step_deg: float = 2.0
    """Round the prefetch FOV up to a multiple of this (0: no rounding)."""
    spp: int = 16
    """Path-tracing samples per pixel of the GI maps."""
    denoise: bool = True
    """Denoise the GI maps (OIDN with albedo and normal)."""
    denoise_quality: DenoiseQuality = "high"
    """OIDN quality ('fast': about half the denoising time)."""
    max_depth: int = 8
    """Longest traced path (segments)."""
    alpha_pos: float = 0.1
    """Cache position threshold (scene units)."""
    alpha_dir: float = 0.01
    """Cache direction threshold on 1 - dot (0.01 = 8.1 degrees)."""
    seed: int = 0
    """Base seed: a render for request ``seq`` uses ``seed + 1000 + seq``."""
    invalidation: Literal["rule", "all", "none"] = "rule"
    """Animated scenes: what a record of another scene state does. "rule": if the change
    reaches it (reach_m), it serves marked stale while a cheap render replaces it, refined
    later; "all": any change makes it a miss (full invalidation, re-rendered at spp); "none":
    it serves as it is (a stale cache; still marked stale where the rule says so)."""
    reach_m: float | None = None
    """How far (scene units) a change alters GI; None: everywhere (conservative)."""
    cheap_spp: int = 4
    """Samples per pixel of the first render after an invalidation (refined to spp later)."""
    serve_stale: bool = True
    """Reply a stale record at once and render its replacement for the next request (else wait
    for the cheap render and reply it)."""

    def __post_init__(self) -> None:
        for k in ("spp", "max_depth", "cheap_spp"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"CloudConfig.{k} must be an integer >= 1, got {v!r}")
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"CloudConfig.latency_s must be finite and >= 0, got {self.latency_s}")
        if not 0.0 <= self.fov_step_deg < 30.0:
            raise ValueError(
                f"CloudConfig.fov_step_deg must be in [0, 30), got {self.fov_step_deg}"
            )
        if not (self.alpha_pos > 0 and self.alpha_dir > 0):
            raise ValueError("CloudConfig.alpha_pos and alpha_dir must be > 0")
        check_denoise_quality(self.denoise_quality, "CloudConfig.denoise_quality")
        if self.invalidation not in ("rule", "all", "none"):
            raise ValueError(
                f"CloudConfig.invalidation must be 'rule', 'all' or 'none', got "
                f"{self.invalidation!r}"
            )
        r = self.reach_m
        if r is not None and not (isinstance(r, (int, float)) and math.isfinite(r) and r >= 0):
            raise ValueError(f"CloudConfig.reach_m must be finite and >= 0 or None, got {r!r}")


class Cloud(GISource):
    """The in-process cloud: answers GI requests from its cache or by rendering.

    Args:
        scene: the full-detail :class:`icbtool.scene.Scene`.
        store: an open :class:`icbtool.store.Store`, or a directory to open one in (closed with
            the cloud).
        config: :class:`CloudConfig`.
        rasterizer: an open :class:`icbtool.raster.Rasterizer` of ``scene`` to share (one GL
            context per process is cheapest); None opens one on the first render.

    Example:
        >>> with Cloud(scene, "out/cache") as cloud:  # doctest: +SKIP
        ...     reply = cloud.request(GIRequest(camera, v_t, v_r, time_s=0.0))
    """

    kind = "cloud"

    def __init__(
        self,
        scene: Scene,
        store: Store | str | os.PathLike,
        config: CloudConfig | None = None,
        rasterizer: Rasterizer | None = None,
    ) -> None:
        from icbtool import prefetch
        from icbtool import store as store_mod

        self.scene = scene
        self.config = cfg = config or CloudConfig()
        self._prefetch_cfg = prefetch.PrefetchConfig(latency_s=max(cfg.latency_s, 1e-9))
        self._own_store = isinstance(store, (str, os.PathLike))
        scfg = store_mod.StoreConfig(alpha_pos=cfg.alpha_pos, alpha_dir=cfg.alpha_dir)
        self.store = store_mod.open(store, scfg) if self._own_store else store
        self._keys = invalidation.group_keys(scene)
        if not getattr(self.store, "readonly", False):  # a reader follows the writer's scenes
            if scene.is_animated:  # every state shares one octree (module docstring)
                self.store.register_scene(
                    scene_hash=self._keys[0], bounds=scene.bounds, name=scene.name
                )
            else:
                self.store.register_scene(scene)
        self._rasterizer = rasterizer
        self._own_rasterizer = False
        self._now = scene
        self._state_rz: tuple[str, Rasterizer] | None = None
        self.renders = 0
        self.damaged_replaced = 0
        self.stale_served = 0
        """Replies of a record the invalidation rule marks stale."""
        self.invalidated = 0
        """Records replaced because a scene change reached them."""
        self.refinements = 0
        """Cheap records rendered again at full spp."""
        self.samples_traced = 0
        """Path-tracing samples of every render (spp x pixels): render cost free of the load."""

    # ------------------------------------------------------------------ the prefetch camera
    def reference_camera(self, req: GIRequest) -> Camera:
        """The camera the cloud renders (or looks up) for ``req``."""
        from icbtool import prefetch

        if not self.config.prefetch:
            return req.camera
        depth_range = req.depth_range or DEFAULT_DEPTH_RANGE
        cam = prefetch.prefetch_camera(
            req.camera, req.velocity_t, req.velocity_r, self._prefetch_cfg, depth_range=depth_range
        ).camera
        return round_fov(cam, self.config.fov_step_deg, self._prefetch_cfg.max_fov_deg)

    # ------------------------------------------------------------------ scene time
    def scene_at(self, t: float) -> Scene:
        """The cloud's scene at scene time ``t`` (the scene itself when it is static); the same
        object while the state does not change, so what is derived from it is kept."""
        if not self.scene.is_animated or t == self._now.time:
            return self._now
        now = self.scene.at(t)
        if invalidation.state_id(now) != invalidation.state_id(self._now):
            self._now = now
        return self._now

    def judge(self, record: CRTBuffer, now: Scene) -> Verdict:
        """What the invalidation rule says of a stored ``record`` at scene state ``now``."""
        rec_state, rec_t = invalidation.record_state(record.meta)
        cur = invalidation.state_id(now)
        if rec_state == cur:  # a record of an animated scene below the config's spp: refine it
            cheap = (
                self.config.invalidation == "rule"
                and rec_state != invalidation.STATIC_STATE
                and record.meta.spp < self.config.spp
            )
            return Verdict(same_state=True, stale=False, refine=cheap)
        if rec_t is None:  # no state recorded: nothing to compare with
            return Verdict(same_state=False, stale=True, refine=False)
        before = self.scene.at(rec_t)
        if invalidation.state_id(before) != rec_state:  # another animation made it
            change = invalidation.Change(everywhere=True)
        else:
            change = invalidation.scene_change(before, now)
        seen = invalidation.seen_bounds(record.camera, record.depth, record.mask)
        stale = invalidation.is_affected(change, seen, self.config.reach_m)
        return Verdict(same_state=False, stale=stale, refine=False)

    # ------------------------------------------------------------------ the steps
    def lookup(self, ref_cam: Camera) -> tuple[Any, int | None, float]:
        """Look ``ref_cam`` up in the store.

        Returns:
            (record, damaged, lookup_ms): the stored CRT-buffer on a hit (else None); on a miss
            because the similar record is damaged, that record's id (else None).
        """
        _rid, found, damaged, ms = self._lookup(ref_cam)
        return found, damaged, ms

    def _lookup(self, ref_cam: Camera) -> tuple[int | None, Any, int | None, float]:
        """(record id, record, damaged id, lookup_ms): :meth:`lookup` with the hit's id."""
        t0 = time.perf_counter()
        hit = self._covering_hit(ref_cam)
        # a damaged record (payload missing, truncated, checksum) is a miss: get_intact logs it
        found = None if hit is None else self.store.get_intact(hit.record_id)
        damaged = hit.record_id if (hit is not None and found is None) else None
        rid = hit.record_id if found is not None else None
        return rid, found, damaged, 1e3 * (time.perf_counter() - t0)

    def find(self, ref_cam: Camera) -> tuple[Any, float]:
        """Look ``ref_cam`` up in the index only (no payload read): what a server that keeps
        encoded replies of records needs first.

        Returns:
            (info, lookup_ms): the covering record's :class:`icbtool.store.RecordInfo` (its id,
            camera and payload checksum), or None on a miss.
        """
        t0 = time.perf_counter()
        hit = self._covering_hit(ref_cam)
        info = None if hit is None else hit.info
        return info, 1e3 * (time.perf_counter() - t0)

    def _covering_hit(self, ref_cam: Camera) -> Any:
        """The best stored camera that covers ``ref_cam`` with at least its pixel density (a
        64 x 64 record never answers a 1024 x 1024 request), or None."""
        exclude: list[int] = []
        for _ in range(MAX_COARSE_SKIPS + 1):
            hit = self.store.lookup(
                ref_cam, *self._keys, intrinsics="covering", exclude=exclude or None
            )
            if hit is None:
                return None
            cam = hit.camera
            if min(cam.fx / ref_cam.fx, cam.fy / ref_cam.fy) >= MIN_DENSITY:
                return hit
            exclude.append(hit.record_id)
        return None

    def trace_config(self, seq: int, spp: int | None = None) -> Any:
        """The :class:`icbtool.trace.TraceConfig` of the render for request ``seq`` (at ``spp``
        samples per pixel; default the config's)."""
        from icbtool import trace

        cfg = self.config
        return trace.TraceConfig(
            spp=cfg.spp if spp is None else spp,
            seed=cfg.seed + 1000 + seq,
            max_depth=cfg.max_depth,
            denoise=cfg.denoise,
            denoise_quality=cfg.denoise_quality,
        )

    def job(self, camera: Camera, seq: int = 0, spp: int | None = None) -> Any:
        """The :class:`icbtool.bake.RenderJob` of a render at ``camera`` for request ``seq``."""
        from icbtool.bake import RenderJob

        cfg = self.trace_config(seq, spp)
        return RenderJob(camera, cfg, "raster", WRT_BUFFERS, {"frame": seq})

    def store_render(self, ref: Any, damaged: int | None = None) -> int:
        """Put a rendered reference (replacing the damaged record ``damaged``); its id. A render
        of the cloud's scene made elsewhere (a render worker) is tagged with its state first."""
        if self.scene.is_animated and ref.meta.scene_hash == self.scene.content_hash:
            self._tag_state(ref, self.scene)
        if damaged is None:
            return self.store.put(ref)
        self.damaged_replaced += 1
        return self.store.replace_damaged(damaged, ref)

    # ------------------------------------------------------------------ GISource
    def request(self, req: GIRequest, wrt: RasterBuffers | None = None) -> GIReply:
        """Answer ``req`` from the cache, or render and store a new reference; an animated
        scene at the scene time ``req.time_s`` (module docstring)."""
        ref_cam = self.reference_camera(req)
        now = self.scene_at(req.time_s)
        rid, found, damaged, lookup_ms = self._lookup(ref_cam)
        timings = {"lookup": lookup_ms, "render": 0.0}
        mode = self.config.invalidation
        if found is not None and rid is not None:
            v = self.judge(found, now)
            if mode == "all" and not v.same_state:  # full invalidation: a miss
                self.invalidated += 1
                ref = self._render_timed(ref_cam, req.seq, now, None, timings)
                self._replace(rid, ref)
                return GIReply(ref, False, timings, req.seq)
            if mode == "rule" and (v.stale or v.refine):
                spp = self.config.cheap_spp if v.stale else None
                ref = self._render_timed(ref_cam, req.seq, now, spp, timings)
                self._replace(rid, ref)
                if v.stale:
                    self.invalidated += 1
                else:
                    self.refinements += 1
                if not self.config.serve_stale:
                    return GIReply(ref, False, timings, req.seq)
            self.stale_served += int(v.stale)
            return GIReply(found, True, timings, req.seq, stale=v.stale)
        ref = self._render_timed(ref_cam, req.seq, now, None, timings)
        self.store_render(ref, damaged)
        return GIReply(ref, False, timings, req.seq)

    def _render_timed(
        self, camera: Camera, seq: int, scene: Scene, spp: int | None, timings: dict
    ) -> CRTBuffer:
        t0 = time.perf_counter()
        if scene is self.scene and spp is None:  # the static case (subclasses may not take more)
            ref = self.render(camera, seq)
        else:
            ref = self.render(camera, seq, scene=scene, spp=spp)
        timings["render"] = timings.get("render", 0.0) + 1e3 * (time.perf_counter() - t0)
        return ref

    def _replace(self, record_id: int, ref: CRTBuffer) -> int:
        """Put ``ref`` (a fresh or refined render of record ``record_id``), then delete the old."""
        new_id = self.store.put(ref)
        self.store.delete([record_id])
        return new_id

    def render(
        self, camera: Camera, seq: int = 0, *, scene: Scene | None = None, spp: int | None = None
    ) -> CRTBuffer:
        """Render a CRT-buffer (the client's WRT-buffers + path-traced GI) at ``camera``.

        Args:
            camera: the reference camera.
            seq: the request's sequence number (the render's seed follows it).
            scene: the scene state to render (default the cloud's scene); a record of an
                animated scene is tagged with its state (:mod:`icbtool.store.invalidation`).
            spp: samples per pixel (default the config's).
        """
        from icbtool.bake import render_job

        scene = self.scene if scene is None else scene
        self.renders += 1
        job = self.job(camera, seq, spp)
        ref = render_job(scene, job, self._raster_for(scene))
        self.samples_traced += job.trace_config.spp * ref.camera.height * ref.camera.width
        if scene.is_animated:
            self._tag_state(ref, scene)
        return ref

    def _tag_state(self, ref: CRTBuffer, scene: Scene) -> None:
        """Key a render of an animated ``scene`` by the keys all its states share, and tag it
        with its state (:mod:`icbtool.store.invalidation`)."""
        sh, lh = self._keys
        tags = {**ref.meta.tags, **invalidation.state_tags(scene)}
        ref.meta = replace(ref.meta, scene_hash=sh, light_hash=lh, tags=tags)

    def _raster_for(self, scene: Scene) -> Rasterizer:
        """A rasterizer of ``scene``: the cloud's own for its scene's state, else one per state
        (the latest kept)."""
        from icbtool import raster

        state = invalidation.state_id(scene)
        if scene is self.scene or state == invalidation.state_id(self.scene):
            if self._rasterizer is None:
                self._rasterizer = raster.Rasterizer(self.scene)
                self._own_rasterizer = True
            return self._rasterizer
        if self._state_rz is None or self._state_rz[0] != state:
            if self._state_rz is not None:
                self._state_rz[1].close()
            self._state_rz = (state, raster.Rasterizer(scene))
        return self._state_rz[1]

    def close(self) -> None:
        if self._state_rz is not None:
            self._state_rz[1].close()
            self._state_rz = None
        if self._own_rasterizer and self._rasterizer is not None:
            self._rasterizer.close()
            self._rasterizer = None
        if self._own_store:
            self.store.close()


@dataclass(frozen=True)
class Verdict:
    """What the invalidation rule says of a stored record at the current scene state.

    Attributes:
        same_state: the record was rendered under the current state.
        stale: a change since its state may alter its GI (it must not serve unmarked).
        refine: a cheap record at the current state, to render again at full spp.
    """

    same_state: bool
    stale: bool
    refine: bool


def round_fov(cam: Camera, step_deg: float, max_fov_deg: float) -> Camera:
    """``cam`` with its vertical FOV rounded up to a multiple of ``step_deg`` (capped at
    ``max_fov_deg``), the resolution scaled to keep the pixel density at the centre."""
    if step_deg <= 0:
        return cam
    fov = min(math.ceil(cam.fov_y_deg / step_deg - 1e-9) * step_deg, max_fov_deg)
    if fov <= cam.fov_y_deg:
        return cam
    scale = math.tan(math.radians(fov) / 2) / math.tan(math.radians(cam.fov_y_deg) / 2)
    h, w = round(cam.height * scale), round(cam.width * scale)
    return cam.with_fov(fov, h, w)


__all__ = ["DEFAULT_DEPTH_RANGE", "Cloud", "CloudConfig", "Verdict", "round_fov"]
