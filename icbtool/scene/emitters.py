"""Emissive geometry as light: a mesh's emissive faces promoted to :class:`AreaLight` s.

The DL/GI split of icbtool counts as *direct* the light of the scene's lights, area lights
included; an area light is an emissive polygon of the mesh registered in ``scene.lights``. A
mesh file's own emissive faces (OBJ ``Ke``, glTF ``emissiveFactor`` without texture) are at
first plain "seen emission": the camera sees them, but the light they cast reaches the client
only through the GI map. :func:`promote_emitters` registers them as area lights, so the raster
DL computes their exact (polygon) irradiance with shadows and the path tracer counts their
next-event-estimated light as direct, exactly as for the quads of :class:`AreaLight` s:

* the faces stay in the mesh with their emissive material (the camera sees them; a path that
  hits them adds their emission: to ``direct`` when the face lies in an area light and the path
  left the first visible surface, to ``gi`` otherwise, MIS-weighted against the light sample);
* one light per emissive triangle (``shape="triangle"``), except that two triangles of the same
  material sharing an edge whose union is exactly a parallelogram (a quad cut along its
  diagonal, as exporters write an emissive rectangle) become one ``shape="parallelogram"`` light
  (the same surface, the same light, half the raster's shadow maps); pairs are formed greedily
  in face order, each triangle with its nearest (in face order) unpaired exact partner;
* faces already lying in an area light of the scene are left alone (never counted twice);
* above the budget (``max_triangles`` emissive triangles to promote) nothing is promoted: a
  large emissive mesh (a screen, a lamp with thousands of triangles) would cost the raster more
  shadow maps than it can afford. Those faces stay seen emission (their light is in the GI map)
  and a WARNING (logger ``icbtool.scene.emitters``) says so with the count and the budget.

Example:
    >>> # scene = icb.scene.load("cornell.gltf")           # promoted on load (emitter_budget=64)
    >>> # scene = promote_emitters(bare_scene, max_triangles=16)
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from icbtool.scene.derived import derived
from icbtool.scene.types import AreaLight, Scene

log = logging.getLogger(__name__)

#: Default number of emissive triangles promoted to lights (``load(..., emitter_budget=...)``).
DEFAULT_EMITTER_BUDGET = 64
#: Relative tolerance (to the triangle's size) of the exact-parallelogram test when merging.
MERGE_REL_TOL = 1e-6


def light_faces(scene: Scene) -> np.ndarray:
    """Which faces are the geometry of an area light (their light is direct, not GI).

    A face counts when it is emissive and its three vertices lie in one area light's polygon
    (:meth:`AreaLight.contains`). Cached per scene (:mod:`icbtool.scene.derived`).

    Args:
        scene: the scene.

    Returns:
        (F,) bool, read-only.
    """

    def build() -> np.ndarray:
        out = np.zeros(len(scene.faces), bool)
        emissive = scene.emissive_faces
        lights = scene.lights_of("area")
        if len(emissive) and lights:
            tri = scene.vertices[scene.faces[emissive]].astype(np.float64)  # (E, 3, 3)
            inside = np.zeros(len(emissive), bool)
            # each light tests only the faces whose bounding box lies in its own (widened far
            # beyond AreaLight.contains' tolerance): faces sorted by their lowest x, a light's
            # candidates are a slice of them, so L lights cost O(L log E), not O(L E) (a
            # tessellated sphere emitter promoted to 20k triangle lights took minutes)
            lo, hi = tri.min(axis=1), tri.max(axis=1)  # (E, 3)
            order = np.argsort(lo[:, 0], kind="stable")
            lo_x = lo[order, 0]
            for light in lights:
                c, u, v = light.corner, light.edge_u, light.edge_v
                pts = np.stack([c, c + u, c + v, c + u + v])
                if light.shape == "triangle":
                    pts = pts[:3]
                size = float(np.linalg.norm(u) + np.linalg.norm(v))
                margin = 1e-2 * size + 1e-9 * float(np.abs(pts).max())
                l_lo, l_hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
                a = np.searchsorted(lo_x, l_lo[0], side="left")
                b = np.searchsorted(lo_x, l_hi[0], side="right")
                cand = order[a:b]
                cand = cand[
                    ~inside[cand]
                    & np.all(lo[cand] >= l_lo, axis=1)
                    & np.all(hi[cand] <= l_hi, axis=1)
                ]
                if len(cand):
                    inside[cand[light.contains(tri[cand]).all(axis=1)]] = True
            out[emissive[inside]] = True
        out.setflags(write=False)
        return out

    return derived(scene, "light_faces", build)


def promote_emitters(scene: Scene, max_triangles: int = DEFAULT_EMITTER_BUDGET) -> Scene:
    """A copy of ``scene`` whose emissive faces are also area lights (see the module docstring).

    Args:
        scene: the scene (never modified).
        max_triangles: budget: promote only when the emissive triangles not yet covered by an
            area light number at most this many (>= 0; 0 disables promotion).

    Returns:
        ``scene`` itself when there is nothing to promote or the budget is exceeded, else a new
        Scene (``dataclasses.replace``) with the new :class:`AreaLight` s appended to ``lights``
        (named ``"emitter:<material>:<face>"``; a merged pair is named after its first face).

    Raises:
        ValueError: ``max_triangles`` is negative or not an integer.
    """
    if isinstance(max_triangles, bool) or not isinstance(max_triangles, (int, np.integer)):
        raise ValueError(f"max_triangles must be an integer >= 0, got {max_triangles!r}")
    if max_triangles < 0:
        raise ValueError(f"max_triangles must be >= 0, got {max_triangles}")
    covered = light_faces(scene)
    emissive = scene.emissive_faces
    cand = emissive[~np.asarray(covered)[emissive] & (scene.face_areas[emissive] > 0)]
    cand = cand.astype(np.int64)
    if len(cand) == 0:
        return scene
    if len(cand) > max_triangles:
        log.warning(
            "scene '%s': %d emissive triangles exceed the emitter budget of %d: they stay seen "
            "emission (their light is in the GI map, not in the raster DL); raise the budget "
            "with load(..., emitter_budget=N) to make them lights",
            scene.name,
            len(cand),
            max_triangles,
        )
        return scene
    lights = _lights_for(scene, cand)
    log.info(
        "scene '%s': %d emissive triangles promoted to %d area lights (budget %d)",
        scene.name,
        len(cand),
        len(lights),
        max_triangles,
    )
    return dataclasses.replace(scene, lights=(*scene.lights, *lights))


def _lights_for(scene: Scene, faces: np.ndarray) -> list[AreaLight]:
    """Area lights for the emissive ``faces``: exact parallelogram pairs merged, others alone."""
    tri = scene.vertices[scene.faces[faces]].astype(np.float64)  # (E, 3, 3)
    mats = scene.face_material[faces]
    size = np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1) + np.linalg.norm(
        tri[:, 2] - tri[:, 0], axis=1
    )
    # directed edges by rounded end positions (files may duplicate vertices along seams)
    scale = max(float(np.abs(tri).max()), 1e-30)
    q = np.round(tri / (scale * 1e-9)).astype(np.int64)
    edges: dict[tuple, list[tuple[int, int]]] = {}
    for i in range(len(faces)):
        for k in range(3):
            edges.setdefault((tuple(q[i, k]), tuple(q[i, (k + 1) % 3])), []).append((i, k))
    used = np.zeros(len(faces), bool)
    lights: list[AreaLight] = []
    for i in range(len(faces)):
        if used[i]:
            continue
        used[i] = True
        m = scene.materials[int(mats[i])]
        name = f"emitter:{m.name}:{int(faces[i])}"
        # every exact partner; the nearest in face order wins (exporters write a quad's two
        # triangles one after the other; a neighbouring quad's triangle may fit too)
        pair = None
        for k in range(3):
            a, b, o = tri[i, k], tri[i, (k + 1) % 3], tri[i, (k + 2) % 3]
            for j, kj in edges.get((tuple(q[i, (k + 1) % 3]), tuple(q[i, k])), []):
                if used[j] or mats[j] != mats[i] or (pair is not None and j - i >= pair[0] - i):
                    continue
                d = tri[j, (kj + 2) % 3]  # the neighbour's opposite vertex
                tol = MERGE_REL_TOL * max(size[i], size[j])
                if np.linalg.norm(o + d - a - b) <= tol:  # diagonals bisect: a parallelogram
                    pair = (j, a, d, o)
        if pair is None:
            t = tri[i]
            lights.append(
                AreaLight(t[0], t[1] - t[0], t[2] - t[0], m.emission, name, shape="triangle")
            )
        else:
            j, a, d, o = pair
            used[j] = True
            lights.append(AreaLight(a, d - a, o - a, m.emission, name))
    return lights


__all__ = ["DEFAULT_EMITTER_BUDGET", "light_faces", "promote_emitters"]
