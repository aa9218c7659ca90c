"""Binary PLY triangle meshes read with numpy alone (the common case of exported scenes).

A Mitsuba scene may hold hundreds of PLY files; reading each through trimesh costs its import
(seconds, scipy included) and a per-file Scene. :func:`read_binary_ply` reads, in one structured
``np.frombuffer`` per element, a binary PLY whose ``vertex`` element has scalar properties
(``x y z``, optionally ``nx ny nz`` and ``u v`` / ``s t`` / ``texture_u texture_v``) and whose
``face`` element starts with a list property (``vertex_indices`` or ``vertex_index``) with the
same count on every face (triangles; quads are split ``(0, 1, 2), (0, 2, 3)``), then scalar
properties only (colours: ignored). Anything else (ASCII, mixed polygon sizes, per-corner lists
such as ``texcoord``, other elements after the faces) returns None, and the caller reads the file
the general way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_UV_NAMES = (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))


def read_binary_ply(path: Path) -> tuple | None:
    """(vertices (V, 3) float64, faces (F, 3) int64, normals (V, 3) float64 with NaN rows when
    the file has none, uvs (V, 2) float64 as written or None), or None when the file is not of
    the simple binary kind this reader handles (see the module docstring)."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        return None
    body = data.index(b"\n", end) + 1
    elements: list[list] = []  # [name, count, [(prop, dtype) | ("list", count_t, item_t, name)]]
    fmt = None
    for line in data[:end].decode("ascii", "replace").splitlines():
        w = line.split()
        if not w or w[0] in ("comment", "obj_info", "ply"):
            continue
        if w[0] == "format":
            fmt = w[1] if len(w) > 1 else None
        elif w[0] == "element" and len(w) == 3:
            elements.append([w[1], int(w[2]), []])
        elif w[0] == "property" and elements:
            if w[1] == "list" and len(w) == 5 and w[2] in _TYPES and w[3] in _TYPES:
                elements[-1][2].append(("list", _TYPES[w[2]], _TYPES[w[3]], w[4]))
            elif len(w) == 3 and w[1] in _TYPES:
                elements[-1][2].append((w[2], _TYPES[w[1]]))
            else:
                return None
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt or "")
    names = [e[0] for e in elements]
    if order is None or names[:2] != ["vertex", "face"] or len(names) > 2:
        return None
    (_, nv, vprops), (_, nf, fprops) = elements
    lists = [p for p in fprops if p[0] == "list"]
    if any(p[0] == "list" for p in vprops) or len(lists) != 1 or fprops[0][0] != "list":
        return None  # per-corner lists (texcoord) would change the vertices: general reader
    if fprops[0][3] not in ("vertex_indices", "vertex_index"):
        return None
    vdt = np.dtype([(p[0], order + p[1]) for p in vprops])
    if body + nv * vdt.itemsize > len(data):
        return None
    vert = np.frombuffer(data, vdt, count=nv, offset=body)
    _, count_t, item_t, _ = fprops[0]
    pos = body + nv * vdt.itemsize
    if nf == 0 or pos + np.dtype(count_t).itemsize > len(data):
        return None
    k = int(np.frombuffer(data, order + count_t, count=1, offset=pos)[0])
    if k < 3:
        return None
    extra = [(f"_{j}", order + p[1]) for j, p in enumerate(fprops[1:])]  # colours etc.
    fdt = np.dtype([("n", order + count_t), ("i", order + item_t, (k,)), *extra])
    if pos + nf * fdt.itemsize != len(data):
        return None  # mixed polygon sizes (or trailing data): the general reader
    face = np.frombuffer(data, fdt, count=nf, offset=pos)
    if np.any(face["n"] != k):
        return None
    fields = vdt.names or ()
    if not all(c in fields for c in "xyz"):
        return None
    v = np.stack([vert[c] for c in "xyz"], axis=1).astype(np.float64)
    n = np.full_like(v, np.nan)
    if all(c in fields for c in ("nx", "ny", "nz")):
        n = np.stack([vert[c] for c in ("nx", "ny", "nz")], axis=1).astype(np.float64)
    uv = None
    for a, b in _UV_NAMES:
        if a in fields and b in fields:
            uv = np.stack([vert[a], vert[b]], axis=1).astype(np.float64)
            break
    idx = face["i"].astype(np.int64)
    f = np.concatenate([idx[:, [0, j, j + 1]] for j in range(1, k - 1)]) if k > 3 else idx
    if k > 3:  # keep each polygon's triangles together, in order
        f = f.reshape(k - 2, nf, 3).transpose(1, 0, 2).reshape(-1, 3)
    return v, np.ascontiguousarray(f), n, uv


__all__ = ["read_binary_ply"]
