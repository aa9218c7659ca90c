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
  the polygon's normal), so a box's corners are never smoothed across 90 degrees; within a
  smoothing group ``s N`` the corners sharing a position share a vertex whose normal is the sum
  of the area-weighted normals of that group's polygons around it (OBJ's meaning of a smoothing
  group; whole polygons count, not their triangles, so the diagonal a quad is split along does
  not bias it). A polygon's normal is its Newell normal (exact for planar polygons). Faces with
  ``vn`` use the file's normals.
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
``c = Kd + Ks + T`` with ``T = Tf`` for illum 4/6/7 when ``Tf`` is given, else ``T = 1 - opacity``,
then :func:`approximated_albedo` (the one rule of every loader): ``c`` scaled down, hue kept, so
that its largest channel is at most :data:`MAX_APPROXIMATED_ALBEDO` (0.8): an approximated
material never gets an albedo >= 1 (a glass or mirror that absorbed nothing would light a scene
up without end); a colour darker than 0.04 (e.g. a mirror with ``Kd = Ks = 0``) becomes 0.8 grey,
so a mirror never turns black. Emission (``Ke``) is kept as it is.

Vertices: a NaN or Inf position used by a face is an error naming ``file:line``, the OBJ index
and the statement as written (``v 1 nan 0``); unused ones are reported in one warning.
"""

from __future__ import annotations

import itertools
import re
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
#: Largest channel of an approximated (non-diffuse) material's albedo (see
#: :func:`approximated_albedo`); < 1, so an approximation never reflects all the light.
MAX_APPROXIMATED_ALBEDO = 0.8


def approximated_albedo(colour: np.ndarray) -> tuple[np.ndarray, str]:
    """The diffuse albedo standing in for a material icbtool cannot render (the one rule).

    ``colour`` is what the material reflects or transmits in all (each loader says how it is
    summed: MTL ``Kd + Ks + T``, glTF the base colour, Mitsuba its normal-incidence reflectance
    plus transmittance). Negative channels are 0. A colour whose largest channel exceeds
    :data:`MAX_APPROXIMATED_ALBEDO` is scaled down to it (hue kept); one darker than
    :data:`DARK_APPROXIMATION` becomes 0.8 grey (a mirror never turns black). The result's
    channels are therefore always < 1.

    Args:
        colour: (3,) linear RGB.

    Returns:
        ((3,) float64 albedo in [0, 0.8], the rule applied, for the warning).
    """
    c = np.maximum(np.nan_to_num(np.asarray(colour, np.float64), nan=0.0, posinf=1e3), 0.0)
    top = float(c.max())
    if top < DARK_APPROXIMATION:
        return np.full(3, 0.8), "0.8 grey: the colour would be black"
    if top > MAX_APPROXIMATED_ALBEDO:
        return c * (MAX_APPROXIMATED_ALBEDO / top), (
            f"scaled by {MAX_APPROXIMATED_ALBEDO / top:.3g} to a largest channel of "
            f"{MAX_APPROXIMATED_ALBEDO:g} (an approximation never reflects all the light)"
        )
    return c, "as is"


class MaterialApproximationWarning(SceneRepairWarning):
    """A material icbtool cannot render (mirror, glass, glossy, metal, emission texture...) was
    replaced by the nearest diffuse one; the message names the material and what was changed."""


@dataclass
class ObjMesh:
    """An OBJ file as triangle arrays (file coordinates, before any scale or up-axis change).

    Attributes:
        vertices: (V, 3) float64 positions, one per unique corner (see the module docstring).
        faces: (F, 3) int64 indices into ``vertices``.
        normals: (V, 3) float64 unit normals: the file's where ``normal_given``, else computed
            from the polygons (see the module docstring); NaN where they cannot be (zero area).
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


class _Statements:
    """The non-geometry statements (materials, smoothing, libraries, skipped ones) of a file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.mtllibs: list[str] = []
        self.mat_names: list[str] = []
        self.mat_index: dict[str, int] = {}
        self.cur_mat = -1
        self.cur_s = 0
        self.skipped: dict[str, int] = {}

    def handle(self, key: bytes, parts: list[bytes], lineno: int) -> bool:
        """Apply one statement; True when it changed the material or smoothing state."""
        if key == b"usemtl":
            name = b" ".join(parts[1:]).decode("utf-8", "replace") or "default"
            if name not in self.mat_index:
                self.mat_index[name] = len(self.mat_names)
                self.mat_names.append(name)
            self.cur_mat = self.mat_index[name]
            return True
        if key == b"s":
            arg = parts[1].lower() if len(parts) > 1 else b"off"
            if arg in (b"off", b"0"):
                self.cur_s = 0
            else:
                try:
                    self.cur_s = int(arg)
                except ValueError:
                    raise SceneError(
                        f"{self.path}:{lineno}: smoothing group must be an integer or 'off', got "
                        f"{arg.decode(errors='replace')!r}"
                    ) from None
            return True
        if key == b"mtllib":
            # several files on one line; a single name with spaces is kept if it is a file
            names = [x.decode("utf-8", "replace") for x in parts[1:]]
            whole = " ".join(names)
            if len(names) > 1 and (self.path.parent / whole).is_file():
                names = [whole]
            self.mtllibs += names
        elif key in _HARMLESS:
            pass
        elif key == b"l":
            self._skip("line element(s) 'l'")
        elif key == b"p":
            self._skip("point element(s) 'p'")
        elif key in _FREEFORM:
            self._skip("free-form curve/surface statement(s)")
        else:
            self._skip(f"unknown statement(s) '{key.decode(errors='replace')[:20]}'")
        return False

    def _skip(self, what: str) -> None:
        self.skipped[what] = self.skipped.get(what, 0) + 1

    def warn(self) -> None:
        if self.skipped:
            repair_warning(
                str(self.path),
                "ignored "
                + ", ".join(f"{n} {k}" for k, n in self.skipped.items())
                + " (unsupported)",
            )


@dataclass
class _Scan:
    """Everything read from the file before indices are resolved."""

    pos: np.ndarray  # (Nv, 3)
    tex: np.ndarray  # (Nt, 2)
    nrm: np.ndarray  # (Nn, 3)
    idx: np.ndarray  # (C, 3) v, vt, vn per corner as written, 0 = absent
    counts: np.ndarray  # (P,) corners per polygon
    f_line: np.ndarray  # (P,) 1-based line
    state: np.ndarray  # (P, 5) nv, nvt, nvn before the face, material, smoothing group
    pos_line: np.ndarray  # (Nv,) 1-based line of each ``v``


_COMMENT = re.compile(rb"#[^\r\n]*")


def parse_obj(path: str | Path, data: bytes | None = None, *, fast: bool = True) -> ObjMesh:
    """Parse an OBJ file (see the module docstring for what is read and the rules).

    Args:
        path: the .obj file (named in messages; read unless ``data`` is given).
        data: the file's bytes, if already read.
        fast: try the vectorised reader first (any irregular file, and every error, goes
            through the line-by-line reader, which gives the same result).

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
    st = _Statements(p)
    scan = _scan_fast(p, data, st) if fast else None
    if scan is None:
        st = _Statements(p)
        scan = _scan_lines(p, data, st)
    st.warn()
    mesh = _build(p, scan, st)
    _check_positions(p, data, scan)
    return mesh


def _check_positions(p: Path, data: bytes, scan: _Scan) -> None:
    """NaN/Inf vertex positions: an error naming file:line and the statement as written when a
    face uses one; a warning listing the lines of unused ones."""
    bad = ~np.isfinite(scan.pos).all(axis=1)
    if not bad.any():
        return
    used = np.zeros(len(scan.pos), bool)
    corner_face = np.repeat(np.arange(len(scan.counts)), scan.counts)
    col = scan.idx[:, 0]
    r = np.where(col > 0, col - 1, scan.state[corner_face, 0] + col)
    used[r[(r >= 0) & (r < len(used))]] = True
    lines = data.splitlines()

    def written(k: int) -> str:
        ln = int(scan.pos_line[k])
        text = lines[ln - 1].split(b"#", 1)[0].strip() if ln - 1 < len(lines) else b""
        return f"{p}:{ln}: vertex {k + 1} {text.decode('utf-8', 'replace')!r}"

    bad_used = np.flatnonzero(bad & used)
    bad_unused = np.flatnonzero(bad & ~used)
    if len(bad_unused):
        shown = ", ".join(str(int(scan.pos_line[k])) for k in bad_unused[:10])
        more = f" and {len(bad_unused) - 10} more" if len(bad_unused) > 10 else ""
        repair_warning(
            str(p),
            f"{len(bad_unused)} vertex position(s) no face uses are NaN or Inf (line(s) "
            f"{shown}{more}; first: {written(int(bad_unused[0]))}): ignored",
        )
    if len(bad_used):
        raise SceneError(
            f"{written(int(bad_used[0]))} has a NaN or Inf coordinate and is used by a face "
            f"({len(bad_used)} such vertex position(s) in the file)"
        )


def _scan_fast(p: Path, data: bytes, st: _Statements) -> _Scan | None:
    """Vectorised reading of a regular file (one statement per line, keyword first, uniform
    number of coordinates); None when the file is irregular (then :func:`_scan_lines`)."""
    if b"\\" in data:
        return None  # line continuations (or odd names): the generic reader
    if b"#" in data:
        data = _COMMENT.sub(b"", data)
    lines = data.splitlines()
    heads = np.array([x[:2] for x in lines], dtype="S2")
    is_v = (heads == b"v ") | (heads == b"v\t")
    is_vt = heads == b"vt"
    is_vn = heads == b"vn"
    is_f = (heads == b"f ") | (heads == b"f\t")
    ev_line, ev_mat, ev_s = [-1], [-1], [0]
    for i in np.flatnonzero(~(is_v | is_vt | is_vn | is_f)).tolist():
        parts = lines[i].split()
        if not parts:
            continue
        if parts[0] in (b"v", b"vt", b"vn", b"f"):
            return None  # indented or unusual geometry statement
        if st.handle(parts[0], parts, i + 1):
            ev_line.append(i)
            ev_mat.append(st.cur_mat)
            ev_s.append(st.cur_s)
    f_idx = np.flatnonzero(is_f)
    if not is_v.any() or len(f_idx) == 0:
        return None
    pos = _block(lines, is_v, b"v", (3,))
    tex = _block(lines, is_vt, b"vt", (2, 3, 1)) if is_vt.any() else np.zeros((0, 2))
    nrm = _block(lines, is_vn, b"vn", (3,)) if is_vn.any() else np.zeros((0, 3))
    if pos is None or tex is None or nrm is None:
        return None
    f_lines = [lines[i] for i in f_idx.tolist()]
    parts = list(map(bytes.split, f_lines))
    counts = np.fromiter(map(len, parts), np.int64, len(parts)) - 1
    if counts.min() < 3:
        return None
    corners = list(itertools.chain.from_iterable(x[1:] for x in parts))
    idx = _corners_fast(corners)
    if idx is None:
        return None
    ev = np.searchsorted(np.asarray(ev_line), f_idx) - 1
    state = np.column_stack(
        [
            np.cumsum(is_v)[f_idx],
            np.cumsum(is_vt)[f_idx],
            np.cumsum(is_vn)[f_idx],
            np.asarray(ev_mat)[ev],
            np.asarray(ev_s)[ev],
        ]
    ).astype(np.int64)
    return _Scan(pos, tex, nrm, idx, counts, f_idx + 1, state, np.flatnonzero(is_v) + 1)


def _block(lines: list[bytes], mask: np.ndarray, key: bytes, widths: tuple[int, ...]):
    """(N, widths[0]) float64 of the lines in ``mask`` if each has the same count (one of
    ``widths``) of numbers after ``key``; else None."""
    n = int(mask.sum())
    toks = b" ".join([lines[i] for i in np.flatnonzero(mask).tolist()]).split()
    for w in widths:
        if len(toks) != (w + 1) * n:
            continue
        if toks[0 :: w + 1].count(key) != n:
            return None
        del toks[0 :: w + 1]
        try:
            vals = np.fromiter(map(float, toks), np.float64, len(toks)).reshape(n, w)
        except ValueError:
            return None
        out = np.zeros((n, widths[0]))
        k = min(w, widths[0])
        out[:, :k] = vals[:, :k]
        return out
    return None


def _corners_fast(tok: list[bytes]) -> np.ndarray | None:
    """(C, 3) int64 (v, vt, vn) of corner tokens (0 = absent), or None if irregular."""
    n = len(tok)
    nslash = np.fromiter(map(bytes.count, tok, itertools.repeat(b"/")), np.int64, n)
    dbl = np.fromiter(map(bytes.count, tok, itertools.repeat(b"//")), np.int64, n) > 0
    if (nslash > 2).any():
        return None
    out = np.zeros((n, 3), np.int64)
    obj = None
    for sel, sep, cols in (
        ((nslash == 0), b"/", [0]),
        ((nslash == 1), b"/", [0, 1]),
        ((nslash == 2) & ~dbl, b"/", [0, 1, 2]),
        ((nslash == 2) & dbl, b"//", [0, 2]),
    ):
        m = int(sel.sum())
        if m == 0:
            continue
        if m == n:
            group = tok
        else:
            obj = np.array(tok, dtype=object) if obj is None else obj
            group = obj[sel].tolist()
        text = b" ".join(group).replace(sep, b" ")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # junk: an exception on every numpy version
                vals = np.fromstring(text, dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
        if len(vals) != len(cols) * m:
            return None  # empty parts such as "1/" or "1/2/"
        if (vals == 0).any():
            return None  # a literal index 0: the line-by-line reader names the line
        out[np.ix_(np.flatnonzero(sel), cols)] = vals.reshape(m, len(cols))
    return out


def _scan_lines(p: Path, data: bytes, st: _Statements) -> _Scan:
    """The generic line-by-line reader (every error is raised from here, naming file:line)."""
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
            f_state.append((len(v_line), len(vt_line), len(vn_line), st.cur_mat, st.cur_s))
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
        else:
            st.handle(key, parts, lineno)
    if not v_line or not f_n:
        raise SceneError(f"{p}: empty mesh ({len(v_line)} vertices, {len(f_n)} faces)")
    pos = _floats(p, v_tok, v_line, 3, "vertex")
    tex = _floats(p, vt_tok, vt_line, 2, "texture") if vt_line else np.zeros((0, 2))
    nrm = _floats(p, vn_tok, vn_line, 3, "normal") if vn_line else np.zeros((0, 3))
    counts = np.asarray(f_n, np.int64)
    corner_face = np.repeat(np.arange(len(counts)), counts)
    idx = _corner_indices(p, f_tok, f_line, corner_face)
    state = np.asarray(f_state, np.int64).reshape(-1, 5)
    return _Scan(
        pos, tex, nrm, idx, counts, np.asarray(f_line, np.int64), state, np.asarray(v_line)
    )


def _build(p: Path, scan: _Scan, st: _Statements) -> ObjMesh:
    """Resolve indices, split vertices, triangulate (see the module docstring)."""
    pos, tex, nrm, idx = scan.pos, scan.tex, scan.nrm, scan.idx
    counts, state, f_line = scan.counts, scan.state, scan.f_line
    mat_names, mat_index, mtllibs = st.mat_names, st.mat_index, st.mtllibs
    corner_face = np.repeat(np.arange(len(counts)), counts)
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

    corner_pos = pos[resolved[:, 0]]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf positions: reported later
        faces, tri_poly = _triangulate(corner_pos, corner_vertex, counts)
        normals = _computed_normals(
            normals, has_n, corner_pos, corner_face, corner_vertex, counts, resolved[:, 2] < 0
        )
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


def _computed_normals(
    normals: np.ndarray,
    has_n: np.ndarray,
    corner_pos: np.ndarray,
    corner_face: np.ndarray,
    corner_vertex: np.ndarray,
    counts: np.ndarray,
    no_vn: np.ndarray,
) -> np.ndarray:
    """Fill the rows of ``normals`` without a file normal (see the module docstring): the sum
    of the area-weighted (Newell) normals of the polygons sharing the vertex, normalised."""
    need = ~has_n
    if not need.any():
        return normals
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nxt = np.arange(len(corner_pos)) + 1
    nxt[start + counts - 1] = start
    poly_n = np.zeros((len(counts), 3))
    np.add.at(poly_n, corner_face, np.cross(corner_pos, corner_pos[nxt]))
    acc = np.zeros((len(normals), 3))
    np.add.at(acc, corner_vertex[no_vn], poly_n[corner_face[no_vn]])
    ln = np.linalg.norm(acc, axis=1)
    ok = need & (ln > 0) & np.isfinite(ln)
    normals[ok] = acc[ok] / ln[ok, None]
    return normals


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
    for c, s in enumerate(split):
        if any(x.lstrip(b"+-").lstrip(b"0") == b"" and x != b"" for x in s):
            raise SceneError(
                f"{p}:{f_line[corner_face[c]]}: face index 0 out of range in corner "
                f"{tokens[c].decode(errors='replace')!r} (OBJ indices start at 1)"
            )
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
        albedo, rule = approximated_albedo(self.Kd + self.Ks + t)
        return albedo, (
            f"{'; '.join(reasons)}: rendered as diffuse albedo "
            f"{np.round(albedo, 4).tolist()} (Kd + Ks + T, {rule})"
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
    "MAX_APPROXIMATED_ALBEDO",
    "MaterialApproximationWarning",
    "approximated_albedo",
    "MtlMaterial",
    "ObjMesh",
    "material_warning",
    "parse_mtl",
    "parse_obj",
]
