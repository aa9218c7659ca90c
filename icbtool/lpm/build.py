"""Levels of detail of a scene: quadric decimation per material group, UVs and normals
transferred from the full mesh, textures shrunk per level.

How a level is made from the full :class:`~icbtool.scene.Scene` (ratio ``r`` of its triangles):

1. The faces are split by material. Emissive groups (area lights and seen emitters) are kept as
   they are, so lights keep their exact geometry; so are groups of at most
   ``min_group_triangles`` triangles (cheap, and the first to lose their shape).
2. Every other group is welded by position on its own (UV and normal seams split vertices;
   welding makes the group one surface for the decimator, while groups never share a vertex so
   no triangle ever mixes two materials). With ``budget="global"`` (default) all of them go
   through ONE open3d quadric decimation (``simplify_quadric_decimation``, Garland and
   Heckbert) to ``ratio`` of their triangles, so the budget goes where the error is smallest;
   with ``budget="per_group"`` each is decimated alone to ``ratio`` of its own. On Sponza the
   global queue's RMS surface error is 11-14x lower at 5-15 % of the triangles (notes in
   benchmarks.lpm_levels). Every level is decimated from the full mesh (levels are
   independent, not a chain of decimations). open3d was measured against fast-simplification
   0.2.0 and pyfqmr 0.5.0 on the same input (benchmarks.lpm_decimators): at 5-25 % of
   Sponza's triangles open3d's RMS error is 2-400x lower (pyfqmr with borders kept stops at 27 %).
3. open3d drops ``triangle_uvs`` when it decimates (it warns "triangle uvs that are not handled"),
   so uvs and shading normals are transferred back from the full group (nearest points by
   :class:`~icbtool.lpm.closest.ClosestPointQuery`, exact): each decimated triangle
   takes the chart (UV-connected component of the original group) of the original face nearest
   its centroid; a corner whose nearest original point lies in that chart takes that point's
   barycentric uv/normal, any other corner (a triangle that straddles a UV seam) extrapolates
   the affine uv map of the centroid's face. A triangle thus never interpolates across a seam
   (which would smear the whole texture over it). Corners become vertices (deduplicated), so the
   level's seams are split again as in the input. A normal off its face's normal by more than
   ``normal_crease_deg`` is replaced by the face normal.
4. Textures larger than the level's ``texture_max`` are shrunk (``cv2.resize``, INTER_AREA, in
   linear light) and every texture is re-encoded to the bytes that travel (8-bit sRGB PNG or
   JPEG); the level's scene holds the texture decoded from those bytes, so what the client
   assembles equals the level's scene exactly.

The finest level (ratio 1) is the input's geometry, array for array; its textures are the
input's at ``texture_max`` 0 (exactly so when they came from 8-bit files, as loaded textures do).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from icbtool.lpm.chunks import level_chunks
from icbtool.lpm.config import LPMConfig
from icbtool.lpm.textures import decode_texture_bytes as decode_texture_bytes  # re-exported
from icbtool.lpm.textures import encode_texture, shrink_texture
from icbtool.scene.types import Material, Scene


# --------------------------------------------------------------------------- results
@dataclass(eq=False)
class Level:
    """One level of detail.

    Attributes:
        index: 0 is the coarsest.
        ratio: the fraction of the input's triangles asked for.
        scene: the level as a Scene (lights, sky, paths and cameras of the input).
        texture_bytes: the encoded texture file of each textured material (by material index),
            exactly what :meth:`to_chunks` sends.
        texture_format: "png" or "jpeg".
        build_s: seconds to build this level (decimation, transfer, textures).
        max_chunk_bytes: the chunk size bound of :meth:`to_chunks`.
    """

    index: int
    ratio: float
    scene: Scene
    texture_bytes: dict[int, bytes]
    texture_format: str
    build_s: float
    max_chunk_bytes: int

    @property
    def n_triangles(self) -> int:
        return self.scene.n_triangles

    def to_chunks(self, max_chunk_bytes: int | None = None) -> list[tuple[str, str, bytes]]:
        """The level as wire chunks ``(name, part, data)``, part "materials" first, then
        "geometry", then "texture" (layout: docs/lpm.md, :mod:`icbtool.lpm.chunks`).

        Args:
            max_chunk_bytes: bound on every chunk's size (default: the build's).
        """
        return level_chunks(self, max_chunk_bytes or self.max_chunk_bytes)

    def byte_sizes(self) -> dict[str, int]:
        """Bytes on the wire per part ("geometry", "texture", "materials") and "total"."""
        out = {"geometry": 0, "texture": 0, "materials": 0}
        for _, part, data in self.to_chunks():
            out[part] += len(data)
        out["total"] = sum(out.values())
        return out


@dataclass(eq=False)
class LPM:
    """A lightweight progressive mesh: levels coarse to fine (the last is the full mesh).

    Attributes:
        levels: the levels, coarse to fine.
        config: the configuration it was built with.
        source: the input scene.
    """

    levels: list[Level]
    config: LPMConfig
    source: Scene
    _errors: dict[int, dict[str, float]] = field(default_factory=dict, repr=False)

    def chunks(self, max_chunk_bytes: int | None = None) -> list[tuple[str, str, bytes]]:
        """Every level's chunks, coarse to fine (the order to stream them in): each level's
        manifest ("materials") first, then its geometry, then its textures."""
        return [c for lv in self.levels for c in lv.to_chunks(max_chunk_bytes)]

    def stats(self, error: bool = True, seed: int = 0) -> list[dict[str, Any]]:
        """Per level: index, ratio, triangles, vertices, bytes (geometry, texture, materials,
        total), build_s, and (``error=True``) the geometric error against the full mesh
        (:func:`icbtool.lpm.metrics.geometric_error`: RMS and Hausdorff as fractions of the
        bounding-box diagonal, symmetric; cached)."""
        out = []
        for lv in self.levels:
            b = lv.byte_sizes()
            row: dict[str, Any] = {
                "level": lv.index,
                "ratio": lv.ratio,
                "triangles": lv.n_triangles,
                "vertices": len(lv.scene.vertices),
                "bytes_geometry": b["geometry"],
                "bytes_texture": b["texture"],
                "bytes_materials": b["materials"],
                "bytes": b["total"],
                "build_s": lv.build_s,
            }
            if error:
                if lv.index not in self._errors:
                    from icbtool.lpm.metrics import geometric_error

                    self._errors[lv.index] = geometric_error(lv.scene, self.source, seed=seed)
                row["error"] = self._errors[lv.index]
            out.append(row)
        return out


# --------------------------------------------------------------------------- geometry
@dataclass
class _Part:
    vertices: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32
    uvs: np.ndarray | None  # (V, 2) float32
    faces: np.ndarray  # (F, 3) int64 local
    material: int


def sub_mesh(scene: Scene, faces_idx: np.ndarray, material: int) -> _Part:
    """The faces ``faces_idx`` of ``scene`` with their own compact vertex arrays."""
    f = scene.faces[faces_idx]
    used, inv = np.unique(f, return_inverse=True)
    uv = None if scene.uvs is None else scene.uvs[used]
    return _Part(scene.vertices[used], scene.normals[used], uv, inv.reshape(-1, 3), material)


def weld(vertices: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) welded positions and (V,) index of each input vertex's welded one."""
    v = vertices.astype(np.float64)
    key = np.round(v / tol).astype(np.int64) if tol > 0 else v
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return v[first], inv.reshape(-1)


def _charts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(F,) connected-component id of each face, faces connected through shared vertex
    indices (so a UV/normal seam, which splits vertices, separates charts)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n_vertices, n_vertices))
    _, comp = connected_components(g, directed=False)
    return comp[faces[:, 0]]


def _affine_weights(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of points ``p`` (N, 3) projected onto the planes of ``tri``
    (N, 3, 3), extrapolated outside the triangles."""
    a = tri[:, 0]
    e0, e1, d = tri[:, 1] - a, tri[:, 2] - a, p - a
    d00 = (e0 * e0).sum(1)
    d01 = (e0 * e1).sum(1)
    d11 = (e1 * e1).sum(1)
    d20 = (d * e0).sum(1)
    d21 = (d * e1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-300, den, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], 1)


def _decimate_part(part: _Part, target: int, cfg: LPMConfig, diag: float) -> _Part:
    """``part`` decimated to about ``target`` triangles, uvs and normals transferred."""
    from icbtool.optional import require

    o3d = require("open3d", "LPM decimation (icbtool.lpm)")
    welded, wmap = weld(part.vertices, cfg.weld_tolerance * diag)
    wf = wmap[part.faces]
    ok = (wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(welded), o3d.utility.Vector3iVector(wf[ok].astype(np.int32))
    )
    dec = mesh.simplify_quadric_decimation(int(target), boundary_weight=float(cfg.boundary_weight))
    p = np.asarray(dec.vertices, np.float64)
    t = np.asarray(dec.triangles, np.int64).reshape(-1, 3)
    if len(t):
        cr = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
        t = t[np.linalg.norm(cr, axis=1) > 1e-12 * diag * diag]
    if len(t) == 0:  # decimated away: keep the group as it was rather than lose it
        return part
    return _transfer(part, p, t, cfg)


def _decimate_global(
    parts: dict[int, _Part], ratio: float, cfg: LPMConfig, diag: float, targets: dict[int, int]
) -> dict[int, _Part]:
    """Decimate all ``parts`` (by material) in ONE quadric queue to ``ratio`` of their triangles.

    Each group is welded on its own, so groups stay separate components (a collapse never joins
    two materials); the queue spends the budget where the quadric error is smallest, whatever
    the group. A group the queue collapses entirely is decimated alone to its
    :func:`group_targets` share instead. The group of every output vertex travels as its vertex
    colour (open3d averages colours on a collapse, and only equal colours are ever averaged).
    """
    from icbtool.optional import require

    o3d = require("open3d", "LPM decimation (icbtool.lpm)")
    keys = sorted(parts)
    verts, faces, gid = [], [], []
    off = 0
    for k, m in enumerate(keys):
        welded, wmap = weld(parts[m].vertices, cfg.weld_tolerance * diag)
        wf = wmap[parts[m].faces]
        ok = (wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])
        verts.append(welded)
        faces.append(wf[ok] + off)
        gid.append(np.full(len(welded), k))
        off += len(welded)
    n_in = sum(len(parts[m].faces) for m in keys)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(verts)),
        o3d.utility.Vector3iVector(np.concatenate(faces).astype(np.int32)),
    )
    code = np.concatenate(gid).astype(np.float64) / _GROUP_CODE
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.stack([code] * 3, 1))
    dec = mesh.simplify_quadric_decimation(
        max(int(round(ratio * n_in)), 1), boundary_weight=float(cfg.boundary_weight)
    )
    p = np.asarray(dec.vertices, np.float64)
    t = np.asarray(dec.triangles, np.int64).reshape(-1, 3)
    vg = np.round(np.asarray(dec.vertex_colors)[:, 0] * _GROUP_CODE).astype(np.int64)
    if len(t):
        cr = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
        t = t[np.linalg.norm(cr, axis=1) > 1e-12 * diag * diag]
    tg = vg[t]
    if not np.all(tg == tg[:, :1]):  # cannot happen: groups share no vertex
        raise RuntimeError("LPM decimation joined two material groups (a bug)")
    out = {}
    for k, m in enumerate(keys):
        tk = t[tg[:, 0] == k]
        if len(tk) == 0:  # the queue collapsed the whole group: decimate it alone instead
            out[m] = _decimate_part(parts[m], targets[m], cfg, diag)
            continue
        used, inv = np.unique(tk, return_inverse=True)
        out[m] = _transfer(parts[m], p[used], inv.reshape(-1, 3), cfg)
    return out


#: Scale of the group index stored in the decimator's vertex colours (exact in float64).
_GROUP_CODE = 1 << 20


def _transfer(part: _Part, p: np.ndarray, t: np.ndarray, cfg: LPMConfig) -> _Part:
    """uvs and normals of the decimated (``p`` (P, 3), ``t`` (T, 3)) from the original part."""
    from icbtool.lpm.closest import ClosestPointQuery

    ov = part.vertices.astype(np.float64)
    of = part.faces
    cpq = ClosestPointQuery(ov, of)
    chart = _charts(of, len(ov))

    def closest(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = cpq.query(q)
        return r.face, r.weights

    cf, _ = closest(p[t].mean(1))  # (T,) the original face nearest each centroid
    vf, vw = closest(p)  # (P,) the original face nearest each decimated vertex
    corner_f = vf[t]  # (T, 3)
    corner_w = vw[t]  # (T, 3, 3)
    same = chart[corner_f] == chart[cf][:, None]
    ext_w = _affine_weights(p[t].reshape(-1, 3), np.repeat(ov[of[cf]], 3, axis=0)).reshape(-1, 3, 3)
    use_f = np.where(same, corner_f, cf[:, None])  # (T, 3)
    use_w = np.where(same[..., None], corner_w, ext_w)  # (T, 3, 3)
    src = of[use_f]  # (T, 3, 3) original vertex indices of each corner's face

    n = (use_w[..., None] * part.normals[src].astype(np.float64)).sum(2)  # (T, 3, 3)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
    fn = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    crease = (n * fn[:, None]).sum(-1) < np.cos(np.radians(cfg.normal_crease_deg))
    n = np.where(crease[..., None], fn[:, None], n)

    cols = [t.reshape(-1, 1).astype(np.float64), n.reshape(-1, 3)]
    uv = None
    if part.uvs is not None:
        uv = (use_w[..., None] * part.uvs[src].astype(np.float64)).sum(2)  # (T, 3, 2)
        cols.append(uv.reshape(-1, 2))
    wedge = np.concatenate(cols, 1).astype(np.float32)
    uniq, inv = np.unique(wedge, axis=0, return_inverse=True)
    verts = p[uniq[:, 0].astype(np.int64)].astype(np.float32)
    normals = uniq[:, 1:4]
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    uvs = None if uv is None else np.ascontiguousarray(uniq[:, 4:6])
    return _Part(
        verts, normals.astype(np.float32), uvs, inv.reshape(-1, 3).astype(np.int64), part.material
    )


def _merge(parts: list[_Part], base: Scene, materials: tuple[Material, ...]) -> Scene:
    offs = np.cumsum([0] + [len(p.vertices) for p in parts])
    verts = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offs[:-1])])
    normals = np.concatenate([p.normals for p in parts])
    fm = np.concatenate([np.full(len(p.faces), p.material, np.int32) for p in parts])
    uvs = None
    if base.uvs is not None:
        uvs = np.concatenate([p.uvs for p in parts])  # type: ignore[misc]
    return dataclasses.replace(
        base,
        vertices=verts,
        faces=faces,
        normals=normals,
        face_material=fm,
        uvs=uvs,
        materials=materials,
    )


def _level_materials(
    scene: Scene, max_side: int, cfg: LPMConfig, cache: dict[tuple, tuple[Material, bytes]]
) -> tuple[tuple[Material, ...], dict[int, bytes]]:
    """The materials of a level (textures shrunk and passed through their encoding)."""
    mats: list[Material] = []
    tex: dict[int, bytes] = {}
    for i, m in enumerate(scene.materials):
        if m.texture is None:
            mats.append(m)
            continue
        small = shrink_texture(m.texture, max_side)
        key = (i, small.shape)
        hit = cache.get(key)
        if hit is None:
            data = encode_texture(small, cfg.texture_format, cfg.jpeg_quality)
            dec = decode_texture_bytes(data, f"material '{m.name}' texture")
            if dec.shape == m.texture.shape and np.array_equal(dec, m.texture):
                new = m  # the input's texture survives its encoding exactly: keep the object
            else:
                new = Material(m.name, m.albedo, m.emission, dec, m.texture_path)
            hit = cache[key] = (new, data)
        mats.append(hit[0])
        tex[i] = hit[1]
    return tuple(mats), tex


def group_targets(scene: Scene, ratio: float, cfg: LPMConfig) -> dict[int, int]:
    """Triangles asked of each material group at ``ratio`` (a group absent from the result,
    or asked for all it has, is kept as it is: emissive groups always are)."""
    counts = np.bincount(scene.face_material, minlength=len(scene.materials))
    out = {}
    for m, n in enumerate(counts):
        if n == 0:
            continue
        if scene.materials[m].is_emissive:
            out[m] = int(n)
        else:
            out[m] = int(min(n, max(round(ratio * n), cfg.min_group_triangles)))
    return out


def _level_parts(
    scene: Scene, groups: dict[int, np.ndarray], ratio: float, cfg: LPMConfig, diag: float
) -> dict[int, _Part]:
    """The decimated (or kept) part of every material group at ``ratio``."""
    parts = {m: sub_mesh(scene, idx, m) for m, idx in groups.items()}
    targets = group_targets(scene, ratio, cfg)
    todo = [m for m in groups if targets[m] < len(groups[m])]
    if cfg.budget == "global":
        if todo:
            parts.update(_decimate_global({m: parts[m] for m in todo}, ratio, cfg, diag, targets))
    else:
        for m in todo:
            parts[m] = _decimate_part(parts[m], targets[m], cfg, diag)
    return parts


def build(scene: Scene, cfg: LPMConfig = LPMConfig(), progress: bool = False) -> LPM:  # noqa: B008
    """Build the levels of detail of ``scene`` (see the module docstring).

    Args:
        scene: the full scene (the cloud's).
        cfg: an :class:`LPMConfig`.
        progress: show a tqdm bar (one step per material group per level).

    Returns:
        An :class:`LPM`, levels coarse to fine; the last level's geometry is ``scene``'s.

    Raises:
        TypeError: ``cfg`` is not an LPMConfig or ``scene`` not a Scene.
        MissingOptionalDependency: open3d (the ``mesh`` extra) is not installed and a level
            needs decimation.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"build: scene must be an icbtool Scene, got {type(scene).__name__}")
    if not isinstance(cfg, LPMConfig):
        raise TypeError(f"build: cfg must be an LPMConfig, got {type(cfg).__name__}")
    diag = max(scene.diagonal, 1e-12)
    order = np.argsort(scene.face_material, kind="stable")
    bounds = np.searchsorted(scene.face_material[order], np.arange(len(scene.materials) + 1))
    groups = {
        m: order[bounds[m] : bounds[m + 1]]
        for m in range(len(scene.materials))
        if bounds[m + 1] > bounds[m]
    }
    bar: Any = None
    tick: Callable[[str], None] = lambda _s: None  # noqa: E731
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(cfg.ratios) * len(groups), desc=f"lpm {scene.name}", unit="group")

        def tick(s: str) -> None:
            bar.set_postfix_str(s, refresh=False)
            bar.update(1)

    cache: dict[tuple, tuple[Material, bytes]] = {}
    levels: list[Level] = []
    try:
        for li, (ratio, max_side) in enumerate(zip(cfg.ratios, cfg.texture_max)):
            t0 = time.perf_counter()
            mats, tex = _level_materials(scene, max_side, cfg, cache)
            if ratio >= 1.0:
                lscene = dataclasses.replace(scene, materials=mats)
                for m in groups:
                    tick(f"L{li} {scene.materials[m].name}")
            else:
                parts = _level_parts(scene, groups, ratio, cfg, diag)
                for m in groups:
                    tick(f"L{li} {scene.materials[m].name}")
                lscene = _merge([parts[m] for m in groups], scene, mats)
            levels.append(
                Level(
                    li,
                    ratio,
                    lscene,
                    tex,
                    cfg.texture_format,
                    time.perf_counter() - t0,
                    int(cfg.max_chunk_bytes),
                )
            )
    finally:
        if bar is not None:
            bar.close()
    return LPM(levels, cfg, scene)


__all__ = [
    "LPM",
    "Level",
    "build",
    "decode_texture_bytes",
    "encode_texture",
    "group_targets",
    "shrink_texture",
    "sub_mesh",
    "weld",
]
