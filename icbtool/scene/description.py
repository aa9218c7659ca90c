"""Scene description files (TOML): a mesh plus lights, sky, camera intrinsics and named paths.

Parsed with the standard library's ``tomllib``; every table accepts only the keys listed below,
anything else is an error naming the key and the file. Relative paths are relative to the
description file; ``${VAR}`` and ``${VAR:-default}`` expand environment variables.

.. code-block:: toml

    [scene]
    name = "sponza"                     # default: the file stem
    mesh = "${ICBTOOL_SPONZA:-../../../shared/scenes/sponza}/sponza_textured.obj"
                                        # optional when [[meshes]] are given
    scale = 1.0                         # file units -> metres
    up_axis = "y"                       # the file's up axis: "y", "z" or "x" (rotated to +y)
    translation = [0.0, 0.0, 0.0]       # after scaling
    flip_v = false                      # uv origin at the image's top-left in this file
    textures = true                     # decode texture images
    file_lights = true                  # keep the mesh file's own lights (glTF
                                        #   KHR_lights_punctual) besides [[lights]]

    [[meshes]]                          # any number of further meshes, merged with [scene] mesh
    path = "props/chair.obj"            # required; relative to this file, ${VAR} expanded
    scale = 1.0                         # also up_axis, translation, flip_v, textures (as above)
    transform = [[1, 0, 0, 2], [0, 1, 0, 0], [0, 0, 1, -1], [0, 0, 0, 1]]
                                        # 4x4 world_from_file (row-major, rows or 16 numbers),
                                        #   applied after scale, up axis and translation
    name = "chair"                      # prefix of its material names on a clash (default: stem)
    material = { albedo = [0.5, 0.5, 0.5] }        # overrides every material of this mesh
    materials = { seat = { albedo = [0.6, 0.1, 0.1], emission = [0, 0, 0] } }
                                        # overrides by material name (an unknown name: error)
    keyframes = [{t = 0.0}, {t = 2.0, translate = [0.5, 0, 0], rotate = [0, 1, 0, 90]}]
                                        # optional rigid motion over time (seconds); rotate is
                                        #   [axis_x, axis_y, axis_z, angle_deg] about pivot
    pivot = [2.0, 0.5, -1.0]            # default: the centre of the placed mesh's bounds

    [camera]                            # intrinsics of the default camera and of every path
    fov_y_deg = 60.0
    height = 256
    width = 256

    [[lights]]                          # any number; type: directional | point | spot | area
    type = "directional"
    direction = [0.4, -0.9, 0.15]       # the way the light travels
    irradiance = [9.0, 8.5, 7.5]        # W/m^2
    # point: position, intensity; spot: position, direction, intensity, inner_deg, outer_deg;
    # area: corner, edge_u, edge_v, radiance (emits towards cross(edge_u, edge_v)); all: name
    keyframes = [{t = 0.0, direction = [0.4, -0.9, 0.15]}, {t = 3.0, direction = [0.9, -0.2, 0]}]
                                        # optional: fields over time (see
                                        #   icbtool.scene.animation); the scene loads at t = 0

    [sky]                               # optional; type: uniform (zenith) | gradient | envmap
    type = "gradient"
    zenith = [0.3, 0.45, 0.8]
    horizon = [0.7, 0.75, 0.8]
    ground = [0.2, 0.18, 0.15]
    # envmap: map = "sky.exr" (EXR or Radiance .hdr, lat-long, relative to this file),
    # scale = 1.0, rotation = [axis_x, axis_y, axis_z, angle_deg] or a 3x3 matrix (rows), map
    # space to world (Mitsuba's envmap convention: map +y is up)

    [default_camera]                    # optional; also fov_y_deg, height, width, up
    eye = [-10.0, 1.8, 0.0]
    target = [10.0, 4.0, 0.0]
    # a thin lens (depth of field in `icbtool trace`; the ICB pipeline renders its pinhole):
    # aperture_radius = 0.05 (world units), focus_distance (default: the target's depth)

    [paths.train]                       # any number of named paths; type: flythrough | orbit |
    type = "flythrough"                 #   random_walk; each may set fov_y_deg, image_height,
                                        #   image_width (``height`` is the orbit's parameter)
    waypoints = [[-10, 1.7, 0], [10, 1.7, 0]]
    targets = [[0, 1.7, 0], [20, 1.7, 0]]   # optional
    n = 150
    speed = 1.4
    # orbit: center, radius, height, n, duration_s, start_deg, sweep_deg, look_height, up
    # random_walk: n, seed, speed, dt, height_range, clearance, lookahead, turn_rate_deg,
    #   pitch_range_deg, max_floor_step, start (see icbtool.scene.walk.random_walk)
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.scene.animation import LightTrack, animate, light_track, mesh_track
from icbtool.scene.types import (
    LIGHT_TYPES,
    AreaLight,
    Light,
    Material,
    Scene,
    Sky,
    light_parameters,
)
from icbtool.scene.validate import SceneError, check_file

#: [scene] keys passed on to :func:`icbtool.scene.mesh.load_mesh` (also build() overrides).
_MESH_KEYS = ("scale", "up_axis", "translation", "flip_v", "textures")
_SCENE_KEYS = {"name", "mesh", "file_lights", *_MESH_KEYS}
_MESHES_KEYS = {
    "path",
    "name",
    "transform",
    "material",
    "materials",
    "keyframes",
    "pivot",
    *_MESH_KEYS,
}
_MATERIAL_KEYS = {"albedo", "emission"}
_CAMERA_KEYS = {"fov_y_deg", "height", "width"}
_TOP_KEYS = {"scene", "meshes", "camera", "lights", "sky", "default_camera", "paths"}
_LIGHT_KEYS = {kind: light_parameters(kind) for kind in LIGHT_TYPES}
_SKY_KEYS = {"type", "zenith", "horizon", "ground", "up"}
_ENVMAP_KEYS = {"type", "map", "scale", "rotation"}
#: A thin lens (rendered by icbtool trace; the ICB pipeline renders its pinhole).
_LENS_KEYS = {"aperture_radius", "focus_distance"}
_DEFAULT_CAMERA_KEYS = {"eye", "target", "up"} | _CAMERA_KEYS | _LENS_KEYS
#: Per-path intrinsics keys (``height`` is an orbit parameter, so image sizes are spelled out).
_PATH_CAMERA_KEYS = {"fov_y_deg": "fov_y_deg", "image_height": "height", "image_width": "width"}
_PATH_KEYS = {
    "flythrough": ({"waypoints"}, {"targets", "n", "speed", "up"}),
    "orbit": (
        {"center", "radius", "height"},
        {"n", "duration_s", "start_deg", "sweep_deg", "look_height", "up"},
    ),
    "random_walk": (
        {"n", "seed"},
        {
            "speed",
            "dt",
            "height_range",
            "clearance",
            "lookahead",
            "turn_rate_deg",
            "pitch_range_deg",
            "max_floor_step",
            "start",
        },
    ),
}
#: Keyword arguments accepted by :meth:`SceneDescription.build`.
BUILD_OVERRIDES = (
    "name",
    "mesh",
    *_MESH_KEYS,
    "fov_y_deg",
    "height",
    "width",
    "lights",
    "sky",
    "with_paths",
)

_ENV = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


def expand_env(text: str, where: str) -> str:
    """Expand ``${VAR}`` / ``${VAR:-default}`` (an empty variable counts as unset).

    Raises:
        SceneError: a variable without default is unset.
    """

    def sub(m: re.Match) -> str:
        val = os.environ.get(m.group(1))
        if val:
            return val
        if m.group(2) is not None:
            return m.group(2)
        raise SceneError(f"{where}: environment variable {m.group(1)} is not set (no default)")

    return _ENV.sub(sub, text)


def _sky(table: Any, path: Path, where: str) -> Sky:
    """The [sky] table: a uniform or gradient sky, or an environment map (``type = "envmap"``)."""
    kind = table.get("type", "uniform") if isinstance(table, dict) else None
    if kind != "envmap":
        s = _check_keys(table, _SKY_KEYS, where, "sky", {"zenith"})
        try:
            return Sky(
                zenith=s["zenith"],
                horizon=s.get("horizon"),
                ground=s.get("ground"),
                kind=s.get("type", "uniform"),
                up=s.get("up", (0.0, 1.0, 0.0)),
            )
        except (ValueError, TypeError) as e:
            raise SceneError(f"{where}: [sky]: {e}") from None
    s = _check_keys(table, _ENVMAP_KEYS, where, "sky", {"map"})
    if not isinstance(s["map"], str) or not s["map"]:
        raise SceneError(f"{where}: [sky] map must be a file name, got {s['map']!r}")
    m = Path(s["map"]).expanduser()
    if not m.is_absolute():
        m = (path.parent / m).resolve()
    try:
        rot = envmap_rotation(s.get("rotation"))
        return Sky.from_envmap(m, scale=s.get("scale", 1.0), world_from_map=rot)
    except FileNotFoundError:
        raise SceneError(f"{where}: [sky] map {str(m)!r} not found") from None
    except (ValueError, TypeError, OSError) as e:
        raise SceneError(f"{where}: [sky] map {str(m)!r}: {e}") from None


def envmap_rotation(spec: Any) -> np.ndarray:
    """(3, 3) rotation of an environment map from ``[sky] rotation``: None (identity), an
    axis-angle ``[x, y, z, angle_deg]`` (as Mitsuba's ``<rotate>``), or a 3x3 matrix (rows).

    Raises:
        ValueError: any other shape, a zero axis, a non-finite value.
    """
    if spec is None:
        return np.eye(3)
    a = np.asarray(spec, dtype=np.float64)
    if a.shape == (3, 3) and np.all(np.isfinite(a)):
        return a
    if a.shape == (4,) and np.all(np.isfinite(a)):
        axis, ang = a[:3], math.radians(a[3])
        n = np.linalg.norm(axis)
        if n == 0:
            raise ValueError(f"rotation axis must not be zero, got {spec!r}")
        x, y, z = axis / n
        c, sn = math.cos(ang), math.sin(ang)
        k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
        return np.eye(3) * c + sn * k + (1 - c) * np.outer([x, y, z], [x, y, z])
    raise ValueError(
        f"rotation must be [axis_x, axis_y, axis_z, angle_deg] or a 3x3 matrix, got {spec!r}"
    )


def _check_keys(
    table: Any, allowed: set[str], where: str, section: str, required: set[str] = frozenset()
) -> dict:
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [{section}] must be a table, got {type(table).__name__}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SceneError(
            f"{where}: unknown key(s) {unknown} in [{section}]; allowed: {sorted(allowed)}"
        )
    missing = sorted(required - set(table))
    if missing:
        raise SceneError(f"{where}: [{section}] is missing required key(s) {missing}")
    return dict(table)


@dataclass(frozen=True)
class Intrinsics:
    """Camera intrinsics of a description (centred, square pixels)."""

    fov_y_deg: float = 60.0
    """Vertical field of view in degrees, in (0, 180)."""
    height: int = 256
    """Image height in pixels."""
    width: int = 256
    """Image width in pixels."""

    def __post_init__(self) -> None:
        if not (0 < float(self.fov_y_deg) < 180):
            raise ValueError(f"fov_y_deg must be in (0, 180), got {self.fov_y_deg}")
        for k in ("height", "width"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or not (1 <= v <= 32768):
                raise ValueError(f"{k} must be an integer in [1, 32768], got {v!r}")

    def camera(self):
        from icbtool.camera import Camera

        return Camera.from_fov(self.fov_y_deg, self.height, self.width)


@dataclass(frozen=True)
class MeshSpec:
    """One ``[[meshes]]`` entry of a description (see the module docstring)."""

    path: Path
    """The mesh file (absolute, environment variables expanded)."""
    name: str
    """Name used to tell its materials apart on a clash (default: the file stem)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments for :func:`icbtool.scene.mesh.load_mesh` (scale, up_axis, ...)."""
    world_from_file: np.ndarray | None = None
    """(4, 4) transform applied after ``options`` (None: identity)."""
    material: dict[str, Any] | None = None
    """Overrides (albedo, emission) of every material of the mesh."""
    materials: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Overrides (albedo, emission) by material name."""
    keyframes: list[dict[str, Any]] | None = None
    """Its rigid motion over time (``translate`` / ``rotate`` keys, see
    :mod:`icbtool.scene.animation`), or None (it stays where it is)."""
    pivot: tuple[float, float, float] | None = None
    """The point it rotates about (None: the centre of its bounds as placed)."""


@dataclass(frozen=True)
class SceneDescription:
    """A parsed scene description (see the module docstring for the file format)."""

    path: Path
    """The description file."""
    name: str
    """Scene name."""
    mesh: Path | None
    """The [scene] mesh file (absolute, environment variables expanded), or None when the
    description lists only [[meshes]]."""
    mesh_options: dict[str, Any]
    """Keyword arguments for :func:`icbtool.scene.mesh.load_mesh` (scale, up_axis, ...)."""
    intrinsics: Intrinsics = field(default_factory=Intrinsics)
    """Intrinsics of the default camera and the paths."""
    lights: tuple[Light, ...] = ()
    """Lights (area lights are added to the mesh on build)."""
    sky: Sky | None = None
    """Environment radiance, or None (black)."""
    default_camera: dict[str, Any] | None = None
    """The [default_camera] table, or None."""
    paths: dict[str, dict[str, Any]] = field(default_factory=dict)
    """The [paths.*] tables by name."""
    file_lights: bool = True
    """Keep the lights the mesh file itself declares (glTF KHR_lights_punctual) besides
    :attr:`lights`; False drops them."""
    meshes: tuple[MeshSpec, ...] = ()
    """The [[meshes]] entries, merged after the [scene] mesh."""
    light_tracks: tuple[LightTrack, ...] = ()
    """Keyed lights (``keyframes`` of [[lights]] entries; indices into :attr:`lights`)."""

    def build(self, **overrides: Any) -> Scene:
        """Load the mesh and assemble the Scene.

        Args:
            **overrides: replace description values: ``name``, ``mesh``, ``scale``, ``up_axis``,
                ``translation``, ``flip_v``, ``textures`` (mesh), ``fov_y_deg``, ``height``,
                ``width`` (intrinsics of the default camera and every path), ``lights`` (replace
                every light: the description's and the file's), ``sky``, and
                ``with_paths=False`` to skip building the camera paths.

        Raises:
            TypeError: an unknown override.
            SceneError, FileNotFoundError: as :func:`icbtool.scene.load`.
        """
        from icbtool.scene.mesh import load_mesh

        unknown = sorted(set(overrides) - set(BUILD_OVERRIDES))
        if unknown:
            raise TypeError(
                f"{self.path}: unknown override(s) {unknown}; allowed: {sorted(BUILD_OVERRIDES)}"
            )
        where = str(self.path)
        mesh_kw = dict(self.mesh_options)
        for k in _MESH_KEYS:
            if k in overrides:
                mesh_kw[k] = overrides[k]
        name = overrides.get("name", self.name)
        mesh = overrides.get("mesh", self.mesh)
        parts = []
        if mesh is not None:
            if not Path(mesh).exists():
                raise FileNotFoundError(f"{where}: mesh file not found: {mesh}")
            parts.append(load_mesh(Path(mesh), name=name, **mesh_kw))
        for spec in self.meshes:
            parts.append(_load_spec(spec, where))
        scene = parts[0] if len(parts) == 1 else merge_meshes(parts, name)
        own = list(overrides.get("lights", self.lights))  # their area quads join the mesh
        kept = list(scene.lights) if self.file_lights and "lights" not in overrides else []
        offsets = np.cumsum([0] + [len(part.vertices) for part in parts])
        scene = add_area_lights(scene, [lt for lt in own if isinstance(lt, AreaLight)])
        lights = kept + own
        scene = dataclasses.replace(
            scene, name=name, lights=lights, sky=overrides.get("sky", self.sky), source=where
        )
        scene = self._animate(scene, parts, offsets, len(kept), "lights" in overrides)
        try:
            intr = Intrinsics(
                float(overrides.get("fov_y_deg", self.intrinsics.fov_y_deg)),
                overrides.get("height", self.intrinsics.height),
                overrides.get("width", self.intrinsics.width),
            )
        except ValueError as e:
            raise SceneError(f"{where}: bad camera override: {e}") from None
        size_override = {k: overrides[k] for k in _CAMERA_KEYS if k in overrides}
        if self.default_camera is not None:
            scene = dataclasses.replace(
                scene,
                default_camera=_default_camera(self.default_camera, intr, size_override, where),
            )
        if overrides.get("with_paths", True):
            paths = {
                pname: _build_path(scene, pname, spec, intr, size_override, where)
                for pname, spec in self.paths.items()
            }
            scene = dataclasses.replace(scene, paths=paths)
        return scene

    def _animate(
        self, scene: Scene, parts: list[Scene], offsets: np.ndarray, n_kept: int, new_lights: bool
    ) -> Scene:
        """The scene at time 0 with the description's keyframes, or as it is without any."""
        first = 0 if self.mesh is None else 1  # parts[first + i] is self.meshes[i]
        where = str(self.path)
        moving = []
        for i, spec in enumerate(self.meshes):
            if spec.keyframes is None:
                continue
            part, start, stop = (
                parts[first + i],
                int(offsets[first + i]),
                int(offsets[first + i + 1]),
            )
            if any(m.is_emissive for m in part.materials):
                raise SceneError(
                    f"{where}: [[meshes]] {spec.name}: a mesh with emissive faces cannot move "
                    "(its faces are area lights); key a light instead"
                )
            b = part.bounds
            pivot = spec.pivot if spec.pivot is not None else (b[0] + b[1]) / 2
            moving.append(
                mesh_track(
                    spec.keyframes,
                    spec.name,
                    start,
                    stop,
                    pivot,
                    f"{where}: [[meshes]] {spec.name}",
                )
            )
        tracks = (
            []
            if new_lights
            else [dataclasses.replace(tr, index=tr.index + n_kept) for tr in self.light_tracks]
        )
        if not moving and not tracks:
            return scene
        return animate(scene, tracks, moving, 0.0)


def _load_spec(spec: MeshSpec, where: str) -> Scene:
    """One [[meshes]] entry loaded, transformed and with its material overrides."""
    from icbtool.scene.mesh import load_mesh

    if not spec.path.exists():
        raise FileNotFoundError(
            f"{where}: [[meshes]] {spec.name}: mesh file not found: {spec.path}"
        )
    s = load_mesh(spec.path, name=spec.name, **spec.options)
    if spec.world_from_file is not None:
        s = transform_scene(s, spec.world_from_file)
    if spec.material is None and not spec.materials:
        return s
    names = [m.name for m in s.materials]
    unknown = sorted(set(spec.materials) - set(names))
    if unknown:
        raise SceneError(
            f"{where}: [[meshes]] {spec.name}: no material(s) {unknown} in {spec.path.name}; "
            f"it has {names}"
        )
    mats = []
    for m in s.materials:
        change = {**(spec.material or {}), **spec.materials.get(m.name, {})}
        try:
            mats.append(dataclasses.replace(m, **change) if change else m)
        except (ValueError, TypeError) as e:
            raise SceneError(f"{where}: [[meshes]] {spec.name}: material '{m.name}': {e}") from None
    return dataclasses.replace(s, materials=mats)


def transform_scene(scene: Scene, world_from_file: np.ndarray) -> Scene:
    """The scene with its geometry and file lights mapped by a (4, 4) affine transform.

    Normals go through the inverse transpose; a mirroring transform (det < 0) reverses the face
    winding so that the geometric normals keep facing the same side.

    Raises:
        ValueError: a singular or non-finite transform.
    """
    m = np.asarray(world_from_file, np.float64)
    lin, t = m[:3, :3], m[:3, 3]
    det = float(np.linalg.det(lin)) if np.all(np.isfinite(m)) else 0.0
    if abs(det) < 1e-12:
        raise ValueError(f"transform must be finite and invertible, got {m.tolist()}")
    v = scene.vertices.astype(np.float64) @ lin.T + t
    n = scene.normals.astype(np.float64) @ np.linalg.inv(lin)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    f = scene.faces if det > 0 else scene.faces[:, ::-1]
    lights = []
    for lt in scene.lights:
        ch: dict[str, Any] = {}
        if hasattr(lt, "position"):
            ch["position"] = lin @ lt.position + t
        if hasattr(lt, "direction"):
            ch["direction"] = lin @ lt.direction
        lights.append(dataclasses.replace(lt, **ch) if ch else lt)
    shapes = [
        dataclasses.replace(sh, world_from_local=m @ sh.world_from_local) for sh in scene.shapes
    ]
    return dataclasses.replace(scene, vertices=v, normals=n, faces=f, lights=lights, shapes=shapes)


def merge_meshes(scenes: list[Scene], name: str) -> Scene:
    """One Scene of several (geometry, materials and file lights concatenated).

    A material whose name another mesh already uses is renamed ``<mesh name>:<material>``.
    """
    v, f, n, fm, uv, mats, lights, shapes = [], [], [], [], [], [], [], []
    any_uv = any(s.uvs is not None for s in scenes)
    offset = 0
    n_faces = 0
    names: set[str] = set()
    for s in scenes:
        base = len(mats)
        for m in s.materials:
            new = m.name if m.name not in names else f"{s.name}:{m.name}"
            while new in names:
                new += "_"
            names.add(new)
            mats.append(m if new == m.name else dataclasses.replace(m, name=new))
        v.append(s.vertices)
        f.append(s.faces.astype(np.int64) + offset)
        n.append(s.normals)
        fm.append(s.face_material + base)
        if any_uv:
            uv.append(s.uvs if s.uvs is not None else np.zeros((len(s.vertices), 2), np.float32))
        lights += list(s.lights)
        for sh in s.shapes:
            a, b = sh.faces
            fa = (a + n_faces, b + n_faces)
            shapes.append(dataclasses.replace(sh, material=sh.material + base, faces=fa))
        offset += len(s.vertices)
        n_faces += len(s.faces)
    return Scene(
        name=name,
        vertices=np.concatenate(v),
        faces=np.concatenate(f),
        normals=np.concatenate(n),
        face_material=np.concatenate(fm),
        materials=mats,
        uvs=np.concatenate(uv) if any_uv else None,
        lights=lights,
        source=scenes[0].source,
        shapes=shapes,
    )


def add_area_lights(scene: Scene, lights: list[AreaLight]) -> Scene:
    """A new Scene with each area light's emissive polygon appended to the mesh."""
    if not lights:
        return scene
    v, f, n, fm = [scene.vertices], [scene.faces], [scene.normals], [scene.face_material]
    uv = None if scene.uvs is None else [scene.uvs]
    mats = list(scene.materials)
    nv = len(scene.vertices)
    for lt in lights:
        mats.append(Material(f"emitter:{lt.name}", albedo=np.zeros(3), emission=lt.radiance))
        lv = lt.vertices
        v.append(lv.astype(np.float32))
        f.append(lt.triangles + nv)
        n.append(np.tile(lt.normal, (len(lv), 1)).astype(np.float32))
        fm.append(np.full(len(lt.triangles), len(mats) - 1, np.int32))
        if uv is not None:
            uv.append(np.array([[0, 0], [1, 0], [1, 1], [0, 1]][: len(lv)], np.float32))
        nv += len(lv)
    return Scene(
        name=scene.name,
        vertices=np.concatenate(v),
        faces=np.concatenate(f),
        normals=np.concatenate(n),
        face_material=np.concatenate(fm),
        materials=mats,
        uvs=None if uv is None else np.concatenate(uv),
        lights=list(scene.lights),
        sky=scene.sky,
        up=scene.up,
        source=scene.source,
        shapes=scene.shapes,  # the new faces come after theirs
    )


def _intr_for(spec: dict, intr: Intrinsics, size_override: dict, where: str, what: str, keys: dict):
    kw = {name: spec[k] for k, name in keys.items() if k in spec}
    kw.update(size_override)  # build() overrides win over per-path values
    try:
        return Intrinsics(
            float(kw.get("fov_y_deg", intr.fov_y_deg)),
            kw.get("height", intr.height),
            kw.get("width", intr.width),
        ).camera()
    except ValueError as e:
        raise SceneError(f"{where}: {what}: {e}") from None


def _default_camera(spec: dict, intr: Intrinsics, size_override: dict, where: str):
    from icbtool.camera import look_at_pose

    keys = {k: k for k in _CAMERA_KEYS}
    cam = _intr_for(spec, intr, size_override, where, "[default_camera]", keys)
    try:
        pose = look_at_pose(spec["eye"], spec["target"], spec.get("up", (0.0, 1.0, 0.0)))
        cam = cam.with_pose(pose)
        if "aperture_radius" in spec or "focus_distance" in spec:
            target_depth = float(np.linalg.norm(np.subtract(spec["target"], spec["eye"])))
            cam = dataclasses.replace(
                cam,
                aperture_radius=float(spec.get("aperture_radius", 0.0)),
                focus_distance=float(spec.get("focus_distance", target_depth)),
            )
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: [default_camera]: {e}") from None
    return cam


def _build_path(scene: Scene, pname: str, spec: dict, intr, size_override: dict, where: str):
    from icbtool.camera import CameraPath
    from icbtool.scene.walk import random_walk

    cam = _intr_for(spec, intr, size_override, where, f"[paths.{pname}]", _PATH_CAMERA_KEYS)
    kind = spec["type"]
    kw = {k: v for k, v in spec.items() if k not in set(_PATH_CAMERA_KEYS) | {"type"}}
    try:
        if kind == "flythrough":
            return CameraPath.flythrough(intrinsics=cam, name=pname, **kw)
        if kind == "orbit":
            return CameraPath.orbit(intrinsics=cam, name=pname, **kw)
        for k in ("height_range", "pitch_range_deg"):
            if k in kw:
                kw[k] = tuple(kw[k])
        return random_walk(scene, cam, name=pname, **kw)
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: [paths.{pname}] ({kind}): {e}") from None


def _light(spec: Any, i: int, where: str) -> Light:
    if not isinstance(spec, dict) or "type" not in spec:
        raise SceneError(f"{where}: [[lights]] entry {i} needs a 'type' ({sorted(_LIGHT_KEYS)})")
    kind = spec["type"]
    if kind not in _LIGHT_KEYS:
        raise SceneError(
            f"{where}: [[lights]] entry {i}: unknown type {kind!r}; one of {sorted(_LIGHT_KEYS)}"
        )
    req, opt = _LIGHT_KEYS[kind]
    kw = _check_keys(spec, set(req | opt | {"type"}), where, f"lights {i} ({kind})", set(req))
    kw.pop("type")
    cls = LIGHT_TYPES[kind]
    kw.setdefault("name", f"{kind}{i}")
    try:
        return cls(**kw)
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: [[lights]] entry {i} ({kind}): {e}") from None


def read_description(path: str | os.PathLike) -> SceneDescription:
    """Parse and validate a scene description file (the mesh is not loaded yet).

    Raises:
        FileNotFoundError: no such file.
        SceneError: TOML syntax error, unknown or missing keys, bad values (names the file).
    """
    p = check_file(path, (".toml",)).resolve()
    where = str(p)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{where}: not valid TOML: {e}") from None
    _check_keys(doc, _TOP_KEYS, where, "top level", {"scene"})
    sc = _check_keys(doc["scene"], _SCENE_KEYS, where, "scene")
    meshes = _read_meshes(doc.get("meshes", []), p, where)
    if "mesh" not in sc and not meshes:
        raise SceneError(f'{where}: no mesh: give [scene] mesh = "..." or [[meshes]] tables')
    mesh = None
    if "mesh" in sc:
        if not isinstance(sc["mesh"], str):
            raise SceneError(
                f"{where}: [scene] mesh must be a string path (several meshes: [[meshes]] tables "
                "with a path each)"
            )
        mesh = _mesh_path(sc["mesh"], p, where)
    mesh_options = {k: sc[k] for k in _MESH_KEYS if k in sc}
    file_lights = sc.get("file_lights", True)
    if not isinstance(file_lights, bool):
        raise SceneError(f"{where}: [scene] file_lights must be true or false, got {file_lights!r}")
    try:
        intr = Intrinsics(**_check_keys(doc.get("camera", {}), _CAMERA_KEYS, where, "camera"))
    except (ValueError, TypeError) as e:
        raise SceneError(f"{where}: [camera]: {e}") from None
    raw_lights = doc.get("lights", [])
    if not isinstance(raw_lights, list):
        raise SceneError(f"{where}: 'lights' must be an array of tables ([[lights]])")
    lights, light_tracks = [], []
    for i, spec in enumerate(raw_lights):
        keys = spec.pop("keyframes", None) if isinstance(spec, dict) else None
        lights.append(_light(spec, i, where))
        if keys is not None:
            at = f"{where}: [[lights]] entry {i} ({lights[-1].name})"
            try:
                light_tracks.append(light_track(keys, lights[-1], i, at))
            except ValueError as e:
                raise SceneError(str(e)) from None
    sky = None
    if "sky" in doc:
        sky = _sky(doc["sky"], p, where)
    default_camera = None
    if "default_camera" in doc:
        default_camera = _check_keys(
            doc["default_camera"],
            _DEFAULT_CAMERA_KEYS,
            where,
            "default_camera",
            {"eye", "target"},
        )
    paths = {}
    for pname, spec in _check_keys(
        doc.get("paths", {}), set(doc.get("paths", {})), where, "paths"
    ).items():
        if not isinstance(spec, dict) or spec.get("type") not in _PATH_KEYS:
            raise SceneError(
                f"{where}: [paths.{pname}] needs a 'type' in {sorted(_PATH_KEYS)}, got "
                f"{spec.get('type') if isinstance(spec, dict) else spec!r}"
            )
        req, opt = _PATH_KEYS[spec["type"]]
        paths[pname] = _check_keys(
            spec, req | opt | set(_PATH_CAMERA_KEYS) | {"type"}, where, f"paths.{pname}", req
        )
    return SceneDescription(
        path=p,
        name=sc.get("name", p.stem),
        mesh=mesh,
        mesh_options=mesh_options,
        intrinsics=intr,
        lights=tuple(lights),
        sky=sky,
        default_camera=default_camera,
        paths=paths,
        file_lights=file_lights,
        meshes=meshes,
        light_tracks=tuple(light_tracks),
    )


def _mesh_path(text: str, p: Path, where: str) -> Path:
    mesh = Path(expand_env(text, where)).expanduser()
    return mesh if mesh.is_absolute() else (p.parent / mesh).resolve()


def _read_meshes(raw: Any, p: Path, where: str) -> tuple[MeshSpec, ...]:
    """The [[meshes]] tables (see the module docstring)."""
    if not isinstance(raw, list):
        raise SceneError(f"{where}: 'meshes' must be an array of tables ([[meshes]])")
    out = []
    for i, spec in enumerate(raw):
        section = f"meshes {i}"
        t = _check_keys(spec, _MESHES_KEYS, where, section, {"path"})
        if not isinstance(t["path"], str):
            raise SceneError(f"{where}: [[meshes]] entry {i}: path must be a string")
        path = _mesh_path(t["path"], p, where)
        name = t.get("name", path.stem)
        world = None
        if "transform" in t:
            try:
                world = np.asarray(t["transform"], np.float64).reshape(4, 4)
            except (ValueError, TypeError):
                raise SceneError(
                    f"{where}: [[meshes]] entry {i} ({name}): transform must be 4x4 numbers "
                    f"(4 rows of 4 or 16), got {t['transform']!r}"
                ) from None
            if not np.all(np.isfinite(world)) or abs(np.linalg.det(world[:3, :3])) < 1e-12:
                raise SceneError(
                    f"{where}: [[meshes]] entry {i} ({name}): transform must be finite and "
                    "invertible"
                )
            if not np.allclose(world[3], [0, 0, 0, 1]):
                raise SceneError(
                    f"{where}: [[meshes]] entry {i} ({name}): transform's last row must be "
                    f"[0, 0, 0, 1], got {world[3].tolist()}"
                )
        material = None
        if "material" in t:
            material = _check_keys(t["material"], _MATERIAL_KEYS, where, f"{section} material")
        materials = {}
        for mname, m in _check_keys(
            t.get("materials", {}), set(t.get("materials", {})), where, f"{section} materials"
        ).items():
            materials[mname] = _check_keys(m, _MATERIAL_KEYS, where, f"{section} materials.{mname}")
        options = {k: t[k] for k in _MESH_KEYS if k in t}
        pivot = None
        if "pivot" in t:
            try:
                pivot = tuple(float(x) for x in np.asarray(t["pivot"], np.float64).reshape(3))
            except (ValueError, TypeError):
                pivot = (math.nan,)
            if len(pivot) != 3 or not all(math.isfinite(x) for x in pivot):
                raise SceneError(
                    f"{where}: [[meshes]] entry {i} ({name}): pivot must be 3 finite numbers, "
                    f"got {t['pivot']!r}"
                )
        keys = t.get("keyframes")
        if keys is not None:  # checked now, so a bad key fails before any mesh is loaded
            try:
                mesh_track(
                    keys, str(name), 0, 1, pivot or (0.0, 0.0, 0.0), f"{where}: [[meshes]] {name}"
                )
            except ValueError as e:
                raise SceneError(str(e)) from None
        out.append(MeshSpec(path, str(name), options, world, material, materials, keys, pivot))
    return tuple(out)
