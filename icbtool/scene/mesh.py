"""Mesh files (OBJ+MTL, glTF/GLB, PLY) read into one Scene (:func:`load_mesh`).

Everything is merged into ONE :class:`~icbtool.scene.types.Scene` (one vertex/face array, a
material per face). Materials are read as follows:

* OBJ + MTL: our own strict parser, :mod:`icbtool.scene.obj` (negative indices, tabs, n-gons,
  smoothing groups, several ``mtllib``; errors name ``file:line``). ``Kd`` (linear albedo,
  multiplies ``map_Kd``), ``Ke`` (emitted radiance), ``map_Kd`` (an sRGB image, decoded to linear
  float32); mirrors, glass, glossy and transparent materials become the nearest diffuse material
  with a :class:`~icbtool.scene.obj.MaterialApproximationWarning` (rule in that module). uvs are
  OBJ's ``vt`` as they are: uv (0, 0) is the bottom-left of the image, the Scene convention.
* glTF/GLB (geometry, node transforms, primitives and uvs through trimesh, ``process=False``):
  ``baseColorFactor`` (linear; trimesh stores it as 8 bits), ``emissiveFactor`` (times
  ``KHR_materials_emissive_strength``), ``baseColorTexture`` (sRGB). trimesh flips glTF's top-left
  uv origin to bottom-left on load. What icbtool cannot render is approximated with a
  ``MaterialApproximationWarning`` naming the material: an ``emissiveTexture`` drops the
  material's emission (the renderers have no emission textures, and spreading
  ``emissiveFactor`` over the whole surface would make e.g. a helmet glow white); metals
  (``metallicFactor`` > 0.5; 1 when absent, the glTF default) and ``KHR_materials_transmission``
  (> 0) become diffuse with their base colour as albedo (by the rule of
  :func:`icbtool.scene.obj.approximated_albedo`: never >= 1); normal, occlusion and
  metallic-roughness maps are dropped with a warning naming them. ``KHR_lights_punctual`` lights
  are read from the file's JSON (:mod:`icbtool.scene.gltf`).
* PLY: geometry only; one default material (albedo 0.8). Vertex colours are ignored (warned).

Up axis: glTF is +y by its specification. For OBJ and PLY, ``up_axis="auto"`` (the default)
guesses from the data (:func:`guess_up_axis`): "z" when the area of faces perpendicular to z
(floors, roofs, table tops of a z-up file) exceeds twice that perpendicular to y and twice that
perpendicular to x, else "y" (the OBJ convention: an ambiguous mesh keeps it). The choice and its
evidence (the share of the area facing each axis) are logged (logger ``icbtool.scene.mesh``, INFO);
when the evidence is weak (neither y nor z faces twice the area of the others) a WARNING says so
and how to override it. ``up_axis="y"``/"z"/"x" overrides the guess.

Missing normals are computed (area-weighted); what is validated and what is repaired is listed in
:mod:`icbtool.scene.validate`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.scene.obj import (
    MtlMaterial,
    approximated_albedo,
    material_warning,
    parse_mtl,
    parse_obj,
)
from icbtool.scene.types import Material, Scene, fill_vertex_normals, vertex_normals
from icbtool.scene.validate import (
    MESH_SUFFIXES,
    SceneError,
    check_albedo,
    check_arrays,
    check_file,
    ply_header_counts,
    repair_warning,
)

log = logging.getLogger(__name__)

#: Rotations taking a file's up axis to +y (proper rotations, handedness kept).
UP_AXIS_ROTATIONS: dict[str, np.ndarray] = {
    "y": np.eye(3),
    "z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),  # (x, y, z) -> (x, z, -y)
    "x": np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # (x, y, z) -> (-y, x, z)
}

#: Accepted ``up_axis`` values ("auto": glTF "y", OBJ/PLY guessed by :func:`guess_up_axis`).
UP_AXES = ("auto", "y", "z", "x")
#: Area ratio by which z-perpendicular faces must outweigh the others for ``auto`` to pick "z".
Z_UP_AREA_RATIO = 2.0

#: Keyword arguments accepted by :func:`load_mesh` besides the path (and by
#: :func:`icbtool.scene.load` for a mesh file).
MESH_OPTIONS = ("name", "scale", "up_axis", "translation", "textures", "flip_v")


def load_mesh(
    path: str | os.PathLike,
    *,
    name: str | None = None,
    scale: float = 1.0,
    up_axis: str = "auto",
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
        up_axis: the file's up axis, "y" (no change), "z" or "x", rotated to +y; "auto": "y" for
            glTF (its specification), guessed for OBJ/PLY (see :func:`guess_up_axis`).
        translation: (3,) world offset applied after scaling.
        textures: decode texture images (False: base colours only, faster).
        flip_v: replace v by 1 - v, for files whose uv origin is the image's TOP-left (against
            the OBJ convention; e.g. the Sponza OBJ converted from Mitsuba 0.6, whose loader
            flipped texture coordinates). See the Scene uv convention in types.py.

    Returns:
        The merged Scene (``source`` = the path); glTF ``KHR_lights_punctual`` lights are in
        ``lights``.

    Raises:
        FileNotFoundError, SceneError: see :mod:`icbtool.scene.validate`.
    """
    p = check_file(path, MESH_SUFFIXES)
    scale = float(scale)
    if not np.isfinite(scale) or scale <= 0:
        raise SceneError(f"{p}: scale must be a finite number > 0, got {scale}")
    if up_axis not in UP_AXES:
        raise SceneError(f"{p}: up_axis must be one of {list(UP_AXES)}, got {up_axis!r}")
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise SceneError(f"{p}: translation must be a finite 3-vector, got {translation!r}")
    suffix = p.suffix.lower()
    data = p.read_bytes()
    ply_counts = None
    lights: list = []
    materials = _MaterialTable(p, textures)
    if suffix == ".obj":
        parts = [_obj_part(p, data, materials)]
    else:
        if suffix == ".ply":
            ply_counts = ply_header_counts(p, data)
        elif suffix == ".glb" and not data.startswith(b"glTF"):
            raise SceneError(f"{p}: not a GLB file (missing 'glTF' magic): corrupt")
        tm_scene = _trimesh_load(p)
        if suffix in (".gltf", ".glb"):
            from icbtool.scene.gltf import read_gltf_json, read_punctual_lights

            materials.gltf = read_gltf_json(p, data)
        parts = _collect_parts(p, tm_scene, materials)
        if suffix in (".gltf", ".glb"):
            lights = read_punctual_lights(p, materials.gltf)
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
    fm = np.concatenate([x[4] for x in parts]).astype(np.int32)
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
    verts = _check_file_positions(p, verts, faces)
    if up_axis == "auto":
        if suffix in (".gltf", ".glb"):
            up_axis = "y"
        else:
            guess = up_axis_evidence(verts, faces)
            up_axis = guess.axis
            log.info("%s: up axis '%s' (auto): %s", p, guess.axis, guess.evidence)
            if guess.weak:
                log.warning(
                    "%s: up axis '%s' guessed on weak evidence (%s); if the model lies on its "
                    "side, load it with up_axis='z' (or 'x'; CLI --up-axis)",
                    p,
                    guess.axis,
                    guess.evidence,
                )
    rot = UP_AXIS_ROTATIONS[up_axis]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices: reported below
        verts = scale * verts @ rot.T + t
    if normals is not None:
        normals = normals @ rot.T
    where = str(p)
    to_compute = np.concatenate([x[5] for x in parts])  # no normal in the file: computed below
    if normals is not None:
        normals[to_compute] = (0.0, 0.0, 1.0)  # placeholder, not a "repair"
        if to_compute.all():
            normals = None
    v, f, n, uv, fm = check_arrays(where, verts, faces, normals, uvs, fm)
    if n is None:
        n = vertex_normals(v, f)
    else:  # not in the file, or rejected
        fill_vertex_normals(v, f, n, ~np.isfinite(n).all(axis=1) | to_compute)
    mats = materials.materials
    if uv is None and any(m.is_textured for m in mats):
        repair_warning(where, "textured materials but no texture coordinates: textures dropped")
        mats = [Material(m.name, m.albedo, m.emission) for m in mats]
    if lights:
        lights = [_transform_light(lt, scale * rot, t) for lt in lights]
    return Scene(
        name=name or p.stem,
        vertices=v,
        faces=f,
        normals=n,
        face_material=fm,
        materials=mats,
        uvs=uv,
        lights=lights,
        source=str(p),
    )


def _check_file_positions(p: Path, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """NaN/Inf positions read by trimesh (PLY, glTF), before any transform: an error naming the
    file, the vertex (0-based, in the file's order) and its coordinates as read when a face
    uses it; unused ones are reported and moved onto a used vertex (they are never drawn)."""
    bad = ~np.isfinite(verts).all(axis=1)
    if not bad.any():
        return verts
    used = np.zeros(len(verts), bool)
    used[faces.reshape(-1)] = True
    bad_used = np.flatnonzero(bad & used)
    if len(bad_used):
        k = int(bad_used[0])
        raise SceneError(
            f"{p}: vertex {k} (0-based, file order) has a NaN or Inf coordinate "
            f"{verts[k].tolist()} and is used by a face ({len(bad_used)} such vertices)"
        )
    bad_unused = np.flatnonzero(bad)
    repair_warning(
        str(p),
        f"{len(bad_unused)} vertex position(s) no face uses are NaN or Inf (first: vertex "
        f"{int(bad_unused[0])} {verts[bad_unused[0]].tolist()}): ignored",
    )
    verts = verts.copy()
    verts[bad] = verts[np.flatnonzero(used)[0]]
    return verts


@dataclasses.dataclass(frozen=True)
class UpAxisGuess:
    """The up axis :func:`up_axis_evidence` guessed, and why.

    Attributes:
        axis: "y" or "z".
        area_share: (3,) share of the mesh's area whose faces are perpendicular to x, y, z
            (``|n . axis| > 0.9``); zeros when there was too little data.
        evidence: one line for the log ("area facing x/y/z: 12/20/55 %: z dominates").
        weak: True when the choice rests on no clear evidence (neither y nor z faces twice the
            area of the other two axes, too few triangles, a flat mesh).
    """

    axis: str
    area_share: np.ndarray
    evidence: str
    weak: bool


def up_axis_evidence(vertices: np.ndarray, faces: np.ndarray) -> UpAxisGuess:
    """:func:`guess_up_axis` with its evidence (see there for the rule)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    none = np.zeros(3)
    if len(f) < 12 or f.min() < 0 or f.max() >= len(v):
        return UpAxisGuess("y", none, f"only {len(f)} triangles: 'y' by convention", False)
    used = v[np.unique(f)]
    with np.errstate(invalid="ignore"):
        ext = used.max(0) - used.min(0)
    if not np.all(np.isfinite(ext)) or ext.min() < 0.05 * ext.max():
        thin = "xyz"[int(np.argmin(np.nan_to_num(ext, nan=np.inf)))]
        why = f"a flat mesh (thinnest along {thin}): 'y' by convention"
        return UpAxisGuess("y", none, why, thin != "y")  # a z-flat terrain may be z-up
    with np.errstate(invalid="ignore", over="ignore"):
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = np.linalg.norm(n, axis=1)
        cos = np.abs(n) / np.maximum(area, 1e-300)[:, None]
    area = np.where(np.isfinite(area), area, 0.0)
    by_axis = np.array([(area * (cos[:, k] > 0.9)).sum() for k in range(3)])
    total = max(float(area.sum()), 1e-300)
    share = by_axis / total
    ax, ay, az = by_axis
    pct = "/".join(f"{100 * x:.0f}" for x in share)
    if az > Z_UP_AREA_RATIO * max(ay, ax) and az > 0:
        return UpAxisGuess("z", share, f"area facing x/y/z {pct} %: z dominates", False)
    if ay > Z_UP_AREA_RATIO * max(az, ax) and ay > 0:
        return UpAxisGuess("y", share, f"area facing x/y/z {pct} %: y dominates", False)
    why = f"area facing x/y/z {pct} %: no axis faces twice the area of the others"
    return UpAxisGuess("y", share, why + ", 'y' by convention", True)


def guess_up_axis(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Guess a mesh file's up axis from its geometry: "z" or "y" (never "x").

    The rule: floors, ceilings, roofs and table tops are perpendicular to the up axis. Faces
    whose unit normal is within ~25 degrees of an axis (``|n . axis| > 0.9``) count, by area, for
    that axis; "z" is returned when the z area exceeds :data:`Z_UP_AREA_RATIO` times both the y
    and the x area, otherwise "y" (the OBJ/glTF convention, also for meshes without dominant
    planes such as a scanned statue). Too little data also gives "y": fewer than 12 triangles, or
    a flat mesh (smallest extent < 5 % of the largest).

    Args:
        vertices: (V, 3) positions in the file's coordinates.
        faces: (F, 3) vertex indices.

    Returns:
        "z" or "y".
    """
    return up_axis_evidence(vertices, faces).axis


def _transform_light(light: Any, linear: np.ndarray, t: np.ndarray) -> Any:
    """A light mapped by ``x -> linear @ x + t`` (scale and up-axis rotation)."""

    changes: dict[str, Any] = {}
    if hasattr(light, "position"):
        changes["position"] = linear @ light.position + t
    if hasattr(light, "direction"):
        changes["direction"] = linear @ light.direction
    return dataclasses.replace(light, **changes) if changes else light


# --------------------------------------------------------------------------- OBJ
def _obj_part(p: Path, data: bytes, materials: _MaterialTable) -> tuple:
    """(vertices, faces, normals (NaN rows = compute), uvs|None, face materials) of an OBJ."""
    mesh = parse_obj(p, data)
    library: dict[str, MtlMaterial] = {}
    found = False
    for fname in mesh.mtllibs:
        mtl = p.parent / fname.replace("\\", "/")
        if not mtl.is_file():
            repair_warning(str(p), f"material library {mtl} not found: default materials")
            continue
        found = True
        library.update(parse_mtl(mtl))
    missing = [n for n in mesh.material_names if n != "default" and n not in library]
    if missing and (found or not mesh.mtllibs):
        where = "the material libraries" if found else "a material library (no mtllib)"
        repair_warning(
            str(p),
            f"material(s) {missing} not found in {where}: default albedo 0.8",
        )
    index = np.array([materials.obj_index(n, library.get(n)) for n in mesh.material_names])
    fm = index[mesh.face_material]
    computed_bad = ~mesh.normal_given & ~np.isfinite(mesh.normals).all(axis=1)
    return mesh.vertices, mesh.faces, mesh.normals, mesh.uvs, fm, computed_bad


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
    """(vertices, faces, normals|None, uvs|None, (F,) materials, (V,) normal missing) per
    geometry instance."""
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
        missing = np.full(len(v), n is None)
        parts.append((v, f, n, uv, np.full(len(f), mat, np.int32), missing))
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
        self.gltf: dict[str, Any] | None = None  # the glTF JSON, for what trimesh does not keep
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
                    tex.setflags(write=False)  # shared by the materials that use it, not copied
                except Exception as e:  # noqa: BLE001 - any decoder failure = unreadable image
                    repair_warning(
                        str(self.path),
                        f"material '{mat_name}': texture {file} unreadable ({e}): base colour used",
                    )
            self.tex_cache[key] = (tex, key)
        return self.tex_cache[key][0]

    def obj_index(self, name: str, spec: MtlMaterial | None) -> int:
        """The material index of an OBJ ``usemtl`` name with its MTL entry (or None)."""
        if name in self.by_key:
            return self.by_key[name]
        if spec is None:
            return self._add(name, Material(name or "default"))
        where = str(self.path)
        albedo, approx = spec.diffuse()
        if approx:
            material_warning(where, name, approx)
        albedo = check_albedo(where, name, albedo)
        emission = np.maximum(spec.Ke, 0.0)
        tex = tex_path = None
        if self.textures and spec.map_Kd is not None:
            tex = self._texture_file(spec.map_Kd, name)
            tex_path = str(spec.map_Kd) if tex is not None else None
        return self._add(name, Material(name, albedo, emission, tex, tex_path))

    def index_for(self, gname: str, visual: Any) -> int:
        mat = getattr(visual, "material", None)
        where = str(self.path)
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
            spec = _gltf_material_json(self.gltf, name)
            ext = spec.get("extensions", {}) if isinstance(spec, dict) else {}
            strength = ext.get("KHR_materials_emissive_strength", {}).get("emissiveStrength")
            if strength is not None and float(strength) >= 0:
                emission = emission * float(strength)
            tex = None
            img = getattr(mat, "baseColorTexture", None)
            if self.textures and img is not None:
                try:
                    tex = decode_texture(img)
                except Exception as e:  # noqa: BLE001
                    repair_warning(where, f"material '{name}': texture unreadable ({e})")
            approx = []
            if getattr(mat, "emissiveTexture", None) is not None or "emissiveTexture" in spec:
                if np.any(emission > 0):
                    approx.append(
                        f"emissiveTexture not supported: emission {np.round(emission, 4).tolist()}"
                        " dropped (it would cover the whole surface)"
                    )
                emission = np.zeros(3)
            pbr = spec.get("pbrMetallicRoughness", {}) if spec else {}
            metallic = pbr.get("metallicFactor") if spec else getattr(mat, "metallicFactor", None)
            metallic = 1.0 if metallic is None else float(metallic)  # glTF default: 1
            transmission = ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0)
            if metallic > METALLIC_THRESHOLD or float(transmission) > 0:
                base = albedo
                albedo, rule = approximated_albedo(base)
                shown = f"{np.round(base, 4).tolist()} -> albedo {np.round(albedo, 4).tolist()}"
                if metallic > METALLIC_THRESHOLD:
                    approx.append(
                        f"metal (metallicFactor {metallic:g}) rendered as diffuse with its base "
                        f"colour {shown} ({rule})"
                    )
                if float(transmission) > 0:
                    approx.append(
                        f"transmission (KHR_materials_transmission {float(transmission):g}) "
                        f"rendered as opaque diffuse with its base colour {shown} ({rule})"
                    )
            dropped = [k for k in DROPPED_GLTF_MAPS if k in spec or k in pbr]
            if dropped:
                approx.append(
                    f"{', '.join(dropped)} dropped (icbtool shades with the interpolated vertex "
                    "normals and no baked occlusion or roughness)"
                )
            if approx:
                material_warning(where, name, "; ".join(approx))
            return self._add(key, Material(name, albedo, emission, tex, None))
        # PLY, or anything without a material
        if getattr(visual, "kind", None) in ("vertex", "face"):
            repair_warning(where, f"'{gname}': per-vertex/face colours ignored (albedo 0.8)")
        if "default" in self.by_key:
            return self.by_key["default"]
        return self._add("default", Material(self.path.stem))


#: glTF materials with a metallicFactor above this are approximated as diffuse (with a warning).
METALLIC_THRESHOLD = 0.5
#: glTF texture maps icbtool does not use; a material that has one gets a warning naming it.
DROPPED_GLTF_MAPS = ("normalTexture", "occlusionTexture", "metallicRoughnessTexture")


def _gltf_material_json(gltf: dict[str, Any] | None, name: str) -> dict[str, Any]:
    """The glTF JSON material named ``name`` ({} when unknown or not a glTF file)."""
    if not gltf:
        return {}
    found = [m for m in gltf.get("materials", []) if isinstance(m, dict) and m.get("name") == name]
    return found[0] if len(found) == 1 else {}
