"""The scene data model shared by the rasterizer, the path tracer and the cache.

A :class:`Scene` is one merged triangle mesh (all geometry in world coordinates) with a material
per face, plus analytic lights and an optional sky. Everything is linear RGB:

* ``Material.albedo``: linear diffuse reflectance in [0, 1], multiplied by the texture if any.
* ``Material.emission``: emitted radiance (W / (m^2 sr)), one-sided along the face normal.
* ``Material.texture``: (h, w, 3) float32 *linear* albedo (sRGB files are decoded on load); its
  texel (0, 0) is the top-left of the image file; uv (0, 0) is the bottom-left (OBJ/glTF-after-flip
  convention), so ``row = (1 - v) * h``.

Light units: a :class:`DirectionalLight` gives irradiance on a surface facing it (W/m^2); point and
spot lights give radiant intensity (W/sr); an :class:`AreaLight` quad is emissive geometry (its
radiance) and is also part of the mesh, so cameras see it and paths can hit it.

Face winding is counter-clockwise seen from the front; the geometric normal is
``cross(v1 - v0, v2 - v0)``. Shading normals (per vertex) are unit length.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from icbtool.scene.derived import derived

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera, CameraPath


def _vec3(x: Any, name: str, nonneg: bool = False) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape == (1,):
        a = np.repeat(a, 3)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {x!r}")
    if nonneg and np.any(a < 0):
        raise ValueError(f"{name} must be >= 0, got {a.tolist()}")
    a.setflags(write=False)
    return a


def _unit(x: Any, name: str) -> np.ndarray:
    a = np.array(_vec3(x, name))
    n = np.linalg.norm(a)
    if n < 1e-12:
        raise ValueError(f"{name} must be non-zero")
    a = a / n
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Material:
    """A Lambertian material (optionally textured and/or emissive).

    Attributes:
        name: material name (from the file, or given).
        albedo: (3,) linear diffuse reflectance in [0, 1] (multiplies the texture).
        emission: (3,) emitted radiance, >= 0.
        texture: optional (h, w, 3) float32 linear albedo texture in [0, 1], read-only (a
            read-only float32 array in range is kept as given, shared; anything else is copied).
        texture_path: where the texture came from (for messages and hashing), if a file.
        bsdf: a declared BSDF (:mod:`icbtool.scene.bsdf`, Mitsuba 3's plugins) the tracer
            evaluates instead of the Lambertian ``albedo``/``texture``, which then stand in
            for it where no BSDF is evaluated (raster, denoiser albedo); None: Lambertian.
    """

    name: str
    albedo: np.ndarray = field(default_factory=lambda: np.full(3, 0.8))
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3))
    texture: np.ndarray | None = None
    texture_path: str | None = None
    bsdf: Any = None

    def __post_init__(self) -> None:
        alb = _vec3(self.albedo, f"material '{self.name}' albedo", nonneg=True)
        if np.any(alb > 1.0):
            raise ValueError(
                f"material '{self.name}' albedo must be in [0, 1] (energy conserving), "
                f"got {alb.tolist()}"
            )
        object.__setattr__(self, "albedo", alb)
        object.__setattr__(
            self, "emission", _vec3(self.emission, f"material '{self.name}' emission", True)
        )
        if self.texture is not None:
            t = np.asarray(self.texture, dtype=np.float32)
            if t.ndim != 3 or t.shape[2] != 3 or t.shape[0] < 1 or t.shape[1] < 1:
                raise ValueError(f"material '{self.name}' texture must be (h, w, 3), got {t.shape}")
            if not np.all(np.isfinite(t)):
                raise ValueError(f"material '{self.name}' texture has NaN/Inf texels")
            # a read-only float32 texture already in [0, 1] (a loader's decoded image, another
            # material's texture) is shared, not copied: materials of one image hold it once
            if t.flags.writeable or t.min() < 0.0 or t.max() > 1.0:
                t = np.clip(t, 0.0, 1.0)
                t.setflags(write=False)
            object.__setattr__(self, "texture", t)
        if self.bsdf is not None:
            from icbtool.scene.bsdf import BSDF_TYPES

            if not isinstance(self.bsdf, BSDF_TYPES):
                raise ValueError(
                    f"material '{self.name}' bsdf must be one of icbtool.scene.bsdf's BSDFs, "
                    f"got {type(self.bsdf).__name__}"
                )

    @property
    def is_emissive(self) -> bool:
        return bool(np.any(self.emission > 0))

    @property
    def is_textured(self) -> bool:
        return self.texture is not None


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light (the sun).

    Attributes:
        direction: (3,) unit direction the light travels (from the sun towards the scene).
        irradiance: (3,) W/m^2 on a surface perpendicular to ``direction``.
        name: label.
    """

    direction: np.ndarray
    irradiance: np.ndarray
    name: str = "sun"
    kind: Literal["directional"] = "directional"

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", _unit(self.direction, f"{self.name}.direction"))
        object.__setattr__(
            self, "irradiance", _vec3(self.irradiance, f"{self.name}.irradiance", True)
        )


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light: ``intensity`` (3,) in W/sr at ``position`` (3,)."""

    position: np.ndarray
    intensity: np.ndarray
    name: str = "point"
    kind: Literal["point"] = "point"

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, f"{self.name}.position"))
        object.__setattr__(self, "intensity", _vec3(self.intensity, f"{self.name}.intensity", True))


@dataclass(frozen=True)
class SpotLight:
    """A spot light: ``intensity`` (W/sr) on its axis, full inside ``inner_deg``, falling to
    zero at ``outer_deg`` (half-angles from the axis): smoothly (``profile="smoothstep"``,
    smoothstep in cos, as glTF viewers draw it), or linearly in the angle
    (``profile="linear"``: Mitsuba 3's spot, ``inner_deg`` its ``beam_width`` and
    ``outer_deg`` its ``cutoff_angle``)."""

    position: np.ndarray
    direction: np.ndarray
    intensity: np.ndarray
    inner_deg: float = 20.0
    outer_deg: float = 30.0
    name: str = "spot"
    profile: Literal["smoothstep", "linear"] = "smoothstep"
    kind: Literal["spot"] = "spot"

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, f"{self.name}.position"))
        object.__setattr__(self, "direction", _unit(self.direction, f"{self.name}.direction"))
        object.__setattr__(self, "intensity", _vec3(self.intensity, f"{self.name}.intensity", True))
        if not (0.0 <= self.inner_deg < self.outer_deg <= 90.0):
            raise ValueError(
                f"{self.name}: need 0 <= inner_deg < outer_deg <= 90, "
                f"got {self.inner_deg}, {self.outer_deg}"
            )
        if self.profile not in SPOT_PROFILES:
            raise ValueError(
                f"{self.name}.profile must be one of {list(SPOT_PROFILES)}, got {self.profile!r}"
            )

    def falloff(self, cos_angle: np.ndarray) -> np.ndarray:
        """Angular falloff in [0, 1] for the cosine between the axis and the light-to-point ray."""
        c = np.asarray(cos_angle, np.float64)
        if self.profile == "linear":
            a = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
            return np.clip((self.outer_deg - a) / (self.outer_deg - self.inner_deg), 0.0, 1.0)
        c_in = math.cos(math.radians(self.inner_deg))
        c_out = math.cos(math.radians(self.outer_deg))
        x = np.clip((c - c_out) / (c_in - c_out), 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class AreaLight:
    """An emissive parallelogram ``corner + s*edge_u + t*edge_v`` (s, t in [0, 1]), or with
    ``shape="triangle"`` the triangle ``(corner, corner + edge_u, corner + edge_v)`` (s, t >= 0,
    s + t <= 1).

    It emits ``radiance`` on the side of ``normal = cross(edge_u, edge_v)`` (one-sided). Area
    lights are also part of the scene mesh (triangles with an emissive material, added by
    :meth:`SceneBuilder.add_area_light` or the scene description, or the mesh's own emissive faces
    promoted by :func:`icbtool.scene.emitters.promote_emitters`): the renderers count the light
    of the mesh faces lying in an area light as direct light, that of other emissive faces as GI.
    """

    corner: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    radiance: np.ndarray
    name: str = "area"
    shape: Literal["parallelogram", "triangle"] = "parallelogram"
    kind: Literal["area"] = "area"

    def __post_init__(self) -> None:
        for k in ("corner", "edge_u", "edge_v"):
            object.__setattr__(self, k, _vec3(getattr(self, k), f"{self.name}.{k}"))
        object.__setattr__(self, "radiance", _vec3(self.radiance, f"{self.name}.radiance", True))
        if self.shape not in AREA_SHAPES:
            raise ValueError(
                f"{self.name}.shape must be one of {list(AREA_SHAPES)}, got {self.shape!r}"
            )

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        ln = np.linalg.norm(n)
        return n / ln if ln > 0 else n

    @property
    def area(self) -> float:
        a = float(np.linalg.norm(np.cross(self.edge_u, self.edge_v)))
        return 0.5 * a if self.shape == "triangle" else a

    @property
    def vertices(self) -> np.ndarray:
        """(4, 3) corners of a parallelogram, (3, 3) of a triangle, counter-clockwise seen from
        the emitting side."""
        c, u, v = self.corner, self.edge_u, self.edge_v
        if self.shape == "triangle":
            return np.stack([c, c + u, c + v])
        return np.stack([c, c + u, c + u + v, c + v])

    @property
    def triangles(self) -> np.ndarray:
        """(T, 3) vertex indices into :attr:`vertices` of the light's mesh triangles."""
        if self.shape == "triangle":
            return np.array([[0, 1, 2]])
        return np.array([[0, 1, 2], [0, 2, 3]])

    def sample_points(self, k: int) -> np.ndarray:
        """(k*k, 3) stratified points: the centres of a k x k grid of equal cells (a
        parallelogram), or the centroids of the k*k equal sub-triangles of a triangle whose edges
        are cut in k (both: equal areas, deterministic)."""
        c, u, v = self.corner, self.edge_u, self.edge_v
        if self.shape == "parallelogram":
            st = [((i + 0.5) / k, (j + 0.5) / k) for j in range(k) for i in range(k)]
        else:
            st = []
            for j in range(k):  # row j of sub-triangles between t = j/k and (j+1)/k
                for i in range(k - j):  # "upward" sub-triangle (i, j)
                    st.append(((i + 1 / 3) / k, (j + 1 / 3) / k))
                for i in range(k - j - 1):  # "downward" sub-triangle between them
                    st.append(((i + 2 / 3) / k, (j + 2 / 3) / k))
        a = np.array(st, np.float64)
        return c + a[:, :1] * u + a[:, 1:] * v

    def contains(self, points: np.ndarray, rel_tol: float = 1e-4) -> np.ndarray:
        """Whether points lie in the light's polygon (on its plane, inside its edges).

        Args:
            points: (..., 3) positions.
            rel_tol: tolerance relative to the light's size (sum of its edge lengths).

        Returns:
            (...) bool.
        """
        p = np.asarray(points, np.float64) - self.corner
        size = max(float(np.linalg.norm(self.edge_u) + np.linalg.norm(self.edge_v)), 1e-30)
        on_plane = np.abs(p @ self.normal) <= rel_tol * size
        u, v = self.edge_u, self.edge_v
        gram = np.array([[u @ u, u @ v], [u @ v, v @ v]])
        if abs(np.linalg.det(gram)) < 1e-300:
            return np.zeros(p.shape[:-1], bool)
        st = np.linalg.solve(gram, np.stack([p @ u, p @ v], -1).reshape(-1, 2).T).T
        st = st.reshape(*p.shape[:-1], 2)
        eps = 10 * rel_tol
        inside = np.all(st >= -eps, axis=-1)
        if self.shape == "triangle":
            inside &= st.sum(-1) <= 1 + eps
        else:
            inside &= np.all(st <= 1 + eps, axis=-1)
        return on_plane & inside


#: A :class:`SpotLight`'s falloff profiles.
SPOT_PROFILES = ("smoothstep", "linear")

#: The shapes an :class:`AreaLight` can take.
AREA_SHAPES = ("parallelogram", "triangle")


@dataclass(frozen=True)
class Sky:
    """Environment radiance for rays that leave the scene.

    ``kind='uniform'``: ``zenith`` everywhere. ``kind='gradient'``: a simple sky blending from
    ``horizon`` (at the horizon) to ``zenith`` (straight up) with ``sqrt(cos)`` of the elevation,
    and ``ground`` below the horizon. ``up`` is the world up axis.

    ``kind='envmap'``: a latitude-longitude HDR map (:meth:`from_envmap`), with Mitsuba 3's
    ``envmap`` parametrisation, so a Mitsuba ``to_world`` rotation is ``world_from_map`` as it
    is. In map space ``+y`` is up; the direction of the image point (u, v) in [0, 1]^2 is
    ``(sin(phi) sin(theta), cos(theta), -cos(phi) sin(theta))`` with ``theta = v pi``,
    ``phi = u 2 pi``; texel centres sit at ``u = (i + 0.5) / W`` and at ``v = j / (H - 1)`` (the
    first row is the north pole, the last the south pole) and the map is interpolated
    bilinearly, periodic in u. The radiance is ``envmap_scale * map``. For an envmap ``zenith``,
    ``horizon`` and ``ground`` hold its mean radiance over the sphere (what a uniform sky of the
    same power would be) and ``up`` is ``world_from_map``'s second column. See docs/guide/scenes.md,
    "Environment maps".

    Attributes:
        envmap: (H, W, 3) float32 linear radiance, read-only (``kind='envmap'`` only).
        envmap_scale: the map's multiplier.
        world_from_map: (3, 3) rotation, map space to world.
    """

    zenith: np.ndarray | None = None
    horizon: np.ndarray | None = None
    ground: np.ndarray | None = None
    kind: Literal["uniform", "gradient", "envmap"] = "uniform"
    up: np.ndarray | None = None
    envmap: np.ndarray | None = None
    envmap_scale: float = 1.0
    world_from_map: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("uniform", "gradient", "envmap"):
            raise ValueError(
                f"sky kind must be 'uniform', 'gradient' or 'envmap', got {self.kind!r}"
            )
        if self.kind == "envmap":
            self._init_envmap()
            return
        if self.envmap is not None or self.world_from_map is not None:
            raise ValueError(f"sky kind {self.kind!r} takes no envmap / world_from_map")
        if self.zenith is None:
            raise ValueError(f"sky kind {self.kind!r} needs a zenith radiance")
        object.__setattr__(self, "zenith", _vec3(self.zenith, "sky.zenith", True))
        hz = self.zenith if self.horizon is None else self.horizon
        object.__setattr__(self, "horizon", _vec3(hz, "sky.horizon", True))
        gr = np.zeros(3) if self.ground is None else self.ground
        object.__setattr__(self, "ground", _vec3(gr, "sky.ground", True))
        up = np.array([0.0, 1.0, 0.0]) if self.up is None else self.up
        object.__setattr__(self, "up", _unit(up, "sky.up"))

    def _init_envmap(self) -> None:
        if self.envmap is None:
            raise ValueError("sky kind 'envmap' needs an envmap (H, W, 3) array")
        m = np.array(self.envmap, dtype=np.float32)
        if m.ndim == 2:
            m = np.repeat(m[..., None], 3, axis=2)
        if m.ndim != 3 or m.shape[2] not in (1, 3, 4):
            raise ValueError(f"sky.envmap must be (H, W, 3), got shape {m.shape}")
        if m.shape[2] == 1:
            m = np.repeat(m, 3, axis=2)
        m = np.ascontiguousarray(m[..., :3])
        if m.shape[0] < 3 or m.shape[1] < 2:
            raise ValueError(f"sky.envmap must be at least 3 x 2 texels (H x W), got {m.shape}")
        bad = ~np.isfinite(m)
        if bad.any():
            j, i, _ = np.argwhere(bad)[0]
            raise ValueError(
                f"sky.envmap has {int(bad.any(-1).sum())} NaN/Inf texels (first at row {j}, "
                f"column {i}: {m[j, i].tolist()})"
            )
        if (m < 0).any():
            j, i, _ = np.argwhere(m < 0)[0]
            raise ValueError(
                f"sky.envmap has negative radiance (first at row {j}, column {i}: "
                f"{m[j, i].tolist()})"
            )
        scale = float(self.envmap_scale)
        if not (math.isfinite(scale) and scale >= 0):
            raise ValueError(f"sky.envmap_scale must be finite and >= 0, got {self.envmap_scale!r}")
        r = np.eye(3) if self.world_from_map is None else np.array(self.world_from_map, float)
        if r.shape != (3, 3) or not np.all(np.isfinite(r)):
            raise ValueError(f"sky.world_from_map must be a finite 3x3 rotation, got {r.tolist()}")
        if not np.allclose(r.T @ r, np.eye(3), atol=1e-4):
            raise ValueError(
                f"sky.world_from_map must be a rotation (orthonormal; no scale or shear), got "
                f"{np.round(r, 6).tolist()}"
            )
        m.setflags(write=False)
        r.setflags(write=False)
        object.__setattr__(self, "envmap", m)
        object.__setattr__(self, "envmap_scale", scale)
        object.__setattr__(self, "world_from_map", r)
        mean = envmap_mean_radiance(m) * scale
        for name in ("zenith", "horizon", "ground"):
            object.__setattr__(self, name, mean.copy())
        object.__setattr__(self, "up", r[:, 1].copy())

    @classmethod
    def from_envmap(
        cls,
        path_or_array: Any,
        scale: float = 1.0,
        world_from_map: Any = None,
    ) -> Sky:
        """A latitude-longitude environment map as the sky (Mitsuba 3's ``envmap`` convention).

        Args:
            path_or_array: an EXR or Radiance ``.hdr`` file (linear radiance), or an (H, W, 3)
                array of it.
            scale: radiance multiplier (Mitsuba's ``scale``).
            world_from_map: (3, 3) rotation from map to world (the rotation part of Mitsuba's
                ``to_world``); None = identity (map +y = world +y).

        Raises:
            FileNotFoundError: no such file. ValueError: an unsupported file type, a bad map
            (shape, NaN/Inf, negative texels), scale or rotation (the message names it).
        """
        if isinstance(path_or_array, (str, os.PathLike)):
            from icbtool.imageio import read_hdr

            data = read_hdr(path_or_array)
        else:
            data = np.asarray(path_or_array)
        return cls(kind="envmap", envmap=data, envmap_scale=scale, world_from_map=world_from_map)

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """Radiance (..., 3) float32 arriving from the unit ``directions`` (..., 3)."""
        d = np.asarray(directions)
        if self.kind == "envmap":
            local = d @ self.world_from_map  # map_from_world = world_from_map.T
            return envmap_lookup(self.envmap, local) * np.float32(self.envmap_scale)
        if self.kind == "uniform":
            return np.broadcast_to(self.zenith.astype(np.float32), d.shape).copy()
        c = d @ self.up
        w = np.sqrt(np.clip(c, 0.0, 1.0))[..., None]
        sky = (1 - w) * self.horizon + w * self.zenith
        out = np.where(c[..., None] >= 0, sky, self.ground)
        return out.astype(np.float32)

    @property
    def max_radiance(self) -> float:
        if self.kind == "envmap":
            return float(self.envmap.max()) * self.envmap_scale
        return float(max(self.zenith.max(), self.horizon.max(), self.ground.max()))


def envmap_periodic(envmap: np.ndarray) -> np.ndarray:
    """(H, W + 1, 3) float32: the map with its first column repeated at the end (the periodic
    texel grid the bilinear lookup of :func:`envmap_lookup` reads, as Mitsuba's envmap)."""
    m = np.asarray(envmap, np.float32)
    return np.ascontiguousarray(np.concatenate([m, m[:, :1]], axis=1))


def envmap_uv(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map-space unit directions (..., 3) -> (u, v) in [0, 1] (Mitsuba's ``direction_to_uv``)."""
    d = np.asarray(local, np.float64)
    u = np.arctan2(d[..., 0], -d[..., 2]) / (2 * np.pi)
    v = np.arccos(np.clip(d[..., 1], -1.0, 1.0)) / np.pi
    return u, v


def envmap_lookup(envmap: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Bilinear radiance (..., 3) float32 of a lat-long map (H, W, 3) along map-space unit
    directions (..., 3) (the lookup of :class:`Sky` ``kind='envmap'``)."""
    m = envmap_periodic(envmap)
    h, w1 = m.shape[:2]
    u, v = envmap_uv(local)
    u = u - 0.5 / (w1 - 1)
    u = u - np.floor(u)
    x = u * (w1 - 1)
    y = v * (h - 1)
    xi = np.minimum(x.astype(np.int64), w1 - 2)
    yi = np.minimum(y.astype(np.int64), h - 2)
    fx = (x - xi)[..., None]
    fy = (y - yi)[..., None]
    top = (1 - fx) * m[yi, xi] + fx * m[yi, xi + 1]
    bot = (1 - fx) * m[yi + 1, xi] + fx * m[yi + 1, xi + 1]
    return ((1 - fy) * top + fy * bot).astype(np.float32)


def envmap_mean_radiance(envmap: np.ndarray) -> np.ndarray:
    """(3,) mean radiance of a lat-long map over the sphere (1/(4 pi) of its integral over solid
    angle, rows weighted by the solid angle around their latitude)."""
    m = np.asarray(envmap, np.float64)
    h = m.shape[0]
    th = np.arange(h) * (np.pi / (h - 1))
    # each node row j stands for the band [theta_j - d/2, theta_j + d/2] clipped to [0, pi]
    lo = np.clip(th - 0.5 * np.pi / (h - 1), 0, np.pi)
    hi = np.clip(th + 0.5 * np.pi / (h - 1), 0, np.pi)
    w = np.cos(lo) - np.cos(hi)
    return (m.mean(axis=1) * w[:, None]).sum(0) / w.sum()


#: The kinds of :class:`AnalyticShape`.
SHAPE_KINDS = ("sphere", "disk", "cylinder")


@dataclass(frozen=True, eq=False)
class AnalyticShape:
    """An exact quadric of the scene (Mitsuba 3's ``sphere``, ``disk``, ``cylinder``).

    The path tracer intersects, shades and (when its material is emissive) samples the shape
    itself: a sphere light by the cone of directions it subtends, a disk or cylinder light by
    area, as Mitsuba 3 does. The Scene's mesh keeps a tessellation of it (faces ``faces[0] ..
    faces[1] - 1``) for everything else (the client's raster, LPM, GUI, the raster DL's area
    lights); the tracer ignores those faces.

    The local shapes, mapped by ``world_from_local``: ``sphere`` the unit sphere about the
    origin (the map must be a similarity: rotation, uniform scale, translation); ``disk`` the
    unit disk in the local xy plane, facing local +z (any invertible affine map: an ellipse is
    exact too); ``cylinder`` the open tube of radius 1 about local z, 0 <= z <= 1 (the map must
    keep its cross-section a circle: local x and y mapped to orthogonal vectors of one length,
    both orthogonal to the image of z). Normals point outwards (sphere, cylinder) or along the
    image of local +z under the inverse transpose (disk), reversed with ``flip_normals``; an
    emissive material emits on that side only (Mitsuba's area emitter), and the material must
    be untextured.

    Attributes:
        kind: one of :data:`SHAPE_KINDS`.
        world_from_local: (4, 4) float64 affine map, read-only.
        material: index into ``Scene.materials``.
        faces: (start, stop): the shape's tessellation in the Scene's faces.
        flip_normals: the normal (and the emitting side) reversed.
        name: label (messages).
    """

    kind: Literal["sphere", "disk", "cylinder"]
    world_from_local: np.ndarray
    material: int
    faces: tuple[int, int]
    flip_normals: bool = False
    name: str = "shape"

    def __post_init__(self) -> None:
        where = f"shape '{self.name}'"
        if self.kind not in SHAPE_KINDS:
            raise ValueError(f"{where}: kind must be one of {list(SHAPE_KINDS)}, got {self.kind!r}")
        m = np.array(self.world_from_local, np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"{where}: world_from_local must be a finite 4x4 matrix")
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise ValueError(f"{where}: world_from_local must be affine (last row 0 0 0 1)")
        lin = m[:3, :3]
        scale = float(np.abs(lin).max())
        if not scale > 0 or abs(np.linalg.det(lin)) < 1e-12 * scale**3:
            raise ValueError(f"{where}: world_from_local is singular")
        ex, ey, ez = lin[:, 0], lin[:, 1], lin[:, 2]
        tol = 1e-6 * scale * scale

        def orthogonal(a: np.ndarray, b: np.ndarray) -> bool:
            return abs(float(a @ b)) <= tol

        if self.kind == "sphere" and not (
            orthogonal(ex, ey) and orthogonal(ex, ez) and orthogonal(ey, ez)
            and abs(ex @ ex - ey @ ey) <= tol and abs(ex @ ex - ez @ ez) <= tol
        ):  # fmt: skip
            raise ValueError(
                f"{where}: a sphere's world_from_local must be a similarity (rotation, uniform "
                "scale, translation)"
            )
        if self.kind == "cylinder" and not (
            orthogonal(ex, ey) and orthogonal(ex, ez) and orthogonal(ey, ez)
            and abs(ex @ ex - ey @ ey) <= tol
        ):  # fmt: skip
            raise ValueError(
                f"{where}: a cylinder's world_from_local must keep its cross-section a circle "
                "(local x, y mapped to orthogonal vectors of one length, orthogonal to z's)"
            )
        fa = tuple(int(x) for x in np.asarray(self.faces).reshape(-1))
        if len(fa) != 2 or not 0 <= fa[0] < fa[1]:
            raise ValueError(f"{where}: faces must be (start, stop) with 0 <= start < stop")
        if isinstance(self.material, bool) or int(self.material) != self.material:
            raise ValueError(f"{where}: material must be an integer index")
        m.setflags(write=False)
        object.__setattr__(self, "world_from_local", m)
        object.__setattr__(self, "faces", fa)
        object.__setattr__(self, "material", int(self.material))
        object.__setattr__(self, "flip_normals", bool(self.flip_normals))

    @property
    def center(self) -> np.ndarray:
        """(3,) the image of the local origin (a sphere's or disk's centre, a cylinder's p0)."""
        return self.world_from_local[:3, 3].copy()

    @property
    def radius(self) -> float:
        """World radius of a sphere or cylinder (a disk: of its local x axis)."""
        return float(np.linalg.norm(self.world_from_local[:3, 0]))

    @property
    def area(self) -> float:
        """World surface area."""
        lin = self.world_from_local[:3, :3]
        if self.kind == "sphere":
            return 4.0 * math.pi * self.radius**2
        if self.kind == "disk":
            return math.pi * float(np.linalg.norm(np.cross(lin[:, 0], lin[:, 1])))
        return 2.0 * math.pi * self.radius * float(np.linalg.norm(lin[:, 2]))


Light = DirectionalLight | PointLight | SpotLight | AreaLight

#: Every light type by its ``kind``: the one place a light type is declared. Its parameters are
#: the dataclass's fields (those without a default are required), read by the scene description,
#: the hashes and the renderers alike.
LIGHT_TYPES: dict[str, type] = {
    "directional": DirectionalLight,
    "point": PointLight,
    "spot": SpotLight,
    "area": AreaLight,
}


def light_parameters(kind: str) -> tuple[frozenset[str], frozenset[str]]:
    """(required, optional) parameter names of the light type ``kind`` (``kind`` excluded).

    Raises:
        KeyError: an unknown kind.
    """
    from dataclasses import MISSING, fields

    fs = [f for f in fields(LIGHT_TYPES[kind]) if f.name != "kind"]
    required = frozenset(
        f.name for f in fs if f.default is MISSING and f.default_factory is MISSING
    )
    return required, frozenset(f.name for f in fs) - required


@dataclass(frozen=True, eq=False)
class Scene:
    """One merged triangle mesh with per-face materials, lights, sky and named camera paths.

    A Scene is immutable: its arrays are read-only, ``materials`` and ``lights`` are tuples and
    ``paths`` a read-only mapping. Change one through a copy, ``dataclasses.replace(scene,
    lights=...)`` (validated again). Data derived from it (Embree BVHs, the tracer's arrays,
    hashes) is cached outside it, in :mod:`icbtool.scene.derived`.

    Attributes:
        name: scene name.
        vertices: (V, 3) float32 world positions.
        faces: (F, 3) int32 vertex indices (counter-clockwise = front).
        normals: (V, 3) float32 unit shading normals.
        uvs: (V, 2) float32 texture coordinates, or None when no material is textured.
        face_material: (F,) int32 index into ``materials``.
        materials: the materials (a tuple).
        lights: analytic and area lights (a tuple; area lights are also in the mesh).
        shapes: exact spheres, disks and cylinders (:class:`AnalyticShape`, a tuple), each
            also tessellated in the mesh; the path tracer uses the exact shape.
        sky: environment radiance, or None (black).
        paths: named camera paths (e.g. "train", "test"), a read-only mapping.
        default_camera: a good first view, or None.
        up: (3,) world up axis.
        source: where the scene came from (file path or "procedural:<name>").
        max_depth: the scene file's path depth (a Mitsuba ``<integrator>``'s ``max_depth``,
            whose convention the tracer shares: >= 1, or -1 unbounded), the trace default for
            this scene; None: the tracer's own default. Not part of :attr:`content_hash` (it
            is a render setting, not content).
        animation: what moves over time (:class:`icbtool.scene.animation.Animation`: keyed
            lights, rigidly moving meshes), or None for a static scene. The scene's arrays and
            lights are those at :attr:`time`; :meth:`at` gives another time.
        time: the scene time (seconds) this scene's contents are at (0 for a static scene).
        instancing: which runs of faces are placed copies of a prototype
            (:class:`icbtool.scene.instancing.Instancing`; a Mitsuba ``instance``), or None. The
            mesh holds every copy; the tracer may build one BVH per prototype from it. Not part
            of :attr:`content_hash` (the mesh is the content).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    face_material: np.ndarray
    materials: Sequence[Material]
    uvs: np.ndarray | None = None
    lights: Sequence[Light] = ()
    sky: Sky | None = None
    paths: Mapping[str, CameraPath] = field(default_factory=dict)
    default_camera: Camera | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    source: str = ""
    max_depth: int | None = None
    animation: Any = None  # an icbtool.scene.animation.Animation (which imports this module)
    time: float = 0.0
    shapes: Sequence[AnalyticShape] = ()
    instancing: Any = None  # an icbtool.scene.instancing.Instancing: runs of faces that are copies

    def __post_init__(self) -> None:
        where = f"scene '{self.name}'" + (f" ({self.source})" if self.source else "")
        if isinstance(self.time, bool) or not math.isfinite(float(self.time)):
            raise ValueError(f"{where}: time must be a finite number, got {self.time!r}")
        object.__setattr__(self, "time", float(self.time))
        md = self.max_depth
        if md is not None and (
            isinstance(md, bool) or not isinstance(md, (int, np.integer)) or (md < 1 and md != -1)
        ):
            raise ValueError(f"{where}: max_depth must be an integer >= 1, -1 or None, got {md!r}")
        v = np.ascontiguousarray(self.vertices, dtype=np.float32)
        f = np.ascontiguousarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"{where}: vertices must be a non-empty (V, 3) array, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"{where}: faces must be a non-empty (F, 3) array, got {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"{where}: faces must be integers, got {f.dtype}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{where}: {int((~np.isfinite(v)).any(1).sum())} vertices are NaN/Inf")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(
                f"{where}: face indices out of range [0, {len(v) - 1}]: "
                f"min {f.min()}, max {f.max()}"
            )
        f = f.astype(np.int32, copy=False)
        n = np.ascontiguousarray(self.normals, dtype=np.float32)
        if n.shape != v.shape or not np.all(np.isfinite(n)):
            raise ValueError(f"{where}: normals must be finite (V, 3) like vertices, got {n.shape}")
        fm = np.ascontiguousarray(self.face_material, dtype=np.int32).reshape(-1)
        if len(fm) != len(f):
            raise ValueError(f"{where}: face_material has {len(fm)} entries for {len(f)} faces")
        if len(self.materials) == 0 or fm.min() < 0 or fm.max() >= len(self.materials):
            raise ValueError(f"{where}: face_material indices out of range of the materials")
        if self.uvs is not None:
            uv = np.ascontiguousarray(self.uvs, dtype=np.float32)
            if uv.shape != (len(v), 2) or not np.all(np.isfinite(uv)):
                raise ValueError(f"{where}: uvs must be finite (V, 2), got {uv.shape}")
            uv.setflags(write=False)
            object.__setattr__(self, "uvs", uv)
        elif any(m.is_textured for m in self.materials):
            raise ValueError(f"{where}: textured materials need uvs")
        for name, a in (("vertices", v), ("faces", f), ("normals", n), ("face_material", fm)):
            if a is getattr(self, name) and a.flags.writeable:
                a = a.copy()  # the caller's array stays theirs (and writeable)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "up", _unit(self.up, f"{where} up"))
        object.__setattr__(self, "materials", tuple(self.materials))
        object.__setattr__(self, "lights", tuple(self.lights))
        object.__setattr__(self, "paths", MappingProxyType(dict(self.paths)))
        object.__setattr__(self, "shapes", tuple(self.shapes))
        self._check_shapes(where)

        if self.animation is not None:
            try:
                self.animation.check(self)
            except ValueError as e:
                raise ValueError(f"{where}: {e}") from None

    # ------------------------------------------------------------------ time
    @property
    def is_animated(self) -> bool:
        """Whether anything in the scene moves over time."""
        return self.animation is not None

    def at(self, t: float) -> Scene:
        """The scene at time ``t`` (seconds): an ordinary immutable Scene whose vertices, normals
        and lights are those of that moment (see :mod:`icbtool.scene.animation`). A static scene
        is returned as it is.

        Raises:
            ValueError: a non-finite ``t``.
        """
        if not math.isfinite(float(t)):
            raise ValueError(f"scene '{self.name}': time must be finite, got {t}")
        if self.animation is None or float(t) == self.time:
            return self
        return self.animation.apply(self, float(t))

    def _check_shapes(self, where: str) -> None:
        taken = np.zeros(len(self.faces), bool)
        for sh in self.shapes:
            if not isinstance(sh, AnalyticShape):
                raise ValueError(f"{where}: shapes must be AnalyticShape, got {type(sh).__name__}")
            a, b = sh.faces
            if b > len(self.faces):
                raise ValueError(
                    f"{where}: shape '{sh.name}' faces {a}..{b - 1} lie beyond the "
                    f"{len(self.faces)} faces"
                )
            if taken[a:b].any():
                raise ValueError(f"{where}: shape '{sh.name}' shares faces with another shape")
            taken[a:b] = True
            if not 0 <= sh.material < len(self.materials):
                raise ValueError(f"{where}: shape '{sh.name}' material {sh.material} out of range")
            if self.materials[sh.material].is_textured:
                raise ValueError(
                    f"{where}: shape '{sh.name}' has a textured material (analytic shapes take "
                    "untextured ones; keep a textured shape as a mesh)"
                )

    # ------------------------------------------------------------------ derived
    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 axis-aligned bounds [min, max]."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)]).astype(np.float64)

    @property
    def diagonal(self) -> float:
        """Length of the bounding box diagonal."""
        b = self.bounds
        return float(np.linalg.norm(b[1] - b[0]))

    @property
    def n_triangles(self) -> int:
        return len(self.faces)

    @property
    def has_textures(self) -> bool:
        return any(m.is_textured for m in self.materials)

    @property
    def emissive_faces(self) -> np.ndarray:
        """(E,) indices of faces with an emissive material."""
        emissive = np.array([m.is_emissive for m in self.materials])
        return np.flatnonzero(emissive[self.face_material])

    @property
    def face_normals(self) -> np.ndarray:
        """(F, 3) float32 unit geometric normals (zero for degenerate faces)."""
        return derived(self, "face_normals", lambda: self._face_geometry()[0])

    @property
    def face_areas(self) -> np.ndarray:
        """(F,) float64 triangle areas."""
        return derived(self, "face_areas", lambda: self._face_geometry()[1])

    def _face_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """(face normals, face areas) from one pass over the faces' cross products (both are
        cached: whoever needs one, the tracer for one, needs the other)."""
        n = self._face_cross()
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        areas = _readonly(0.5 * ln[:, 0])
        normals = _readonly(np.where(ln > 0, n / np.maximum(ln, 1e-300), 0).astype(np.float32))
        del n
        derived(self, "face_areas", lambda: areas)
        derived(self, "face_normals", lambda: normals)
        return normals, areas

    def _face_cross(self) -> np.ndarray:
        return _face_cross_chunked(self.vertices, self.faces)

    def lights_of(self, kind: str) -> list[Light]:
        """The lights of one kind: 'directional', 'point', 'spot' or 'area'."""
        return [light for light in self.lights if light.kind == kind]

    @property
    def content_hash(self) -> str:
        """SHA-256 (hex) of geometry, materials, lights and sky: equal hash, same rendering."""
        return derived(self, "content_hash", self._content_hash)

    def _content_hash(self) -> str:
        h = hashlib.sha256()
        for a in (self.vertices, self.faces, self.normals, self.face_material):
            h.update(np.ascontiguousarray(a).tobytes())
        if self.uvs is not None:
            h.update(self.uvs.tobytes())
        for m in self.materials:
            h.update(m.name.encode())
            h.update(m.albedo.tobytes())
            h.update(m.emission.tobytes())
            if m.texture is not None:
                h.update(np.ascontiguousarray(m.texture).tobytes())
            if m.bsdf is not None:
                from icbtool.scene.bsdf import fingerprint

                h.update(fingerprint(m.bsdf))
        h.update(self.light_hash.encode())
        for sh in self.shapes:  # none: the hash is as before shapes existed (stores stay valid)
            h.update(repr((sh.kind, sh.faces, sh.material, sh.flip_normals)).encode())
            h.update(np.round(sh.world_from_local, 9).tobytes())
        return h.hexdigest()

    @property
    def light_hash(self) -> str:
        """SHA-256 (hex, 16 chars) of the light setup (lights + sky, an environment map's
        texels included) alone."""
        return derived(self, "light_hash", self._light_hash)

    def _light_hash(self) -> str:
        h = hashlib.sha256()
        for light in self.lights:
            h.update(repr(_light_key(light)).encode())
        if self.sky is not None:
            h.update(repr(_light_key(self.sky)).encode())
        return h.hexdigest()[:16]

    def __repr__(self) -> str:
        return (
            f"Scene('{self.name}', {len(self.faces)} triangles, {len(self.materials)} materials, "
            f"{len(self.lights)} lights, sky={'yes' if self.sky else 'no'}, "
            f"paths={sorted(self.paths)})"
        )


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


#: A Sky's environment-map fields: left out of the light hash of a sky without a map.
_ENVMAP_FIELDS = ("envmap", "envmap_scale", "world_from_map")


def _light_key(obj: Any) -> tuple:
    items = []
    for k, v in sorted(vars(obj).items()):
        if (k, v) in (("shape", "parallelogram"), ("profile", "smoothstep")):
            continue  # the defaults: the light hashes of older scenes stay valid
        if k in _ENVMAP_FIELDS and getattr(obj, "envmap", 0) is None:
            continue  # a sky without a map hashes as before maps existed: stores stay valid
        if isinstance(v, np.ndarray) and v.size > 64:  # an envmap: its content's digest
            v = ("sha256", v.shape, hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest())
        elif isinstance(v, np.ndarray):
            v = tuple(np.round(v.astype(np.float64), 9).tolist())
        items.append((k, v))
    return (type(obj).__name__, tuple(items))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 area-weighted vertex normals; vertices used by no face get +up (0, 1, 0).

    Each vertex sums its faces' (unnormalised) normals in float64, corner by corner (first
    corners in face order, then second, then third).
    """
    faces = np.asarray(faces)
    fn = _face_cross_chunked(np.asarray(vertices), faces)
    # np.bincount adds in input order from 0, as np.add.at does, at a fraction of the time
    idx = np.ascontiguousarray(faces.T).reshape(-1)
    vn = np.empty((len(vertices), 3))
    for c in range(3):
        vn[:, c] = np.bincount(idx, weights=np.tile(fn[:, c], 3), minlength=len(vertices))
    del fn
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(ln > 1e-30, vn / np.maximum(ln, 1e-300), np.array([0.0, 1.0, 0.0]))
    return vn.astype(np.float32)


def fill_vertex_normals(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, missing: np.ndarray
) -> None:
    """Set ``normals[missing]`` to :func:`vertex_normals` (in place), computing them from the
    faces that touch a missing vertex only: the same values as the whole mesh's
    ``vertex_normals(vertices, faces)[missing]`` (each vertex sums the same faces in the same
    order), without the whole mesh's work when most normals come from the file.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
        normals: (V, 3) float32, written in place.
        missing: (V,) bool, the rows to compute.
    """
    if not missing.any():
        return
    touching = faces if missing.all() else faces[missing[faces].any(axis=1)]
    normals[missing] = vertex_normals(vertices, touching)[missing]


#: Faces per chunk of the float64 per-face arithmetic on large meshes (bounds its memory).
FACE_CHUNK = 1 << 18


def _face_cross_chunked(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64 ``cross(v1 - v0, v2 - v0)`` per face, computed in chunks of
    :data:`FACE_CHUNK` faces (the (F, 3, 3) float64 corner array never exists whole)."""
    out = np.empty((len(faces), 3))
    for s in range(0, len(faces), FACE_CHUNK):
        tri = vertices[faces[s : s + FACE_CHUNK]].astype(np.float64)
        out[s : s + FACE_CHUNK] = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return out


class SceneBuilder:
    """Accumulates meshes, materials and lights, then builds one merged :class:`Scene`.

    Example:
        >>> b = SceneBuilder("demo")
        >>> white = b.material("white", albedo=(0.8, 0.8, 0.8))
        >>> b.add_quad((-1, 0, -1), (2, 0, 0), (0, 0, 2), white)  # doctest: +SKIP
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._materials: list[Material] = []
        self._by_name: dict[str, int] = {}
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, int]] = []
        self.lights: list[Light] = []
        self.sky: Sky | None = None

    def material(self, name: str, **kwargs: Any) -> int:
        """Add a :class:`Material` (or return the index of an existing one of that name)."""
        if name in self._by_name:
            return self._by_name[name]
        return self.add_material(Material(name, **kwargs))

    def add_material(self, material: Material) -> int:
        name = material.name
        while name in self._by_name:
            name = name + "_"
        if name != material.name:
            material = dataclasses.replace(material, name=name)
        self._materials.append(material)
        self._by_name[name] = len(self._materials) - 1
        return len(self._materials) - 1

    def add_mesh(
        self,
        vertices: Any,
        faces: Any,
        material: int,
        normals: Any | None = None,
        uvs: Any | None = None,
    ) -> None:
        """Add triangles (vertices (N, 3), faces (M, 3)) with one material index."""
        v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        n = vertex_normals(v, f) if normals is None else np.asarray(normals, np.float32)
        uv = None if uvs is None else np.asarray(uvs, np.float32).reshape(-1, 2)
        if not (0 <= material < len(self._materials)):
            raise ValueError(f"unknown material index {material}")
        self._parts.append((v, f, n, uv, material))

    def add_quad(self, corner: Any, edge_u: Any, edge_v: Any, material: int) -> None:
        """Add the parallelogram ``corner + s*edge_u + t*edge_v`` facing ``cross(edge_u, edge_v)``,
        with flat normals and uvs (0,0)..(1,1)."""
        c, u, v = (np.asarray(x, np.float64) for x in (corner, edge_u, edge_v))
        verts = np.stack([c, c + u, c + u + v, c + v])
        n = np.cross(u, v)
        n = n / np.linalg.norm(n)
        uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        self.add_mesh(verts, [[0, 1, 2], [0, 2, 3]], material, np.tile(n, (4, 1)), uvs)

    def add_box(self, center: Any, size: Any, material: int, rotation_y_deg: float = 0.0) -> None:
        """Add a closed box (outward faces, flat normals) rotated about the y axis."""
        c = np.asarray(center, np.float64)
        hx, hy, hz = np.asarray(size, np.float64) / 2
        a = math.radians(rotation_y_deg)
        rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        faces = [  # (corner, edge_u, edge_v) in the box frame, outward normals
            ((-hx, -hy, hz), (2 * hx, 0, 0), (0, 2 * hy, 0)),
            ((hx, -hy, -hz), (-2 * hx, 0, 0), (0, 2 * hy, 0)),
            ((hx, -hy, hz), (0, 0, -2 * hz), (0, 2 * hy, 0)),
            ((-hx, -hy, -hz), (0, 0, 2 * hz), (0, 2 * hy, 0)),
            ((-hx, hy, hz), (2 * hx, 0, 0), (0, 0, -2 * hz)),
            ((-hx, -hy, -hz), (2 * hx, 0, 0), (0, 0, 2 * hz)),
        ]
        for corner, eu, ev in faces:
            self.add_quad(
                c + rot @ np.array(corner), rot @ np.array(eu), rot @ np.array(ev), material
            )

    def add_area_light(self, light: AreaLight) -> None:
        """Add an area light: its emissive polygon goes into the mesh, the light into ``lights``."""
        m = self.add_material(
            Material(f"emitter:{light.name}", albedo=np.zeros(3), emission=light.radiance)
        )
        if light.shape == "parallelogram":
            self.add_quad(light.corner, light.edge_u, light.edge_v, m)
        else:
            verts = light.vertices
            uvs = np.array([[0, 0], [1, 0], [0, 1]], np.float32)
            self.add_mesh(verts, light.triangles, m, np.tile(light.normal, (3, 1)), uvs)
        self.lights.append(light)

    def build(self, **kwargs: Any) -> Scene:
        """Merge everything into a :class:`Scene` (``kwargs`` go to the Scene constructor)."""
        if not self._parts:
            raise ValueError(f"scene '{self.name}' is empty: no geometry was added")
        offs = np.cumsum([0] + [len(p[0]) for p in self._parts])
        any_uv = any(p[3] is not None for p in self._parts)
        verts = np.concatenate([p[0] for p in self._parts])
        faces = np.concatenate([p[1] + o for p, o in zip(self._parts, offs[:-1])])
        normals = np.concatenate([p[2] for p in self._parts])
        fm = np.concatenate([np.full(len(p[1]), p[4], np.int32) for p in self._parts])
        uvs = None
        if any_uv:
            uvs = np.concatenate(
                [
                    p[3] if p[3] is not None else np.zeros((len(p[0]), 2), np.float32)
                    for p in self._parts
                ]
            )
        kwargs.setdefault("lights", self.lights)
        kwargs.setdefault("sky", self.sky)
        return Scene(
            name=self.name,
            vertices=verts,
            faces=faces,
            normals=normals,
            face_material=fm,
            materials=self._materials,
            uvs=uvs,
            **kwargs,
        )
