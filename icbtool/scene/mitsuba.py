"""Mitsuba 3 scene files (.xml): the subset public research scenes use, read into one Scene.

``icb.scene.load("scene.xml")`` (and every CLI command taking a scene) reads a Mitsuba 3 scene
file with the standard library's expat parser (no DTD, no entities: a file declaring either is
refused). What is read, element by element:

* ``<default>`` and ``$name``: parameters with defaults; ``load(path, params={...})`` overrides
  them.
* ``<include>``, ``<path>``: included files are spliced in place (relative to the including file
  or a ``<path>`` folder); at most :data:`MAX_INCLUDE_DEPTH` levels.
* ``<shape>``: ``obj`` (icbtool's OBJ reader; ``flip_tex_coords``), ``ply``, ``serialized``
  (``shape_index``; :func:`read_serialized`), ``rectangle``,
  ``cube``, ``sphere`` (``center``, ``radius``), ``disk``, ``cylinder`` (``p0``, ``p1``,
  ``radius``), each with ``to_world``, ``flip_normals``, ``face_normals``, a nested or referenced
  BSDF and an area emitter. Analytic shapes are tessellated (:data:`SPHERE_SEGMENTS`) for the
  client; ``sphere``, ``disk`` and ``cylinder`` are also exact shapes the path tracer intersects
  and samples (``Scene.shapes``, :class:`~icbtool.scene.types.AnalyticShape`; docs/mitsuba.md,
  "Emitters").
  ``shapegroup`` + ``instance``: each instance is a flattened, transformed copy of the group.
* ``<ref>``: every form Mitsuba accepts (unnamed, ``_arg_N``, ``name="bsdf"``, any name); a
  shape takes BSDFs and emitters by type. Warnings about a referenced object name the ``<ref>``.
* Mitsuba 0.6/1 files (``version`` < 2) are upgraded on load as Mitsuba 3 upgrades them
  (:func:`_upgrade_v1`; one INFO line).
* ``<transform>``: ``translate``, ``rotate`` (axis, degrees), ``scale``, ``matrix`` (16 or 9
  numbers, row-major), ``lookat``; each applies after the previous ones.
* ``<bsdf>``: ``diffuse`` and ``twosided`` exactly; every other type by the rule below.
* ``<texture type="bitmap">``: an sRGB 8-bit image as the diffuse texture (``raw``: linear).
* ``<emitter>``: ``area`` (in a shape: its faces' emission, promoted to area lights on load),
  ``point``, ``spot`` (Mitsuba's falloff), ``directional``, ``constant`` (a uniform
  :class:`~icbtool.scene.types.Sky`), ``envmap`` (``Sky.from_envmap`` with ``scale`` and the
  rotation of ``to_world``). A file whose only emitters are of other types (``sunsky``...) is
  an error unless ``default_light=True`` (:func:`load_mitsuba`).
* ``<sensor>``: ``perspective`` (``fov`` on every ``fov_axis``, ``focal_length``, film size and
  crop, principal point offsets, ``to_world``, ``near_clip``), ``thinlens`` (``aperture_radius``,
  ``focus_distance``) and ``orthographic`` (extent = the ``to_world`` scale): the scene's default
  camera, exactly as Mitsuba casts its rays (``far_clip`` is not applied); the ICB pipeline
  renders a thin lens's or an orthographic sensor's pinhole, with one warning.
* ``<integrator>``: ``max_depth`` (Mitsuba's depth convention is the tracer's) becomes
  ``Scene.max_depth``, the trace default; a path integrator without one means -1 (Mitsuba's
  default, unbounded), ``direct`` means 2; a file without an integrator leaves the tracer's own
  default.

A missing file (mesh, texture, spectrum, include) or a truncated mesh is an error naming the
element's ``file:line``. Anything else (an unknown element, plugin type or property) is skipped
with a :class:`~icbtool.scene.validate.SceneRepairWarning` naming the element, the file and the
line.
Parameters read but not needed to render (``sampler``, ``rfilter``, clip planes, film formats) are
ignored silently.

Approximated BSDFs (one :class:`~icbtool.scene.obj.MaterialApproximationWarning` per material)
become diffuse with the albedo of the one rule (:func:`icbtool.scene.obj.approximated_albedo`,
never >= 1) applied to what the material reflects or transmits at normal incidence:

* ``plastic``/``roughplastic``: ``F * specular_reflectance + (1 - F) * diffuse_reflectance``
  with ``F = ((n - 1) / (n + 1))^2`` of ``n = int_ior / ext_ior`` (a textured diffuse part
  keeps its texture);
* ``conductor``/``roughconductor``: ``specular_reflectance`` times the metal's normal-incidence
  reflectance (``eta``/``k`` if given, else :data:`METAL_F0` by ``material``; ``none``: 1);
* ``dielectric``/``thindielectric``/``roughdielectric``: ``F * specular_reflectance +
  (1 - F) * specular_transmittance``;
* ``principled``: ``base_color``; ``blendbsdf``: the ``weight`` blend of its two BSDFs;
* ``mask`` (opacity dropped), ``bumpmap``/``normalmap`` (map dropped; traced exactly when their
  nested BSDF is, a Mitsuba 0.6 ``scale`` texture around a bump map's bitmap multiplying its
  ``scale``): their nested BSDF;
* ``null``: black (Mitsuba's is invisible); an unknown type: 0.5 grey.

Conventions: Mitsuba's world coordinates are kept as they are (no up-axis change; ``Scene.up`` is
the world axis nearest the sensor's up). Mitsuba's camera looks along its local +z with +x to the
left; icbtool's (OpenCV) has +x right and +y down: ``world_from_cam = to_world @ diag(-1, -1, 1,
1)`` (scale removed). uv: Mitsuba's uv (0, 0) is the image's top-left, the Scene's is the
bottom-left, so ``v_scene = 1 - v_mitsuba`` (for OBJ, whose loader flips by default, the file's
``vt`` are kept). icbtool's BSDFs are two-sided: a one-sided Mitsuba BSDF seen from behind (black
in Mitsuba) is lit here. Spectra (wavelength:value pairs, one value, ``.spd`` files, black
bodies) become linear sRGB on load exactly as Mitsuba 3's RGB variants convert them
(:mod:`icbtool.scene.spectra`; reflectances D65-weighted and clipped to [0, 1], emitted spectra
not). See docs/mitsuba.md for the supported subset.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
import time
import warnings
import xml.parsers.expat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.scene import spectra
from icbtool.scene.obj import approximated_albedo, material_warning, parse_obj
from icbtool.scene.types import (
    AnalyticShape,
    DirectionalLight,
    Material,
    PointLight,
    Scene,
    Sky,
    SpotLight,
    fill_vertex_normals,
)
from icbtool.scene.validate import (
    MITSUBA_SUFFIXES,
    SceneError,
    SceneRepairWarning,
    check_arrays,
    check_file,
    repair_warning,
)

log = logging.getLogger(__name__)

#: Longitudinal segments of a tessellated sphere (latitudinal: half), disk and cylinder.
SPHERE_SEGMENTS = 64
#: Deepest ``<include>`` nesting (a cycle stops here with an error).
MAX_INCLUDE_DEPTH = 16
#: Normal-incidence reflectance (linear RGB) of the metals Mitsuba's ``conductor`` names
#: (``material``), from their complex IORs at 650/550/450 nm; unknown names: 0.9 grey.
METAL_F0: dict[str, tuple[float, float, float]] = {
    "none": (1.0, 1.0, 1.0),
    "Ag": (0.97, 0.96, 0.92),
    "Al": (0.92, 0.92, 0.93),
    "Au": (0.96, 0.78, 0.38),
    "Cu": (0.96, 0.65, 0.54),
    "Cr": (0.65, 0.55, 0.56),
    "Fe": (0.56, 0.57, 0.58),
    "Ni": (0.66, 0.61, 0.53),
    "Pt": (0.67, 0.64, 0.59),
    "Ti": (0.54, 0.50, 0.45),
    "W": (0.50, 0.50, 0.47),
    "Hg": (0.78, 0.78, 0.78),
}
#: Index of refraction of named dielectrics (``int_ior="bk7"``...), at 589 nm.
NAMED_IOR = {
    "vacuum": 1.0,
    "air": 1.000277,
    "water": 1.333,
    "acrylic glass": 1.49,
    "polypropylene": 1.49,
    "bk7": 1.5046,
    "sodium chloride": 1.544,
    "diamond": 2.419,
    "glass": 1.5046,
}
#: Properties and elements read without effect on icbtool's images (no warning).
_IGNORED_PROPERTIES = {
    "far_clip", "sample_count", "pixel_format", "file_format",
    "component_format", "rfilter", "sampler", "banner", "high_quality_edges", "id", "seed",
    "srgb_gamma", "shutter_open", "shutter_close", "mis_compensation",
    "rr_depth", "sample_emitters", "filter_type", "wrap_mode", "samples_per_pass",
}  # fmt: skip
_PROPERTY_TAGS = {
    "float", "integer", "boolean", "string", "rgb", "spectrum", "point", "vector", "transform",
    "color", "srgb",
}  # fmt: skip
_OBJECT_TAGS = {
    "bsdf", "texture", "emitter", "shape", "sensor", "film", "sampler", "rfilter", "integrator",
    "medium", "phase", "volume", "ref",
}  # fmt: skip


# --------------------------------------------------------------------------- XML
@dataclass
class _Node:
    """One XML element with its source position."""

    tag: str
    attrs: dict[str, str]
    file: Path
    line: int
    children: list[_Node] = field(default_factory=list)

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}"

    def describe(self) -> str:
        kind = self.attrs.get("type") or self.attrs.get("name") or ""
        return f"<{self.tag}{' ' + kind if kind else ''}>"


def _parse_xml(path: Path) -> _Node:
    """The element tree of an XML file (expat; DTDs and entities refused)."""
    parser = xml.parsers.expat.ParserCreate()
    root: list[_Node] = []
    stack: list[_Node] = []

    def start(tag: str, attrs: dict[str, str]) -> None:
        node = _Node(tag, dict(attrs), path, parser.CurrentLineNumber)
        (stack[-1].children if stack else root).append(node)
        stack.append(node)

    def end(tag: str) -> None:
        stack.pop()

    def refuse(*_: Any) -> None:
        raise SceneError(
            f"{path}:{parser.CurrentLineNumber}: DTD or entity declarations are not allowed "
            "in a Mitsuba scene file"
        )

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    try:
        parser.Parse(path.read_bytes(), True)
    except xml.parsers.expat.ExpatError as e:
        raise SceneError(f"{path}:{e.lineno}: not valid XML: {e}") from None
    if not root:
        raise SceneError(f"{path}: no XML element")
    return root[0]


def _snake(name: str) -> str:
    """A Mitsuba 0.6 camelCase name as Mitsuba 3's upgrade spells it: ``_`` at each lower-case
    to upper-case step, the run of capitals lower-cased (``toWorld`` -> ``to_world``,
    ``intIOR`` -> ``int_ior``)."""
    return re.sub(r"(?<=[a-z])([A-Z]+)", lambda m: "_" + m.group(1).lower(), name)


#: What :func:`_upgrade_v1` changes, for its one log line.
_UPGRADE_NOTE = (
    "camelCase names to snake_case, <lookAt> to <lookat>, <blackbody> to a blackbody spectrum, "
    "diffuse_reflectance of diffuse BSDFs to reflectance, uoffset/voffset/uscale/vscale to "
    "to_uv"
)


def _upgrade_v1(node: _Node) -> None:
    """A Mitsuba 0.6/1 element tree upgraded in place as Mitsuba 3 upgrades it on load, plus
    what Mitsuba 3.0-3.5 also upgraded (``<lookAt>``) and the 0.6 ``<blackbody
    temperature="6500K" scale=".."/>`` property (a ``<spectrum type="blackbody">`` with a
    ``scale``), which Mitsuba 3.9 no longer reads."""
    if "name" in node.attrs and node.tag != "default":
        node.attrs["name"] = _snake(node.attrs["name"])
    if node.tag == "lookAt":
        node.tag = "lookat"
    elif node.tag == "blackbody":
        kids = []
        for key in ("temperature", "scale"):
            if key in node.attrs:
                value = node.attrs[key].strip().rstrip("kK")
                kids.append(_Node("float", {"name": key, "value": value}, node.file, node.line))
        node.tag = "spectrum"
        node.attrs = {"name": node.attrs.get("name", ""), "type": "blackbody"}
        node.children = kids
    for c in node.children:
        _upgrade_v1(c)
    if node.tag == "bsdf" and node.attrs.get("type") == "diffuse":
        for c in node.children:
            if c.attrs.get("name") == "diffuse_reflectance":
                c.attrs["name"] = "reflectance"
    uv = {c.attrs.get("name"): c for c in node.children if c.tag == "float"}
    keys = [k for k in ("uoffset", "voffset", "uscale", "vscale") if k in uv]
    if keys:
        where = uv[keys[0]]
        ops = []
        if "uoffset" in uv or "voffset" in uv:
            xy = {"x": uv.get("uoffset"), "y": uv.get("voffset")}
            attrs = {k: n.attrs.get("value", "0") for k, n in xy.items() if n is not None}
            ops.append(_Node("translate", attrs, where.file, where.line))
        if "uscale" in uv or "vscale" in uv:
            xy = {"x": uv.get("uscale"), "y": uv.get("vscale")}
            attrs = {k: n.attrs.get("value", "1") for k, n in xy.items() if n is not None}
            ops.append(_Node("scale", attrs, where.file, where.line))
        node.children = [c for c in node.children if c not in [uv[k] for k in keys]]
        node.children.append(_Node("transform", {"name": "to_uv"}, where.file, where.line, ops))


# --------------------------------------------------------------------------- transforms
def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    t = math.radians(angle_deg)
    c, s = math.cos(t), math.sin(t)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) * c + s * k + (1 - c) * np.outer(a, a)


def mitsuba_look_at(origin: Any, target: Any, up: Any | None = None) -> np.ndarray:
    """(4, 4) Mitsuba's ``lookat`` matrix: columns (left, up, forward, origin)."""
    o, t = np.asarray(origin, float), np.asarray(target, float)
    d = t - o
    if np.linalg.norm(d) < 1e-12:
        raise ValueError(f"lookat: origin and target coincide at {o.tolist()}")
    d /= np.linalg.norm(d)
    if up is None or np.linalg.norm(np.cross(np.asarray(up, float), d)) < 1e-9:
        helper = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
        up = helper
    left = np.cross(np.asarray(up, float), d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


# --------------------------------------------------------------------------- results
class _Props(dict):
    """Named children of an element; remembers which were read (the rest get a warning)."""

    def __init__(self) -> None:
        super().__init__()
        self.used: set[str] = set()

    def get(self, key: str, default: Any = None) -> Any:
        self.used.add(key)
        return super().get(key, default)

    def __getitem__(self, key: str) -> Any:
        self.used.add(key)
        return super().__getitem__(key)

    def __contains__(self, key: object) -> bool:
        self.used.add(str(key))
        return super().__contains__(key)


@dataclass
class _Bsdf:
    """A BSDF as icbtool renders it."""

    name: str
    albedo: np.ndarray
    texture: Path | None = None
    raw: bool = False
    declared: Any = None  # the icbtool.scene.bsdf BSDF the tracer evaluates exactly, if any


@dataclass
class _Part:
    vertices: np.ndarray  # (V, 3) world
    faces: np.ndarray  # (F, 3)
    normals: np.ndarray  # (V, 3), NaN rows: computed
    uvs: np.ndarray | None  # (V, 2) Scene convention
    material: int
    exact: tuple | None = None  # an analytic shape: (kind, world_from_local, flip_normals, name)

    def __post_init__(self) -> None:
        # the Scene's float32 now (what the merge would round them to): half the memory while
        # the other shapes load, the same merged arrays
        self.vertices = np.asarray(self.vertices, np.float32)
        self.normals = np.asarray(self.normals, np.float32)
        if self.uvs is not None:
            self.uvs = np.asarray(self.uvs, np.float32)


@dataclass
class MitsubaScene:
    """What a Mitsuba scene file holds, before it becomes a :class:`Scene` (for tests/tools).

    Attributes:
        scene: the merged Scene (emissive faces not yet promoted to area lights).
        shapes: number of shapes read (skipped ones not counted).
        skipped: ``"<element> (file:line)"`` of everything skipped with a warning.
        params: the resolved ``$`` parameters.
        dropped_lights: ``"<emitter kind> (file:line)"`` of the emitters icbtool cannot render.
    """

    scene: Scene
    shapes: int
    skipped: list[str]
    params: dict[str, str]
    dropped_lights: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- reader
class _Values:
    """The reader's state, the file structure (includes, defaults, ids, refs) and property
    values (numbers, colours, transforms); every message names ``file:line``."""

    def __init__(self, path: Path, params: dict[str, Any], textures: bool) -> None:
        self.path = path
        self.params = {k: str(v) for k, v in params.items()}
        self.given = set(self.params)
        self.textures = textures
        self.search = [path.parent]
        self.ids: dict[str, _Node] = {}
        self.via: dict[int, _Node] = {}  # id(object) -> the <ref> that last reached it
        self.skipped: list[str] = []
        self.dropped_lights: list[str] = []  # "<emitter kind> (file:line)" of emitters not read
        self.materials: list[Material] = []
        self.mat_keys: dict[Any, int] = {}
        self.bsdfs: dict[int | str, _Bsdf] = {}
        self.rendered: dict[str, _Bsdf] = {}  # "file:line" of a shape's BSDF -> what renders
        self.checkers: list[str] = []  # "file:line" of the checkerboard textures read
        self.files: list[Path] = [path]  # the scene file and the files it includes
        self.tex_cache: dict[str, np.ndarray | None] = {}
        self.parts: list[_Part] = []
        self.lights: list[Any] = []
        self.sky: Sky | None = None
        self.camera = None
        self.cam_up: np.ndarray | None = None
        self.max_depth: int | None = None
        self.n_shapes = 0
        self.n_instances = 0
        self.geo_cache: dict[int, tuple | None] = {}  # id(shape node) -> its geometry
        # instancing: id(shapegroup) -> (prototype index, instanceable, its shapes' (v, f,
        # exact-free) in its own space); per instance (prototype, 3x4, first and end part)
        self.groups: dict[int, tuple] = {}
        self.instances: list[tuple] = []
        self.group_local: list[tuple] = []
        self.version = (3, 0, 0)
        self.progress = False  # a tqdm bar over the shapes while they load
        # every shape without a BSDF shares this one (Mitsuba's default: diffuse 0.5), so they
        # share one material: materials are keyed by the BSDF object's identity; an area
        # emitter's shape without a BSDF reflects nothing (Mitsuba's default there: diffuse 0)
        self.default_bsdf = _Bsdf("default", np.full(3, 0.5))
        self.default_emitter_bsdf = _Bsdf("default", np.zeros(3))

    # ---------------------------------------------------------------- helpers
    def skip(self, node: _Node, why: str) -> None:
        where = self.where(node)
        self.skipped.append(f"{node.describe()} ({where})")
        repair_warning(where, f"{node.describe()} {why}: skipped")

    def where(self, node: _Node) -> str:
        """``file:line`` of ``node``; for an object reached through a ``<ref>``, the line of
        the referring ``<ref>`` first (where the user looks), then the definition's."""
        ref = self.via.get(id(node))
        return node.where if ref is None else f"{ref.where} (<ref> to {node.where})"

    def attr(self, node: _Node, key: str, default: str | None = None) -> str | None:
        v = node.attrs.get(key)
        if v is None:
            return default
        if "$" not in v:
            return v

        def sub(m: re.Match) -> str:
            name = m.group(1)
            if name not in self.params:
                raise SceneError(
                    f"{node.where}: {node.describe()} uses parameter ${name}, which has no "
                    "<default> and was not given (load(..., params={...}))"
                )
            return self.params[name]

        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", sub, v)

    def numbers(self, node: _Node, text: str, what: str) -> np.ndarray:
        try:
            return np.array([float(x) for x in re.split(r"[,\s]+", text.strip()) if x], float)
        except ValueError:
            raise SceneError(f"{node.where}: {what} {text!r} is not a list of numbers") from None

    def resolve(self, node: _Node, name: str) -> Path:
        p = Path(name.replace("\\", "/")).expanduser()
        if p.is_absolute():
            return p
        for d in [node.file.parent, *self.search]:
            if (d / p).exists():
                return d / p
        return node.file.parent / p

    # ---------------------------------------------------------------- structure
    def flatten(self, root: _Node, depth: int = 0) -> list[_Node]:
        """Top-level children with includes spliced in and defaults/paths applied."""
        if root.tag != "scene":
            raise SceneError(f"{root.where}: the root element must be <scene>, got <{root.tag}>")
        ver = root.attrs.get("version", "3.0.0")
        try:
            self.version = tuple(int(x) for x in ver.split(".")[:3])  # type: ignore[assignment]
        except ValueError:
            raise SceneError(f"{root.where}: bad scene version {ver!r}") from None
        if self.version < (2, 0, 0):
            _upgrade_v1(root)
            log.info(
                "%s: Mitsuba %s file upgraded on load as Mitsuba 3 does (%s)",
                root.file,
                ver,
                _UPGRADE_NOTE,
            )
        out: list[_Node] = []
        for node in root.children:
            if node.tag == "default":
                name, value = node.attrs.get("name"), node.attrs.get("value")
                if name is None or value is None:
                    raise SceneError(f"{node.where}: <default> needs name and value")
                if name not in self.given:
                    self.params[name] = value
            elif node.tag == "path":
                self.search.append(self.resolve(node, self.attr(node, "value", ".")))
            elif node.tag == "include":
                if depth >= MAX_INCLUDE_DEPTH:
                    raise SceneError(
                        f"{node.where}: includes nested deeper than {MAX_INCLUDE_DEPTH} (a cycle?)"
                    )
                fname = self.attr(node, "filename")
                if not fname:
                    raise SceneError(f"{node.where}: <include> needs a filename")
                inc = self.resolve(node, fname)
                if not inc.is_file():
                    raise FileNotFoundError(f"{node.where}: included file not found: {inc}")
                if inc.suffix.lower() != ".xml":
                    self.skip(node, f"includes a non-XML file {inc.name}")
                    continue
                self.files.append(inc)
                out += self.flatten(_parse_xml(inc), depth + 1)
            else:
                out.append(node)
        return out

    def collect_ids(self, nodes: list[_Node]) -> None:
        for node in nodes:
            if node.tag != "ref" and "id" in node.attrs:
                self.ids[node.attrs["id"]] = node
            self.collect_ids(node.children)

    def nested_bsdfs(self, node: _Node) -> list[_Node]:
        """The BSDFs inside ``node`` (a blend's, a twosided's...), references resolved."""
        found = [self.deref(c) for c in node.children if c.tag in ("bsdf", "ref")]
        return [c for c in found if c.tag == "bsdf"]

    def deref(self, node: _Node) -> _Node:
        if node.tag != "ref":
            return node
        rid = self.attr(node, "id")
        if rid not in self.ids:
            raise SceneError(f"{node.where}: <ref id={rid!r}> names no element with that id")
        return self.ids[rid]

    def finish(self, node: _Node, props: _Props) -> None:
        """Warn about the properties of ``node`` nothing read (named, with file:line)."""
        for key in sorted(set(props) - props.used - _IGNORED_PROPERTIES):
            where = self.where(props[key])
            self.skipped.append(f"{node.describe()} property '{key}' ({where})")
            repair_warning(where, f"{node.describe()} property '{key}' is not supported: ignored")

    def props(self, node: _Node) -> _Props:
        """Named children of an element: properties by ``name``; nested or referenced objects
        (``<ref id>``, ``<ref name id>``) by ``name``, except that BSDFs, emitters and media
        (which Mitsuba's shapes take by type) and unnamed or ``_arg_N`` objects (as Mitsuba's
        writer names them) are keyed by their tag (``bsdf``, ``emitter``, ``medium``...)."""
        out = _Props()
        for c in node.children:
            name = c.attrs.get("name")
            if c.tag in _PROPERTY_TAGS:
                if name is None:
                    raise SceneError(f"{c.where}: <{c.tag}> property without a name")
                out[name] = c
            elif c.tag in _OBJECT_TAGS:
                target = self.deref(c) if c.tag == "ref" else c
                if c.tag == "ref":
                    self.via[id(target)] = c
                by_type = target.tag in ("bsdf", "emitter") or (
                    target.tag == "medium" and name not in ("interior", "exterior")
                )
                if name is None or name.startswith("_arg_") or by_type:
                    name = target.tag
                out.setdefault(name, target)
            else:
                self.skip(c, "is not a Mitsuba element icbtool knows")
        out.used.clear()
        return out

    # ---------------------------------------------------------------- values
    def value(self, node: _Node) -> str:
        v = self.attr(node, "value")
        if v is None:
            raise SceneError(f"{node.where}: <{node.tag}> needs a value")
        return v

    def float_(self, props: dict, name: str, default: float | None) -> float | None:
        node = props.get(name)
        if node is None:
            return default
        if node.tag not in ("float", "integer"):
            if node.tag in ("rgb", "spectrum"):
                return float(np.mean(self.colour(node)))
            raise SceneError(f"{node.where}: '{name}' must be a float, got <{node.tag}>")
        x = self.numbers(node, self.value(node), name)
        if len(x) != 1:
            raise SceneError(f"{node.where}: '{name}' must be one number")
        return float(x[0])

    def int_(self, props: dict, name: str, default: int | None) -> int | None:
        x = self.float_(props, name, None)
        return default if x is None else int(x)

    def bool_(self, props: dict, name: str, default: bool) -> bool:
        node = props.get(name)
        if node is None:
            return default
        v = self.value(node).strip().lower()
        if v not in ("true", "false"):
            raise SceneError(f"{node.where}: '{name}' must be true or false, got {v!r}")
        return v == "true"

    def str_(self, props: dict, name: str, default: str | None) -> str | None:
        node = props.get(name)
        return default if node is None else self.value(node)

    def vec(self, node: _Node, what: str, default: float = 0.0) -> np.ndarray:
        if "value" in node.attrs:
            x = self.numbers(node, self.value(node), what)
            if len(x) == 1:
                x = np.repeat(x, 3)
        else:
            x = np.array([float(self.attr(node, k, str(default))) for k in "xyz"])
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise SceneError(f"{node.where}: {what} must be 3 finite numbers")
        return x

    def point(self, props: dict, name: str, default: Any) -> np.ndarray:
        node = props.get(name)
        return np.asarray(default, float) if node is None else self.vec(node, name)

    def colour(self, node: _Node, emitter: bool = False, unbounded: bool = False) -> np.ndarray:
        """(3,) linear RGB of an rgb/spectrum/float/srgb/color property, as Mitsuba 3's RGB
        variants load it (:mod:`icbtool.scene.spectra`): ``emitter`` for emitted spectra (no
        D65 weighting, a one-value spectrum purplish), ``unbounded`` for values that may exceed 1
        (an index of refraction)."""
        if node.tag == "spectrum":
            return self.spectrum(node, emitter, unbounded)
        text = self.value(node)
        if node.tag in ("srgb", "color") or text.startswith("#"):
            from icbtool.imageio import srgb_decode

            if text.startswith("#"):
                h = text.lstrip("#")
                x = np.array([int(h[i : i + 2], 16) / 255 for i in (0, 2, 4)])
            else:
                x = self.numbers(node, text, node.tag)
            return np.asarray(srgb_decode(np.resize(x, 3).astype(np.float32)), float)
        x = self.numbers(node, text, node.tag)
        if len(x) == 1:
            x = np.repeat(x, 3)
        if x.shape != (3,) or not np.all(np.isfinite(x)):
            raise SceneError(f"{node.where}: <{node.tag}> must have 1 or 3 finite numbers")
        return x

    def spectrum(self, node: _Node, emitter: bool, unbounded: bool) -> np.ndarray:
        """(3,) linear sRGB of a ``<spectrum>`` (value pairs, one value, a .spd file, a black
        body), converted as Mitsuba 3's RGB variants convert it at load time."""
        kind = self.attr(node, "type")
        try:
            if kind == "blackbody":
                return self.blackbody(node)
            if kind is not None:
                raise SceneError(f"{node.where}: <spectrum type={kind!r}> is not supported")
            fname, text = self.attr(node, "filename"), self.attr(node, "value")
            if (fname is None) == (text is None):
                raise SceneError(f"{node.where}: <spectrum> needs a value or a filename (one)")
            if fname is not None:
                path = self.resolve(node, fname)
                if not path.is_file():
                    raise FileNotFoundError(f"{node.where}: spectrum file not found: {path}")
                lam, val = spectra.read_spd(path)
            else:
                lam, val = spectra.parse_pairs(text)
            if lam.size == 0:
                return spectra.uniform_to_rgb(float(val[0]), emitter=emitter)
            bounded = not (emitter or unbounded)
            rgb = spectra.spectrum_to_rgb(lam, val, emitter=emitter, bounded=bounded)
            raw = spectra.spectrum_to_rgb(lam, val, emitter=emitter, bounded=False)
        except spectra.SpectrumError as e:
            raise SceneError(
                f"{node.where}: <spectrum {node.attrs.get('name', '')}>: {e}"
            ) from None
        if bounded and np.any(raw > 1.0):
            repair_warning(
                node.where,
                f"spectrum out of the sRGB gamut {np.round(raw, 4).tolist()}: clipped to "
                f"{np.round(rgb, 4).tolist()} (as Mitsuba does)",
            )
        log.debug("%s: spectrum -> linear sRGB %s", node.where, np.round(rgb, 6).tolist())
        return rgb

    def blackbody(self, node: _Node) -> np.ndarray:
        """``<spectrum type="blackbody">`` (temperature, wavelength_min/max) and Mitsuba 0.6's
        ``<blackbody temperature=".." scale=".."/>`` (upgraded on load) as linear sRGB."""
        props = self.props(node)
        temp = self.float_(props, "temperature", None)
        if temp is None:
            raise SceneError(f"{node.where}: a black body needs a temperature")
        rgb = spectra.blackbody_to_rgb(
            temp,
            min_nm=float(self.float_(props, "wavelength_min", spectra.CIE_MIN_NM)),
            max_nm=float(self.float_(props, "wavelength_max", spectra.CIE_MAX_NM)),
        )
        rgb = rgb * float(self.float_(props, "scale", 1.0))
        self.finish(node, props)
        return rgb

    def transform(self, node: _Node | None) -> np.ndarray:
        m = np.eye(4)
        if node is None:
            return m
        if node.tag != "transform":
            raise SceneError(f"{node.where}: expected a <transform>, got <{node.tag}>")
        for c in node.children:
            t = np.eye(4)
            if c.tag == "translate":
                t[:3, 3] = self.vec(c, "translate")
            elif c.tag == "scale":
                t[:3, :3] = np.diag(self.vec(c, "scale", 1.0))
            elif c.tag == "rotate":
                axis = self.vec(c, "rotate axis")
                if np.linalg.norm(axis) < 1e-12:
                    raise SceneError(f"{c.where}: <rotate> needs a non-zero axis")
                t[:3, :3] = _rotation(axis, float(self.attr(c, "angle", "0")))
            elif c.tag == "matrix":
                x = self.numbers(c, self.value(c), "matrix")
                if len(x) == 16:
                    t = x.reshape(4, 4)
                elif len(x) == 9:
                    t[:3, :3] = x.reshape(3, 3)
                else:
                    raise SceneError(f"{c.where}: <matrix> needs 16 or 9 numbers, got {len(x)}")
            elif c.tag == "lookat":
                parse = [
                    None if self.attr(c, k) is None else self.numbers(c, self.attr(c, k), k)
                    for k in ("origin", "target", "up")
                ]
                if parse[0] is None or parse[1] is None:
                    raise SceneError(f"{c.where}: <lookat> needs origin and target")
                try:
                    t = mitsuba_look_at(*parse)
                except ValueError as e:
                    raise SceneError(f"{c.where}: {e}") from None
            else:
                self.skip(c, "is not a transform operation")
                continue
            m = t @ m
        if not np.all(np.isfinite(m)):
            raise SceneError(f"{node.where}: the transform is not finite")
        return m


def _has_to_uv(node: _Node) -> bool:
    """Whether a texture inside ``node`` has a ``to_uv`` transform."""
    if node.tag == "transform" and node.attrs.get("name") == "to_uv":
        return True
    return any(_has_to_uv(c) for c in node.children)


class _Unsupported(Exception):
    """A BSDF or texture the tracer does not evaluate exactly (approximated instead)."""


class _Materials(_Values):
    """Textures and BSDFs as icbtool renders them (the approximation rule), and materials."""

    def reflectance(
        self, node: _Node | None, default: float, emitter: bool = False
    ) -> tuple[np.ndarray, Path | None, bool]:
        """(mean colour (3,), bitmap path or None, raw) of a colour or texture property
        (``emitter``: an emitted quantity, whose spectra convert without D65)."""
        if node is None:
            return np.full(3, default), None, False
        if node.tag != "texture":
            return self.colour(node, emitter), None, False
        kind = node.attrs.get("type")
        props = self.props(node)
        if kind == "bitmap":
            fname = self.str_(props, "filename", None)
            if fname is None:
                raise SceneError(f"{node.where}: bitmap texture without a filename")
            path = self.resolve(node, fname)
            raw = self.bool_(props, "raw", False)
            for k in ("to_uv",):
                if k in props:
                    repair_warning(node.where, f"bitmap '{k}' is not supported: ignored")
            tex = self.texture(node, path, raw)
            self.finish(node, props)
            mean = np.full(3, 0.5) if tex is None else tex.reshape(-1, 3).mean(0)
            return mean, (path if tex is not None else None), raw
        if kind == "checkerboard":
            a = self.reflectance(props.get("color0"), 0.4)[0]
            b = self.reflectance(props.get("color1"), 0.2)[0]
            self.checkers.append(node.where)  # bsdf() warns unless the tracer renders it
            return 0.5 * (a + b), None, False
        self.skip(node, "texture type is not supported (0.5 grey instead)")
        return np.full(3, 0.5), None, False

    def texture(self, node: _Node, path: Path, raw: bool) -> np.ndarray | None:
        key = f"{path}|{raw}"
        if key not in self.tex_cache:
            tex = None
            if not path.is_file():
                raise FileNotFoundError(f"{self.where(node)}: texture file not found: {path}")
            if self.textures:
                try:
                    from PIL import Image

                    with Image.open(path) as im:
                        if raw:
                            tex = np.asarray(im.convert("RGB"), np.float32) / 255.0
                        else:
                            from icbtool.scene.mesh import decode_texture

                            tex = decode_texture(im)
                except Exception as e:  # noqa: BLE001 - any decoder failure = unreadable image
                    raise SceneError(
                        f"{self.where(node)}: texture {path} is not a readable image ({e})"
                    ) from None
                if tex is not None:
                    tex.setflags(write=False)  # shared by its materials and bitmaps, not copied
            self.tex_cache[key] = tex
        return self.tex_cache[key]

    def bsdf(self, node: _Node | None) -> _Bsdf:
        """The rendered form of a BSDF element (one warning per approximated material)."""
        if node is None:
            return self.default_bsdf
        key = id(node)
        if key not in self.bsdfs:
            notes: list[str] = []
            n_checkers = len(self.checkers)
            b = self._bsdf(node, notes)
            if not notes and (len(self.checkers) > n_checkers or _has_to_uv(node)):
                # a diffuse BSDF with a checkerboard (or a to_uv transform): Mitsuba's one-sided
                # diffuse with the texture, traced exactly
                b = _Bsdf(b.name, b.albedo, b.texture, b.raw, self._declared(node))
            for where in self.checkers[n_checkers:]:
                if b.declared is None:
                    repair_warning(where, "checkerboard texture rendered as its mean colour")
            if notes:
                albedo, rule = approximated_albedo(b.albedo)
                declared = self._declared(node)
                b = _Bsdf(b.name, albedo, b.texture, b.raw, declared)
                if declared is None:
                    material_warning(
                        node.where,
                        b.name,
                        f"{'; '.join(notes)}: rendered as diffuse albedo "
                        f"{np.round(albedo, 4).tolist()} ({rule})",
                    )
            self.bsdfs[key] = b
            self.rendered[node.where] = b
        return self.bsdfs[key]

    def _bsdf(self, node: _Node, notes: list[str]) -> _Bsdf:
        props = self.props(node)
        props.used.update(("bsdf", "texture"))  # nested BSDFs, a bump map's texture
        n_notes = len(notes)
        try:
            return self._bsdf_body(node, props, notes)
        finally:
            if len(notes) > n_notes:  # approximated: its other parameters do not matter
                props.used.update(props)
            self.finish(node, props)

    def _bsdf_body(self, node: _Node, props: _Props, notes: list[str]) -> _Bsdf:
        kind = node.attrs.get("type", "")
        name = node.attrs.get("id") or f"{kind}@{node.line}"
        nested = self.nested_bsdfs(node)

        def ior(key: str, default: float) -> float:
            n = props.get(key)
            if n is None:
                return default
            if n.tag == "string":
                v = self.value(n).lower()
                if v not in NAMED_IOR:
                    repair_warning(n.where, f"unknown IOR name {v!r}: 1.5 used")
                return NAMED_IOR.get(v, 1.5)
            return float(self.float_(props, key, default))

        def fresnel() -> float:
            eta = ior("int_ior", 1.5046) / ior("ext_ior", 1.000277)
            return ((eta - 1) / (eta + 1)) ** 2

        if kind == "diffuse":
            c, tex, raw = self.reflectance(props.get("reflectance"), 0.5)
            if tex is not None:
                return _Bsdf(name, np.ones(3), tex, raw)
            return _Bsdf(name, np.clip(c, 0, 1))
        if kind == "twosided":
            if not nested:
                return _Bsdf(name, np.full(3, 0.5))
            if len(nested) > 1:
                notes.append("twosided with a different back BSDF: the front one on both sides")
            inner = self._bsdf(nested[0], notes)
            return _Bsdf(node.attrs.get("id") or inner.name, inner.albedo, inner.texture, inner.raw)
        if kind in ("plastic", "roughplastic"):
            d, tex, raw = self.reflectance(props.get("diffuse_reflectance"), 0.5)
            s = self.reflectance(props.get("specular_reflectance"), 1.0)[0]
            f = fresnel()
            notes.append(f"{kind} (coating F = {f:.3f}; F*specular + (1-F)*diffuse)")
            if tex is not None:
                notes.append("its diffuse texture kept, the coating dropped")
                return _Bsdf(name, np.ones(3), tex, raw)
            return _Bsdf(name, f * s + (1 - f) * d)
        if kind in ("conductor", "roughconductor"):
            s = self.reflectance(props.get("specular_reflectance"), 1.0)[0]
            if "eta" in props:
                eta = self.colour(props["eta"], unbounded=True)
                k = self.colour(props["k"], unbounded=True) if "k" in props else np.zeros(3)
                f0 = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
                what = "eta/k"
            else:
                metal = self.str_(props, "material", "none")
                f0 = np.array(METAL_F0.get(metal, (0.9, 0.9, 0.9)))
                what = f"material {metal!r}" + ("" if metal in METAL_F0 else " (unknown: 0.9)")
            notes.append(f"{kind} ({what}; specular_reflectance * F0)")
            return _Bsdf(name, s * f0)
        if kind in ("dielectric", "thindielectric", "roughdielectric"):
            r = self.reflectance(props.get("specular_reflectance"), 1.0)[0]
            t = self.reflectance(props.get("specular_transmittance"), 1.0)[0]
            f = fresnel()
            notes.append(f"{kind} (F = {f:.3f}; F*reflectance + (1-F)*transmittance, opaque)")
            return _Bsdf(name, f * r + (1 - f) * t)
        if kind in ("principled", "principledthin"):
            c, tex, raw = self.reflectance(props.get("base_color"), 0.5)
            notes.append(f"{kind} (base_color)")
            return _Bsdf(name, np.ones(3) if tex is not None else c, tex, raw)
        if kind in ("mask", "bumpmap", "normalmap"):
            what = {"mask": "opacity mask", "bumpmap": "bump map", "normalmap": "normal map"}
            notes.append(f"{kind}: {what[kind]} dropped")
            if not nested:
                return _Bsdf(name, np.full(3, 0.5))
            inner = self._bsdf(nested[0], notes)
            return _Bsdf(node.attrs.get("id") or inner.name, inner.albedo, inner.texture, inner.raw)
        if kind == "blendbsdf":
            w = float(np.mean(self.reflectance(props.get("weight"), 0.5)[0]))
            if len(nested) != 2:
                raise SceneError(f"{node.where}: blendbsdf needs two nested BSDFs")
            a, b = self._bsdf(nested[0], notes), self._bsdf(nested[1], notes)
            notes.append(f"blendbsdf (weight {w:.3g}: blended albedo, textures dropped)")
            return _Bsdf(name, (1 - w) * a.albedo + w * b.albedo)
        if kind == "null":
            notes.append("null (invisible in Mitsuba): black")
            return _Bsdf(name, np.zeros(3))
        self.skipped.append(f"{node.describe()} ({node.where})")
        notes.append(f"unsupported BSDF type {kind!r} at {node.where}: 0.5 grey")
        return _Bsdf(name, np.full(3, 0.5))

    def _declared(self, node: _Node) -> Any:
        """The BSDF element as an :mod:`icbtool.scene.bsdf` BSDF the tracer evaluates exactly,
        or None when it (or a BSDF or texture nested in it) is a plugin or form the tracer does
        not implement (the diffuse approximation and its warning then stand)."""
        try:
            return self._decl(node)
        except _Unsupported:
            return None
        except ValueError as e:
            raise SceneError(f"{node.where}: {e}") from None

    def _decl(self, node: _Node) -> Any:
        from icbtool.scene import bsdf as sb

        kind = node.attrs.get("type", "")
        props = self.props(node)
        nested = self.nested_bsdfs(node)

        def spec(key: str, default: Any) -> Any:
            n = props.get(key)
            if n is None:
                return default
            if n.tag == "texture":
                return self._decl_texture(n)
            return tuple(float(x) for x in self.colour(n))

        def scalar(key: str, default: Any) -> Any:
            n = props.get(key)
            if n is not None and n.tag == "texture":
                return self._decl_texture(n)
            return self.float_(props, key, default)

        def ior(key: str, default: str) -> Any:
            n = props.get(key)
            if n is None:
                return default
            if n.tag == "string":
                v = self.value(n).lower()
                if v not in sb.NAMED_IOR:
                    raise _Unsupported
                return v
            return self.float_(props, key, None)

        def micro() -> dict:
            d = self.str_(props, "distribution", "beckmann")
            if d not in ("beckmann", "ggx"):
                raise _Unsupported
            a = scalar("alpha", 0.1)
            return {
                "distribution": d,
                "alpha_u": scalar("alpha_u", a),
                "alpha_v": scalar("alpha_v", a),
            }

        if kind == "diffuse":
            return sb.Diffuse(spec("reflectance", 0.5))
        if kind == "twosided":
            if not nested or len(nested) > 2:
                raise _Unsupported
            back = self._decl(nested[1]) if len(nested) == 2 else None
            return sb.TwoSided(self._decl(nested[0]), back)
        if kind in ("plastic", "roughplastic"):
            kw = dict(
                int_ior=ior("int_ior", "polypropylene"),
                ext_ior=ior("ext_ior", "air"),
                diffuse_reflectance=spec("diffuse_reflectance", 0.5),
                specular_reflectance=spec("specular_reflectance", 1.0),
                nonlinear=self.bool_(props, "nonlinear", False),
            )
            if kind == "plastic":
                return sb.Plastic(**kw)
            d = self.str_(props, "distribution", "beckmann")
            a = scalar("alpha", 0.1)
            if d not in ("beckmann", "ggx") or not isinstance(a, float):
                raise _Unsupported
            return sb.RoughPlastic(**kw, distribution=d, alpha=a)
        if kind in ("conductor", "roughconductor"):
            kw = dict(specular_reflectance=spec("specular_reflectance", 1.0))
            if "eta" in props:
                if props["eta"].tag == "texture" or props.get("k", props["eta"]).tag == "texture":
                    raise _Unsupported
                kw["eta"] = tuple(self.colour(props["eta"], unbounded=True))
                k = self.colour(props["k"], unbounded=True) if "k" in props else np.zeros(3)
                kw["k"] = tuple(k)
            else:
                metal = self.str_(props, "material", "none")
                if metal not in sb.CONDUCTOR_ETA_K:
                    raise _Unsupported
                kw["material"] = metal
            if kind == "conductor":
                return sb.Conductor(**kw)
            return sb.RoughConductor(**kw, **micro())
        if kind in ("dielectric", "thindielectric", "roughdielectric"):
            kw = dict(
                int_ior=ior("int_ior", "bk7"),
                ext_ior=ior("ext_ior", "air"),
                specular_reflectance=spec("specular_reflectance", 1.0),
                specular_transmittance=spec("specular_transmittance", 1.0),
            )
            if kind == "dielectric":
                return sb.Dielectric(**kw)
            if kind == "thindielectric":
                return sb.ThinDielectric(**kw)
            return sb.RoughDielectric(**kw, **micro())
        if kind == "blendbsdf":
            if len(nested) != 2:
                raise _Unsupported
            return sb.BlendBSDF(self._decl(nested[0]), self._decl(nested[1]), scalar("weight", 0.5))
        if kind == "mask":
            if len(nested) != 1:
                raise _Unsupported
            return sb.Mask(self._decl(nested[0]), scalar("opacity", 0.5))
        if kind in ("normalmap", "bumpmap"):
            return self._decl_map(node, props, nested)
        raise _Unsupported

    def _decl_map(self, node: _Node, props: _Props, nested: list[_Node]) -> Any:
        """A ``normalmap`` (its texture named ``normalmap``) or ``bumpmap`` (its one texture,
        any name) over its one nested BSDF, as Mitsuba 3 declares them."""
        from icbtool.scene import bsdf as sb

        kind = node.attrs.get("type", "")
        if len(nested) != 1:
            raise SceneError(f"{node.where}: {kind} needs one nested BSDF, got {len(nested)}")
        keys = ("flip_invalid_normals", "use_shadowing_function")
        flags = {k: self.bool_(props, k, True) for k in keys}
        inner = self._decl(nested[0])
        if kind == "normalmap":
            n = props.get("normalmap")
            if n is None:
                raise SceneError(f"{node.where}: normalmap needs a texture named 'normalmap'")
            m = self._decl_texture(n) if n.tag == "texture" else tuple(self.colour(n))
            return sb.NormalMap(m, inner, **flags)
        tex = self._textures_in(node)
        if len(tex) != 1:
            raise SceneError(f"{node.where}: bumpmap needs one texture, got {len(tex)}")
        height, k = tex[0], float(self.float_(props, "scale", 1.0))
        if height.attrs.get("type") == "scale" and len(self._textures_in(height)) == 1:
            # Mitsuba 0.6's scale texture (Mitsuba 3 has none): a factor on the bump scale
            k *= float(self.float_(self.props(height), "scale", 1.0))
            height = self._textures_in(height)[0]
        if height.attrs.get("type") != "bitmap":
            repair_warning(
                height.where,
                f"bumpmap: a {height.attrs.get('type')!r} texture has no gradient in Mitsuba 3: "
                "the bump map is dropped, its nested BSDF traced",
            )
            return inner
        return sb.BumpMap(self._decl_texture(height), inner, k, **flags)

    def _textures_in(self, node: _Node) -> list[_Node]:
        """The textures inside ``node``, references resolved."""
        found = [self.deref(c) for c in node.children if c.tag in ("texture", "ref")]
        return [c for c in found if c.tag == "texture"]

    def _decl_texture(self, node: _Node) -> Any:
        """A ``bitmap`` or ``checkerboard`` texture as :mod:`icbtool.scene.bsdf` declares it."""
        from icbtool.scene import bsdf as sb

        kind = node.attrs.get("type")
        props = self.props(node)
        to_uv = self.transform(props.get("to_uv")) if "to_uv" in props else np.eye(4)
        if kind == "bitmap":
            fname = self.str_(props, "filename", None)
            if fname is None:
                raise SceneError(f"{node.where}: bitmap texture without a filename")
            path = self.resolve(node, fname)
            raw = self.bool_(props, "raw", False)
            tex = self.texture(node, path, raw)
            if tex is None:
                raise _Unsupported
            filt = self.str_(props, "filter_type", "bilinear")
            if filt not in ("bilinear", "nearest"):
                raise _Unsupported
            return sb.Bitmap(tex, filt, str(path), to_uv)
        if kind == "checkerboard":
            c = []
            for key, default in (("color0", 0.4), ("color1", 0.2)):
                n = props.get(key)
                if n is not None and n.tag == "texture":
                    raise _Unsupported
                c.append(np.full(3, default) if n is None else self.colour(n))
            return sb.Checkerboard(tuple(c[0]), tuple(c[1]), to_uv)
        raise _Unsupported

    def material(self, bsdf: _Bsdf, emission: np.ndarray) -> int:
        key = (id(bsdf), tuple(np.round(emission, 9)))
        if key in self.mat_keys:
            return self.mat_keys[key]
        name = bsdf.name
        if np.any(emission > 0):
            name = f"{name}+emitter"
        names = {m.name for m in self.materials}
        while name in names:
            name += "_"
        tex = None
        if bsdf.texture is not None:
            tex = self.tex_cache.get(f"{bsdf.texture}|{bsdf.raw}")
        mat = Material(
            name, bsdf.albedo, emission, tex, str(bsdf.texture) if tex is not None else None,
            bsdf=bsdf.declared,
        )  # fmt: skip
        self.materials.append(mat)
        self.mat_keys[key] = len(self.materials) - 1
        return self.mat_keys[key]


class _Reader(_Materials):
    """Shapes, emitters, the sensor and the integrator, assembled into one Scene."""

    def shape(self, node: _Node, parent: np.ndarray | None = None) -> None:
        """Read one shape into ``self.parts`` (``parent``: the to_world of the instance that
        places it, for the shapes of a shapegroup)."""
        kind = node.attrs.get("type", "")
        if kind == "shapegroup":
            self.check_group(node)  # rendered only through its instances
            return
        if kind == "instance":
            self.instance(node, parent)
            return
        props = self.props(node)
        for tag in ("bsdf", "emitter"):
            given = [c for c in node.children if self.deref(c).tag == tag]
            if len(given) > 1:
                raise SceneError(
                    f"{given[1].where}: {node.describe()} at {node.where} has a second "
                    f"<{tag}> (Mitsuba allows one per shape)"
                )
        own = self.transform(props.get("to_world"))
        to_world = own if parent is None else parent @ own
        if parent is None:
            geo = self.geometry(node, kind, props)
        else:  # a shapegroup's shape is read once for all its instances
            if id(node) not in self.geo_cache:
                self.geo_cache[id(node)] = self.geometry(node, kind, props)
            else:  # warned about at its first instance
                props.used.update(props)
            geo = self.geo_cache[id(node)]
        if geo is None:
            return
        v, f, n, uv = geo
        if kind == "sphere":
            c = self.point(props, "center", (0, 0, 0))
            r = self.float_(props, "radius", 1.0)
            local = np.eye(4)
            local[:3, :3] *= r
            local[:3, 3] = c
            to_world = to_world @ local
            own = own @ local
        lin = to_world[:3, :3]
        v_own = None if parent is None else v @ own[:3, :3].T + own[:3, 3]
        if abs(np.linalg.det(lin)) < 1e-300:
            raise SceneError(f"{node.where}: {node.describe()} to_world is singular")
        v = v @ lin.T + to_world[:3, 3]
        n = n @ np.linalg.inv(lin)  # inverse transpose, row vectors
        if self.bool_(props, "flip_normals", False):
            f = f[:, ::-1].copy()
            n = -n
        if self.bool_(props, "face_normals", False):
            uv = None if uv is None else uv[f].reshape(-1, 2)
            if v_own is not None:
                v_own = v_own[f].reshape(-1, 3)
            v, f = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
            n = np.full_like(v, np.nan)  # computed flat below
        bsdf = self.bsdf(props.get("bsdf"))
        emission = np.zeros(3)
        em = props.get("emitter")
        if em is not None:
            if em.attrs.get("type") != "area":
                self.dropped_lights.append(f"{em.describe()} ({self.where(em)})")
                self.skip(em, "inside a shape must be an area emitter")
            else:
                ep = self.props(em)
                emission, tex, _ = self.reflectance(ep.get("radiance"), 1.0, emitter=True)
                if tex is not None:
                    repair_warning(em.where, "textured radiance: its mean colour is emitted")
                emission = np.maximum(emission, 0.0)
                if props.get("bsdf") is None:
                    bsdf = self.default_emitter_bsdf
        mat = self.material(bsdf, emission)
        exact = None
        if kind in ("sphere", "disk", "cylinder"):
            exact = self.exact_shape(node, kind, props, to_world, bsdf)
        self.finish(node, props)
        self.parts.append(_Part(v, f, n, uv, mat, exact))
        if v_own is not None:  # an instance's shape, in its shapegroup's space
            self.group_local.append((v_own, f, exact is None))
        self.n_shapes += 1

    def check_group(self, node: _Node) -> list[_Node]:
        """The shapes of a ``<shape type="shapegroup">``; what Mitsuba refuses in one (a nested
        group or instance, an emitter) is an error naming its line."""
        shapes = []
        for c in node.children:
            t = self.deref(c)
            if t.tag != "shape":
                if t.tag not in _PROPERTY_TAGS:
                    self.skip(t, "in a shapegroup is not a shape")
                continue
            kind = t.attrs.get("type")
            if kind in ("shapegroup", "instance"):
                raise SceneError(
                    f"{c.where}: <shape {kind}> inside the shapegroup at {node.where}: nested "
                    "instancing is not permitted (Mitsuba refuses it too)"
                )
            if any(self.deref(e).tag == "emitter" for e in t.children):
                raise SceneError(
                    f"{c.where}: a shape with an emitter inside the shapegroup at {node.where}: "
                    "instancing of emitters is not supported (Mitsuba refuses it too)"
                )
            shapes.append(t)
        return shapes

    def instance(self, node: _Node, parent: np.ndarray | None) -> None:
        """``<shape type="instance">``: a copy of every shape of the referenced shapegroup,
        moved by the instance's ``to_world`` (the copies are flattened into the mesh)."""
        if parent is not None:
            raise SceneError(f"{node.where}: nested instancing is not permitted")
        props = self.props(node)
        group = props.get("shape") or props.get("shapegroup")
        if group is None or group.attrs.get("type") != "shapegroup":
            raise SceneError(f"{node.where}: an instance needs a <ref> to a shapegroup")
        to_world = self.transform(props.get("to_world"))
        self.finish(node, props)
        first = len(self.parts)
        self.group_local = []
        for s in self.check_group(group):
            self.shape(s, to_world)
        if id(group) not in self.groups:  # the prototype: the group's shapes in its own space
            ok = bool(self.group_local) and all(e for _, _, e in self.group_local)
            self.groups[id(group)] = (len(self.groups), ok, self.group_local)
        g, ok, _ = self.groups[id(group)]
        if ok:  # (a group holding an exact sphere, disk or cylinder stays flattened)
            self.instances.append((g, to_world[:3, :4].copy(), first, len(self.parts)))
        self.group_local = []
        self.n_instances += 1

    def exact_shape(
        self, node: _Node, kind: str, props: dict, to_world: np.ndarray, bsdf: _Bsdf
    ) -> tuple | None:
        """(kind, world_from_local, flip_normals, name) of a sphere, disk or cylinder for the
        tracer's exact shape (:class:`~icbtool.scene.types.AnalyticShape`), or None (it stays
        tessellated, with a warning) when the shape is textured or ``to_world`` distorts it
        beyond what the exact shape takes (a non-uniformly scaled sphere, an elliptic
        cylinder)."""
        m = np.array(to_world, np.float64)  # a sphere's: centre and radius already applied
        if kind == "cylinder":
            p0 = self.point(props, "p0", (0, 0, 0))
            p1 = self.point(props, "p1", (0, 0, 1))
            r = float(self.float_(props, "radius", 1.0))
            w = p1 - p0
            a = np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 * np.linalg.norm(w) else [0, 1.0, 0])
            a /= np.linalg.norm(a)
            b = np.cross(w / np.linalg.norm(w), a)
            local = np.eye(4)
            local[:3, 0], local[:3, 1], local[:3, 2], local[:3, 3] = r * a, r * b, w, p0
            m = m @ local
        flip = self.bool_(props, "flip_normals", False)
        name = node.attrs.get("id") or f"{kind}@{node.line}"
        if bsdf.texture is not None:
            repair_warning(node.where, f"textured {kind}: kept as triangles, not exact")
            return None
        try:
            AnalyticShape(kind, m, 0, (0, 1), flip, name)  # type: ignore[arg-type]
        except ValueError as e:
            repair_warning(node.where, f"{kind} kept as triangles, not exact: {e}")
            return None
        return (kind, m, flip, name)

    def geometry(self, node: _Node, kind: str, props: dict) -> tuple | None:
        """(vertices, faces, normals (NaN rows: compute), uvs | None) in the shape's space."""
        seg = SPHERE_SEGMENTS
        if kind in ("obj", "ply"):
            fname = self.str_(props, "filename", None)
            if fname is None:
                raise SceneError(f"{node.where}: {node.describe()} needs a filename")
            p = self.resolve(node, fname)
            if not p.is_file():
                raise FileNotFoundError(f"{node.where}: mesh file not found: {p}")
            if kind == "obj":
                mesh = parse_obj(p)
                n = np.where(mesh.normal_given[:, None], mesh.normals, np.nan)
                uv = mesh.uvs
                if uv is not None and not self.bool_(props, "flip_tex_coords", True):
                    uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
                return mesh.vertices, mesh.faces, n, uv
            from icbtool.scene.ply import read_binary_ply

            fast = read_binary_ply(p)  # a binary triangle PLY: numpy alone, no per-file Scene
            if fast is not None:
                v, f, n, uv = fast
                uv = None if uv is None else np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
                return v, f, n, uv
            from icbtool.scene.mesh import load_mesh

            try:
                m = load_mesh(p, up_axis="y", textures=False)
            except SceneError as e:
                raise SceneError(f"{node.where}: {node.describe()}: {e}") from None
            uv = None if m.uvs is None else np.column_stack([m.uvs[:, 0], 1.0 - m.uvs[:, 1]])
            return (
                m.vertices.astype(float),
                m.faces.astype(np.int64),
                m.normals.astype(float),
                uv,
            )
        if kind == "serialized":
            fname = self.str_(props, "filename", None)
            if fname is None:
                raise SceneError(f"{node.where}: {node.describe()} needs a filename")
            p = self.resolve(node, fname)
            if not p.is_file():
                raise FileNotFoundError(f"{node.where}: mesh file not found: {p}")
            index = self.int_(props, "shape_index", 0)
            return read_serialized(p, index, node.where)
        if kind == "rectangle":
            v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
            uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], float)  # Mitsuba (0,0) at (-1,-1)
            n = np.tile([0.0, 0.0, 1.0], (4, 1))
            return v, np.array([[0, 1, 2], [0, 2, 3]]), n, uv
        if kind == "cube":
            return _cube()
        if kind == "disk":
            t = np.linspace(0, 2 * np.pi, seg, endpoint=False)
            v = np.vstack([[0, 0, 0], np.column_stack([np.cos(t), np.sin(t), np.zeros(seg)])])
            f = np.array([[0, 1 + i, 1 + (i + 1) % seg] for i in range(seg)])
            uv = np.column_stack([np.r_[0, np.ones(seg)], 1 - np.r_[0, t / (2 * np.pi)]])
            return v, f, np.tile([0.0, 0.0, 1.0], (seg + 1, 1)), uv
        if kind == "sphere":
            return _sphere(seg)
        if kind == "cylinder":
            p0 = self.point(props, "p0", (0, 0, 0))
            p1 = self.point(props, "p1", (0, 0, 1))
            r = self.float_(props, "radius", 1.0)
            return _cylinder(p0, p1, r, seg)
        self.skip(node, "shape type is not supported")
        return None

    # ---------------------------------------------------------------- emitters, sensor
    def emitter(self, node: _Node) -> None:
        kind = node.attrs.get("type", "")
        props = self.props(node)
        name = node.attrs.get("id") or f"{kind}@{node.line}"
        m = self.transform(props.get("to_world"))
        if kind not in ("area", "point", "spot", "directional", "constant", "envmap"):
            self.dropped_lights.append(f"{node.describe()} ({self.where(node)})")
            self.skip(node, "emitter type is not supported")
            return
        try:
            if kind == "area":
                if "id" not in node.attrs:
                    self.skip(node, "outside a shape emits nothing")
                props.used.add("radiance")
            if kind == "point":
                pos = self.point(props, "position", m[:3, 3])
                inten = self.reflectance(props.get("intensity"), 1.0, emitter=True)[0]
                self.lights.append(PointLight(pos, inten, name=name))
            elif kind == "spot":
                cutoff = float(self.float_(props, "cutoff_angle", 20.0))
                beam = float(self.float_(props, "beam_width", cutoff * 0.75))
                inten = self.reflectance(props.get("intensity"), 1.0, emitter=True)[0]
                # Mitsuba's profile: linear in the angle from beam_width to cutoff_angle (a hard
                # edge, beam_width = cutoff_angle, within 0.1 % of it)
                inner = min(beam, cutoff * 0.999)
                self.lights.append(
                    SpotLight(m[:3, 3], m[:3, 2], inten, inner, cutoff, name, profile="linear")
                )
            elif kind == "directional":
                d = props.get("direction")
                direction = self.vec(d, "direction") if d is not None else m[:3, 2]
                irr = self.reflectance(props.get("irradiance"), 1.0, emitter=True)[0]
                self.lights.append(DirectionalLight(direction, irr, name=name))
            elif kind in ("constant", "envmap"):
                if self.sky is not None:
                    self.skip(node, "is a second environment emitter (only one sky is kept)")
                    props.used.update(props)
                elif kind == "constant":
                    rad = self.reflectance(props.get("radiance"), 1.0, emitter=True)[0]
                    self.sky = Sky(zenith=np.maximum(rad, 0), kind="uniform")
                else:
                    self.sky = self.envmap(node, props, m)
        except ValueError as e:
            if isinstance(e, SceneError):
                raise
            raise SceneError(f"{node.where}: {node.describe()}: {e}") from None
        self.finish(node, props)

    def envmap(self, node: _Node, props: dict, m: np.ndarray) -> Sky:
        fname = self.str_(props, "filename", None)
        if fname is None:
            raise SceneError(f"{node.where}: envmap needs a filename")
        path = self.resolve(node, fname)
        scale = float(self.float_(props, "scale", 1.0))
        lin = m[:3, :3]
        u, _, vt = np.linalg.svd(lin)
        rot = u @ vt  # the rotation of to_world (scale dropped)
        if not hasattr(Sky, "from_envmap"):
            raise SceneError(
                f"{node.where}: environment maps need Sky.from_envmap, which this icbtool "
                "does not have yet"
            )
        if not path.is_file():
            raise FileNotFoundError(f"{node.where}: environment map not found: {path}")
        return Sky.from_envmap(path, scale=scale, world_from_map=rot)

    def sensor(self, node: _Node) -> None:
        """The first sensor becomes the default camera, as Mitsuba casts its rays:
        ``perspective`` (every ``fov_axis``, ``focal_length``, film crops, principal point
        offsets), ``thinlens`` (aperture disk, focus plane) and ``orthographic`` (extent = the
        ``to_world`` scale), each with its near clip; a thin lens or an orthographic sensor warns
        once that the ICB pipeline renders its pinhole (:meth:`Camera.pinhole`)."""
        from icbtool.camera import Camera
        from icbtool.camera.camera import MITSUBA_NEAR_CLIP

        kind = node.attrs.get("type", "")
        if self.camera is not None:
            self.skip(node, "is a second sensor (the first is the default camera)")
            return
        if kind not in ("perspective", "thinlens", "orthographic"):
            self.skip(node, "sensor type is not supported")
            return
        props = self.props(node)
        film = props.get("film")
        fp = self.props(film) if film is not None else _Props()
        w, h, (cw, ch, ox, oy) = self.film(film, fp)
        m = self.transform(props.get("to_world"))
        r = m[:3, :3].copy()
        norms = np.linalg.norm(r, axis=0)
        if np.any(norms < 1e-12):
            raise SceneError(f"{node.where}: sensor to_world is singular")
        u, _, vt = np.linalg.svd(r / norms)
        r = u @ vt
        if np.linalg.det(r) < 0:
            repair_warning(node.where, "sensor to_world mirrors the image: rendered unmirrored")
            r[:, 0] = -r[:, 0]
        near, far = self.clip_range(node, props, MITSUBA_NEAR_CLIP)
        lens: dict[str, Any] = {"near_clip": near}
        if kind == "orthographic":
            # Mitsuba's camera space sees x in [-1, 1], y in [-1 / aspect, 1 / aspect] (full
            # film), scaled by to_world; its rays start at z = near_clip before that scale
            focal_x, focal_y = 0.5 * w / float(norms[0]), 0.5 * w / float(norms[1])
            cx, cy = w / 2 - ox, h / 2 - oy
            lens.update(projection="orthographic", near_clip=near * float(norms[2]))
        else:
            fov_x = self.fov_x(node, props, w / h)
            focal_x = focal_y = 0.5 * w / math.tan(math.radians(fov_x) / 2)
            cx, cy = w / 2 - ox, h / 2 - oy
            if kind == "perspective":
                # every Mitsuba projective camera reads focus_distance; a pinhole never uses it
                self.float_(props, "focus_distance", far)
                ppx = float(self.float_(props, "principal_point_offset_x", 0.0))
                ppy = float(self.float_(props, "principal_point_offset_y", 0.0))
                cx, cy = cx - ppx * w, cy - ppy * h
            else:
                lens.update(self.thin_lens(node, props, far))
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2] = -r[:, 0], -r[:, 1], r[:, 2]
        pose[:3, 3] = m[:3, 3]
        self.camera = Camera(ch, cw, focal_x, focal_y, cx, cy, pose, **lens)
        if kind != "perspective":
            repair_warning(
                node.where,
                f"{kind} sensor: `icbtool trace` renders it exactly; the ICB pipeline (G-buffers, "
                "raster, warping, LPM) renders its pinhole",
            )
        self.cam_up = r[:, 1]
        self.finish(node, props)
        if film is not None:
            self.finish(film, fp)

    def clip_range(self, node: _Node, props: _Props, default_near: float) -> tuple[float, float]:
        """(near_clip, far_clip) of a sensor, Mitsuba's defaults (0.01, 1e4) and checks."""
        near = float(self.float_(props, "near_clip", default_near))
        far = float(self.float_(props, "far_clip", 1e4))
        if not (math.isfinite(near) and near > 0):
            raise SceneError(f"{node.where}: near_clip must be > 0, got {near}")
        if not near < far:
            raise SceneError(f"{node.where}: near_clip ({near}) must be < far_clip ({far})")
        return near, far

    def thin_lens(self, node: _Node, props: _Props, far: float) -> dict[str, float]:
        """``aperture_radius`` (required, as Mitsuba's) and ``focus_distance`` (default: the far
        clip, as Mitsuba's) of a ``thinlens`` sensor; a bad value is an error naming its line."""
        if "aperture_radius" not in props:
            raise SceneError(f"{node.where}: a thinlens sensor needs 'aperture_radius'")
        radius = float(self.float_(props, "aperture_radius", 0.0))
        focus = float(self.float_(props, "focus_distance", far))
        where = lambda k: self.where(props[k]) if k in props else node.where  # noqa: E731
        if not (math.isfinite(radius) and radius >= 0):
            raise SceneError(f"{where('aperture_radius')}: aperture_radius must be >= 0, got "
                             f"{radius}")  # fmt: skip
        if not (math.isfinite(focus) and focus > 0):
            raise SceneError(f"{where('focus_distance')}: focus_distance must be > 0, got {focus}")
        if radius == 0:
            repair_warning(node.where, "thinlens aperture_radius 0: rendered as a pinhole")
        return {"aperture_radius": radius, "focus_distance": focus}

    def film(self, film: _Node | None, fp: _Props) -> tuple[int, int, tuple[int, int, int, int]]:
        """(width, height, (crop width, crop height, crop offset x, crop offset y)) of a film
        (Mitsuba's defaults: 768 x 576, no crop); a crop outside the film is an error."""
        w = self.int_(fp, "width", 768)
        h = self.int_(fp, "height", 576)
        where = film.where if film is not None else str(self.path)
        if w < 1 or h < 1:
            raise SceneError(f"{where}: film size must be positive, got {w} x {h}")
        ox = self.int_(fp, "crop_offset_x", 0)
        oy = self.int_(fp, "crop_offset_y", 0)
        cw = self.int_(fp, "crop_width", w - ox)
        ch = self.int_(fp, "crop_height", h - oy)
        if ox < 0 or oy < 0 or cw < 1 or ch < 1 or ox + cw > w or oy + ch > h:
            raise SceneError(
                f"{where}: film crop (offset {ox}, {oy}, size {cw} x {ch}) is not inside the "
                f"{w} x {h} film"
            )
        return w, h, (cw, ch, ox, oy)

    def fov_x(self, node: _Node, props: _Props, aspect: float) -> float:
        """Horizontal field of view (degrees) of a perspective sensor, by Mitsuba's rules:
        ``fov`` along ``fov_axis`` (x, y, diagonal, smaller, larger), or ``focal_length`` (a
        35 mm film's 43.27 mm diagonal, whatever the film's aspect)."""
        if "fov" in props and "focal_length" in props:
            raise SceneError(f"{node.where}: give either fov or focal_length, not both")
        if "fov" in props:
            fov = float(self.float_(props, "fov", 45.0))
            axis = self.str_(props, "fov_axis", "x").lower()
            if axis == "smaller":
                axis = "y" if aspect > 1 else "x"
            elif axis == "larger":
                axis = "x" if aspect > 1 else "y"
        else:
            text = self.str_(props, "focal_length", "50mm")
            try:
                mm = float(text[:-2] if text.endswith("mm") else text)
            except ValueError:
                raise SceneError(f"{node.where}: focal_length {text!r} is not '<x>mm'") from None
            if not mm > 0:
                raise SceneError(f"{node.where}: focal_length must be > 0, got {text!r}")
            fov = math.degrees(2 * math.atan(math.hypot(36.0, 24.0) / (2 * mm)))
            axis = "diagonal"
        half = math.tan(math.radians(fov) / 2)
        if axis == "x":
            result = fov
        elif axis == "y":
            result = math.degrees(2 * math.atan(half * aspect))
        elif axis == "diagonal":
            result = math.degrees(2 * math.atan(half / math.sqrt(1 + 1 / aspect**2)))
        else:
            raise SceneError(
                f"{node.where}: fov_axis must be x, y, diagonal, smaller or larger, got {axis!r}"
            )
        if not 0 < result < 180:
            raise SceneError(f"{node.where}: sensor fov must be in (0, 180), got {result}")
        return result

    def integrator(self, node: _Node) -> None:
        kind = node.attrs.get("type", "")
        props = self.props(node)
        depth = self.int_(props, "max_depth", None)
        if kind == "direct":
            self.max_depth = 2
        elif depth is not None:
            if depth == 0 or depth < -1:
                raise SceneError(f"{node.where}: max_depth must be >= 1 or -1, got {depth}")
            self.max_depth = depth
        elif kind in ("path", "volpath", "volpathmis", "prb", "ptracer"):
            self.max_depth = -1  # Mitsuba's default for these: unbounded (Russian roulette)
        else:
            inner = [c for c in node.children if c.tag == "integrator"]
            if inner:
                self.integrator(inner[0])
            else:
                self.skip(node, "integrator type is not supported (max depth: the tracer's)")
        if self.bool_(props, "hide_emitters", False):
            repair_warning(
                node.where,
                "hide_emitters is not applied: emitters and the environment the camera sees "
                "directly stay in icbtool's image",
            )
        props.used.add("integrator")
        self.finish(node, props)

    # ---------------------------------------------------------------- assembly
    def read(self, root: _Node) -> None:
        nodes = self.flatten(root)
        self.collect_ids(nodes)
        bar = _shape_bar(self.path, sum(n.tag == "shape" for n in nodes), self.progress)
        for node in nodes:
            tag = node.tag
            if tag == "shape":
                self.shape(node)
                bar.update(1)
            elif tag == "emitter":
                self.emitter(node)
            elif tag == "sensor":
                self.sensor(node)
            elif tag == "integrator":
                self.integrator(node)
            elif tag in ("bsdf", "texture"):
                if "id" not in node.attrs:
                    self.skip(node, "at the top level without an id is unused")
            elif tag in _PROPERTY_TAGS or tag in ("ref",):
                self.skip(node, "at the top level of the scene has no meaning")
            else:
                self.skip(node, "is not supported")
        bar.close()

    def build(self, name: str) -> Scene:
        where = str(self.path)
        if not self.parts:
            raise SceneError(f"{where}: the scene has no shape icbtool can read")
        offs = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        v = np.concatenate([p.vertices for p in self.parts])
        f = np.concatenate([p.faces + o for p, o in zip(self.parts, offs[:-1])])
        n = np.concatenate([p.normals for p in self.parts])
        fm = np.concatenate([np.full(len(p.faces), p.material, np.int32) for p in self.parts])
        uv = None
        if any(p.uvs is not None for p in self.parts):
            uv = np.concatenate(
                [
                    p.uvs if p.uvs is not None else np.zeros((len(p.vertices), 2), np.float32)
                    for p in self.parts
                ]
            )
        part_faces = [len(p.faces) for p in self.parts]
        exacts = [(p.exact, p.material) for p in self.parts]
        self.parts = []  # merged: the shapes' own copies go (peak memory)
        face_id = np.arange(len(f))  # which faces check_arrays keeps (shapes' ranges)
        with warnings.catch_warnings():
            # NaN rows are the normals to compute (no normal in the file), not a repair
            warnings.filterwarnings("ignore", r".*vertex normal\(s\) are NaN", UserWarning)
            v, f, n, uv, face_id = check_arrays(where, v, f, n, uv, face_id)
        fm = fm[face_id]
        shapes = []
        start = np.cumsum([0, *part_faces])
        for (exact, mat), a, b in zip(exacts, start[:-1], start[1:]):
            if exact is not None:
                lo, hi = np.searchsorted(face_id, [a, b])
                if hi > lo:  # its tessellation's kept faces are one run of the scene's
                    kind, m, flip, name = exact
                    shapes.append(AnalyticShape(kind, m, mat, (int(lo), int(hi)), flip, name))
        fill_vertex_normals(v, f, n, ~np.isfinite(n).all(axis=1))
        inst = self.instancing(start, face_id)
        mats = self.materials
        if not any(m.is_textured or m.bsdf is not None for m in mats):
            uv = None  # (declared BSDFs keep them: textures, the anisotropy's tangent frame)
        elif uv is None:
            mats = [dataclasses.replace(m, texture=None, texture_path=None) for m in mats]
        up = np.array([0.0, 1.0, 0.0])
        if self.cam_up is not None:
            k = int(np.argmax(np.abs(self.cam_up)))
            up = np.zeros(3)
            up[k] = math.copysign(1.0, self.cam_up[k])
        return Scene(
            name=name,
            vertices=v,
            faces=f,
            normals=n,
            face_material=fm,
            materials=mats,
            uvs=uv,
            lights=self.lights,
            sky=self.sky,
            default_camera=self.camera,
            up=up,
            max_depth=self.max_depth,
            source=where,
            shapes=shapes,
            instancing=inst,
        )

    def instancing(self, start: np.ndarray, face_id: np.ndarray) -> Any:
        """The scene's :class:`~icbtool.scene.instancing.Instancing` (None without instances):
        each instance is a run of the scene's faces; the faces the mesh checks dropped (e.g.
        degenerate ones) are dropped from its prototype too, and an instance that lost other
        faces than its prototype's first instance stays a plain part of the mesh."""
        from icbtool.scene.instancing import Instancing

        if not self.instances:
            return None
        protos: list = [None] * len(self.groups)
        for g, ok, local in self.groups.values():
            if ok:
                offs = np.cumsum([0] + [len(vv) for vv, _, _ in local])
                protos[g] = (
                    np.concatenate([vv for vv, _, _ in local]).astype(np.float32),
                    np.concatenate([ff + o for (_, ff, _), o in zip(local, offs)]).astype(np.int32),
                )
        proto, xform, face0 = [], [], []
        keep: dict[int, np.ndarray] = {}  # per prototype: its faces the mesh checks kept
        for g, m, pa, pb in self.instances:
            a, b = int(start[pa]), int(start[pb])
            if protos[g] is None or b == a or len(protos[g][1]) != b - a:
                continue
            lo, hi = np.searchsorted(face_id, [a, b])
            kept = face_id[lo:hi] - a  # (a degenerate face dropped from every copy: from the
            if hi == lo or not np.array_equal(keep.setdefault(g, kept), kept):  # prototype too)
                continue
            proto.append(g)
            xform.append(m)
            face0.append(int(lo))
        for g, kept in keep.items():
            if len(kept) != len(protos[g][1]):
                protos[g] = (protos[g][0], protos[g][1][kept])
        self.groups, self.instances = {}, []
        if not proto:
            return None
        empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        return Instancing(
            tuple(p if p is not None else empty for p in protos),
            np.array(proto, np.int32),
            np.array(xform, np.float32).reshape(-1, 3, 4),
            np.array(face0, np.int64),
        )


def _shape_bar(path: Path, n_shapes: int, progress: bool) -> Any:
    """A tqdm bar over a file's shapes (stderr; off unless ``progress``)."""
    from tqdm import tqdm

    return tqdm(total=n_shapes, desc=f"load {path.name}", unit="shape", disable=not progress)


#: Mitsuba's serialized mesh format: file identifier and flags of the compressed header.
_SERIALIZED_ID = 0x041C
_SER_NORMALS, _SER_UVS, _SER_COLORS, _SER_DOUBLE = 0x0001, 0x0002, 0x0008, 0x2000


def read_serialized(path: Path, index: int = 0, where: str | None = None) -> tuple:
    """Shape ``index`` of a Mitsuba ``.serialized`` file (format versions 3 and 4).

    Each shape is ``uint16 0x041C, uint16 version`` and a zlib stream holding ``uint32 flags``,
    (version 4) a NUL-terminated name, ``uint64`` vertex and triangle counts, positions (float32,
    or float64 with flag 0x2000), normals (0x0001), uvs (0x0002), colours (0x0008, skipped) and
    the indices (uint32, uint64 above 2^32 vertices); the file ends with the shapes' offsets
    (uint64 in version 4, uint32 in 3) and their count (uint32).

    Returns:
        (vertices (V, 3), faces (F, 3), normals (V, 3) with NaN rows when absent, uvs (V, 2) in
        the Scene convention (``1 - v``) or None).

    Raises:
        SceneError: not a serialized file, a missing shape index, a corrupt stream (names the
            file and, with ``where``, the scene element).
    """
    import struct
    import zlib

    who = f"{where}: {path}" if where else str(path)
    data = path.read_bytes()
    if len(data) < 8 or struct.unpack_from("<H", data, 0)[0] != _SERIALIZED_ID:
        raise SceneError(f"{who}: not a Mitsuba serialized mesh (bad file identifier)")
    version = struct.unpack_from("<H", data, 2)[0]
    if version not in (3, 4):
        raise SceneError(f"{who}: serialized format version {version} is not supported (3, 4)")
    count = struct.unpack_from("<I", data, len(data) - 4)[0]
    width = 8 if version == 4 else 4
    table = len(data) - 4 - width * count
    if table < 4:
        raise SceneError(
            f"{who}: truncated or corrupt serialized file ({len(data)} bytes cannot hold the "
            f"{count} shapes its last 4 bytes declare)"
        )
    if not 0 <= index < count:
        raise SceneError(f"{who}: shape_index {index} out of range: the file has {count} shapes")
    (offset,) = struct.unpack_from("<Q" if width == 8 else "<I", data, table + width * index)
    if not 0 <= offset < table:
        raise SceneError(f"{who}: truncated or corrupt serialized file (shape {index} offset)")
    try:
        raw = zlib.decompressobj().decompress(data[offset + 4 : table])
        pos = 0
        (flags,) = struct.unpack_from("<I", raw, pos)
        pos += 4
        if version == 4:
            end = raw.index(b"\0", pos)
            pos = end + 1
        nv, nf = struct.unpack_from("<QQ", raw, pos)
        pos += 16
        real = np.float64 if flags & _SER_DOUBLE else np.float32
        rsize = np.dtype(real).itemsize

        def take(n: int, dtype: Any) -> np.ndarray:
            nonlocal pos
            a = np.frombuffer(raw, dtype=dtype, count=n, offset=pos)
            pos += n * np.dtype(dtype).itemsize
            return a

        v = take(3 * nv, real).reshape(-1, 3).astype(np.float64)
        n = take(3 * nv, real).reshape(-1, 3).astype(np.float64) if flags & _SER_NORMALS else None
        uv = take(2 * nv, real).reshape(-1, 2).astype(np.float64) if flags & _SER_UVS else None
        if flags & _SER_COLORS:
            pos += 3 * nv * rsize
        f = take(3 * nf, np.uint64 if nv > 0xFFFFFFFF else np.uint32).reshape(-1, 3)
    except (zlib.error, struct.error, ValueError) as e:
        raise SceneError(f"{who}: shape {index}: corrupt serialized stream ({e})") from None
    if n is None:
        n = np.full_like(v, np.nan)
    if uv is not None:
        uv = np.column_stack([uv[:, 0], 1.0 - uv[:, 1]])
    return v, f.astype(np.int64), n, uv


def _cube() -> tuple:
    """Mitsuba's cube: [-1, 1]^3, outward faces, flat normals, uvs per face."""
    verts, faces, normals, uvs = [], [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            nrm = np.zeros(3)
            nrm[axis] = sign
            a, b = [k for k in range(3) if k != axis]
            quad = []
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[a], p[b] = sign, s, t
                quad.append(p)
            quad = np.array(quad)
            if np.dot(np.cross(quad[1] - quad[0], quad[2] - quad[0]), nrm) < 0:
                quad = quad[::-1]
            base = len(verts)
            verts += list(quad)
            normals += [nrm] * 4
            uvs += [[0, 1], [1, 1], [1, 0], [0, 0]]
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.array(verts), np.array(faces), np.array(normals), np.array(uvs, float)


def _sphere(seg: int) -> tuple:
    """A unit UV sphere (outward), ``seg`` x ``seg // 2`` cells, poles shared."""
    n_lat = max(seg // 2, 2)
    theta = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    v = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    uv = np.vstack([[0.5, 1], np.column_stack([p.ravel() / (2 * np.pi), 1 - t.ravel() / np.pi]),
                    [0.5, 0]])  # fmt: skip
    faces = []
    idx = lambda i, j: 1 + i * seg + (j % seg)  # noqa: E731
    for j in range(seg):
        faces.append([0, idx(0, j), idx(0, j + 1)])
        last = len(v) - 1
        faces.append([last, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
        for i in range(n_lat - 2):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            faces += [[a, b, c], [a, c, d]]
    return v, np.array(faces), v.copy(), uv


def _cylinder(p0: np.ndarray, p1: np.ndarray, r: float, seg: int) -> tuple:
    """An open tube of radius ``r`` from ``p0`` to ``p1`` (outward normals)."""
    axis = p1 - p0
    length = np.linalg.norm(axis)
    if length < 1e-12 or not r > 0:
        raise SceneError(f"cylinder needs p0 != p1 and radius > 0, got {p0}, {p1}, {r}")
    w = axis / length
    a = np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(w, a)
    t = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    ring = np.outer(np.cos(t), a) + np.outer(np.sin(t), b)
    v = np.vstack([p0 + r * ring, p1 + r * ring])
    faces = []
    for i in range(seg):
        j = (i + 1) % seg
        faces += [[i, j, seg + j], [i, seg + j, seg + i]]
    uv = np.column_stack([np.r_[t, t] / (2 * np.pi), np.r_[np.ones(seg), np.zeros(seg)]])
    return v, np.array(faces), np.vstack([ring, ring]), uv


def _to_xml(node: _Node, depth: int = 0) -> str:
    from xml.sax.saxutils import quoteattr

    pad = "    " * depth
    attrs = "".join(f" {k}={quoteattr(v)}" for k, v in node.attrs.items())
    if not node.children:
        return f"{pad}<{node.tag}{attrs}/>\n"
    inner = "".join(_to_xml(c, depth + 1) for c in node.children)
    return f"{pad}<{node.tag}{attrs}>\n{inner}{pad}</{node.tag}>\n"


def _diffuse_node(old: _Node, b: _Bsdf) -> _Node:
    """``<bsdf type="twosided"><bsdf type="diffuse">`` of what icbtool renders for ``old``."""
    keep = {k: v for k, v in old.attrs.items() if k in ("id", "name")}
    if b.texture is not None:
        refl = _Node("texture", {"type": "bitmap", "name": "reflectance"}, old.file, old.line)
        refl.children = [
            _Node("string", {"name": "filename", "value": str(b.texture)}, old.file, old.line),
            _Node("boolean", {"name": "raw", "value": str(b.raw).lower()}, old.file, old.line),
        ]
    else:
        value = ", ".join(f"{x:.9g}" for x in b.albedo)
        refl = _Node("rgb", {"name": "reflectance", "value": value}, old.file, old.line)
    diffuse = _Node("bsdf", {"type": "diffuse"}, old.file, old.line, [refl])
    return _Node("bsdf", {"type": "twosided", **keep}, old.file, old.line, [diffuse])


def diffuse_twin(
    path: str | os.PathLike, out_dir: str | os.PathLike, *, params: dict[str, Any] | None = None
) -> Path:
    """Write a copy of a Mitsuba scene for Mitsuba itself that renders what icbtool renders.

    The scene's folder is copied into ``out_dir``; in the copy of the scene file and of every file
    it includes, each BSDF a shape uses that icbtool approximates becomes the two-sided diffuse
    BSDF icbtool renders for it (the same albedo after the approximation rule, or the same
    bitmap; a BSDF icbtool traces exactly, :mod:`icbtool.scene.bsdf`, stays), and every pixel filter
    becomes ``box`` (icbtool's pixel footprint). Everything else (shapes, transforms, emitters,
    the sensor, ``$`` parameters) is written as read. Used to verify icbtool against Mitsuba
    (``benchmarks.mitsuba_xml_compare``).

    Args:
        path: the scene file.
        out_dir: an existing folder; the copy is ``out_dir / <scene folder name>``.
        params: ``$`` parameters, as for :func:`read_mitsuba`.

    Returns:
        The copied scene file.

    Raises:
        SceneError: as :func:`read_mitsuba`; an included file outside the scene's folder.
    """
    import shutil

    p = check_file(path, MITSUBA_SUFFIXES).resolve()
    reader = _Reader(p, dict(params or {}), True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loader has said it all already
        reader.read(_parse_xml(p))
    dst = Path(out_dir) / p.parent.name
    shutil.copytree(p.parent, dst, dirs_exist_ok=True)

    def rewrite(node: _Node) -> _Node:
        if node.tag == "bsdf" and node.where in reader.rendered:
            if reader.rendered[node.where].declared is not None:
                return node  # traced exactly (icbtool.scene.bsdf): Mitsuba's own BSDF
            return _diffuse_node(node, reader.rendered[node.where])
        if node.tag == "rfilter":
            return _Node("rfilter", {"type": "box"}, node.file, node.line)
        node.children = [rewrite(c) for c in node.children]
        return node

    for f in dict.fromkeys(reader.files):
        try:
            rel = f.resolve().relative_to(p.parent)
        except ValueError:
            raise SceneError(f"{f}: included from outside the scene folder {p.parent}") from None
        (dst / rel).write_text(_to_xml(rewrite(_parse_xml(f))))
    return dst / p.name


def read_mitsuba(
    path: str | os.PathLike,
    *,
    params: dict[str, Any] | None = None,
    textures: bool = True,
    progress: bool = False,
) -> MitsubaScene:
    """Read a Mitsuba 3 scene file (see the module docstring for what is read and how).

    Args:
        path: the .xml file.
        params: values of the file's ``$`` parameters (override its ``<default>`` s).
        textures: decode bitmap textures (False: base colours only, faster).
        progress: show a tqdm bar (stderr) over the shapes as they load.

    Returns:
        The :class:`MitsubaScene` (the Scene, with the shape count and what was skipped).

    Raises:
        FileNotFoundError: the file, an included file or a mesh file is missing.
        SceneError: invalid XML, a bad value (message ``file:line: ...``), no shape.
    """
    p = check_file(path, MITSUBA_SUFFIXES)
    reader = _Reader(p, dict(params or {}), textures)
    reader.progress = bool(progress)
    reader.read(_parse_xml(p))
    t0 = time.perf_counter()
    scene = reader.build(p.stem)
    log.info("%s: shapes merged and checked in %.1f s", p, time.perf_counter() - t0)
    log.info(
        "%s: %d shapes, %d triangles, %d materials, %d lights, sky %s, camera %s, max_depth %s",
        p,
        reader.n_shapes,
        scene.n_triangles,
        len(scene.materials),
        len(scene.lights),
        "yes" if scene.sky is not None else "no",
        "yes" if scene.default_camera is not None else "no",
        scene.max_depth,
    )
    return MitsubaScene(
        scene, reader.n_shapes, reader.skipped, dict(reader.params), reader.dropped_lights
    )


def load_mitsuba(
    path: str | os.PathLike, *, default_light: bool = False, **overrides: Any
) -> Scene:
    """A Mitsuba scene file as a Scene (emissive faces not yet promoted; see
    :func:`icbtool.scene.load`, which does that).

    Args:
        path: the .xml file.
        default_light: when every emitter of the file is one icbtool cannot render (``sunsky``,
            ``sun``, ``sky``...), return the unlit scene with a warning naming what the default
            sun and sky replace (:func:`icbtool.scene.load` then adds them with
            :func:`icbtool.scene.with_default_light`) instead of failing.
        **overrides: ``params`` (dict of ``$`` parameters), ``textures`` (bool), ``progress``
            (bool: a bar over the shapes), ``name`` and the Scene fields ``lights``, ``sky``,
            ``paths``, ``default_camera``, ``max_depth``.

    Raises:
        TypeError: an unknown override.
        FileNotFoundError, SceneError: as :func:`read_mitsuba`.
        SceneError: the file's only emitters cannot be rendered and ``default_light`` is False
            (the message names each emitter and its line).
    """
    allowed = {"params", "textures", "name", "lights", "sky", "paths", "default_camera"}
    allowed.update(("max_depth", "progress"))
    if "up_axis" in overrides:
        raise SceneError(
            f"{path}: up_axis applies to mesh files; a Mitsuba scene keeps its world axes (its "
            "sensor says which way is up)"
        )
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise TypeError(
            f"load({Path(path).name}): unknown override(s) {unknown}; allowed: {sorted(allowed)}"
        )
    ms = read_mitsuba(
        path,
        params=overrides.pop("params", None),
        textures=overrides.pop("textures", True),
        progress=overrides.pop("progress", False),
    )
    scene = dataclasses.replace(ms.scene, **overrides) if overrides else ms.scene
    lit = bool(scene.lights) or scene.sky is not None or len(scene.emissive_faces) > 0
    if ms.dropped_lights and not lit:
        dropped = ", ".join(ms.dropped_lights)
        if not default_light:
            raise SceneError(
                f"{path}: the scene's only light(s) cannot be rendered by icbtool: {dropped}; "
                "pass default_light=True (command line: --default-light) to render it with "
                "icbtool's default sun and sky instead"
            )
        warnings.warn(
            f"{path}: {dropped} replaced by icbtool's default sun and sky (default_light)",
            SceneRepairWarning,
            stacklevel=2,
        )
    return scene


__all__ = [
    "METAL_F0",
    "MITSUBA_SUFFIXES",
    "MitsubaScene",
    "load_mitsuba",
    "mitsuba_look_at",
    "read_mitsuba",
    "read_serialized",
    "diffuse_twin",
]
