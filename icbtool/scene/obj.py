"""A small, strict Wavefront OBJ + MTL reader (faithful, or it fails naming ``file:line``).

What it reads:

* ``v`` (extra components such as ``w`` or vertex colours are ignored), ``vt`` (u, v; a missing
  v is 0), ``vn``; keywords may be followed by tabs or several spaces; ``\\`` at the end of a
  line continues it; ``#`` starts a comment.
* ``f`` with ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn`` corners; positive indices count from 1
  over the whole file, negative ones count back from the last element defined *before* the face
  (``-1`` is the latest ``v``). A corner without ``vt`` (``vn``) in a face whose other corners
  have one gets uv (0, 0) (a computed normal).
* Polygons are triangulated: a convex polygon as a fan from its first corner; a non-convex one by
  ear clipping in the plane of its Newell normal (quads: split along the diagonal from the reflex
  corner). Every triangle keeps the polygon's winding.
* ``usemtl`` sets the material of the following faces (it is not reset by ``o``/``g``); faces
  before any ``usemtl`` get the material ``default`` (albedo 0.8). ``mtllib`` may name several
  files (on one line or several lines).
* ``s`` smoothing groups decide the normals of faces without ``vn`` (our rule): with ``s off``/
  ``s 0`` (the default) each polygon is flat (its corners are separate vertices whose normal is
  the polygon's area-weighted normal), so a box's corners are never smoothed across 90 degrees;
  within a smoothing group ``s N`` the corners sharing a position share a vertex and get the
  area-weighted average normal of that group's faces (OBJ's meaning of a smoothing group). Faces
  with ``vn`` use the file's normals.
* ``l``, ``p`` and free-form curves/surfaces (``curv``, ``surf``, ``cstype``...) are skipped
  with one :class:`~icbtool.scene.validate.SceneRepairWarning` giving their counts; so are
  unknown statements.

Scene vertices are the unique ``(v, vt, vn, smoothing key)`` tuples of the face corners, in order
of first use.

Errors (:class:`~icbtool.scene.validate.SceneError`, message starting ``path:line:``): a number
that is not a number, an index of 0 or out of range (with the count defined so far for a relative
index), a face with fewer than 3 corners, a vertex with fewer than 3 coordinates.

MTL: ``Kd`` (diffuse albedo), ``Ke`` (emitted radiance), ``Ks``, ``Ns``, ``Ni``, ``d``/``Tr``
(opacity; ``Tr`` = 1 - d, used only without ``d``), ``Tf``, ``illum`` and ``map_Kd`` (options such
as ``-s 1 1 1`` before the file name are skipped). icbtool renders only Lambertian materials; a
material that is not (illum 3-7: mirror/glass/refraction; ``Ks`` larger than ``Kd``: glossy;
opacity < 1: transparent) is replaced by the *nearest diffuse* material, with a
:class:`MaterialApproximationWarning` naming it and what was approximated. The rule: the diffuse
surface reflects all the energy the original reflects or transmits,
``albedo = clip(Kd + Ks + T, 0, 1)`` with ``T = Tf`` for illum 4/6/7 when ``Tf`` is given, else
``T = 1 - opacity``; if that is still darker than 0.04 (e.g. a mirror with ``Kd = Ks = 0``) it is
0.8 grey, so a mirror never turns black. Emission (``Ke``) is kept as it is.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from icbtool.scene.validate import SceneError, SceneRepairWarning, repair_warning

#: Free-form geometry statements we skip (counted in one warning).
_FREEFORM = {
    b"cstype", b"deg", b"bmat", b"step", b"curv", b"curv2", b"surf", b"parm", b"trim", b"hole",
    b"scrv", b"sp", b"end", b"con", b"vp",
}  # fmt: skip
#: Statements that do not change geometry or materials (skipped silently).
_HARMLESS = {
    b"o", b"g", b"mg", b"lod", b"bevel", b"c_interp", b"d_interp", b"shadow_obj", b"trace_obj",
    b"maplib", b"usemap", b"call", b"csh",
}  # fmt: skip
#: Albedo below which an approximated (non-diffuse) material is made 0.8 grey instead of black.
DARK_APPROXIMATION = 0.04


class MaterialApproximationWarning(SceneRepairWarning):
    """A material icbtool cannot render (mirror, glass, glossy, metal, emission texture...) was
    replaced by the nearest diffuse one; the message names the material and what was changed."""


@dataclass
class ObjMesh:
    """An OBJ file as triangle arrays (file coordinates, before any scale or up-axis change).

    Attributes:
        vertices: (V, 3) float64 positions, one per unique corner (see the module docstring).
        faces: (F, 3) int64 indices into ``vertices``.
        normals: (V, 3) float64 file normals; rows where ``normal_given`` is False are NaN.
        normal_given: (V,) bool, True where the file gives the vertex a ``vn``.
        uvs: (V, 2) float64, or None when no face corner has a ``vt``.
        face_material: (F,) int32 index into ``material_names``.
        material_names: the ``usemtl`` names in order of first use (``default`` if none).
        mtllibs: the material library file names, as written.
        face_line: (F,) int64 the 1-based line of the face statement each triangle comes from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    normal_given: np.ndarray
    uvs: np.ndarray | None
    face_material: np.ndarray
    material_names: list[str]
    mtllibs: list[str] = field(default_factory=list)
    face_line: np.ndarray | None = None


def _logical_lines(data: bytes) -> list[tuple[int, bytes]]:
    """(1-based line number, text without comment) for each line, continuations joined."""
    lines = data.splitlines()
    if b"\\" not in data:
        return list(enumerate(lines, 1))
    out: list[tuple[int, bytes]] = []
    i = 0
    while i < len(lines):
        start, line = i + 1, lines[i]
        while line.rstrip().endswith(b"\\") and i + 1 < len(lines):
            i += 1
            line = line.rstrip()[:-1] + b" " + lines[i]
        out.append((start, line))
        i += 1
    return out


def _floats(path: Path, tokens: list[bytes], lines: list[int], width: int, what: str) -> np.ndarray:
    """Parse ``width`` numbers per line (tokens flattened); errors name file:line."""
    try:
        return np.array(tokens, dtype=np.bytes_).astype(np.float64).reshape(-1, width)
    except ValueError:
        for k, t in enumerate(tokens):
            try:
                float(t)
            except ValueError:
                raise SceneError(
                    f"{path}:{lines[k // width]}: {what} coordinate {t.decode(errors='replace')!r}"
                    " is not a number"
                ) from None
        raise  # pragma: no cover - a token that float() takes but numpy does not


def parse_obj(path: str | Path, data: bytes | None = None) -> ObjMesh:
    """Parse an OBJ file (see the module docstring for what is read and the rules).

    Args:
        path: the .obj file (named in messages; read unless ``data`` is given).
        data: the file's bytes, if already read.

    Returns:
        The triangulated :class:`ObjMesh`.

    Raises:
        SceneError: ``path:line: problem`` for a malformed statement; empty mesh.
    """
    p = Path(path)
    if data is None:
        data = p.read_bytes()
    if b"\x00" in data[:65536]:
        raise SceneError(f"{p}: not a text OBJ file (contains NUL bytes): corrupt or binary")
    v_tok: list[bytes] = []
    v_line: list[int] = []
    vt_tok: list[bytes] = []
    vt_line: list[int] = []
    vn_tok: list[bytes] = []
    vn_line: list[int] = []
    f_tok: list[bytes] = []
    f_n: list[int] = []  # corners per polygon
    f_line: list[int] = []
    f_state: list[tuple[int, int, int, int, int]] = []  # (nv, nvt, nvn, material, smoothing)
    mtllibs: list[str] = []
    mat_names: list[str] = []
    mat_index: dict[str, int] = {}
    cur_mat = -1
    cur_s = 0
    skipped: dict[str, int] = {}
    for lineno, raw in _logical_lines(data):
        if b"#" in raw:
            raw = raw.split(b"#", 1)[0]
        parts = raw.split()
        if not parts:
            continue
        key = parts[0]
        if key == b"v":
            if len(parts) < 4:
                raise SceneError(f"{p}:{lineno}: vertex needs 3 coordinates: {raw.strip()!r}")
            v_tok += parts[1:4]
            v_line.append(lineno)
        elif key == b"f":
            if len(parts) < 4:
                raise SceneError(
                    f"{p}:{lineno}: face has {len(parts) - 1} corner(s) (need >= 3): file "
                    f"truncated or corrupt ({raw.strip()[:60]!r})"
                )
            f_tok += parts[1:]
            f_n.append(len(parts) - 1)
            f_line.append(lineno)
            f_state.append((len(v_line), len(vt_line), len(vn_line), cur_mat, cur_s))
        elif key == b"vt":
            if len(parts) < 2:
                raise SceneError(f"{p}:{lineno}: texture coordinate without numbers")
            vt_tok += (parts[1:3] + [b"0"])[:2]
            vt_line.append(lineno)
        elif key == b"vn":
            if len(parts) < 4:
                raise SceneError(f"{p}:{lineno}: normal needs 3 coordinates: {raw.strip()!r}")
            vn_tok += parts[1:4]
            vn_line.append(lineno)
        elif key == b"usemtl":
            name = b" ".join(parts[1:]).decode("utf-8", "replace") or "default"
            if name not in mat_index:
                mat_index[name] = len(mat_names)
                mat_names.append(name)
            cur_mat = mat_index[name]
        elif key == b"s":
            arg = parts[1].lower() if len(parts) > 1 else b"off"
            if arg in (b"off", b"0"):
                cur_s = 0
            else:
                try:
                    cur_s = int(arg)
                except ValueError:
                    raise SceneError(
                        f"{p}:{lineno}: smoothing group must be an integer or 'off', got "
                        f"{arg.decode(errors='replace')!r}"
                    ) from None
        elif key == b"mtllib":
            # several files on one line; a name with spaces is rare but kept if it is one file
            names = [x.decode("utf-8", "replace") for x in parts[1:]]
            whole = " ".join(names)
            if len(names) > 1 and (p.parent / whole).is_file():
                names = [whole]
            mtllibs += names
        elif key in _HARMLESS:
            continue
        elif key == b"l":
            skipped["line element(s) 'l'"] = skipped.get("line element(s) 'l'", 0) + 1
        elif key == b"p":
            skipped["point element(s) 'p'"] = skipped.get("point element(s) 'p'", 0) + 1
        elif key in _FREEFORM:
            k = "free-form curve/surface statement(s)"
            skipped[k] = skipped.get(k, 0) + 1
        else:
            k = f"unknown statement(s) '{key.decode(errors='replace')[:20]}'"
            skipped[k] = skipped.get(k, 0) + 1
    if skipped:
        repair_warning(
            str(p),
            "ignored " + ", ".join(f"{n} {k}" for k, n in skipped.items()) + " (unsupported)",
        )
    if not v_line or not f_n:
        raise SceneError(f"{p}: empty mesh ({len(v_line)} vertices, {len(f_n)} faces)")

    pos = _floats(p, v_tok, v_line, 3, "vertex")
    tex = _floats(p, vt_tok, vt_line, 2, "texture") if vt_line else np.zeros((0, 2))
    nrm = _floats(p, vn_tok, vn_line, 3, "normal") if vn_line else np.zeros((0, 3))

    counts = np.asarray(f_n, np.int64)
    state = np.asarray(f_state, np.int64).reshape(-1, 5)
    corner_face = np.repeat(np.arange(len(counts)), counts)
    idx = _corner_indices(p, f_tok, f_line, corner_face)  # (C, 3), 0 = absent
    resolved = np.empty_like(idx)
    kinds = ((len(pos), "vertex"), (len(tex), "texture"), (len(nrm), "normal"))
    for k, (total, what) in enumerate(kinds):
        col = idx[:, k]
        before = state[corner_face, k]
        r = np.where(col > 0, col - 1, before + col)  # negative: relative to those defined so far
        absent = col == 0
        if k == 0 and absent.any():
            c = int(np.argmax(absent))
            raise SceneError(
                f"{p}:{f_line[corner_face[c]]}: face vertex index 0 out of range "
                "(OBJ indices start at 1; 0 is not valid)"
            )
        bad = ~absent & ((r < 0) | (r >= total))
        if bad.any():
            c = int(np.argmax(bad))
            i, n_before = int(col[c]), int(before[c])
            hint = (
                f"{n_before} defined before this face (relative indices -1..-{n_before})"
                if i < 0
                else f"the file has {total} (indices 1..{total})"
            )
            raise SceneError(
                f"{p}:{f_line[corner_face[c]]}: face {what} index {i} out of range: {hint}"
            )
        resolved[:, k] = np.where(absent, -1, r)

    # smoothing key: corners with a normal or in a smoothing group are shared by position;
    # flat faces (no vn, s off) get their own vertices (key = -(polygon + 1))
    s_face = state[:, 4]
    skey = np.where(s_face[corner_face] != 0, s_face[corner_face], -(corner_face + 1))
    skey = np.where(resolved[:, 2] >= 0, 0, skey)
    keys = np.column_stack([resolved, skey])
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first, kind="stable")  # vertices in order of first use
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    corner_vertex = rank[inverse]
    uniq = keys[first[order]]

    vertices = pos[uniq[:, 0]]
    normals = np.full((len(uniq), 3), np.nan)
    has_n = uniq[:, 2] >= 0
    normals[has_n] = nrm[uniq[has_n, 2]]
    uvs = None
    if (uniq[:, 1] >= 0).any():
        uvs = np.zeros((len(uniq), 2))
        has_t = uniq[:, 1] >= 0
        uvs[has_t] = tex[uniq[has_t, 1]]

    faces, tri_poly = _triangulate(pos[resolved[:, 0]], corner_vertex, counts)
    mats = state[:, 3]
    if (mats < 0).any():
        if "default" not in mat_index:
            mat_index["default"] = len(mat_names)
            mat_names.append("default")
        mats = np.where(mats < 0, mat_index["default"], mats)
    # drop materials no face uses (a usemtl followed by no faces), keeping first-use order
    used = np.unique(mats)
    remap = np.full(len(mat_names), -1, np.int64)
    remap[used] = np.arange(len(used))
    names = [mat_names[i] for i in used]
    return ObjMesh(
        vertices=vertices,
        faces=faces,
        normals=normals,
        normal_given=has_n,
        uvs=uvs,
        face_material=remap[mats[tri_poly]].astype(np.int32),
        material_names=names,
        mtllibs=mtllibs,
        face_line=np.asarray(f_line, np.int64)[tri_poly],
    )


def _corner_indices(
    p: Path, tokens: list[bytes], f_line: list[int], corner_face: np.ndarray
) -> np.ndarray:
    """(C, 3) int64 (v, vt, vn) per face corner as written; 0 where a part is absent."""
    split = [t.split(b"/") for t in tokens]
    nparts = np.fromiter(map(len, split), np.int64, len(split))
    if (nparts > 3).any():
        c = int(np.argmax(nparts > 3))
        raise SceneError(
            f"{p}:{f_line[corner_face[c]]}: face corner {tokens[c].decode(errors='replace')!r} "
            "is not v, v/vt, v//vn or v/vt/vn"
        )
    cols = []
    for k in range(3):
        col = [s[k] if len(s) > k and s[k] else b"0" for s in split]
        try:
            cols.append(np.array(col, dtype=np.bytes_).astype(np.int64))
        except ValueError:
            for c, t in enumerate(col):
                try:
                    int(t)
                except ValueError:
                    raise SceneError(
                        f"{p}:{f_line[corner_face[c]]}: corrupt face line: index "
                        f"{t.decode(errors='replace')!r} in corner "
                        f"{tokens[c].decode(errors='replace')!r} is not an integer"
                    ) from None
            raise  # pragma: no cover
    return np.column_stack(cols)


def _triangulate(
    corner_pos: np.ndarray, corner_vertex: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (T, 3) of scene vertex indices and (T,) their polygon index.

    Args:
        corner_pos: (C, 3) corner positions (for convexity).
        corner_vertex: (C,) scene vertex of each corner.
        counts: (P,) corners per polygon.
    """
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris: list[np.ndarray] = []
    polys: list[np.ndarray] = []
    # triangles
    sel = np.flatnonzero(counts == 3)
    if len(sel):
        c = start[sel, None] + np.arange(3)
        tris.append(c)
        polys.append(sel)
    # quads: fan from corner 0, or from corner 1 when corner 1 or 3 is reflex
    sel = np.flatnonzero(counts == 4)
    if len(sel):
        c = start[sel, None] + np.arange(4)
        q = corner_pos[c]
        n = _newell(q)
        e_in = q - np.roll(q, 1, axis=1)
        e_out = np.roll(q, -1, axis=1) - q
        turn = np.einsum("qkj,qj->qk", np.cross(e_in, e_out), n)
        shift = (turn[:, 1] < 0) | (turn[:, 3] < 0)
        c = np.where(shift[:, None], np.roll(c, -1, axis=1), c)
        tris.append(np.concatenate([c[:, [0, 1, 2]], c[:, [0, 2, 3]]]))
        polys.append(np.concatenate([sel, sel]))
    # n-gons: fan if convex, else ear clipping
    for i in np.flatnonzero(counts > 4):
        c = start[i] + np.arange(counts[i])
        local = _ear_clip(corner_pos[c])
        tris.append(c[local])
        polys.append(np.full(len(local), i))
    corners = np.concatenate(tris)
    poly = np.concatenate(polys)
    order = np.argsort(poly, kind="stable")  # triangles in file order
    return corner_vertex[corners[order]].astype(np.int64), poly[order]


def _newell(q: np.ndarray) -> np.ndarray:
    """(..., 3) Newell normal (unnormalised) of polygons (..., n, 3)."""
    nxt = np.roll(q, -1, axis=-2)
    return np.cross(q, nxt).sum(axis=-2)


def _ear_clip(q: np.ndarray) -> np.ndarray:
    """(n - 2, 3) local corner indices triangulating the (possibly non-convex) polygon ``q``.

    The polygon is projected onto the plane of its Newell normal; a convex polygon is fanned
    from corner 0; otherwise ears are clipped (O(n^2)). A polygon that is not simple (no ear
    found) falls back to the fan.
    """
    n = len(q)
    normal = _newell(q)
    ln = np.linalg.norm(normal)
    fan = np.column_stack([np.zeros(n - 2, np.int64), np.arange(1, n - 1), np.arange(2, n)])
    if ln == 0:
        return fan
    normal = normal / ln
    a = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    xy = np.column_stack([q @ a, q @ b])  # counter-clockwise seen along +normal

    def cross2(o: np.ndarray, u: np.ndarray, w: np.ndarray) -> float:
        return float((u[0] - o[0]) * (w[1] - o[1]) - (u[1] - o[1]) * (w[0] - o[0]))

    turns = [cross2(xy[i - 1], xy[i], xy[(i + 1) % n]) for i in range(n)]
    if min(turns) >= 0:
        return fan
    idx = list(range(n))
    out = []
    guard = 0
    while len(idx) > 3 and guard < n * n:
        guard += 1
        m = len(idx)
        for k in range(m):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % m]
            if cross2(xy[i0], xy[i1], xy[i2]) <= 0:
                continue  # reflex or flat corner: not an ear
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                pt = xy[j]
                if (
                    cross2(xy[i0], xy[i1], pt) >= 0
                    and cross2(xy[i1], xy[i2], pt) >= 0
                    and cross2(xy[i2], xy[i0], pt) >= 0
                ):
                    inside = True
                    break
            if not inside:
                out.append((i0, i1, i2))
                idx.pop(k)
                break
        else:
            return fan  # not a simple polygon
    out.append(tuple(idx))
    return np.asarray(out, np.int64)


# --------------------------------------------------------------------------- MTL
@dataclass
class MtlMaterial:
    """One ``newmtl`` block as read (colours linear RGB, (3,) float64)."""

    name: str
    Kd: np.ndarray = field(default_factory=lambda: np.full(3, 0.8))
    Ke: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Ks: np.ndarray = field(default_factory=lambda: np.zeros(3))
    Tf: np.ndarray | None = None
    Ns: float | None = None
    Ni: float | None = None
    d: float | None = None
    Tr: float | None = None
    illum: int | None = None
    map_Kd: Path | None = None
    line: int = 0

    @property
    def opacity(self) -> float:
        """``d``, else ``1 - Tr``, else 1."""
        if self.d is not None:
            return self.d
        if self.Tr is not None:
            return 1.0 - self.Tr
        return 1.0

    def diffuse(self) -> tuple[np.ndarray, str | None]:
        """The nearest diffuse albedo (3,) and what was approximated (None if nothing)."""
        reasons = []
        if self.illum is not None and 3 <= self.illum <= 7:
            kind = {3: "mirror", 4: "glass", 5: "mirror (Fresnel)", 6: "refraction", 7: "glass"}
            reasons.append(f"{kind[self.illum]} (illum {self.illum})")
        kd_max, ks_max = float(np.max(self.Kd)), float(np.max(self.Ks))
        if ks_max > kd_max and ks_max > 0:
            ns = f", Ns {self.Ns:g}" if self.Ns is not None else ""
            reasons.append(f"specular Ks {np.round(self.Ks, 4).tolist()} > Kd{ns} (glossy)")
        op = self.opacity
        if op < 1.0:
            reasons.append(f"transparent (opacity {op:g})")
        if not reasons:
            return self.Kd, None
        if self.Tf is not None and self.illum in (4, 6, 7):
            t = np.asarray(self.Tf, np.float64)
        else:
            t = np.full(3, max(0.0, 1.0 - op))
        albedo = np.clip(self.Kd + self.Ks + t, 0.0, 1.0)
        rule = "clip(Kd + Ks + T)"
        if albedo.max() < DARK_APPROXIMATION:
            albedo = np.full(3, 0.8)
            rule = "0.8 grey (Kd + Ks + T would be black)"
        return albedo, (
            f"{'; '.join(reasons)}: rendered as diffuse albedo "
            f"{np.round(albedo, 4).tolist()} ({rule})"
        )


def parse_mtl(path: str | Path) -> dict[str, MtlMaterial]:
    """Read the ``newmtl`` blocks of an MTL file.

    Raises:
        SceneError: ``path:line:`` a colour or number that is not a number.
    """
    p = Path(path)
    mats: dict[str, MtlMaterial] = {}
    cur: MtlMaterial | None = None
    text = p.read_text(encoding="utf-8", errors="replace")
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0]
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        low = key.lower()
        if key == "newmtl":
            name = " ".join(parts[1:])
            cur = mats[name] = MtlMaterial(name, line=lineno)
            continue
        if cur is None:
            continue
        try:
            if low in ("kd", "ke", "ks", "tf"):
                if parts[1:2] and parts[1] in ("spectral", "xyz"):
                    raise SceneError(f"{p}:{lineno}: {key} {parts[1]} colours are not supported")
                vals = [float(x) for x in parts[1:4]]
                if len(vals) == 1:
                    vals = vals * 3
                if len(vals) != 3:
                    raise SceneError(f"{p}:{lineno}: {key} needs 1 or 3 numbers: {line.strip()!r}")
                setattr(cur, {"kd": "Kd", "ke": "Ke", "ks": "Ks", "tf": "Tf"}[low], np.array(vals))
            elif low in ("ns", "ni", "d", "tr"):
                val = parts[-1] if low == "d" else parts[1]  # "d -halo 0.5"
                setattr(cur, {"ns": "Ns", "ni": "Ni", "d": "d", "tr": "Tr"}[low], float(val))
            elif low == "illum":
                cur.illum = int(parts[1])
            elif low == "map_kd" and len(parts) > 1:
                cur.map_Kd = p.parent / _map_file(parts[1:]).replace("\\", "/")
        except (ValueError, IndexError):
            raise SceneError(f"{p}:{lineno}: bad {key} value {line.strip()!r}") from None
    return mats


#: Number of arguments of each MTL texture map option (``-o u v w`` takes up to 3).
_MAP_OPTIONS = {
    "-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
    "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1, "-type": 1,
}  # fmt: skip


def _map_file(args: list[str]) -> str:
    """The file name of a ``map_*`` statement's arguments (options come first)."""
    i = 0
    while i < len(args) and args[i] in _MAP_OPTIONS:
        n = _MAP_OPTIONS[args[i]]
        i += 1
        for _ in range(n):  # -o/-s/-t take 1 to 3 numbers
            if i < len(args) - 1 and _is_number(args[i]):
                i += 1
            elif n == 1 and i < len(args) - 1:
                i += 1
    return " ".join(args[i:]) if i < len(args) else args[-1]


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def material_warning(where: str, name: str, what: str) -> None:
    """Emit a :class:`MaterialApproximationWarning` ``"<where>: material '<name>': <what>"``."""
    warnings.warn(f"{where}: material '{name}': {what}", MaterialApproximationWarning, stacklevel=3)


__all__ = [
    "MaterialApproximationWarning",
    "MtlMaterial",
    "ObjMesh",
    "material_warning",
    "parse_mtl",
    "parse_obj",
]
