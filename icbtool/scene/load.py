"""Load scenes from files: a TOML scene description, or a bare mesh (OBJ+MTL, glTF/GLB, PLY).

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
  (> 0) become diffuse with their base colour as albedo. ``KHR_lights_punctual`` lights are read
  from the file's JSON (:mod:`icbtool.scene.gltf`).
* PLY: geometry only; one default material (albedo 0.8). Vertex colours are ignored (warned).

Up axis: glTF is +y by its specification. For OBJ and PLY, ``up_axis="auto"`` (the default)
guesses from the data (:func:`guess_up_axis`): "z" when the area of faces perpendicular to z
(floors, roofs, table tops of a z-up file) exceeds twice that perpendicular to y and twice that
perpendicular to x, else "y" (the OBJ convention: an ambiguous mesh keeps it).
``up_axis="y"``/"z"/"x" overrides the guess.

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

from icbtool.scene.emitters import DEFAULT_EMITTER_BUDGET, promote_emitters
from icbtool.scene.obj import MtlMaterial, material_warning, parse_mtl, parse_obj
from icbtool.scene.types import Material, Scene, vertex_normals
from icbtool.scene.validate import (
    DESCRIPTION_SUFFIXES,
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

#: Keyword arguments accepted by :func:`load_mesh` besides the path.
MESH_OPTIONS = ("name", "scale", "up_axis", "translation", "textures", "flip_v")
#: Scene fields that may be given to :func:`load` for a bare mesh.
SCENE_FIELDS = ("lights", "sky", "paths", "default_camera")
#: Options of :func:`load` itself (for meshes and descriptions alike).
LOAD_OPTIONS = ("emitter_budget",)


def load(
    path: str | os.PathLike, *, emitter_budget: int = DEFAULT_EMITTER_BUDGET, **overrides: Any
) -> Scene:
    """Load a scene description (.toml) or a bare mesh file (.obj, .gltf, .glb, .ply).

    The mesh's emissive faces (OBJ ``Ke``, glTF ``emissiveFactor`` without texture) become area
    lights (:func:`icbtool.scene.emitters.promote_emitters`): their light is direct light (raster
    DL, the tracer's ``direct``), not GI, while the faces stay in the mesh for the camera. When
    there are more than ``emitter_budget`` of them (not counting faces of the description's own
    area lights) they stay seen emission, their light in GI, and a warning says so.

    Args:
        path: the file.
        emitter_budget: at most this many emissive triangles are promoted to lights (>= 0; 0:
            none, every emissive face stays seen emission). Default
            :data:`~icbtool.scene.emitters.DEFAULT_EMITTER_BUDGET` (64).
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
    if (
        isinstance(emitter_budget, bool)
        or not isinstance(emitter_budget, (int, np.integer))
        or emitter_budget < 0
    ):
        raise SceneError(f"{p}: emitter_budget must be an integer >= 0, got {emitter_budget!r}")
    if p.suffix.lower() in DESCRIPTION_SUFFIXES:
        from icbtool.scene.description import read_description

        scene = read_description(p).build(**overrides)
        return promote_emitters(scene, int(emitter_budget))
    unknown = set(overrides) - set(MESH_OPTIONS) - set(SCENE_FIELDS)
    if unknown:
        raise TypeError(
            f"load({p.name}): unknown override(s) {sorted(unknown)}; "
            f"allowed: {sorted(MESH_OPTIONS + SCENE_FIELDS + LOAD_OPTIONS)}"
        )
    mesh_kw = {k: v for k, v in overrides.items() if k in MESH_OPTIONS}
    scene = load_mesh(p, **mesh_kw)
    scene = dataclasses.replace(scene, **{k: overrides[k] for k in SCENE_FIELDS if k in overrides})
    return promote_emitters(scene, int(emitter_budget))


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
    if up_axis == "auto":
        up_axis = "y" if suffix in (".gltf", ".glb") else guess_up_axis(verts, faces)
        if up_axis != "y":
            log.info("%s: guessed up axis %s from the geometry (override: up_axis='y')", p, up_axis)
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
    computed = vertex_normals(v, f)
    if n is None:
        n = computed
    else:
        bad = ~np.isfinite(n).all(axis=1) | to_compute  # not in the file, or rejected
        n[bad] = computed[bad]
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
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) < 12 or f.min() < 0 or f.max() >= len(v):
        return "y"
    with np.errstate(invalid="ignore"):
        ext = v[np.unique(f)].max(0) - v[np.unique(f)].min(0)
    if not np.all(np.isfinite(ext)) or ext.min() < 0.05 * ext.max():
        return "y"  # a flat mesh says nothing about up
    with np.errstate(invalid="ignore", over="ignore"):
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = np.linalg.norm(n, axis=1)
        cos = np.abs(n) / np.maximum(area, 1e-300)[:, None]
    area = np.where(np.isfinite(area), area, 0.0)
    by_axis = [(area * (cos[:, k] > 0.9)).sum() for k in range(3)]
    ax, ay, az = by_axis
    return "z" if az > Z_UP_AREA_RATIO * max(ay, ax) and az > 0 else "y"


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
            if metallic > METALLIC_THRESHOLD:
                approx.append(
                    f"metal (metallicFactor {metallic:g}) rendered as diffuse with its base colour "
                    f"{np.round(albedo, 4).tolist()} as albedo"
                )
            transmission = ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0)
            if float(transmission) > 0:
                approx.append(
                    f"transmission (KHR_materials_transmission {float(transmission):g}) rendered "
                    f"as opaque diffuse with its base colour {np.round(albedo, 4).tolist()}"
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


def _gltf_material_json(gltf: dict[str, Any] | None, name: str) -> dict[str, Any]:
    """The glTF JSON material named ``name`` ({} when unknown or not a glTF file)."""
    if not gltf:
        return {}
    found = [m for m in gltf.get("materials", []) if isinstance(m, dict) and m.get("name") == name]
    return found[0] if len(found) == 1 else {}


# --------------------------------------------------------------------------- default light
#: Irradiance (W/m^2, white) of the default sun of :func:`with_default_light`.
DEFAULT_SUN_IRRADIANCE = 2.5
#: Radiances of the default gradient sky of :func:`with_default_light` (zenith, horizon, ground).
DEFAULT_SKY_RADIANCE = ((0.35, 0.45, 0.6), (0.6, 0.6, 0.6), (0.15, 0.15, 0.15))


def has_light(scene: Scene) -> bool:
    """True when the scene has a light, a sky or an emissive face."""
    return bool(scene.lights) or scene.sky is not None or len(scene.emissive_faces) > 0


def with_default_light(scene: Scene) -> Scene:
    """The scene itself if it has any light; else a copy lit by the documented default light.

    A bare mesh (no lights, no sky, no emissive faces) would render black. The default light
    is a sun and a sky, both defined relative to ``scene.up``:

    * a :class:`DirectionalLight` "default_sun" of :data:`DEFAULT_SUN_IRRADIANCE` W/m^2 (white)
      travelling along ``normalize(-up - 0.5 * front + 0.3 * right)``, where ``front`` is the
      side the automatic camera stands on (:func:`icbtool.camera.camera.default_view_direction`)
      and ``right`` its right: it comes from above, from the front and a little from the left,
      so the faces the default camera sees are lit and cast visible shadows;
    * a gradient :class:`Sky` (:data:`DEFAULT_SKY_RADIANCE`: blue-grey zenith, grey horizon,
      dark ground), which lights the shadows through the path tracer's GI.

    A note is logged (logger ``icbtool.scene.load``, level WARNING) when the light is added.

    Args:
        scene: the scene (never modified).

    Returns:
        ``scene`` unchanged, or a new Scene (``dataclasses.replace``) with the light.
    """
    from icbtool.camera.camera import default_view_direction
    from icbtool.scene.types import DirectionalLight, Sky

    if has_light(scene):
        return scene
    up = np.asarray(scene.up, np.float64)
    view = default_view_direction(up)
    front = -(view - (view @ up) * up)
    front /= np.linalg.norm(front)
    right = np.cross(view, up)
    right /= np.linalg.norm(right)
    sun = DirectionalLight(
        direction=-up - 0.5 * front + 0.3 * right,
        irradiance=np.full(3, DEFAULT_SUN_IRRADIANCE),
        name="default_sun",
    )
    zenith, horizon, ground = DEFAULT_SKY_RADIANCE
    sky = Sky(zenith=zenith, horizon=horizon, ground=ground, kind="gradient", up=up)
    log.warning(
        "scene '%s' has no light (no lights, sky or emissive faces): using the default sun "
        "(%.3g W/m^2) and gradient sky (icbtool.scene.with_default_light)",
        scene.name,
        DEFAULT_SUN_IRRADIANCE,
    )
    return dataclasses.replace(scene, lights=(sun,), sky=sky)
