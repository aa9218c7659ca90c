"""The client: rasterizes its own WRT-buffer, gets GI from a source, warps, combines, blends.

One :meth:`Client.frame` (docs/design.md section 6):

1. rasterize the WRT-buffer (DL, albedo, world normal, depth; the mask comes with it) at the
   client's camera;
2. ask the :class:`~icbtool.system.source.GISource` for the GI of a request (sent earlier, by the
   client's clock: the driver decides when), telling it the depth range the client sees;
3. warp the reply's reference GI to the current camera with the client's depth (backward warp,
   holes by cause), combine it with the previous reference's warp, inpaint what is left;
4. blend: ``final = DL + gi_weight * GI``.

An animated scene (docs/dynamic.md): ``frame(..., time_s=t)`` rasterizes the scene at time ``t``
(DL and G-buffers are always current); a reply the cloud marks stale makes the frame stale
(``ClientFrame.stale``), and the previous reference is combined only when it was rendered under
the same scene state as the current one (GI is never mixed across a change unmarked).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from icbtool.buffers import WRT_BUFFERS
from icbtool.camera import Camera
from icbtool.store import invalidation
from icbtool.system.messages import GIReply, GIRequest
from icbtool.system.source import GISource

if TYPE_CHECKING:  # pragma: no cover (types only: the layers stay lazy)
    from icbtool.raster import RasterBuffers, Rasterizer
    from icbtool.scene.types import Scene
    from icbtool.store.record import CRTBuffer
    from icbtool.warp.api import WarpResult


@dataclass(frozen=True)
class ClientConfig:
    """How the :class:`Client` turns a reference GI map into its frame."""

    combine_previous: bool = True
    """Combine the warp of the current reference with the previous one."""
    inpaint: bool = True
    """Inpaint the holes left after combining (they stay reported)."""
    gi_weight: float = 1.0
    """Final = DL + gi_weight * GI (1 is physically right)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.gi_weight) and self.gi_weight >= 0):
            raise ValueError(
                f"ClientConfig.gi_weight must be finite and >= 0, got {self.gi_weight}"
            )


@dataclass
class ClientFrame:
    """One client frame.

    Attributes:
        camera: the client's camera.
        wrt: its raster buffers (:class:`icbtool.raster.RasterBuffers`: dl, albedo,
            normal_world, depth, mask).
        reply: what the GI source answered.
        warped: the current reference alone warped to ``camera``
            (:class:`icbtool.warp.WarpResult`, holes by cause).
        combined: after combining with the previous reference and inpainting (its ``holes``
            are those left after combining, before inpainting).
        hole_ratio_combined: holes after combining, before inpainting.
        gi: (H, W, 3) float32 the GI the client shows.
        final: (H, W, 3) float32 ``dl + gi_weight * gi``.
        raster_ms, warp_ms: time of the client's raster and of warp + combine + inpaint.
        request_ms: time of the source's answer (request -> reply, as the client waited).
        stale: the GI shown was rendered under another scene state that the change since may
            alter (the reply was marked stale).
        time_s: the scene time the client rasterized (None: the scene as given).
    """

    camera: Camera
    wrt: RasterBuffers
    reply: GIReply
    warped: WarpResult
    combined: WarpResult
    hole_ratio_combined: float
    gi: np.ndarray
    final: np.ndarray
    raster_ms: float
    warp_ms: float
    request_ms: float = 0.0
    stale: bool = False
    time_s: float | None = None


class Client:
    """A client of the ICB system.

    Args:
        scene: the scene the client rasterizes (today the full scene; the LPM later).
        source: where GI comes from (a :class:`~icbtool.system.cloud.Cloud` in-process).
        config: :class:`ClientConfig`.
        rasterizer: an open :class:`icbtool.raster.Rasterizer` of ``scene`` to share; None opens
            one (closed with the client).
    """

    def __init__(
        self,
        scene: Scene,
        source: GISource,
        config: ClientConfig | None = None,
        rasterizer: Rasterizer | None = None,
    ) -> None:
        if not isinstance(source, GISource):
            raise TypeError(f"Client source must be a GISource, got {type(source).__name__}")
        self.scene = scene
        self.source = source
        self.config = config or ClientConfig()
        self._own_rasterizer = rasterizer is None
        if rasterizer is None:
            from icbtool import raster

            rasterizer = raster.Rasterizer(scene)
        self.rasterizer = rasterizer
        self._previous: CRTBuffer | None = None
        self._state = invalidation.state_id(scene)

    def use_scene(self, scene: Scene) -> None:
        """Rasterize ``scene`` from now on (a finer mesh level arrived): a new rasterizer of it
        (owned and closed by the client)."""
        from icbtool import raster

        if self._own_rasterizer:
            self.rasterizer.close()
        self.scene = scene
        self.rasterizer = raster.Rasterizer(scene)
        self._own_rasterizer = True
        self._state = invalidation.state_id(scene)

    def set_time(self, t: float) -> None:
        """Rasterize the (animated) scene at scene time ``t`` from now on; a rasterizer of the
        new state replaces the old one only when the state changed. A static scene ignores it."""
        if not self.scene.is_animated:
            return
        now = self.scene.at(t)
        if invalidation.state_id(now) != self._state:
            self.use_scene(now)

    def rasterize(self, camera: Camera) -> RasterBuffers:
        """The WRT-buffer at ``camera``, plus any buffer the GI source needs."""
        extra = tuple(b for b in self.source.needs if b not in WRT_BUFFERS and b != "mask")
        return self.rasterizer.render(camera, buffers=(*WRT_BUFFERS, *extra))

    def frame(
        self, camera: Camera, request: GIRequest, *, time_s: float | None = None
    ) -> ClientFrame:
        """Make one frame at ``camera`` with the GI answering ``request`` (see module docstring).

        ``request.depth_range``, if None, is filled from what the client sees now. ``time_s``:
        the scene time to rasterize an animated scene at (None: as it is).
        """
        from icbtool import warp

        if time_s is not None:
            self.set_time(time_s)
        t0 = time.perf_counter()
        wrt = self.rasterize(camera)
        raster_ms = 1e3 * (time.perf_counter() - t0)
        if request.depth_range is None:
            request = dataclasses.replace(request, depth_range=visible_depth_range(wrt))
        t0 = time.perf_counter()
        reply = self.source.request(request, wrt)
        request_ms = 1e3 * (time.perf_counter() - t0)
        ref = reply.reference
        cfg = self.config
        t0 = time.perf_counter()
        w_cur = warp.backward(ref.gi, ref.depth, ref.camera, wrt.depth, camera, ref.mask, wrt.mask)
        results = [w_cur]
        prev = self._previous
        if cfg.combine_previous and prev is not None and prev is not ref and _same_state(prev, ref):
            results.append(
                warp.backward(
                    prev.gi, prev.depth, prev.camera, wrt.depth, camera, prev.mask, wrt.mask
                )
            )
        both = warp.combine(results) if len(results) > 1 else w_cur
        hole_combined = both.hole_ratio
        if cfg.inpaint:
            both = warp.inpaint(both, depth=wrt.depth)
        warp_ms = 1e3 * (time.perf_counter() - t0)
        self._previous = ref
        gi = both.image
        return ClientFrame(
            camera=camera,
            wrt=wrt,
            reply=reply,
            warped=w_cur,
            combined=both,
            hole_ratio_combined=hole_combined,
            gi=gi,
            final=wrt.dl + cfg.gi_weight * gi,
            raster_ms=raster_ms,
            warp_ms=warp_ms,
            request_ms=request_ms,
            stale=reply.stale,
            time_s=time_s,
        )

    def close(self) -> None:
        if self._own_rasterizer:
            self.rasterizer.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _same_state(a: object, b: object) -> bool:
    """Whether two references were rendered under one scene state (no metadata: assumed)."""
    ma, mb = getattr(a, "meta", None), getattr(b, "meta", None)
    if ma is None or mb is None:
        return True
    return invalidation.record_state(ma)[0] == invalidation.record_state(mb)[0]


def visible_depth_range(wrt: RasterBuffers) -> tuple[float, float] | None:
    """(near, far) view depths of the geometry in a raster buffer set, or None if it sees none."""
    from icbtool import prefetch

    try:
        near, far = prefetch.depth_range_from_depth(wrt.depth, wrt.mask)
    except ValueError:
        return None
    return max(near, 1e-3), far


__all__ = ["Client", "ClientConfig", "ClientFrame", "visible_depth_range"]
