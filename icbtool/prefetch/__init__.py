"""Prefetch cameras for 3D warping (docs/design.md section 4): wider, pulled back, dense enough.

The cloud renders the reference (GI map) for a camera that still covers the client's view after
the interaction latency ``T_IL`` (cloud render + encode + transfer, :class:`LatencyModel`).

Derivation (the geometric intent of the paper's Eq. 1-4; Eq. 1 as printed,
``2*pi*cot(max(|T V_t.x|, |asp T V_t.y|) / V_t.z) + alpha``, is dimensionally garbled: it can
exceed 2*pi and is undefined when V_t.z = 0, so no literal version is kept):

* Predicted motions. Translations in the client's camera frame, over ``T_IL``:
  ``motion_model="axes"`` (default, the paper's six directions) uses ``+-s`` along each of x, y and
  z with ``s = |V_t| * T_IL``; by the convexity argument below this covers every displacement in
  the octahedron they span (``|dx| + |dy| + |dz| <= s``), so a diagonal move at full speed (L1
  norm up to ``sqrt(3) s``) may poke out slightly;
  ``"velocity"`` uses the actual displacement ``V_t * T_IL`` only. Rotations: ``+-|V_r.x| T_IL``
  (pitch), ``+-|V_r.y| T_IL`` (yaw), ``+-|V_r.z| T_IL`` (roll) about the client's axes in
  ``axes`` mode, the actual rotation vector ``V_r * T_IL`` in ``velocity`` mode. The identity is
  always included, and every translation is combined with every rotation.
* Frustum containment. A predicted client frustum, cut to the scene's depth range
  ``[z_near, z_far]``, is a convex polyhedron with 8 corners. The prefetch camera has the client's
  orientation and sits at ``(0, 0, -b)`` in the client frame (pulled back by ``b``, Eq. 4). A
  pinhole projection maps a convex set in front of the camera to the convex hull of its corners'
  projections, so the frustum is inside the prefetch image iff all 8 corners are:
  ``tan_x = max |x / (z + b)|``, ``tan_y = max |y / (z + b)|`` over all corners of all predicted
  frusta. With the client's aspect ratio ``asp`` kept (square pixels), the vertical FOV is
  ``2 atan(max(tan_y, tan_x / asp))``, plus the margin ``alpha`` (``margin_deg``, added to the full
  FOV: ``alpha / 2`` on each side, as the paper adds it to theta).
  Closed form for a sideways move ``dx`` alone: ``tan_x = (z_near tan(phi_x / 2) + |dx|) /
  (z_near + b)``; for a yaw by ``a`` alone with ``b = 0``: ``phi_x / 2 + a`` (the paper's Eq. 2).
* Pull-back ``b`` (Eq. 4, "z moved by V_t.z"): by default the largest backward motion among the
  predicted motions (``s`` in ``axes`` mode, ``max(0, -V_t.z) T_IL`` in ``velocity`` mode), so a
  client stepping back stays in front of the reference camera; a fixed value can be given.
  Pulling back further would narrow the FOV needed for sideways motion, but puts more scene
  between the reference and the client (occluders, walls behind the client), so it is not done.
* Clamp. ``max_fov_deg`` (default 150): near 180 deg a pinhole image degenerates (the focal
  length goes to 0 and the edge pixels cover ``1 / cos^2`` times fewer radians than the centre:
  15x at 150 deg), so the density rule below would need impractical resolutions. Motions that
  need more are not fully contained (``PrefetchResult.clamped``).
* Resolution rule. A wider, pulled-back reference at the client's resolution is magnified when
  warped (blur, cracks). ``resolution_rule``: ``"same"`` (the paper: the client's size);
  ``"center"``: the reference's focal length (pixels per radian at the image centre) is at least
  the client's, ``f_ref >= f_client``, i.e. the size grows by ``tan(fov_ref / 2) /
  tan(fov_client / 2)``; ``"near"``: also compensates the pull-back at the near depth (a surface at
  ``z_near`` is ``(z_near + b) / z_near`` times farther from the reference), ``f_ref >= f_client
  (z_near + b) / z_near``. The pixel count is capped at ``max_pixels`` (keeping the aspect).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from icbtool.camera import Camera

__all__ = [
    "LatencyModel",
    "PrefetchConfig",
    "PrefetchResult",
    "depth_range_from_depth",
    "predicted_cameras",
    "prefetch_camera",
]


@dataclass(frozen=True)
class LatencyModel:
    """The interaction latency ``T_IL`` as the sum of its parts (seconds)."""

    render_s: float = 0.05
    """Cloud render (or store lookup) time."""
    encode_s: float = 0.01
    """Encoding (and decoding) of the GI map."""
    transfer_s: float = 0.04
    """Network transfer, including round trip."""

    def __post_init__(self) -> None:
        for name in ("render_s", "encode_s", "transfer_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LatencyModel.{name} must be finite and >= 0, got {v}")

    @property
    def total_s(self) -> float:
        """``T_IL`` = render + encode + transfer."""
        return self.render_s + self.encode_s + self.transfer_s


@dataclass(frozen=True)
class PrefetchConfig:
    """How the prefetch camera is chosen (see the module docstring for the derivation)."""

    latency_s: float = 0.1
    """Interaction latency T_IL in seconds (e.g. ``LatencyModel(...).total_s``)."""
    margin_deg: float = 0.0
    """The paper's margin alpha, added to the full vertical FOV (degrees)."""
    max_fov_deg: float = 150.0
    """Clamp of the vertical FOV (a pinhole camera near 180 deg is unusable)."""
    motion_model: Literal["axes", "velocity"] = "axes"
    """``axes``: +-|v| T along each camera axis and +-|w_i| T about each; ``velocity``: the
    actual displacement and rotation only."""
    pullback: Literal["auto"] | float = "auto"
    """``auto``: the largest predicted backward motion; or a fixed distance (scene units)."""
    resolution_rule: Literal["same", "center", "near"] = "center"
    """Reference size: the client's, equal centre pixel density, or equal density at z_near."""
    max_pixels: int = 1024 * 1024
    """Cap of the reference's pixel count for the density rules."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ValueError(f"PrefetchConfig.latency_s must be >= 0, got {self.latency_s}")
        if not (0 <= self.margin_deg < 90):
            raise ValueError(f"PrefetchConfig.margin_deg must be in [0, 90), got {self.margin_deg}")
        if not (0 < self.max_fov_deg < 180):
            raise ValueError(
                f"PrefetchConfig.max_fov_deg must be in (0, 180), got {self.max_fov_deg}"
            )
        if self.motion_model not in ("axes", "velocity"):
            raise ValueError(
                f"PrefetchConfig.motion_model must be axes|velocity, got {self.motion_model!r}"
            )
        if self.pullback != "auto" and not (
            isinstance(self.pullback, (int, float)) and self.pullback >= 0
        ):
            raise ValueError(
                f"PrefetchConfig.pullback must be 'auto' or >= 0, got {self.pullback!r}"
            )
        if self.resolution_rule not in ("same", "center", "near"):
            raise ValueError(
                f"PrefetchConfig.resolution_rule must be same|center|near, got "
                f"{self.resolution_rule!r}"
            )
        if int(self.max_pixels) < 1:
            raise ValueError(f"PrefetchConfig.max_pixels must be >= 1, got {self.max_pixels}")


@dataclass(frozen=True)
class PrefetchResult:
    """The prefetch (cloud reference) camera and how it was derived.

    Attributes:
        camera: the reference camera (client orientation, pulled back, wider, resized).
        fov_y_deg: its vertical FOV (after margin and clamp).
        fov_x_deg: its horizontal FOV.
        required_fov_y_deg: the FOV the predicted motions need, with margin, before the clamp.
        pullback: distance moved back along the client's view direction (scene units).
        clamped: True if the clamp cut the FOV (some predicted frusta are not contained).
        latency_s: T_IL used.
        depth_range: (z_near, z_far) used.
        n_motions: number of predicted client poses checked.
    """

    camera: Camera
    fov_y_deg: float
    fov_x_deg: float
    required_fov_y_deg: float
    pullback: float
    clamped: bool
    latency_s: float
    depth_range: tuple[float, float]
    n_motions: int


def _rotvec_matrix(rv: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(rv))
    if th < 1e-15:
        return np.eye(3)
    k = rv / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * kx + (1 - math.cos(th)) * (kx @ kx)


def _motion_parts(
    v_t: np.ndarray, v_r: np.ndarray, t: float, model: str
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(translations (3,), rotations as (4, 4) with the rotation in [:3, :3]) whose every
    pairing is one predicted client pose (:func:`_motions`)."""
    if model == "velocity":
        trans = [np.zeros(3), v_t * t]
        rots = [np.zeros(3), v_r * t]
    else:
        s = float(np.linalg.norm(v_t)) * t
        trans = [np.zeros(3)] + [sg * s * np.eye(3)[i] for i in range(3) for sg in (1, -1)]
        rots = [np.zeros(3)] + [
            sg * abs(v_r[i]) * t * np.eye(3)[i] for i in range(3) for sg in (1, -1)
        ]
    mats = []
    for rv in rots:  # each rotation once (not once per translation)
        m = np.eye(4)
        m[:3, :3] = _rotvec_matrix(rv)
        mats.append(m)
    return trans, mats


def _motions(v_t: np.ndarray, v_r: np.ndarray, t: float, model: str) -> list[np.ndarray]:
    """Predicted client poses, as (4, 4) ``client_now_from_client_future`` transforms."""
    trans, mats = _motion_parts(v_t, v_r, t, model)
    out = []
    for tr in trans:
        for r in mats:
            m = r.copy()
            m[:3, 3] = tr
            out.append(m)
    return out


def predicted_cameras(
    client_cam: Camera, v_t: np.ndarray, v_r: np.ndarray, config: PrefetchConfig
) -> list[Camera]:
    """The client cameras after ``T_IL`` under the predicted motions (see module docstring)."""
    v_t = np.asarray(v_t, np.float64).reshape(3)
    v_r = np.asarray(v_r, np.float64).reshape(3)
    return [
        client_cam.with_pose(client_cam.world_from_cam @ m)
        for m in _motions(v_t, v_r, config.latency_s, config.motion_model)
    ]


def _frustum_corners(cam: Camera, near: float, far: float) -> np.ndarray:
    """(8, 3) corners of the camera's frustum cut to [near, far], in its camera frame."""
    uv = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], float)
    x = (uv[:, 0] - cam.cx) / cam.fx
    y = (uv[:, 1] - cam.cy) / cam.fy
    pts = [np.stack([x * z, y * z, np.full(4, z)], -1) for z in (near, far)]
    return np.concatenate(pts)


def depth_range_from_depth(
    depth: np.ndarray, mask: np.ndarray | None = None, percentiles: tuple[float, float] = (0, 100)
) -> tuple[float, float]:
    """(z_near, z_far) of a client depth map (H, W, 1) over its geometry pixels.

    Raises:
        ValueError: if no pixel has geometry.
    """
    z = np.asarray(depth, np.float64).reshape(-1)
    ok = np.isfinite(z) & (z > 0)
    if mask is not None:
        ok &= np.asarray(mask).reshape(-1) > 0.5
    if not ok.any():
        raise ValueError("depth_range_from_depth: the depth map has no valid pixel")
    lo, hi = np.percentile(z[ok], percentiles)
    return float(lo), float(max(hi, lo * (1 + 1e-9)))


def prefetch_camera(
    client_cam: Camera,
    v_t: np.ndarray,
    v_r: np.ndarray,
    config: PrefetchConfig = PrefetchConfig(),  # noqa: B008 (frozen)
    depth_range: tuple[float, float] = (0.1, 100.0),
) -> PrefetchResult:
    """The reference camera the cloud should render for a moving client.

    Args:
        client_cam: the client camera now (centred principal point assumed for the FOV).
        v_t: (3,) translation velocity in the client's camera frame (units / s).
        v_r: (3,) angular velocity about the client's camera axes (rad / s: x pitch, y yaw,
            z roll).
        config: a :class:`PrefetchConfig`.
        depth_range: (z_near, z_far) of the scene in the client view (e.g. from
            :func:`depth_range_from_depth`).

    Returns:
        A :class:`PrefetchResult`.

    Raises:
        ValueError: on non-finite velocities or a bad depth range.
    """
    v_t = np.asarray(v_t, np.float64).reshape(-1)
    v_r = np.asarray(v_r, np.float64).reshape(-1)
    if v_t.shape != (3,) or not np.all(np.isfinite(v_t)):
        raise ValueError(f"prefetch_camera: v_t must be a finite 3-vector, got {v_t}")
    if v_r.shape != (3,) or not np.all(np.isfinite(v_r)):
        raise ValueError(f"prefetch_camera: v_r must be a finite 3-vector, got {v_r}")
    near, far = (float(x) for x in depth_range)
    if not (0 < near <= far and math.isfinite(far)):
        raise ValueError(f"prefetch_camera: need 0 < z_near <= z_far < inf, got {depth_range}")
    t = config.latency_s
    trans, mats = _motion_parts(v_t, v_r, t, config.motion_model)
    if config.pullback == "auto":
        b = max(0.0, max(-float(tr[2]) for tr in trans))
    else:
        b = float(config.pullback)

    corners = _frustum_corners(client_cam, near, far)  # client frame
    # every motion's corners: each rotation once, then each translation added to it
    rotated = [corners @ m[:3, :3].T for m in mats]
    pts = np.concatenate([c + tr for tr in trans for c in rotated])
    z = pts[:, 2] + b
    asp = client_cam.aspect * client_cam.fy / client_cam.fx  # width / height in angle terms
    max_half = math.radians(config.max_fov_deg) / 2
    if np.any(z <= 1e-9):
        required_half = math.pi / 2  # some corner is behind the reference: no pinhole contains it
    else:
        tan_x = float(np.max(np.abs(pts[:, 0]) / z))
        tan_y = float(np.max(np.abs(pts[:, 1]) / z))
        # the client's own half-FOV is the floor (the identity motion is included)
        required_half = math.atan(max(tan_y, tan_x / asp))
    required_half += math.radians(config.margin_deg) / 2
    half = min(required_half, max_half)
    clamped = required_half > max_half + 1e-12
    fov_y = math.degrees(2 * half)

    # resolution rule
    tan_c = 0.5 * client_cam.height / client_cam.fy
    if config.resolution_rule == "same":
        scale = 1.0
    else:
        scale = math.tan(half) / tan_c
        if config.resolution_rule == "near":
            scale *= (near + b) / near
    h = max(1, round(client_cam.height * scale))
    w = max(1, round(client_cam.width * scale))
    if config.resolution_rule != "same" and h * w > config.max_pixels:
        k = math.sqrt(config.max_pixels / (h * w))
        h, w = max(1, int(h * k)), max(1, int(w * k))
    pose = client_cam.world_from_cam.copy()
    pose[:3, 3] = pose[:3, 3] - b * pose[:3, 2]
    # both half-angles exact whatever the rounding of (h, w): pixels may be non-square by < 1 %
    fy = 0.5 * h / math.tan(half)
    fx = 0.5 * w / (math.tan(half) * asp)
    cam = Camera(h, w, fx, fy, w / 2.0, h / 2.0, pose)
    return PrefetchResult(
        camera=cam,
        fov_y_deg=fov_y,
        fov_x_deg=cam.fov_x_deg,
        required_fov_y_deg=math.degrees(2 * required_half),
        pullback=b,
        clamped=clamped,
        latency_s=t,
        depth_range=(near, far),
        n_motions=len(trans) * len(mats),
    )
