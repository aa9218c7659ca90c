"""The one camera model of icbtool: a pinhole, and for the path tracer a thin lens or an
orthographic projection (Mitsuba 3's ``thinlens`` and ``orthographic`` sensors).

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

Lens and projection (:attr:`Camera.projection`, :attr:`Camera.aperture_radius`,
:attr:`Camera.focus_distance`, :attr:`Camera.near_clip`) follow Mitsuba 3's sensors:

* ``perspective`` with ``aperture_radius`` r > 0 (``thinlens``): a camera ray through the image
  point (u, v) aims at the point of the pinhole ray through (u, v) at depth ``focus_distance``
  (the focus plane is perpendicular to the optical axis), from a point of the aperture disk of
  radius r in the camera's z = 0 plane, drawn uniformly with the concentric map
  (:func:`concentric_disk`); r = 0 is the pinhole.
* ``orthographic``: ``u = fx * x + cx``, ``v = fy * y + cy`` (fx, fy in pixels per world unit);
  every ray is parallel to +z and starts in the z = ``near_clip`` plane.
* ``near_clip``: rays start where they cross the plane z = ``near_clip`` (Mitsuba's default is
  0.01, which its scene reader sets; icbtool's own cameras use 0: no clip).

Only :mod:`icbtool.trace` renders the lens and the orthographic projection. The ICB pipeline
(G-buffers, raster, warping, LPM) uses :meth:`Camera.pinhole`. A thin-lens camera's geometry
methods (``project``, ``rays``, ``K``) are its pinhole's (the lens centre's rays); an orthographic
camera's ``project``, ``unproject`` and ``rays`` are orthographic, and it has no ``K``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

ArrayLike = Any

#: Mitsuba 3's defaults for a sensor's near clip distance and for a thin lens's focus distance
#: (its far clip distance).
MITSUBA_NEAR_CLIP = 1e-2
MITSUBA_FOCUS_DISTANCE = 1e4
#: :meth:`Camera.pinhole` of an orthographic camera stands this many half-widths behind it.
ORTHO_PINHOLE_DISTANCE = 50.0


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


def concentric_disk(u: ArrayLike) -> np.ndarray:
    """Shirley and Chiu's concentric map of the unit square onto the unit disk (area-preserving;
    Mitsuba 3's ``square_to_uniform_disk_concentric``).

    Args:
        u: (..., 2) points of [0, 1]^2.

    Returns:
        (..., 2) float64 points of the unit disk.
    """
    u = np.asarray(u, dtype=np.float64)
    a = 2.0 * u[..., 0] - 1.0
    b = 2.0 * u[..., 1] - 1.0
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(first, 0.25 * np.pi * (b / a), 0.5 * np.pi - 0.25 * np.pi * (a / b))
    phi = np.where((a == 0) & (b == 0), 0.0, phi)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=-1)


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera (OpenCV axes, pixel centres at half-integers; see the module docstring): a
    pinhole by default, a thin lens or an orthographic projection for the path tracer.

    Attributes:
        height: image height in pixels.
        width: image width in pixels.
        fx, fy: focal lengths in pixels (orthographic: pixels per world unit).
        cx, cy: principal point in continuous pixel coordinates (``width / 2`` when centred).
        world_from_cam: (4, 4) float64 rigid transform, camera coordinates to world.
        projection: ``"perspective"`` or ``"orthographic"``.
        aperture_radius: thin-lens aperture radius in world units (0: a pinhole; perspective
            only).
        focus_distance: depth (view-space z) of the plane in focus, > 0; used when
            ``aperture_radius > 0`` (Mitsuba's default: 1e4, its far clip).
        near_clip: rays start at the plane z = near_clip (>= 0; 0: at the camera).
    """

    height: int
    width: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_from_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    projection: Literal["perspective", "orthographic"] = "perspective"
    aperture_radius: float = 0.0
    focus_distance: float = MITSUBA_FOCUS_DISTANCE
    near_clip: float = 0.0

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
        if self.projection not in ("perspective", "orthographic"):
            raise ValueError(
                f"Camera projection must be 'perspective' or 'orthographic', got "
                f"{self.projection!r}"
            )
        for name in ("aperture_radius", "focus_distance", "near_clip"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"Camera {name} must be finite, got {v}")
            object.__setattr__(self, name, v)
        if self.aperture_radius < 0:
            raise ValueError(f"Camera aperture_radius must be >= 0, got {self.aperture_radius}")
        if self.focus_distance <= 0:
            raise ValueError(f"Camera focus_distance must be > 0, got {self.focus_distance}")
        if self.near_clip < 0:
            raise ValueError(f"Camera near_clip must be >= 0, got {self.near_clip}")
        if self.projection == "orthographic" and self.aperture_radius > 0:
            raise ValueError("an orthographic Camera has no lens: aperture_radius must be 0")

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
    def is_pinhole(self) -> bool:
        """True for a perspective camera without lens and near clip (what the ICB pipeline
        renders; :meth:`pinhole` makes one of any camera)."""
        return (
            self.projection == "perspective" and self.aperture_radius == 0 and self.near_clip == 0
        )

    def _need_perspective(self, what: str) -> None:
        if self.projection != "perspective":
            raise ValueError(
                f"Camera.{what}: an orthographic camera has no pinhole intrinsics; use "
                "camera.pinhole() (a distant pinhole)"
            )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsics, icbtool pixel convention (pixel centres at +0.5).

        Raises:
            ValueError: for an orthographic camera.
        """
        self._need_perspective("K")
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
        """Vertical field of view in degrees (for a centred principal point).

        Raises:
            ValueError: for an orthographic camera.
        """
        self._need_perspective("fov_y_deg")
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view in degrees (for a centred principal point).

        Raises:
            ValueError: for an orthographic camera.
        """
        self._need_perspective("fov_x_deg")
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
        """A centred camera at the same pose with another vertical FOV (and optionally size),
        the same lens and near clip.

        The horizontal FOV follows from the aspect ratio with square pixels.

        Raises:
            ValueError: for an orthographic camera (it has no field of view).
        """
        self._need_perspective("with_fov")
        cam = Camera.from_fov(
            fov_y_deg,
            self.height if height is None else height,
            self.width if width is None else width,
            self.world_from_cam,
        )
        return replace(
            cam,
            aperture_radius=self.aperture_radius,
            focus_distance=self.focus_distance,
            near_clip=self.near_clip,
        )

    def pinhole(self) -> Camera:
        """The pinhole the ICB pipeline (G-buffers, raster, warping, LPM) renders for this
        camera: itself without lens and near clip; for an orthographic camera, a pinhole
        :data:`ORTHO_PINHOLE_DISTANCE` half-widths behind it with the same image of its near
        plane (rays within ``atan(1 / ORTHO_PINHOLE_DISTANCE)`` of parallel)."""
        if self.is_pinhole:
            return self
        base = replace(self, projection="perspective", aperture_radius=0.0, near_clip=0.0)
        if self.projection == "perspective":
            return replace(base, focus_distance=MITSUBA_FOCUS_DISTANCE)
        back = ORTHO_PINHOLE_DISTANCE * 0.5 * self.width / self.fx
        pose = self.world_from_cam.copy()
        pose[:3, 3] = pose[:3, 3] + (self.near_clip - back) * pose[:3, 2]
        return replace(
            base,
            fx=self.fx * back,
            fy=self.fy * back,
            world_from_cam=pose,
            focus_distance=MITSUBA_FOCUS_DISTANCE,
        )

    # ------------------------------------------------------------------ geometry
    def project(self, points_world: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to continuous pixel coordinates.

        Args:
            points_world: (..., 3) world points.

        Returns:
            uv: (..., 2) pixel coordinates (icbtool convention), NaN where depth <= 0
                (orthographic: where depth < near_clip).
            depth: (...,) view-space z; <= 0 means behind the camera.
        """
        p = np.asarray(points_world, dtype=np.float64)
        if p.shape[-1] != 3:
            raise ValueError(f"points_world must have shape (..., 3), got {p.shape}")
        m = self.cam_from_world
        pc = p @ m[:3, :3].T + m[:3, 3]
        z = pc[..., 2]
        if self.projection == "orthographic":
            seen = z >= self.near_clip
            u = np.where(seen, self.fx * pc[..., 0] + self.cx, np.nan)
            v = np.where(seen, self.fy * pc[..., 1] + self.cy, np.nan)
            return np.stack([u, v], axis=-1), z
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
        scale = 1.0 if self.projection == "orthographic" else d
        x = (uv[..., 0] - self.cx) / self.fx * scale
        y = (uv[..., 1] - self.cy) / self.fy * scale
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
        """World-space primary rays (a thin lens's: through the lens centre; near clip not
        applied: see :meth:`sample_rays`).

        Args:
            uv: (..., 2) pixel coordinates; default: every pixel centre, shape (H, W, 2).

        Returns:
            origins: (..., 3) float64 (the camera centre, broadcast; orthographic: the point of
                the z = 0 plane seen at ``uv``).
            directions: (..., 3) float64 unit directions.
            depth_per_distance: (...,) view-space z per unit of ray length (cosine to the axis),
                so ``depth = distance * depth_per_distance``.
        """
        uv = self.pixel_centers() if uv is None else np.asarray(uv, dtype=np.float64)
        if self.projection == "orthographic":
            o, d = self.sample_rays(uv, np.full(uv.shape, 0.5))
            o = o - self.near_clip * d
            return o, d, np.ones(uv.shape[:-1])
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        dc = np.stack([x, y, np.ones_like(x)], axis=-1)
        norm = np.linalg.norm(dc, axis=-1)
        dc = dc / norm[..., None]
        d = dc @ self.world_from_cam[:3, :3].T
        o = np.broadcast_to(self.position, d.shape).copy()
        return o, d, 1.0 / norm

    def sample_rays(self, uv: ArrayLike, lens: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """World-space camera rays as the path tracer casts them (Mitsuba 3's
        ``Sensor.sample_ray``): through the image points ``uv``, from the aperture points the
        lens samples ``lens`` map to (:func:`concentric_disk`; ignored by a pinhole and an
        orthographic camera), starting at the near clip plane.

        Args:
            uv: (..., 2) pixel coordinates.
            lens: (..., 2) lens samples in [0, 1]^2 (0.5, 0.5: the lens centre).

        Returns:
            origins: (..., 3) float64 ray origins (on the plane z = near_clip).
            directions: (..., 3) float64 unit directions.
        """
        uv = np.asarray(uv, dtype=np.float64)
        lens = np.broadcast_to(np.asarray(lens, dtype=np.float64), uv.shape)
        if uv.shape[-1] != 2:
            raise ValueError(f"uv must have shape (..., 2), got {uv.shape}")
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        one = np.ones_like(x)
        if self.projection == "orthographic":
            oc = np.stack([x, y, self.near_clip * one], axis=-1)
            dc = np.stack([0 * one, 0 * one, one], axis=-1)
        else:
            # Mitsuba's camera axes are icbtool's with x and y negated: so is its disk point
            a = -self.aperture_radius * concentric_disk(lens)
            fd = self.focus_distance
            dc = np.stack([x * fd - a[..., 0], y * fd - a[..., 1], fd * one], axis=-1)
            dc = dc / np.linalg.norm(dc, axis=-1, keepdims=True)
            t = self.near_clip / dc[..., 2]
            oc = np.stack([a[..., 0], a[..., 1], 0 * one], axis=-1) + t[..., None] * dc
        m = self.world_from_cam
        return oc @ m[:3, :3].T + m[:3, 3], dc @ m[:3, :3].T

    def circle_of_confusion(self, depth: ArrayLike) -> np.ndarray:
        """Diameter in pixels (along x) of the blur disk of a point at view-space ``depth``: the
        thin lens's ``2 r fx |depth - focus_distance| / (focus_distance * depth)`` (0 for a
        pinhole and an orthographic camera).

        Args:
            depth: (...,) view-space z, > 0.

        Returns:
            (...,) float64 diameters in pixels.
        """
        z = np.asarray(depth, dtype=np.float64)
        if self.projection == "orthographic" or self.aperture_radius == 0:
            return np.zeros_like(z)
        fd = self.focus_distance
        return 2.0 * self.aperture_radius * self.fx * np.abs(z - fd) / (fd * z)

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
        self._need_perspective("gl_projection_matrix")
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
        """A JSON-able dict (round-trips through :meth:`from_dict`); the lens and projection
        keys only where they differ from a pinhole's defaults."""
        d = {
            "height": self.height,
            "width": self.width,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "world_from_cam": self.world_from_cam.tolist(),
        }
        for k, default in _LENS_DEFAULTS.items():
            if getattr(self, k) != default:
                d[k] = getattr(self, k)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        """Inverse of :meth:`to_dict`. Raises ValueError on missing or unknown keys."""
        keys = {"height", "width", "fx", "fy", "cx", "cy", "world_from_cam"}
        unknown = set(d) - keys - set(_LENS_DEFAULTS)
        if not keys <= set(d) or unknown:
            raise ValueError(
                f"camera dict keys must be {sorted(keys)} (and optionally "
                f"{sorted(_LENS_DEFAULTS)}): missing {sorted(keys - set(d))}, "
                f"unknown {sorted(unknown)}"
            )
        return cls(**{k: d[k] for k in d})

    def _lens_key(self) -> tuple:
        return (self.projection, self.aperture_radius, self.focus_distance, self.near_clip)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.height == other.height
            and self.width == other.width
            and (self.fx, self.fy, self.cx, self.cy) == (other.fx, other.fy, other.cx, other.cy)
            and np.array_equal(self.world_from_cam, other.world_from_cam)
            and self._lens_key() == other._lens_key()
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
                self._lens_key(),
            )
        )

    def __repr__(self) -> str:
        p = np.round(self.position, 4).tolist()
        f = np.round(self.forward, 4).tolist()
        if self.projection == "orthographic":
            view = f"orthographic {self.width / self.fx:.4g} x {self.height / self.fy:.4g} units"
        else:
            view = f"fov_y={self.fov_y_deg:.2f} deg"
            if self.aperture_radius > 0:
                view += f", aperture {self.aperture_radius:.4g}, focus {self.focus_distance:.4g}"
        return f"Camera({self.height}x{self.width}, {view}, position={p}, forward={f})"


#: The lens and projection fields and their defaults (a pinhole's).
_LENS_DEFAULTS = {
    "projection": "perspective",
    "aperture_radius": 0.0,
    "focus_distance": MITSUBA_FOCUS_DISTANCE,
    "near_clip": 0.0,
}


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
