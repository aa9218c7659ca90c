"""The one pinhole camera model of icbtool.

Conventions (used by every module; converted for OpenGL only inside :mod:`icbtool.raster`, and for
kornia only through :meth:`Camera.K_kornia`):

* Camera axes are OpenCV's: +x right, +y down, +z forward (the viewing direction).
* ``world_from_cam`` is a 4x4 rigid transform taking camera coordinates to world coordinates.
* Continuous pixel coordinates ``(u, v)``: ``u`` grows to the right (columns), ``v`` down (rows).
  The image covers ``[0, width] x [0, height]``; the centre of pixel ``(row i, col j)`` is at
  ``(u, v) = (j + 0.5, i + 0.5)``. This is OpenGL's and Mitsuba's convention. kornia (and OpenCV's
  ``cv2.remap``) put pixel centres at integer coordinates: :meth:`Camera.K_kornia` shifts the
  principal point by -0.5 for them.
* ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
* ``depth`` is view-space z (distance along the optical axis); ``distance`` is the ray length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

ArrayLike = Any


def _as_vec3(x: ArrayLike, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a


_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def _check_rigid(m: np.ndarray, name: str) -> None:
    if m.shape != (4, 4):
        raise ValueError(f"{name} must be 4x4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} contains NaN or Inf")
    r = m[:3, :3]
    # np.allclose's test (|a - b| <= atol + rtol |b|, rtol 1e-5) written out: m is finite
    # here, and allclose's own overhead was most of a camera's construction (every request)
    orthonormal = (np.abs(r.T @ r - _EYE3) <= 1e-4 + 1e-5 * _EYE3).all()
    if not orthonormal or abs(np.linalg.det(r) - 1.0) > 1e-4:
        raise ValueError(f"{name} rotation part is not a proper rotation (orthonormal, det +1)")
    if not (np.abs(m[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all():
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {m[3].tolist()}")


class CameraPlacementError(ValueError):
    """A camera sits inside geometry or too close to a surface; the message says where.

    Raised by :func:`icbtool.scene.check_camera` and :func:`icbtool.scene.random_walk`.
    """


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera (OpenCV axes, pixel centres at half-integers; see module docstring).

    Attributes:
        height: image height in pixels.
        width: image width in pixels.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in continuous pixel coordinates (``width / 2`` when centred).
        world_from_cam: (4, 4) float64 rigid transform, camera coordinates to world.
    """

    height: int
    width: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_from_cam: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        for name in ("height", "width"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1 or int(v) > 32768:
                raise ValueError(f"Camera {name} must be an integer in [1, 32768], got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"Camera {name} must be finite, got {v}")
            object.__setattr__(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        m = np.array(self.world_from_cam, dtype=np.float64)
        _check_rigid(m, "Camera.world_from_cam")
        m.setflags(write=False)
        object.__setattr__(self, "world_from_cam", m)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_fov(
        cls,
        fov_y_deg: float,
        height: int,
        width: int,
        world_from_cam: ArrayLike | None = None,
    ) -> Camera:
        """A centred camera with square pixels and the given vertical field of view.

        Raises:
            ValueError: if ``fov_y_deg`` is not in (0, 180).
        """
        if not (0.0 < float(fov_y_deg) < 180.0):
            raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
        f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2.0)
        pose = np.eye(4) if world_from_cam is None else np.asarray(world_from_cam, np.float64)
        return cls(height, width, f, f, width / 2.0, height / 2.0, pose)

    @classmethod
    def look_at(
        cls,
        eye: ArrayLike,
        target: ArrayLike,
        up: ArrayLike = (0.0, 1.0, 0.0),
        fov_y_deg: float = 45.0,
        height: int = 256,
        width: int = 256,
    ) -> Camera:
        """A camera at ``eye`` looking at ``target``, with ``up`` pointing up in the image.

        Raises:
            ValueError: if eye == target or the view direction is parallel to ``up``.
        """
        return cls.from_fov(fov_y_deg, height, width, look_at_pose(eye, target, up))

    @classmethod
    def frame(
        cls,
        bounds: ArrayLike,
        *,
        up: ArrayLike = (0.0, 1.0, 0.0),
        fov_y_deg: float = 45.0,
        height: int = 256,
        width: int = 256,
        view_direction: ArrayLike | None = None,
        margin: float = 1.0,
    ) -> Camera:
        """A centred camera whose view just contains a bounding box's (or a sphere's) sphere.

        The camera looks at the sphere's centre along ``view_direction`` from the distance at
        which the sphere's tangent cone has the half-angle of the narrower field of view
        (``distance = margin * radius / sin(min(fov_y, fov_x) / 2)``), so the sphere touches the
        top and bottom edges of the image (or the left and right ones when the image is taller
        than wide) and lies inside it.

        Args:
            bounds: (2, 3) axis-aligned box ``[min, max]`` (its circumscribed sphere is framed),
                or (4,) sphere ``(cx, cy, cz, radius)``.
            up: (3,) world direction shown up in the image.
            fov_y_deg: vertical field of view in degrees, in (0, 180).
            height: image height in pixels.
            width: image width in pixels.
            view_direction: (3,) direction the camera looks along (any length); default
                :func:`default_view_direction` of ``up`` (from the front, slightly above).
            margin: >= 1 pulls the camera back by this factor (1: the sphere just fits).

        Returns:
            The camera.

        Raises:
            ValueError: bad bounds (wrong shape, NaN, min > max, zero size), bad margin, or a
                view direction parallel to ``up``.
        """
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape == (2, 3):
            if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
                raise ValueError(f"Camera.frame: bounds must be finite [min, max]: {b.tolist()}")
            centre, radius = b.mean(0), 0.5 * float(np.linalg.norm(b[1] - b[0]))
        elif b.shape == (4,):
            if not np.all(np.isfinite(b)):
                raise ValueError(f"Camera.frame: sphere must be finite, got {b.tolist()}")
            centre, radius = b[:3], float(b[3])
        else:
            raise ValueError(
                f"Camera.frame: bounds must be a (2, 3) box or a (4,) sphere, got shape {b.shape}"
            )
        if not radius > 0:
            raise ValueError(f"Camera.frame: the bounds have zero size (radius {radius})")
        if not (math.isfinite(margin) and margin >= 1.0):
            raise ValueError(f"Camera.frame: margin must be >= 1, got {margin}")
        up_v = _as_vec3(up, "up")
        d = default_view_direction(up_v) if view_direction is None else view_direction
        d = _as_vec3(d, "view_direction")
        if np.linalg.norm(d) < 1e-12:
            raise ValueError("Camera.frame: view_direction must be non-zero")
        d = d / np.linalg.norm(d)
        cam = cls.from_fov(fov_y_deg, height, width)
        half = math.radians(min(cam.fov_y_deg, cam.fov_x_deg)) / 2.0
        distance = margin * radius / math.sin(half)
        return cam.with_pose(look_at_pose(centre - distance * d, centre, up_v))

    @classmethod
    def from_K(
        cls, K: ArrayLike, height: int, width: int, world_from_cam: ArrayLike | None = None
    ) -> Camera:
        """From a 3x3 intrinsic matrix in icbtool's pixel convention (centres at +0.5)."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {K.shape}")
        if abs(K[0, 1]) > 1e-9 or np.any(np.abs(K[2] - [0, 0, 1]) > 1e-9):
            raise ValueError("K must have zero skew and last row [0, 0, 1]")
        pose = np.eye(4) if world_from_cam is None else np.asarray(world_from_cam, np.float64)
        return cls(height, width, K[0, 0], K[1, 1], K[0, 2], K[1, 2], pose)

    # ------------------------------------------------------------------ properties
    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsics, icbtool pixel convention (pixel centres at +0.5)."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def K_kornia(self) -> np.ndarray:
        """(3, 3) intrinsics for kornia / OpenCV remap, whose pixel centres are integers."""
        K = self.K
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K

    @property
    def cam_from_world(self) -> np.ndarray:
        """(4, 4) float64 inverse of ``world_from_cam``."""
        r = self.world_from_cam[:3, :3]
        t = self.world_from_cam[:3, 3]
        m = np.eye(4)
        m[:3, :3] = r.T
        m[:3, 3] = -r.T @ t
        return m

    @property
    def position(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.world_from_cam[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction (+z camera axis) in world coordinates."""
        return self.world_from_cam[:3, 2].copy()

    @property
    def up(self) -> np.ndarray:
        """(3,) unit image-up direction (-y camera axis) in world coordinates."""
        return -self.world_from_cam[:3, 1]

    @property
    def right(self) -> np.ndarray:
        """(3,) unit image-right direction (+x camera axis) in world coordinates."""
        return self.world_from_cam[:3, 0].copy()

    @property
    def fov_y_deg(self) -> float:
        """Vertical field of view in degrees (for a centred principal point)."""
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees (for a centred principal point)."""
        return math.degrees(2.0 * math.atan(0.5 * self.width / self.fx))

    @property
    def aspect(self) -> float:
        """width / height."""
        return self.width / self.height

    # ------------------------------------------------------------------ derived cameras
    def with_pose(self, world_from_cam: ArrayLike) -> Camera:
        """The same intrinsics at another pose."""
        return replace(self, world_from_cam=np.asarray(world_from_cam, np.float64))

    def resized(self, height: int, width: int) -> Camera:
        """The same view (same FOV) at another resolution; intrinsics scale with the image."""
        sx, sy = width / self.width, height / self.height
        return replace(
            self,
            height=height,
            width=width,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
        )

    def with_fov(self, fov_y_deg: float, height: int | None = None, width: int | None = None):
        """A centred camera at the same pose with another vertical FOV (and optionally size).

        The horizontal FOV follows from the aspect ratio with square pixels.
        """
        return Camera.from_fov(
            fov_y_deg,
            self.height if height is None else height,
            self.width if width is None else width,
            self.world_from_cam,
        )

    # ------------------------------------------------------------------ geometry
    def project(self, points_world: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to continuous pixel coordinates.

        Args:
            points_world: (..., 3) world points.

        Returns:
            uv: (..., 2) pixel coordinates (icbtool convention), NaN where depth <= 0.
            depth: (...,) view-space z; <= 0 means behind the camera.
        """
        p = np.asarray(points_world, dtype=np.float64)
        if p.shape[-1] != 3:
            raise ValueError(f"points_world must have shape (..., 3), got {p.shape}")
        m = self.cam_from_world
        pc = p @ m[:3, :3].T + m[:3, 3]
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            safe = np.where(z > 0, z, np.nan)
            u = self.fx * pc[..., 0] / safe + self.cx
            v = self.fy * pc[..., 1] / safe + self.cy
        return np.stack([u, v], axis=-1), z

    def unproject(self, uv: ArrayLike, depth: ArrayLike) -> np.ndarray:
        """Lift pixel coordinates with view-space depth to world points.

        Args:
            uv: (..., 2) continuous pixel coordinates (icbtool convention).
            depth: (...,) view-space z.

        Returns:
            (..., 3) float64 world points.
        """
        uv = np.asarray(uv, dtype=np.float64)
        d = np.asarray(depth, dtype=np.float64)
        if uv.shape[-1] != 2:
            raise ValueError(f"uv must have shape (..., 2), got {uv.shape}")
        x = (uv[..., 0] - self.cx) / self.fx * d
        y = (uv[..., 1] - self.cy) / self.fy * d
        pc = np.stack([x, y, np.broadcast_to(d, x.shape)], axis=-1)
        m = self.world_from_cam
        return pc @ m[:3, :3].T + m[:3, 3]

    def pixel_centers(self) -> np.ndarray:
        """(H, W, 2) float64 continuous coordinates (u, v) of every pixel centre."""
        u = np.arange(self.width, dtype=np.float64) + 0.5
        v = np.arange(self.height, dtype=np.float64) + 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def rays(self, uv: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World-space primary rays.

        Args:
            uv: (..., 2) pixel coordinates; default: every pixel centre, shape (H, W, 2).

        Returns:
            origins: (..., 3) float64 (the camera centre, broadcast).
            directions: (..., 3) float64 unit directions.
            depth_per_distance: (...,) view-space z per unit of ray length (cosine to the axis),
                so ``depth = distance * depth_per_distance``.
        """
        uv = self.pixel_centers() if uv is None else np.asarray(uv, dtype=np.float64)
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        dc = np.stack([x, y, np.ones_like(x)], axis=-1)
        norm = np.linalg.norm(dc, axis=-1)
        dc = dc / norm[..., None]
        d = dc @ self.world_from_cam[:3, :3].T
        o = np.broadcast_to(self.position, d.shape).copy()
        return o, d, 1.0 / norm

    # ------------------------------------------------------------------ other conventions
    def gl_view_matrix(self) -> np.ndarray:
        """(4, 4) OpenGL view matrix (``gl_cam_from_world``: OpenGL camera looks down -z, +y up)."""
        flip = np.diag([1.0, -1.0, -1.0, 1.0])
        return flip @ self.cam_from_world

    def gl_world_from_cam(self) -> np.ndarray:
        """(4, 4) pose of the OpenGL camera (as pyrender's camera node pose)."""
        return self.world_from_cam @ np.diag([1.0, -1.0, -1.0, 1.0])

    def gl_projection_matrix(self, znear: float, zfar: float) -> np.ndarray:
        """(4, 4) OpenGL projection with these intrinsics (window origin bottom-left).

        Maps the continuous pixel coordinate ``(u, v)`` (icbtool convention, v down) to NDC
        ``x = 2u/W - 1``, ``y = 1 - 2v/H``, so OpenGL's fragment centres (+0.5) coincide with
        icbtool's pixel centres once the read-back image is flipped upside down.
        """
        if not (0 < znear < zfar):
            raise ValueError(f"need 0 < znear < zfar, got znear={znear}, zfar={zfar}")
        w, h = self.width, self.height
        p = np.zeros((4, 4))
        p[0, 0] = 2.0 * self.fx / w
        p[0, 2] = 1.0 - 2.0 * self.cx / w
        p[1, 1] = 2.0 * self.fy / h
        p[1, 2] = 2.0 * self.cy / h - 1.0
        p[2, 2] = -(zfar + znear) / (zfar - znear)
        p[2, 3] = -2.0 * zfar * znear / (zfar - znear)
        p[3, 2] = -1.0
        return p

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict (round-trips through :meth:`from_dict`)."""
        return {
            "height": self.height,
            "width": self.width,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "world_from_cam": self.world_from_cam.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`. Raises ValueError on missing or unknown keys."""
        keys = {"height", "width", "fx", "fy", "cx", "cy", "world_from_cam"}
        if set(d) != keys:
            raise ValueError(
                f"camera dict keys must be {sorted(keys)}: missing {sorted(keys - set(d))}, "
                f"unknown {sorted(set(d) - keys)}"
            )
        return cls(**{k: d[k] for k in keys})

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.height == other.height
            and self.width == other.width
            and (self.fx, self.fy, self.cx, self.cy) == (other.fx, other.fy, other.cx, other.cy)
            and np.array_equal(self.world_from_cam, other.world_from_cam)
        )

    def __hash__(self) -> int:
        return hash(
            (
                self.height,
                self.width,
                self.fx,
                self.fy,
                self.cx,
                self.cy,
                self.world_from_cam.tobytes(),
            )
        )

    def __repr__(self) -> str:
        p = np.round(self.position, 4).tolist()
        f = np.round(self.forward, 4).tolist()
        return (
            f"Camera({self.height}x{self.width}, fov_y={self.fov_y_deg:.2f} deg, "
            f"position={p}, forward={f})"
        )


def look_at_pose(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) ``world_from_cam`` for an OpenCV-axes camera at ``eye`` looking at ``target``.

    Raises:
        ValueError: if eye == target, or the view direction is parallel to ``up``.
    """
    eye = _as_vec3(eye, "eye")
    target = _as_vec3(target, "target")
    up = _as_vec3(up, "up")
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise ValueError(f"look_at: eye and target coincide at {eye.tolist()}")
    z /= n
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(1.0, np.linalg.norm(up)):
        raise ValueError(
            f"look_at: view direction {z.tolist()} is parallel to up {up.tolist()}; pick another up"
        )
    x /= nx
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def pose_from_forward(eye: ArrayLike, forward: ArrayLike, up: ArrayLike = (0, 1, 0)) -> np.ndarray:
    """(4, 4) ``world_from_cam`` at ``eye`` looking along ``forward``."""
    eye = _as_vec3(eye, "eye")
    return look_at_pose(eye, eye + _as_vec3(forward, "forward"), up)


def default_view_direction(up: ArrayLike = (0.0, 1.0, 0.0)) -> np.ndarray:
    """(3,) unit direction of a "from the front, slightly above" view for a world ``up``.

    The front is the world axis least aligned with ``up`` in the order z, x, y (for +y up: the
    camera stands on the +z side), made horizontal; the view looks back along it and down at
    about 17 degrees: ``normalize(-(front + 0.3 * up))``.
    """
    u = _as_vec3(up, "up")
    u = u / np.linalg.norm(u)
    axes = np.eye(3)[[2, 0, 1]]
    front = axes[int(np.argmin(np.abs(axes @ u)))]
    front = front - (front @ u) * u
    front /= np.linalg.norm(front)
    d = -(front + 0.3 * u)
    return d / np.linalg.norm(d)
