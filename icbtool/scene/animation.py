"""Time in scenes: keyframed lights and rigidly moving meshes, and the scene at a time.

A :class:`~icbtool.scene.Scene` may carry an :class:`Animation`: tracks that give some of its
lights' parameters and some of its meshes' rigid placement as functions of the scene time ``t``
(seconds). ``scene.at(t)`` is the static scene at that time, an ordinary immutable Scene (its
arrays, lights and hashes are those of that moment), which every renderer takes as it is. A
scene without an animation is static: ``scene.at(t)`` is the scene itself.

Interpolation between keys:

* vectors and numbers (positions, intensities, irradiances, radiances, cone angles, translations):
  linear;
* unit directions (a directional or spot light's ``direction``): spherical linear (constant angular
  speed, so a setting sun moves evenly); two consecutive keys may not point in opposite
  directions (the arc between them would be undefined);
* rotations (a mesh's ``rotate``, written ``[axis_x, axis_y, axis_z, angle_deg]``): quaternion slerp
  along the shorter arc between consecutive keys.

Before the first key and after the last a value is held. A mesh moves rigidly about its ``pivot``
(default: the centre of its bounds as placed by its ``[[meshes]]`` table): at time ``t`` a point
``p`` of the placed mesh goes to ``R(t) (p - pivot) + pivot + translate(t)``, and its normals turn
with ``R(t)``. An area light's ``corner``, ``edges`` and ``radiance`` may be keyed: its polygon
in the mesh (the faces of its ``emitter:NAME`` material) and their emission follow. A mesh with
emissive faces of its own cannot move (its faces are area lights: key a light instead). What is
not handled: deforming meshes, materials or the sky changing over time, and cameras (they have
their own timed paths).

In a scene description (TOML) a light or a mesh takes an array of keys, each a table with ``t``
and the keyed fields:

.. code-block:: toml

    [[lights]]
    type = "point"
    position = [0.0, 1.9, 0.0]
    intensity = [5.0, 5.0, 5.0]
    keyframes = [{t = 0.0, position = [0.0, 1.9, 0.0]}, {t = 1.5, position = [0.6, 1.9, 0.2]}]

    [[meshes]]
    path = "box.obj"
    pivot = [0.0, 0.3, 0.0]             # optional
    keyframes = [{t = 0.0}, {t = 2.0, translate = [0.4, 0.0, 0.0], rotate = [0, 1, 0, 90]}]

Key times must be finite and strictly increasing. A mesh's key is a whole placement: a
``translate`` or ``rotate`` it does not give is zero (``{t = 0.0}`` is the mesh where its table
puts it). A light's key gives some of its fields: a field that only some keys give is
interpolated between the keys that give it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from icbtool.scene.types import Material, Scene

#: Light fields that may be keyed, by light kind (the rest describe what a light is, not its state).
KEYABLE_LIGHT_FIELDS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "directional": ("direction", "irradiance"),
        "point": ("position", "intensity"),
        "spot": ("position", "direction", "intensity", "inner_deg", "outer_deg"),
        "area": ("corner", "edge_u", "edge_v", "radiance"),
    }
)
#: Fields interpolated as unit directions (slerp).
_DIRECTIONS = frozenset({"direction"})
#: Fields of a mesh key.
MESH_KEY_FIELDS = ("translate", "rotate")


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Track:
    """One keyed quantity: values at strictly increasing times, interpolated in between.

    Attributes:
        times: (K,) float64 key times, strictly increasing, K >= 1.
        values: (K, D) float64 values (D = 1 for a number, 3 for a vector or direction, 4 for a
            rotation quaternion ``(w, x, y, z)``).
        kind: ``"linear"``, ``"direction"`` (slerp of unit vectors) or ``"rotation"`` (slerp of
            unit quaternions).
    """

    times: np.ndarray
    values: np.ndarray
    kind: str = "linear"

    def __post_init__(self) -> None:
        t = np.asarray(self.times, np.float64).reshape(-1)
        v = np.asarray(self.values, np.float64)
        v = v.reshape(len(t), -1) if v.size else v
        if len(t) == 0 or v.shape[0] != len(t):
            raise ValueError(f"a track needs K >= 1 times and K values, got {t.shape}, {v.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
            raise ValueError("track times and values must be finite (no NaN/Inf)")
        if np.any(np.diff(t) <= 0):
            raise ValueError(f"key times must be strictly increasing, got {t.tolist()}")
        if self.kind not in ("linear", "direction", "rotation"):
            raise ValueError(f"unknown track kind {self.kind!r}")
        if self.kind in ("direction", "rotation"):
            n = np.linalg.norm(v, axis=1, keepdims=True)
            if np.any(n < 1e-12):
                raise ValueError(f"a {self.kind} key must not be zero")
            v = v / n
            if self.kind == "rotation":  # the shorter arc between consecutive keys
                for i in range(1, len(v)):
                    if v[i] @ v[i - 1] < 0:
                        v[i] = -v[i]
            elif np.any(np.einsum("ij,ij->i", v[1:], v[:-1]) < -1 + 1e-9):
                raise ValueError("consecutive direction keys must not point in opposite directions")
        object.__setattr__(self, "times", _readonly(t))
        object.__setattr__(self, "values", _readonly(v))

    def at(self, t: float) -> np.ndarray:
        """(D,) the value at time ``t`` (held before the first and after the last key)."""
        ts, vs = self.times, self.values
        if t <= ts[0]:
            return vs[0].copy()
        if t >= ts[-1]:
            return vs[-1].copy()
        i = int(np.searchsorted(ts, t, side="right")) - 1
        a = (t - ts[i]) / (ts[i + 1] - ts[i])
        if self.kind == "linear":
            return (1 - a) * vs[i] + a * vs[i + 1]
        return _slerp(vs[i], vs[i + 1], a)


def _slerp(p: np.ndarray, q: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation between unit vectors ``p`` and ``q`` (not opposite)."""
    d = float(np.clip(p @ q, -1.0, 1.0))
    theta = math.acos(d)
    if theta < 1e-9:
        return p.copy()
    s = math.sin(theta)
    out = (math.sin((1 - a) * theta) * p + math.sin(a * theta) * q) / s
    return out / np.linalg.norm(out)


def quaternion_from_axis_angle(axis: Any, angle_deg: float) -> np.ndarray:
    """(4,) unit quaternion ``(w, x, y, z)`` of a rotation by ``angle_deg`` about ``axis``.

    Raises:
        ValueError: a zero or non-finite axis, or a non-finite angle.
    """
    ax = np.asarray(axis, np.float64).reshape(3)
    n = float(np.linalg.norm(ax))
    if not (np.isfinite(n) and n > 1e-12 and math.isfinite(angle_deg)):
        raise ValueError(f"rotation axis must be finite and non-zero, got {ax.tolist()}")
    h = math.radians(angle_deg) / 2
    return np.concatenate([[math.cos(h)], math.sin(h) * ax / n])


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of the unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True, eq=False)
class LightTrack:
    """Keyed parameters of one light.

    Attributes:
        index: the light's index in ``Scene.lights``.
        rest: the light as written (the fields that are not keyed keep its values).
        fields: track by field name (see :data:`KEYABLE_LIGHT_FIELDS`).
    """

    index: int
    rest: Any
    fields: Mapping[str, Track]

    def at(self, t: float) -> Any:
        """The light at time ``t``."""
        change = {}
        for name, tr in self.fields.items():
            v = tr.at(t)
            change[name] = float(v[0]) if len(v) == 1 else v
        return dataclasses.replace(self.rest, **change)

    def __post_init__(self) -> None:
        object.__setattr__(self, "fields", MappingProxyType(dict(self.fields)))


@dataclass(frozen=True, eq=False)
class MeshTrack:
    """A rigid motion of one mesh: the vertices ``[start, stop)`` of the scene.

    Attributes:
        name: the mesh's name (for messages).
        start: first vertex of the mesh in ``Scene.vertices``.
        stop: one past its last vertex.
        pivot: (3,) the point it rotates about.
        translate: (3,) translation track, or None (no translation).
        rotate: rotation quaternion track, or None (no rotation).
    """

    name: str
    start: int
    stop: int
    pivot: np.ndarray
    translate: Track | None = None
    rotate: Track | None = None

    def __post_init__(self) -> None:
        if not (0 <= self.start < self.stop):
            raise ValueError(f"mesh '{self.name}': bad vertex range [{self.start}, {self.stop})")
        p = np.asarray(self.pivot, np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"mesh '{self.name}': pivot must be finite, got {p.tolist()}")
        object.__setattr__(self, "pivot", _readonly(p))

    def transform(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """((3, 3) rotation, (3,) offset) at time ``t``: ``p -> R p + offset``."""
        rot = np.eye(3) if self.rotate is None else rotation_matrix(self.rotate.at(t))
        move = np.zeros(3) if self.translate is None else self.translate.at(t)
        return rot, self.pivot - rot @ self.pivot + move


@dataclass(frozen=True, eq=False)
class Animation:
    """What changes over time in a scene, relative to its rest state.

    The rest state is the scene as built from its description, before any key applies: the
    vertices and normals of the moving meshes and the keyed lights as written. :meth:`apply`
    gives the scene at a time from any scene that shares this animation (so
    ``scene.at(a).at(b)`` is ``scene.at(b)``); lights and materials that no track names are taken
    from that scene as they are.

    Attributes:
        lights: keyed lights.
        meshes: moving meshes (disjoint vertex ranges).
        rest_vertices: (V, 3) float32 vertices at rest.
        rest_normals: (V, 3) float32 normals at rest.
    """

    lights: tuple[LightTrack, ...] = ()
    meshes: tuple[MeshTrack, ...] = ()
    rest_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    rest_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))

    def __post_init__(self) -> None:
        object.__setattr__(self, "lights", tuple(self.lights))
        object.__setattr__(self, "meshes", tuple(self.meshes))
        for k in ("rest_vertices", "rest_normals"):
            a = np.array(getattr(self, k), np.float32)
            object.__setattr__(self, k, _readonly(a))
        spans = sorted((m.start, m.stop, m.name) for m in self.meshes)
        for (_, b, n1), (c, _, n2) in zip(spans, spans[1:]):
            if c < b:
                raise ValueError(f"moving meshes '{n1}' and '{n2}' share vertices")
        if spans and spans[-1][1] > len(self.rest_vertices):
            raise ValueError(f"mesh '{spans[-1][2]}' reaches past the scene's vertices")
        if len({lt.index for lt in self.lights}) != len(self.lights):
            raise ValueError("a light has more than one track")

    def check(self, scene: Scene) -> None:
        """Raise ValueError unless this animation fits ``scene`` (same vertex count, keyed
        lights where the tracks say)."""
        if len(self.rest_vertices) != len(scene.vertices):
            raise ValueError(
                f"the animation moves {len(self.rest_vertices)} vertices, the scene has "
                f"{len(scene.vertices)}"
            )
        for lt in self.lights:
            ok = lt.index < len(scene.lights)
            if not ok or scene.lights[lt.index].name != lt.rest.name:
                raise ValueError(
                    f"keyed light '{lt.rest.name}' is not light {lt.index} of the scene"
                )

    @property
    def key_times(self) -> np.ndarray:
        """(N,) sorted distinct times of every key (where the motion may change course)."""
        ts = [tr.times for lt in self.lights for tr in lt.fields.values()]
        ts += [tr.times for m in self.meshes for tr in (m.translate, m.rotate) if tr is not None]
        return np.unique(np.concatenate(ts)) if ts else np.zeros(0)

    def apply(self, scene: Scene, t: float) -> Scene:
        """The static scene at time ``t`` (``scene`` shares this animation)."""
        if not math.isfinite(t):
            raise ValueError(f"scene time must be finite, got {t}")
        v = self.rest_vertices.copy()
        n = self.rest_normals.copy()
        for m in self.meshes:
            rot, off = m.transform(t)
            sl = slice(m.start, m.stop)
            v[sl] = (v[sl].astype(np.float64) @ rot.T + off).astype(np.float32)
            n[sl] = (n[sl].astype(np.float64) @ rot.T).astype(np.float32)
        lights = list(scene.lights)
        mats = list(scene.materials)
        for lt in self.lights:
            light = lights[lt.index] = lt.at(t)
            if light.kind != "area":
                continue
            mi = [i for i, m in enumerate(mats) if m.name == f"emitter:{light.name}"]
            if not mi:
                raise ValueError(f"area light '{light.name}' has no emitter faces in the mesh")
            if "radiance" in lt.fields:
                m = mats[mi[0]]
                mats[mi[0]] = Material(m.name, m.albedo, light.radiance)
            if {"corner", "edge_u", "edge_v"} & set(lt.fields):
                ids = np.unique(scene.faces[scene.face_material == mi[0]])
                if len(ids) != len(light.vertices):
                    raise ValueError(
                        f"area light '{light.name}': its polygon has {len(light.vertices)} "
                        f"corners, its faces {len(ids)} vertices"
                    )
                v[ids] = light.vertices
                n[ids] = light.normal
        return dataclasses.replace(
            scene, vertices=v, normals=n, lights=lights, materials=mats, time=float(t)
        )


def parse_keys(
    raw: Any, allowed: Sequence[str], where: str
) -> tuple[np.ndarray, dict[str, list[tuple[float, Any]]]]:
    """Check a ``keyframes`` array and split it by field.

    Args:
        raw: the array of key tables as read from the file.
        allowed: the fields a key may give besides ``t``.
        where: names the file and the table, for messages.

    Returns:
        ((K,) key times, {field: [(t, value), ...]}).

    Raises:
        ValueError: not an array of tables, a missing or non-finite ``t``, unsorted times, an
            unknown field (all with ``where`` and the key's number).
    """
    if not isinstance(raw, list) or not raw:
        raise ValueError(f"{where}: keyframes must be a non-empty array of tables")
    times: list[float] = []
    by_field: dict[str, list[tuple[float, Any]]] = {}
    for i, key in enumerate(raw):
        at = f"{where}: keyframes[{i}]"
        if not isinstance(key, dict) or "t" not in key:
            raise ValueError(f"{at}: a key is a table with a time 't', got {key!r}")
        t = key["t"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
            raise ValueError(f"{at}: t must be a finite number, got {t!r}")
        if times and t <= times[-1]:
            raise ValueError(f"{at}: key times must be strictly increasing ({times[-1]} then {t})")
        times.append(float(t))
        unknown = sorted(set(key) - {"t"} - set(allowed))
        if unknown:
            raise ValueError(f"{at}: unknown field(s) {unknown}; keyable here: {sorted(allowed)}")
        for name in allowed:
            if name in key:
                by_field.setdefault(name, []).append((float(t), key[name]))
    return np.asarray(times), by_field


def _track(pairs: list[tuple[float, Any]], kind: str, dim: int, at: str) -> Track:
    try:
        vals = np.asarray([v for _, v in pairs], np.float64).reshape(len(pairs), dim)
    except (ValueError, TypeError):
        raise ValueError(
            f"{at}: each value must be {dim} number(s), got {[v for _, v in pairs]!r}"
        ) from None
    try:
        return Track(np.asarray([t for t, _ in pairs]), vals, kind)
    except ValueError as e:
        raise ValueError(f"{at}: {e}") from None


def light_track(raw: Any, light: Any, index: int, where: str) -> LightTrack:
    """The :class:`LightTrack` of a light's ``keyframes`` array (see the module docstring).

    Every key must give a valid light: the light is built at each key time, so a value its type
    refuses (a negative intensity, inner_deg >= outer_deg) is reported with the key.

    Raises:
        ValueError: a bad key (names ``where``, the key and the field).
    """
    allowed = KEYABLE_LIGHT_FIELDS[light.kind]
    _, by_field = parse_keys(raw, allowed, where)
    if not by_field:
        raise ValueError(f"{where}: keyframes key nothing; keyable: {list(allowed)}")
    tracks = {}
    for name, pairs in by_field.items():
        dim = np.asarray(getattr(light, name), np.float64).size
        kind = "direction" if name in _DIRECTIONS else "linear"
        tracks[name] = _track(pairs, kind, dim, f"{where}: keyframes field '{name}'")
    out = LightTrack(index, light, tracks)
    for t in sorted({t for pairs in by_field.values() for t, _ in pairs}):
        try:
            out.at(t)
        except (ValueError, TypeError) as e:
            raise ValueError(f"{where}: keyframes at t = {t}: {e}") from None
    return out


def mesh_track(raw: Any, name: str, start: int, stop: int, pivot: Any, where: str) -> MeshTrack:
    """The :class:`MeshTrack` of a mesh's ``keyframes`` array (see the module docstring): every
    key is a whole rigid placement (a missing ``translate`` is zero, a missing ``rotate`` none).

    Raises:
        ValueError: a bad key (names ``where``, the key and the field).
    """
    times, by_field = parse_keys(raw, MESH_KEY_FIELDS, where)
    given = {name: dict(pairs) for name, pairs in by_field.items()}
    translate = rotate = None
    if "translate" in given:
        moves = [(t, given["translate"].get(t, (0.0, 0.0, 0.0))) for t in times]
        translate = _track(moves, "linear", 3, f"{where}: keyframes 'translate'")
    if "rotate" in given:
        quats = []
        for t in times:
            v = given["rotate"].get(t, (1.0, 0.0, 0.0, 0.0))
            try:
                ax = np.asarray(v, np.float64).reshape(4)
                quats.append((t, quaternion_from_axis_angle(ax[:3], float(ax[3]))))
            except (ValueError, TypeError) as e:
                raise ValueError(
                    f"{where}: keyframes 'rotate' at t = {t}: [axis_x, axis_y, axis_z, angle_deg] "
                    f"with a non-zero finite axis, got {v!r} ({e})"
                ) from None
        rotate = _track(quats, "rotation", 4, f"{where}: keyframes 'rotate'")
    return MeshTrack(name, start, stop, np.asarray(pivot, np.float64), translate, rotate)


def animate(
    scene: Scene,
    lights: Sequence[LightTrack] = (),
    meshes: Sequence[MeshTrack] = (),
    t: float = 0.0,
) -> Scene:
    """``scene`` (its current state taken as the rest state) with an animation, at time ``t``.

    Args:
        scene: a static scene.
        lights: keyed lights (indices into ``scene.lights``).
        meshes: moving meshes (vertex ranges of ``scene``).
        t: the time of the returned scene.

    Returns:
        The animated scene at ``t``; ``.at(t2)`` gives it at any other time.
    """
    anim = Animation(tuple(lights), tuple(meshes), scene.vertices, scene.normals)
    return anim.apply(dataclasses.replace(scene, animation=anim), t)
