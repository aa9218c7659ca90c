"""What the client and the cloud say to each other: a GI request and its reply.

Both are plain data (a camera, vectors, numbers, a CRT-buffer), so a network layer can encode
them field by field in a language-neutral format; nothing here refers to a process or a socket.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from icbtool.camera import Camera

if TYPE_CHECKING:  # pragma: no cover (types only: the layers stay lazy)
    from numpy.typing import ArrayLike

    from icbtool.store.record import CRTBuffer


def _vec3(x: ArrayLike, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"GIRequest.{name} must be a finite 3-vector, got {x!r}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class GIRequest:
    """A client's request for a GI map (docs/design.md section 6, step 2).

    The client sends where it is and how it moves; the cloud picks the camera it renders for
    (the prefetch camera) so that the reply still covers the client after the latency.

    Attributes:
        camera: the client's camera when it sent the request.
        velocity_t: (3,) translation velocity in the camera frame (OpenCV axes), units/s.
        velocity_r: (3,) angular velocity (pitch, yaw, roll rates) in rad/s.
        time_s: the client's clock when it sent the request.
        seq: the request's sequence number (the cloud derives its render seeds from it).
        depth_range: (near, far) view depths of what the client sees, or None (the cloud uses
            its default range for the prefetch camera's clipping).
    """

    camera: Camera
    velocity_t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity_r: np.ndarray = field(default_factory=lambda: np.zeros(3))
    time_s: float = 0.0
    seq: int = 0
    depth_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.camera, Camera):
            raise ValueError(f"GIRequest.camera must be an icbtool Camera, got {type(self.camera)}")
        object.__setattr__(self, "velocity_t", _vec3(self.velocity_t, "velocity_t"))
        object.__setattr__(self, "velocity_r", _vec3(self.velocity_r, "velocity_r"))
        if not np.isfinite(self.time_s):
            raise ValueError(f"GIRequest.time_s must be finite, got {self.time_s}")
        if isinstance(self.seq, bool) or int(self.seq) != self.seq or self.seq < 0:
            raise ValueError(f"GIRequest.seq must be an integer >= 0, got {self.seq!r}")
        if self.depth_range is not None:
            near, far = (float(x) for x in self.depth_range)
            if not (np.isfinite(near) and np.isfinite(far) and 0 < near <= far):
                raise ValueError(
                    f"GIRequest.depth_range must be finite with 0 < near <= far, got "
                    f"{self.depth_range!r}"
                )
            object.__setattr__(self, "depth_range", (near, far))


@dataclass(frozen=True)
class GIReply:
    """The answer to a :class:`GIRequest`: a reference GI map with the depth to warp it.

    Attributes:
        reference: the CRT-buffer (:class:`icbtool.store.CRTBuffer`) rendered for, or found near,
            the camera the source chose; it holds at least ``gi``, ``depth``, ``mask`` and its
            ``camera``.
        cache_hit: the reference came from the cloud's store (no render).
        timings_ms: where the time went, by stage (e.g. ``lookup``, ``render``; a network source
            adds ``encode``, ``transfer``, ``decode``).
        seq: the request's sequence number.
        stale: the reference was rendered under another state of an animated scene and the
            invalidation rule says the change since may alter its GI
            (:mod:`icbtool.store.invalidation`): it serves while a fresh one renders, and the
            client must not show it as current.
    """

    reference: CRTBuffer
    cache_hit: bool
    timings_ms: dict[str, float] = field(default_factory=dict)
    seq: int = 0
    stale: bool = False

    def __post_init__(self) -> None:
        for name in ("gi", "depth", "camera"):
            if getattr(self.reference, name, None) is None:
                raise ValueError(f"GIReply.reference has no {name!r}: cannot be warped")


__all__ = ["GIReply", "GIRequest"]
