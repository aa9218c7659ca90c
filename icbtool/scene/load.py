"""Load scenes from files: a TOML scene description, or a bare mesh (OBJ+MTL, glTF/GLB, PLY).

Everything is merged into ONE :class:`~icbtool.scene.types.Scene` (one vertex/face array, a
material per face). Parsing is trimesh's (``process=False``: vertices are neither merged nor
reordered); materials are read as follows:

* OBJ: the MTL is parsed here: ``Kd`` (linear albedo, multiplies ``map_Kd``), ``Ke`` (emitted
  radiance), ``map_Kd`` (an sRGB image, decoded to linear float32). uvs are OBJ's ``vt`` as they
  are: uv (0, 0) is the bottom-left of the image, the Scene convention.
* glTF/GLB: ``baseColorFactor`` (linear; trimesh stores it as 8 bits), ``emissiveFactor``,
  ``baseColorTexture`` (sRGB). trimesh flips glTF's top-left uv origin to bottom-left on load.
* PLY: geometry only; one default material (albedo 0.8). Vertex colours are ignored (warned).

Missing normals are computed (area-weighted); what is validated and what is repaired is listed in
:mod:`icbtool.scene.validate`.
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.scene.types import Material, Scene, vertex_normals
from icbtool.scene.validate import (
    DESCRIPTION_SUFFIXES,
    MESH_SUFFIXES,
    SceneError,
    check_albedo,
    check_arrays,
    check_file,
    check_obj_text,
    ply_header_counts,
    repair_warning,
)

#: Rotations taking a file's up axis to +y (proper rotations, handedness kept).
UP_AXIS_ROTATIONS: dict[str, np.ndarray] = {
    "y": np.eye(3),
    "z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),  # (x, y, z) -> (x, z, -y)
    "x": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # (x, y, z) -> (-y, x, z)
}

#: Keyword arguments accepted by :func:`load_mesh` besides the path.
MESH_OPTIONS = ("name", "scale", "up_axis", "translation", "textures", "flip_v")
#: Scene fields that may be given to :func:`load` for a bare mesh.
SCENE_FIELDS = ("lights", "sky", "paths", "default_camera")


def load(path: str | os.PathLike, **overrides: Any) -> Scene:
    """Load a scene description (.toml) or a bare mesh file (.obj, .gltf, .glb, .ply).

    Args:
        path: the file.
        **overrides: for a mesh, any of ``name``, ``scale``, ``up_axis``, ``translation``,
            ``textures`` (see :func:`load_mesh`) and the Scene fields ``lights``, ``sky``,
            ``paths``, ``default_camera``. For a description, the same keys replace the
            description's values (see :meth:`SceneDescription.build
            <icbtool.scene.description.SceneDescription.build>`).

    Returns:
        The merged :class:`Scene`.

    Raises:
        FileNotFoundError: missing file (or missing mesh named by a description).
        SceneError: unknown file type, unusable content, bad description (message names the file).
        TypeError: an unknown override.
    """
    p = check_file(path, MESH_SUFFIXES + DESCRIPTION_SUFFIXES)
    if p.suffix.lower() in DESCRIPTION_SUFFIXES:
        from icbtool.scene.description import read_description

        return read_description(p).build(**overrides)
    unknown = set(overrides) - set(MESH_OPTIONS) - set(SCENE_FIELDS)
    if unknown:
        raise TypeError(
            f"load({p.name}): unknown override(s) {sorted(unknown)}; "
            f"allowed: {sorted(MESH_OPTIONS + SCENE_FIELDS)}"
        )
    mesh_kw = {k: v for k, v in overrides.items() if k in MESH_OPTIONS}
    scene = load_mesh(p, **mesh_kw)
    return dataclasses.replace(scene, **{k: overrides[k] for k in SCENE_FIELDS if k in overrides})


def load_mesh(
    path: str | os.PathLike,
    *,
    name: str | None = None,
    scale: float = 1.0,
    up_axis: str = "y",
    translation: Any = (0.0, 0.0, 0.0),
    textures: bool = True,
    flip_v: bool = False,
) -> Scene:
    """Load a mesh file into a Scene without lights, sky or paths.

    The file's coordinates are mapped to world as ``world = scale * R_up @ p + translation``.

    Args:
        path: .obj (with its .mtl), .gltf, .glb or .ply.
        name: scene name (default: the file stem).
        scale: uniform scale (> 0) to world units (metres).
        up_axis: the file's up axis, "y" (no change), "z" or "x"; rotated to +y.
        translation: (3,) world offset applied after scaling.
        textures: decode texture images (False: base colours only, faster).
        flip_v: replace v by 1 - v, for files whose uv origin is the image's TOP-left (against
            the OBJ convention; e.g. the Sponza OBJ converted from Mitsuba 0.6, whose loader
            flipped texture coordinates). See the Scene uv convention in types.py.

    Returns:
        The merged Scene (``source`` = the path).

    Raises:
        FileNotFoundError, SceneError: see :mod:`icbtool.scene.validate`.
    """
    p = check_file(path, MESH_SUFFIXES)
    scale = float(scale)
    if not np.isfinite(scale) or scale <= 0:
        raise SceneError(f"{p}: scale must be a finite number > 0, got {scale}")
    if up_axis not in UP_AXIS_ROTATIONS:
        raise SceneError(
            f"{p}: up_axis must be one of {sorted(UP_AXIS_ROTATIONS)}, got {up_axis!r}"
        )
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise SceneError(f"{p}: translation must be a finite 3-vector, got {translation!r}")
    suffix = p.suffix.lower()
    data = p.read_bytes()
    ply_counts = None
    if suffix == ".obj":
        check_obj_text(p, data)
    elif suffix == ".ply":
        ply_counts = ply_header_counts(p, data)
    elif suffix == ".glb" and not data.startswith(b"glTF"):
        raise SceneError(f"{p}: not a GLB file (missing 'glTF' magic): corrupt")

    tm_scene = _trimesh_load(p)
    materials = _MaterialTable(p, textures)
    if suffix == ".obj":
        materials.mtl = _read_obj_mtls(p, data)
    parts = _collect_parts(p, tm_scene, materials)
    if ply_counts is not None:
        nv = sum(len(x[0]) for x in parts)
        nf = sum(len(x[1]) for x in parts)
        if nv < ply_counts.get("vertex", 0) or nf < ply_counts.get("face", 0):
            raise SceneError(
                f"{p}: truncated or corrupt PLY: header declares {ply_counts.get('vertex', 0)} "
                f"vertices and {ply_counts.get('face', 0)} faces, read {nv} and {nf}"
            )

    # merge (one concatenation per array, no Python loop over faces)
    offsets = np.cumsum([0] + [len(x[0]) for x in parts])
    verts = np.concatenate([x[0] for x in parts]).astype(np.float64)
    faces = np.concatenate([x[1] + o for x, o in zip(parts, offsets[:-1])])
    fm = np.concatenate([np.full(len(x[1]), x[4], np.int32) for x in parts])
    normals = None
    if any(x[2] is not None for x in parts):
        normals = np.concatenate(
            [x[2] if x[2] is not None else np.full((len(x[0]), 3), np.nan) for x in parts]
        )
    uvs = None
    if any(x[3] is not None for x in parts):
        uvs = np.concatenate(
            [x[3] if x[3] is not None else np.zeros((len(x[0]), 2)) for x in parts]
        )

    if uvs is not None and flip_v:
        uvs[:, 1] = 1.0 - uvs[:, 1]
    rot = UP_AXIS_ROTATIONS[up_axis]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices: reported below
        verts = scale * verts @ rot.T + t
    if normals is not None:
        normals = normals @ rot.T
    where = str(p)
    v, f, n, uv, fm = check_arrays(where, verts, faces, normals, uvs, fm)
    computed = vertex_normals(v, f)
    if n is None:
        n = computed
    else:
        bad = ~np.isfinite(n).all(axis=1)  # parts without normals, or rows check_arrays rejected
        n[bad] = computed[bad]
    mats = materials.materials
    if uv is None and any(m.is_textured for m in mats):
        repair_warning(where, "textured materials but no texture coordinates: textures dropped")
        mats = [Material(m.name, m.albedo, m.emission) for m in mats]
    return Scene(
        name=name or p.stem,
        vertices=v,
        faces=f,
        normals=n,
        face_material=fm,
        materials=mats,
        uvs=uv,
        source=str(p),
    )


# --------------------------------------------------------------------------- trimesh
def _trimesh_load(p: Path):
    try:
        import trimesh
    except ImportError as e:  # pragma: no cover - trimesh is a hard dependency
        raise ImportError("icbtool.scene.load needs trimesh: pip install trimesh") from e
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # trimesh's numpy RuntimeWarnings on uv bookkeeping
            s = trimesh.load(str(p), process=False, force="scene")
    except Exception as e:  # noqa: BLE001 - any parser failure is a corrupt file
        raise SceneError(
            f"{p}: could not parse the {p.suffix} file (truncated or corrupt?): "
            f"{type(e).__name__}: {str(e)[:200]}"
        ) from e
    if len(s.geometry) == 0:
        raise SceneError(f"{p}: empty mesh: no geometry could be read")
    return s


def _collect_parts(p: Path, tm_scene, materials: _MaterialTable) -> list[tuple]:
    """(vertices, faces, normals|None, uvs|None, material index) per geometry instance."""
    import trimesh

    parts = []
    for node in tm_scene.graph.nodes_geometry:
        transform, gname = tm_scene.graph[node]
        g = tm_scene.geometry[gname]
        if not isinstance(g, trimesh.Trimesh):
            repair_warning(str(p), f"skipped non-triangle geometry '{gname}' ({type(g).__name__})")
            continue
        if len(g.faces) == 0:
            continue
        v = np.asarray(g.vertices, dtype=np.float64)
        f = np.asarray(g.faces, dtype=np.int64)
        cached = getattr(getattr(g, "_cache", None), "cache", {})
        n = cached.get("vertex_normals")  # from the file (vn / NORMAL), never computed here
        n = None if n is None or len(n) != len(v) else np.asarray(n, np.float64)
        m = np.asarray(transform, dtype=np.float64)
        if not np.allclose(m, np.eye(4)):
            v = v @ m[:3, :3].T + m[:3, 3]
            if n is not None:
                n = n @ np.linalg.inv(m[:3, :3])  # inverse transpose, row vectors
        visual = g.visual
        uv = getattr(visual, "uv", None)
        if uv is not None and len(uv) != len(v):
            repair_warning(str(p), f"geometry '{gname}': uv count != vertex count: uvs dropped")
            uv = None
        if uv is not None:
            uv = np.asarray(uv, np.float64)
        mat = materials.index_for(gname, visual)
        parts.append((v, f, n, uv, mat))
    if not parts:
        raise SceneError(f"{p}: empty mesh: no triangles")
    return parts


# --------------------------------------------------------------------------- materials
_SRGB_LUT: np.ndarray | None = None


def decode_texture(image: Any) -> np.ndarray:
    """A PIL image or (h, w[, c]) uint8 array in sRGB -> (h, w, 3) float32 linear."""
    global _SRGB_LUT
    if _SRGB_LUT is None:
        from icbtool.imageio import srgb_decode

        _SRGB_LUT = srgb_decode(np.arange(256, dtype=np.float32) / 255.0)
    if hasattr(image, "convert"):
        if image.mode not in ("RGB", "L", "RGBA", "P"):
            image = image.convert("RGBA")
        arr = np.asarray(image.convert("RGB"))
    else:
        arr = np.asarray(image)
        if arr.ndim == 2:
            arr = np.repeat(arr[..., None], 3, axis=2)
        arr = arr[..., :3]
    if arr.dtype != np.uint8:
        raise ValueError(f"texture must be 8-bit, got {arr.dtype}")
    return _SRGB_LUT[arr]


class _MaterialTable:
    """Materials by name, with texture decoding cached by file."""

    def __init__(self, path: Path, textures: bool) -> None:
        self.path = path
        self.textures = textures
        self.materials: list[Material] = []
        self.by_key: dict[Any, int] = {}
        self.mtl: dict[str, dict[str, Any]] | None = None
        self.tex_cache: dict[Any, tuple[np.ndarray | None, str | None]] = {}

    def _add(self, key: Any, mat: Material) -> int:
        names = {m.name for m in self.materials}
        name = mat.name
        while name in names:
            name += "_"
        if name != mat.name:
            mat = Material(name, mat.albedo, mat.emission, mat.texture, mat.texture_path)
        self.materials.append(mat)
        self.by_key[key] = len(self.materials) - 1
        return self.by_key[key]

    def _texture_file(self, file: Path, mat_name: str) -> np.ndarray | None:
        key = str(file)
        if key not in self.tex_cache:
            tex = None
            if not file.is_file():
                repair_warning(
                    str(self.path),
                    f"material '{mat_name}': texture file {file} not found: using its base colour",
                )
            else:
                try:
                    from PIL import Image

                    with Image.open(file) as im:
                        tex = decode_texture(im)
                except Exception as e:  # noqa: BLE001 - any decoder failure = unreadable image
                    repair_warning(
                        str(self.path),
                        f"material '{mat_name}': texture {file} unreadable ({e}): base colour used",
                    )
            self.tex_cache[key] = (tex, key)
        return self.tex_cache[key][0]

    def index_for(self, gname: str, visual: Any) -> int:
        mat = getattr(visual, "material", None)
        where = str(self.path)
        if self.mtl is not None:  # OBJ: our own MTL reading
            name = getattr(mat, "name", None) or gname
            if name in self.by_key:
                return self.by_key[name]
            spec = self.mtl.get(name)
            if spec is None:
                return self._add(name, Material(name or "default"))
            albedo = check_albedo(where, name, spec.get("Kd", np.full(3, 0.8)))
            emission = np.maximum(spec.get("Ke", np.zeros(3)), 0.0)
            tex = tex_path = None
            if self.textures and spec.get("map_Kd") is not None:
                tex = self._texture_file(spec["map_Kd"], name)
                tex_path = str(spec["map_Kd"]) if tex is not None else None
            return self._add(name, Material(name, albedo, emission, tex, tex_path))
        if mat is not None and hasattr(mat, "baseColorFactor"):  # glTF PBR
            key = ("pbr", id(mat))
            if key in self.by_key:
                return self.by_key[key]
            name = getattr(mat, "name", None) or gname
            bcf = mat.baseColorFactor
            if bcf is None:
                albedo = np.ones(3)
            else:
                bcf = np.asarray(bcf)
                albedo = bcf[:3] / 255.0 if np.issubdtype(bcf.dtype, np.integer) else bcf[:3]
            albedo = check_albedo(where, name, albedo)
            ef = getattr(mat, "emissiveFactor", None)
            emission = np.zeros(3) if ef is None else np.maximum(np.asarray(ef, float)[:3], 0)
            tex = None
            img = getattr(mat, "baseColorTexture", None)
            if self.textures and img is not None:
                try:
                    tex = decode_texture(img)
                except Exception as e:  # noqa: BLE001
                    repair_warning(where, f"material '{name}': texture unreadable ({e})")
            if getattr(mat, "emissiveTexture", None) is not None:
                repair_warning(where, f"material '{name}': emissiveTexture ignored (unsupported)")
            return self._add(key, Material(name, albedo, emission, tex, None))
        # PLY, or anything without a material
        if getattr(visual, "kind", None) in ("vertex", "face"):
            repair_warning(where, f"'{gname}': per-vertex/face colours ignored (albedo 0.8)")
        if "default" in self.by_key:
            return self.by_key["default"]
        return self._add("default", Material(self.path.stem))


_MTLLIB = re.compile(rb"(?m)^mtllib[ \t]+([^\r\n]+)")


def _read_obj_mtls(obj_path: Path, data: bytes) -> dict[str, dict[str, Any]]:
    """Parse the MTL files named by ``mtllib`` lines: {name: {Kd, Ke, map_Kd}}."""
    out: dict[str, dict[str, Any]] = {}
    for m in _MTLLIB.findall(data):
        fname = m.decode("utf-8", "replace").strip()
        mtl = obj_path.parent / fname.replace("\\", "/")
        if not mtl.is_file():
            repair_warning(str(obj_path), f"material library {mtl} not found: default materials")
            continue
        out.update(parse_mtl(mtl))
    return out


def parse_mtl(path: Path) -> dict[str, dict[str, Any]]:
    """Read ``newmtl`` blocks: ``Kd``/``Ke`` as (3,) float arrays, ``map_Kd`` as a Path.

    Raises:
        SceneError: a colour line with non-numbers.
    """
    mats: dict[str, dict[str, Any]] = {}
    cur: dict[str, Any] | None = None
    text = path.read_text(encoding="utf-8", errors="replace")
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.strip().split()
        if not parts or parts[0].startswith("#"):
            continue
        key = parts[0]
        if key == "newmtl":
            cur = mats.setdefault(" ".join(parts[1:]), {})
        elif cur is None:
            continue
        elif key in ("Kd", "Ke"):
            try:
                vals = [float(x) for x in parts[1:4]]
            except ValueError:
                raise SceneError(f"{path}:{lineno}: bad colour {line.strip()!r}") from None
            if len(vals) == 1:
                vals = vals * 3
            if len(vals) != 3:
                raise SceneError(f"{path}:{lineno}: {key} needs 1 or 3 numbers: {line.strip()!r}")
            cur[key] = np.array(vals)
        elif key == "map_Kd" and len(parts) > 1:
            cur["map_Kd"] = path.parent / parts[-1].replace("\\", "/")  # options come first
    return mats
