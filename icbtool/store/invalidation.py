"""Which stored records a scene change makes stale: scene states and the invalidation rule.

A record of an animated scene (:mod:`icbtool.scene.animation`) is rendered under one *state* of
the scene: its keyed lights and moving meshes at the scene time ``t``. This module gives

* :func:`state_id`: a compact id of that state (16 hex characters of a hash of every animated
  parameter at ``t``: the keyed lights' fields and the moving meshes' placements), equal for two
  times that look the same (before the first key, after the last, or on a hold);
* :func:`group_keys`: the store keys (``scene_hash``, ``light_hash``) that every state of an
  animated scene shares, so that a record made before a change is still *found* after it and the
  rule below decides whether it may serve. A static scene keeps its own hashes;
* :func:`state_tags` / :func:`record_state`: the state a record was rendered under, kept in its
  metadata's ``tags`` (``{"state": id, "scene_time": t}``), hence in the index and in the
  self-describing payload alike: no store format change, old stores read as before (their
  records have no state: static);
* :func:`scene_change`: what differs between two states of one scene (which lights, which meshes,
  and a world box holding the old and the new extent of everything that changed);
* :func:`is_affected`: the invalidation rule itself, on a record's *seen bounds*
  (:func:`seen_bounds`, the world box of the surfaces its camera sees).

The rule (conservative; docs/dynamic.md, "Design notes"): a change alters the GI of a record
unless the record's seen bounds lie farther than ``reach_m`` from the changed region (the box
of a moved mesh's old and new bounds; a keyed light's old and new extent). With ``reach_m`` None
(the default) every change reaches every record: light bounces through the whole of a closed
room, so nothing smaller is safe without knowing the scene. A finite reach is the user's
statement that what changes farther away does not matter (rooms behind walls, a large open
scene); it ignores light carried farther by bright bounces. A directional light, or anything the
rule cannot bound (a changed sky, a different animation), reaches everything.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: The state id of a static scene (and of records written before states existed).
STATIC_STATE = "static"


def state_id(scene: Any) -> str:
    """The id of the state an :class:`icbtool.scene.Scene` is in (see module docstring).

    Two moments of one animated scene get the same id iff every animated parameter (keyed light
    fields, moving meshes' rotation and offset) is the same, to 1e-9; a static scene is
    :data:`STATIC_STATE`.
    """
    anim = scene.animation
    if anim is None:
        return STATIC_STATE
    h = hashlib.sha256()
    for lt in anim.lights:
        light = scene.lights[lt.index]
        for name in sorted(lt.fields):
            v = np.round(np.asarray(getattr(light, name), np.float64), 9) + 0.0
            h.update(f"L{lt.index}.{name}".encode())
            h.update(v.tobytes())
    for m in anim.meshes:
        rot, off = m.transform(scene.time)
        h.update(f"M{m.start}:{m.stop}".encode())
        h.update((np.round(np.concatenate([rot.ravel(), off]), 9) + 0.0).tobytes())
    return h.hexdigest()[:16]


def group_keys(scene: Any) -> tuple[str, str]:
    """(scene_hash, light_hash) under which a store keeps the records of ``scene``: its own
    hashes for a static scene; for an animated one, keys shared by all its states (derived
    from its state at t = 0 and marked, so they never equal a static scene's)."""
    if scene.animation is None:
        return scene.content_hash, scene.light_hash
    base = scene.at(0.0)
    key = hashlib.sha256(f"animated:{base.content_hash}".encode()).hexdigest()
    return key, "animated:" + base.light_hash[:7]


def state_tags(scene: Any) -> dict[str, Any]:
    """The tags that mark a record of ``scene`` with its state (empty for a static scene)."""
    if scene.animation is None:
        return {}
    return {"state": state_id(scene), "scene_time": float(scene.time)}


def record_state(meta: Any) -> tuple[str, float | None]:
    """(state id, scene time) a record was rendered under, from its
    :class:`~icbtool.store.RecordMeta`; ``(STATIC_STATE, None)`` for a record without a state."""
    tags = meta.tags
    state = tags.get("state")
    t = tags.get("scene_time")
    if not isinstance(state, str) or not isinstance(t, (int, float)) or not math.isfinite(t):
        return STATIC_STATE, None
    return state, float(t)


@dataclass(frozen=True)
class Change:
    """What differs between two states of one scene.

    Attributes:
        lights: indices of the keyed lights whose parameters differ.
        meshes: names of the moving meshes whose placement differs.
        region: (2, 3) float64 world box [min, max] holding the old and the new extent of every
            changed light and mesh, or None when nothing changed or the change is unbounded.
        everywhere: the change cannot be bounded (a directional light, a different animation).
    """

    lights: tuple[int, ...] = ()
    meshes: tuple[str, ...] = ()
    region: np.ndarray | None = None
    everywhere: bool = False

    @property
    def empty(self) -> bool:
        """Nothing changed."""
        return not (self.lights or self.meshes or self.everywhere)


def _light_extent(light: Any) -> np.ndarray | None:
    """(N, 3) points whose box holds a light's emitting extent; None for a directional light."""
    if light.kind == "area":
        return np.asarray(light.vertices, np.float64).reshape(-1, 3)
    if light.kind in ("point", "spot"):
        return np.asarray(light.position, np.float64).reshape(1, 3)
    return None


def scene_change(before: Any, after: Any) -> Change:
    """What changed from scene state ``before`` to ``after`` (two moments of one scene).

    Args:
        before, after: :class:`icbtool.scene.Scene` s sharing one animation (``s.at(t)``).

    Returns:
        A :class:`Change`; ``everywhere`` if the two do not share an animation.
    """
    anim = after.animation
    if anim is None or before.animation is not anim:
        same = before.content_hash == after.content_hash
        return Change() if same else Change(everywhere=True)
    pts: list[np.ndarray] = []
    lights: list[int] = []
    everywhere = False
    for lt in anim.lights:
        a, b = before.lights[lt.index], after.lights[lt.index]
        if all(np.allclose(getattr(a, f), getattr(b, f), rtol=0.0, atol=1e-9) for f in lt.fields):
            continue
        lights.append(lt.index)
        ext = [_light_extent(x) for x in (a, b)]
        if ext[0] is None or ext[1] is None:
            everywhere = True
        else:
            pts += ext
    meshes: list[str] = []
    for m in anim.meshes:
        (ra, oa), (rb, ob) = m.transform(before.time), m.transform(after.time)
        if np.allclose(ra, rb, rtol=0.0, atol=1e-9) and np.allclose(oa, ob, rtol=0.0, atol=1e-9):
            continue
        meshes.append(m.name)
        pts += [before.vertices[m.start : m.stop], after.vertices[m.start : m.stop]]
    region = None
    if pts and not everywhere:
        p = np.concatenate([np.asarray(x, np.float64) for x in pts])
        region = np.stack([p.min(0), p.max(0)])
    return Change(tuple(lights), tuple(meshes), region, everywhere)


def seen_bounds(camera: Any, depth: np.ndarray, mask: np.ndarray | None) -> np.ndarray | None:
    """(2, 3) world box of the surfaces a record's camera sees, or None if it sees none.

    Args:
        camera: the record's :class:`icbtool.camera.Camera`.
        depth: (H, W, 1) view-space z.
        mask: (H, W, 1) 1 where a surface was hit, or None (every finite depth > 0 counts).
    """
    z = np.asarray(depth, np.float64)[..., 0]
    ok = np.isfinite(z) & (z > 0)
    if mask is not None:
        ok &= np.asarray(mask)[..., 0] > 0
    if not ok.any():
        return None
    v, u = np.nonzero(ok)
    p = camera.unproject(np.stack([u + 0.5, v + 0.5], 1), z[v, u])
    return np.stack([p.min(0), p.max(0)])


def box_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance between two (2, 3) boxes [min, max] (0 if they overlap)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    gap = np.maximum(0.0, np.maximum(a[0] - b[1], b[0] - a[1]))
    return float(np.linalg.norm(gap))


def is_affected(change: Change, seen: np.ndarray | None, reach_m: float | None = None) -> bool:
    """The invalidation rule: may ``change`` alter the GI of a record that sees ``seen``?

    Args:
        change: what changed since the record's state (:func:`scene_change`).
        seen: the record's seen bounds (:func:`seen_bounds`); None (it sees nothing) is never
            affected: it has no GI to alter.
        reach_m: how far (scene units) a change can alter GI; None: everywhere (conservative,
            see module docstring).

    Returns:
        True when the record must not serve as fresh.

    Raises:
        ValueError: ``reach_m`` negative or not finite.
    """
    if reach_m is not None and not (math.isfinite(reach_m) and reach_m >= 0):
        raise ValueError(f"reach_m must be finite and >= 0 or None, got {reach_m!r}")
    if change.empty or seen is None:
        return False
    if change.everywhere or reach_m is None or change.region is None:
        return True
    return box_distance(change.region, seen) <= reach_m


__all__ = [
    "STATIC_STATE",
    "Change",
    "box_distance",
    "group_keys",
    "is_affected",
    "record_state",
    "scene_change",
    "seen_bounds",
    "state_id",
    "state_tags",
]
