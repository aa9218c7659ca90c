"""Validation and documented repairs of scene inputs (used by :func:`icbtool.scene.load`).

Every problem either raises :class:`SceneError` (a ``ValueError``) naming the file and the problem,
or is repaired with a :class:`SceneRepairWarning` saying what was changed:

=====================================  ==========================================================
problem                                outcome
=====================================  ==========================================================
missing file                           ``FileNotFoundError`` naming the path
unknown file type                      SceneError (lists the supported suffixes)
empty file, empty mesh                 SceneError
truncated / corrupt file               SceneError (OBJ: ``file:line`` of a face with < 3
                                       corners, a bad number, an index of 0 or out of range
                                       (:mod:`icbtool.scene.obj`); PLY: fewer elements than the
                                       header declares; binary formats: the parser's complaint)
NaN / Inf vertex positions used by a   SceneError (OBJ: ``file:line``, the index and the
face                                   statement as written; PLY/glTF: the file's vertex and its
                                       coordinates as read, before any transform)
NaN / Inf positions no face uses       repaired: ignored (SceneRepairWarning with the lines)
face index out of range                SceneError (the offending index and the vertex count)
degenerate faces (repeated index or    repaired: dropped (SceneRepairWarning with the count)
zero area)
NaN / zero-length normals              repaired: those vertices get area-weighted normals
NaN / Inf texture coordinates          repaired: set to (0, 0)
missing or unreadable texture image    repaired: the material uses its base colour alone
albedo outside [0, 1]                  repaired: clipped
mirror, glass, glossy, transparent,    repaired: the nearest diffuse material
metal, emission texture                (``MaterialApproximationWarning``, a SceneRepairWarning
                                       naming the material; rules in :mod:`icbtool.scene.obj` and
                                       :mod:`icbtool.scene.load`)
unsupported OBJ statements (``l``,     repaired: skipped, one warning with their counts
``p``, curves, surfaces)
absurd scale (bounds diagonal          SceneError (fix ``scale`` in the description)
< 1e-6 or > 1e7 units)
=====================================  ==========================================================
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from icbtool.scene.types import _face_cross_chunked

#: Mesh file suffixes :func:`icbtool.scene.load` understands (lower case), and the description.
MESH_SUFFIXES = (".obj", ".gltf", ".glb", ".ply")
DESCRIPTION_SUFFIXES = (".toml",)
#: Mitsuba 3 scene files (:mod:`icbtool.scene.mitsuba`).
MITSUBA_SUFFIXES = (".xml",)
#: Bounds diagonal limits (scene units) outside which a scene is considered mis-scaled.
MIN_DIAGONAL = 1e-6
MAX_DIAGONAL = 1e7
#: A face whose area is below this fraction of diagonal**2 counts as degenerate.
DEGENERATE_AREA_FRACTION = 1e-14


class SceneError(ValueError):
    """A scene file or description is unusable; the message names the file and the problem."""


class SceneRepairWarning(UserWarning):
    """A scene input was repaired on load; the message says what was changed and why."""


def repair_warning(where: str, message: str) -> None:
    """Emit a :class:`SceneRepairWarning` ``"<where>: <message>"`` (attributed to the caller)."""
    warnings.warn(f"{where}: {message}", SceneRepairWarning, stacklevel=3)


def check_file(path: str | os.PathLike, allowed: tuple[str, ...] | None = None) -> Path:
    """Check that ``path`` is an existing, non-empty file of a supported type.

    Args:
        path: the file.
        allowed: accepted lower-case suffixes (default: meshes and descriptions).

    Returns:
        The path as a :class:`Path`.

    Raises:
        FileNotFoundError: if it does not exist or is not a file.
        SceneError: if the suffix is unknown or the file is empty.
    """
    p = Path(path)
    allowed = allowed or (MESH_SUFFIXES + DESCRIPTION_SUFFIXES + MITSUBA_SUFFIXES)
    if not p.exists():
        raise FileNotFoundError(f"scene file not found: {p}")
    if not p.is_file():
        raise FileNotFoundError(f"scene path is not a file: {p}")
    if p.suffix.lower() not in allowed:
        raise SceneError(
            f"{p}: unknown scene file type '{p.suffix}'; supported: {', '.join(allowed)}"
        )
    if p.stat().st_size == 0:
        raise SceneError(f"{p}: file is empty")
    return p


# --------------------------------------------------------------------------- format pre-checks
def ply_header_counts(path: Path, data: bytes) -> dict[str, int]:
    """Element counts declared in a PLY header (e.g. ``{'vertex': 642, 'face': 1280}``).

    Raises:
        SceneError: if the header is missing or malformed.
    """
    if not data.startswith(b"ply"):
        raise SceneError(f"{path}: not a PLY file (missing 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise SceneError(f"{path}: PLY header has no 'end_header': truncated or corrupt")
    counts = {}
    for line in data[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] == "element":
            try:
                counts[parts[1]] = int(parts[2])
            except ValueError:
                raise SceneError(f"{path}: bad PLY header line {line!r}") from None
    return counts


# --------------------------------------------------------------------------- arrays
@dataclass
class MeshArrays:
    """One mesh part as plain arrays (what the loader merges into a Scene).

    Attributes:
        vertices: (V, 3) float32.
        faces: (F, 3) int64.
        normals: (V, 3) float32 or None (computed later).
        uvs: (V, 2) float32 or None.
        material: index into the loader's material list.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    uvs: np.ndarray | None
    material: int


def check_arrays(
    where: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None,
    uvs: np.ndarray | None,
    face_material: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """Validate merged mesh arrays; repair what can be repaired (with warnings).

    Args:
        where: the file (or scene) name used in messages.
        vertices: (V, 3) float.
        faces: (F, 3) int.
        normals: (V, 3) float or None; NaN / zero-length rows are marked for recomputation.
        uvs: (V, 2) float or None.
        face_material: (F,) int.

    Returns:
        vertices (V, 3) float32, faces (F', 3) int64 without degenerate faces, normals (V, 3)
        float32 with NaN rows where they must be recomputed (or None), uvs (V, 2) float32 or None,
        face_material (F',) int32.

    Raises:
        SceneError: empty mesh, NaN/Inf vertices, out-of-range indices, absurd scale.
    """
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise SceneError(f"{where}: empty mesh (no vertices)")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise SceneError(f"{where}: empty mesh (no triangles)")
    f = f.astype(np.int64)
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise SceneError(
            f"{where}: {len(bad)} vertex position(s) are NaN or Inf (first: vertex {bad[0]} = "
            f"{v[bad[0]].tolist()})"
        )
    if f.min() < 0 or f.max() >= len(v):
        i = f.max() if f.max() >= len(v) else f.min()
        raise SceneError(f"{where}: face vertex index {int(i)} out of range for {len(v)} vertices")
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    diag = float(np.linalg.norm(hi - lo))
    if not (MIN_DIAGONAL <= diag <= MAX_DIAGONAL):
        raise SceneError(
            f"{where}: absurd scale: bounds {lo.tolist()} .. {hi.tolist()} (diagonal {diag:.3g}) "
            f"outside [{MIN_DIAGONAL:g}, {MAX_DIAGONAL:g}] units; set 'scale' in the description"
        )
    fm = np.asarray(face_material, dtype=np.int32).reshape(-1)
    # degenerate faces: repeated indices or (near) zero area
    area2 = np.linalg.norm(_face_cross_chunked(v, f), axis=1)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    degenerate = repeated | (0.5 * area2 <= DEGENERATE_AREA_FRACTION * diag * diag)
    if degenerate.any():
        n_bad = int(degenerate.sum())
        if n_bad == len(f):
            raise SceneError(f"{where}: all {n_bad} triangles are degenerate (zero area)")
        repair_warning(
            where,
            f"dropped {n_bad} degenerate triangle(s) (repeated vertex or zero area) of {len(f)}",
        )
        f, fm = f[~degenerate], fm[~degenerate]
    n = None
    if normals is not None:
        n = np.array(normals, dtype=np.float32)
        ln = np.linalg.norm(n, axis=1)
        bad = ~np.isfinite(ln) | (ln < 1e-6)
        if bad.any():
            repair_warning(
                where,
                f"{int(bad.sum())} vertex normal(s) are NaN or zero length: recomputed from faces",
            )
            n[bad] = np.nan
        good = ~bad
        n[good] /= ln[good, None]
    uv = None
    if uvs is not None:
        uv = np.array(uvs, dtype=np.float32)
        bad = ~np.isfinite(uv).all(axis=1)
        if bad.any():
            repair_warning(where, f"{int(bad.sum())} texture coordinate(s) are NaN/Inf: set to 0")
            uv[bad] = 0.0
    return v, f, n, uv, fm


def check_albedo(where: str, name: str, albedo: np.ndarray) -> np.ndarray:
    """Clip a material albedo to [0, 1] (with a warning when it was outside)."""
    a = np.asarray(albedo, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        repair_warning(where, f"material '{name}' has a NaN/Inf colour {a.tolist()}: using 0.8")
        return np.full(3, 0.8)
    c = np.clip(a, 0.0, 1.0)
    if not np.array_equal(a, c):
        repair_warning(where, f"material '{name}' albedo {a.tolist()} clipped to [0, 1]")
    return c
