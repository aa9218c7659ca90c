"""A first view of a scene that shows something: the file's camera, a room from inside, or a
framing of the whole from outside.

:meth:`Camera.frame <icbtool.camera.Camera.frame>` frames a bounding box from outside. For an
interior (a room, a house, a classroom: geometry that closes around its empty space) that shows
the outer walls and nothing of what the scene is about. :func:`default_view` picks, in order:

1. the scene's own camera (``scene.default_camera``: a description's ``[default_camera]``, a
   Mitsuba file's ``<sensor>``, a procedural scene's);
2. for an *open box* (geometry closed on five sides of its bounds and open on one horizontal
   side, as a Cornell box without its camera): a view from outside the opening, looking in, that
   frames the whole box (:func:`open_box_view`). A side is *open* when, from at least one of
   3 x 3 x 3 points inside the bounds, at least :data:`OPEN_SIDE_ESCAPE` of a cone of rays
   (:data:`SIDE_CONE_DEG` around the side's axis) leave the bounds through that side without a
   hit, *closed* when from every point at most :data:`CLOSED_SIDE_ESCAPE` do; an open box has
   exactly one open horizontal side and five closed ones;
3. a view from inside the largest enclosed open volume: candidate points on a
   :data:`GRID` ^3 grid inside the bounds (5 % inset) each cast :data:`N_RAYS` rays over the sphere;
   a point is *enclosed* when at least :data:`ENCLOSED_HIT_FRACTION` of them hit geometry and at
   most :data:`MAX_BACK_FRACTION` hit back faces (it is in a room, not inside a solid); the scene
   is an interior when at least :data:`MIN_ENCLOSED_SHARE` of the points are enclosed, and the
   enclosed point with the largest mean free distance lies in its largest room. The camera
   stands on the far side of that point: along the horizontal direction with the longest free
   distance from it, the camera is moved back by :data:`BACK_OFF` of the free distance behind,
   and looks across the room, :data:`PITCH_DEG` down;
4. otherwise :meth:`Camera.frame` of the bounds from outside.

The choice and its evidence are logged (logger ``icbtool.scene.view``, INFO): which rule, the
share of enclosed candidate points, the chosen point.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from icbtool.camera.camera import Camera, look_at_pose

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.scene.types import Scene

log = logging.getLogger(__name__)

#: Candidate points per axis of the bounds.
GRID = 7
#: Rays cast from each candidate point.
N_RAYS = 96
#: A point is enclosed when at least this share of its rays hit geometry.
ENCLOSED_HIT_FRACTION = 0.9
#: ... and at most this share hit back faces (more: it is inside a solid).
MAX_BACK_FRACTION = 0.1
#: An interior needs at least this share of the candidate points enclosed (fewer: cavities in
#: furniture or between objects, not a room).
MIN_ENCLOSED_SHARE = 0.1
#: The camera stands this share of the free distance behind the chosen point.
BACK_OFF = 0.8
#: Downward pitch of the interior view in degrees.
PITCH_DEG = 10.0
#: Half-angle (degrees) of the cone of rays that tests a side of the bounds for an opening.
SIDE_CONE_DEG = 25.0
#: A side is open when at least this share of its cone escapes, closed when at most
#: CLOSED_SIDE_ESCAPE does.
OPEN_SIDE_ESCAPE = 0.6
CLOSED_SIDE_ESCAPE = 0.1


def default_view(
    scene: Scene, *, height: int = 256, width: int = 256, fov_y_deg: float = 45.0
) -> Camera:
    """A first camera for ``scene`` (see the module docstring for the rules).

    Args:
        scene: the scene.
        height, width: image size of the camera (the scene's own camera is resized to it).
        fov_y_deg: vertical field of view of a computed view (the scene's camera keeps its own).

    Returns:
        The camera.
    """
    if scene.default_camera is not None:
        log.info("scene '%s': its own camera", scene.name)
        cam = scene.default_camera
        return cam if (cam.height, cam.width) == (height, width) else cam.resized(height, width)
    box = open_box_view(scene, height=height, width=width, fov_y_deg=fov_y_deg)
    if box is not None:
        return box
    inside = interior_view(scene, height=height, width=width, fov_y_deg=fov_y_deg)
    if inside is not None:
        return inside
    return Camera.frame(scene.bounds, up=scene.up, fov_y_deg=fov_y_deg, height=height, width=width)


def _side_escapes(scene: Scene, es: object) -> dict[tuple[int, float], float]:
    """For each side ``(axis, sign)`` of the bounds, the largest share of a cone of rays that
    leaves the bounds through it without a hit, over a 3 x 3 x 3 grid of points inside the
    bounds (so that objects in the box do not hide an opening from every point)."""
    lo, hi = scene.bounds
    f = np.array([0.25, 0.5, 0.75])
    grid = np.stack(np.meshgrid(f, f, f, indexing="ij"), -1).reshape(-1, 3)
    origins = lo + grid * (hi - lo)
    k = np.linspace(-1.0, 1.0, 7)
    a, b = np.meshgrid(k, k)
    spread = math.tan(math.radians(SIDE_CONE_DEG))
    out = {}
    for axis in range(3):
        others = [i for i in range(3) if i != axis]
        for sign in (-1.0, 1.0):
            d = np.zeros((a.size, 3))
            d[:, axis] = sign
            d[:, others[0]] = spread * a.ravel()
            d[:, others[1]] = spread * b.ravel()
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            o = np.repeat(origins, len(d), axis=0)
            dd = np.tile(d, (len(origins), 1))
            h = es.intersect(o, dd)  # type: ignore[attr-defined]
            with np.errstate(divide="ignore", invalid="ignore"):
                t_exit = np.where(dd > 0, (hi - o) / dd, np.where(dd < 0, (lo - o) / dd, np.inf))
            through = (h.prim < 0) & (np.argmin(t_exit, axis=1) == axis)  # out by this side
            out[(axis, sign)] = float(through.reshape(len(origins), -1).mean(1).max())
    return out


def open_box_view(
    scene: Scene, *, height: int = 256, width: int = 256, fov_y_deg: float = 45.0
) -> Camera | None:
    """For an open box (closed on five sides, open on one horizontal side: a Cornell box), a
    camera outside the opening looking in that frames the whole box; else None.

    Args:
        scene: the scene.
        height, width: image size.
        fov_y_deg: vertical field of view.

    Returns:
        The camera, or None when the scene is not an open box.
    """
    from icbtool.scene.raycast import EmbreeScene

    up = np.asarray(scene.up, np.float64)
    up_axis = int(np.argmax(np.abs(up)))
    escapes = _side_escapes(scene, EmbreeScene.from_scene(scene))
    open_sides = [s for s, e in escapes.items() if e >= OPEN_SIDE_ESCAPE]
    closed = [s for s, e in escapes.items() if e <= CLOSED_SIDE_ESCAPE]
    if len(open_sides) != 1 or len(closed) != 5 or open_sides[0][0] == up_axis:
        return None
    axis, sign = open_sides[0]
    look = np.zeros(3)
    look[axis] = -sign  # from outside the opening, into the box
    log.info(
        "scene '%s': open box view: the side %s%s of the bounds is open (up to %.0f %% of its "
        "rays escape, the five others' at most %.0f %%); the camera looks in along %s",
        scene.name,
        "+" if sign > 0 else "-",
        "xyz"[axis],
        100 * escapes[open_sides[0]],
        100 * CLOSED_SIDE_ESCAPE,
        look.tolist(),
    )
    return Camera.frame(
        scene.bounds, up=up, fov_y_deg=fov_y_deg, height=height, width=width, view_direction=look
    )


def interior_view(
    scene: Scene, *, height: int = 256, width: int = 256, fov_y_deg: float = 45.0
) -> Camera | None:
    """A camera inside the largest enclosed open volume, or None (logged why) for an exterior.

    Args:
        scene: the scene.
        height, width: image size.
        fov_y_deg: vertical field of view.

    Returns:
        The camera, or None when no candidate point is enclosed.
    """
    from icbtool.scene.raycast import EmbreeScene
    from icbtool.scene.walk import sphere_directions

    es = EmbreeScene.from_scene(scene)
    lo, hi = scene.bounds
    inset = 0.05 * (hi - lo)
    axes = [np.linspace(a + e, b - e, GRID) for a, b, e in zip(lo, hi, inset)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d = sphere_directions(N_RAYS)
    o = np.repeat(pts, len(d), axis=0)
    dd = np.tile(d, (len(pts), 1))
    h = es.intersect(o, dd)
    hit = (h.prim >= 0).reshape(len(pts), -1)
    back = (hit.reshape(-1) & (np.einsum("ij,ij->i", h.ng, dd) > 0)).reshape(len(pts), -1)
    hit_frac, back_frac = hit.mean(1), back.mean(1)
    t = np.where(hit, h.t.reshape(len(pts), -1), 0.0)
    free = t.sum(1) / np.maximum(hit.sum(1), 1)
    enclosed = (hit_frac >= ENCLOSED_HIT_FRACTION) & (back_frac <= MAX_BACK_FRACTION)
    share = float(enclosed.mean())
    if enclosed.any() and share < MIN_ENCLOSED_SHARE:
        log.info(
            "scene '%s': outside view (Camera.frame): only %.0f %% of the candidate points are "
            "enclosed (need %.0f %%): small cavities, not a room",
            scene.name,
            100 * share,
            100 * MIN_ENCLOSED_SHARE,
        )
        return None
    if not enclosed.any():
        log.info(
            "scene '%s': outside view (Camera.frame): no candidate point inside the bounds is "
            "enclosed (best: %.0f %% of rays hit, need %.0f %%): an exterior",
            scene.name,
            100 * float(hit_frac[back_frac <= MAX_BACK_FRACTION].max(initial=0.0)),
            100 * ENCLOSED_HIT_FRACTION,
        )
        return None
    k = int(np.argmax(np.where(enclosed, free, -1.0)))
    p = pts[k]
    up = np.asarray(scene.up, np.float64)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(a, up)
    ang = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    hd = np.outer(np.cos(ang), a) + np.outer(np.sin(ang), b)
    hh = es.intersect(np.repeat(p[None], 2 * len(hd), 0), np.vstack([hd, -hd]))
    span = float(np.linalg.norm(hi - lo))
    dist = np.where(hh.prim >= 0, hh.t, span)
    j = int(np.argmax(dist[: len(hd)]))
    fwd, behind = hd[j], float(dist[len(hd) + j])
    eye = p - BACK_OFF * behind * fwd
    pitch = math.radians(PITCH_DEG)
    look = math.cos(pitch) * fwd - math.sin(pitch) * up
    cam = Camera.from_fov(fov_y_deg, height, width, look_at_pose(eye, eye + look, up))
    log.info(
        "scene '%s': interior view: %.0f %% of %d candidate points are enclosed; camera in the "
        "largest open volume (mean free distance %.3g) at %s, looking along %s",
        scene.name,
        100 * share,
        len(pts),
        float(free[k]),
        np.round(eye, 3).tolist(),
        np.round(look, 3).tolist(),
    )
    return cam


__all__ = ["default_view", "interior_view", "open_box_view"]
