"""Scene loading that is faithful or fails loudly: OBJ/MTL (icbtool.scene.obj), glTF materials and
KHR_lights_punctual (icbtool.scene.gltf), up axis, Camera.frame, default light, CLI on bare meshes.

Every expected count, bound and area below is counted by hand from the file written in the test
(or from tests/data/scenes/cornell_style.obj, whose header describes its geometry).
"""

from __future__ import annotations

import base64
import io
import json
import math
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

import icbtool.scene as sc
from icbtool.camera import Camera
from icbtool.scene import (
    MaterialApproximationWarning,
    SceneError,
    SceneRepairWarning,
    has_light,
    load,
    with_default_light,
)
from icbtool.scene.obj import parse_obj

DATA = Path(__file__).parent / "data" / "scenes"


def _write(tmp: Path, name: str, text: str) -> Path:
    p = tmp / name
    p.write_text(text)
    return p


def _load_quiet(p: Path, **kw):
    """Load, failing on any warning (a clean file must load without repairs)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return load(p, **kw)


def _messages(w) -> str:
    return " | ".join(str(x.message) for x in w)


# --------------------------------------------------------------------------- OBJ geometry
def test_cornell_style_fixture_known_counts():
    s = _load_quiet(DATA / "cornell_style.obj")
    # 11 quads (5 room faces, 5 box faces, the light), flat: 4 own vertices each
    assert s.n_triangles == 22 and len(s.vertices) == 44
    np.testing.assert_allclose(s.face_areas.sum(), 5 * 4 + 5 * 0.25 + 0.25, rtol=1e-6)
    np.testing.assert_allclose(s.bounds, [[-1, 0, -1], [1, 2, 1]], atol=1e-6)
    names = [m.name for m in s.materials]
    assert names == ["white", "red", "green", "box", "light"]  # first use; 'g' keeps usemtl
    assert np.bincount(s.face_material).tolist() == [6, 2, 2, 10, 2]
    light = s.materials[names.index("light")]
    np.testing.assert_allclose(light.emission, [17, 12, 4])
    np.testing.assert_allclose(s.materials[0].albedo, [0.725, 0.71, 0.68])
    assert len(s.emissive_faces) == 2
    # the box (relative indices reaching back 8 vertices) is closed but for its bottom:
    # outward normals on all 5 faces, area 5 * 0.25
    box = s.face_material == names.index("box")
    np.testing.assert_allclose(s.face_areas[box].sum(), 1.25, rtol=1e-6)
    n = s.face_normals[box]
    centre = s.vertices[s.faces[box]].mean(1) - [0.3, 0.25, 0.3]
    assert np.all(np.einsum("ij,ij->i", n, centre) > 0)
    # flat shading: every vertex normal equals its face normal
    np.testing.assert_allclose(s.normals[s.faces[:, 0]], s.face_normals, atol=1e-6)


def test_tabs_spaces_negative_indices_and_forms(tmp_path):
    text = (
        "v\t0 0 0\nv  1   0\t0\nv 1 1 0\nv\t\t0 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "vn 0 0 1\n"
        "f\t1/1/1  2/2/1\t3/3/1\n"  # v/vt/vn
        "f -4//-1 -2//-1 -1//-1\n"  # v//vn, relative
        "f 1/1 3/3 4/4\n"  # v/vt, no normal -> computed (flat)
        "f -4 -3 -1\n"  # v only
    )
    s = _load_quiet(_write(tmp_path, "forms.obj", text))
    assert s.n_triangles == 4
    # unique (v, vt, vn, smoothing) corners: face 1: 3; face 2: (1,-,1) (3,-,1) (4,-,1) -> 3;
    # face 3: 3 own flat corners; face 4: 3 own flat corners
    assert len(s.vertices) == 12
    np.testing.assert_allclose(s.face_areas, [0.5, 0.5, 0.5, 0.5], rtol=1e-6)
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1.0], (12, 1)), atol=1e-6)
    # vertex 3 (1, 1, 0) is used by faces 1 and 3 with uv (1, 1) and by face 2 without uv (0, 0)
    at = np.flatnonzero(np.all(s.vertices == [1, 1, 0], axis=1))
    assert sorted(map(tuple, np.round(s.uvs[at], 6).tolist())) == [(0, 0), (1, 1), (1, 1)]


def test_line_continuation_comments_and_ignored_statements(tmp_path):
    text = (
        "# comment line\n"
        "v 0 0 0 # trailing comment\n"
        "v 2 0 0\nv 2 2 0\nv 0 2 \\\n 0\n"
        "l 1 2\nl 2 3\np 1\ncstype bspline\ncurv 0 1 1 2\nfoo bar\n"
        "f 1 2 \\\n 3 4\n"
    )
    p = _write(tmp_path, "cont.obj", text)
    with pytest.warns(SceneRepairWarning) as w:
        s = load(p)
    msg = _messages(w)
    assert "2 line element(s) 'l'" in msg and "1 point element(s) 'p'" in msg
    assert "2 free-form curve/surface statement(s)" in msg and "1 unknown statement(s) 'foo'" in msg
    assert s.n_triangles == 2
    np.testing.assert_allclose(s.face_areas.sum(), 4.0)
    np.testing.assert_allclose(s.bounds, [[0, 0, 0], [2, 2, 0]])


def test_convex_ngon_is_a_fan(tmp_path):
    ang = np.arange(6) * np.pi / 3
    vs = "".join(f"v {math.cos(a):.9f} {math.sin(a):.9f} 0\n" for a in ang)
    s = _load_quiet(_write(tmp_path, "hex.obj", vs + "f 1 2 3 4 5 6\n"))
    assert s.n_triangles == 4 and len(s.vertices) == 6
    np.testing.assert_allclose(s.face_areas.sum(), 3 * math.sqrt(3) / 2, rtol=1e-6)
    assert np.all(s.face_normals[:, 2] > 0.999)


@pytest.mark.parametrize(
    "corners, area",
    [
        # dart (quad) whose reflex corner is the 4th: a fan from corner 0 would cover area 3
        ([(0, 0), (2, 1), (0, 2), (1, 1)], 1.0),
        # L-shape starting at a corner that cannot see the whole polygon
        ([(2, 1), (1, 1), (1, 2), (0, 2), (0, 0), (2, 0)], 3.0),
        # a U: two reflex corners
        ([(0, 0), (3, 0), (3, 2), (2, 2), (2, 1), (1, 1), (1, 2), (0, 2)], 5.0),
    ],
)
def test_non_convex_polygons_are_triangulated_correctly(tmp_path, corners, area):
    # tilted out of the xy plane (about x by 30 degrees) so the polygon plane is not an axis plane
    c, s_ = math.cos(math.radians(30)), math.sin(math.radians(30))
    pts = [(x, y * c, y * s_) for x, y in corners]
    text = "".join(f"v {x} {y} {z}\n" for x, y, z in pts)
    text += "f " + " ".join(str(i + 1) for i in range(len(pts))) + "\n"
    s = _load_quiet(_write(tmp_path, "poly.obj", text))
    assert s.n_triangles == len(corners) - 2
    np.testing.assert_allclose(s.face_areas.sum(), area, rtol=1e-6)
    normal = np.array([0, -s_, c])
    assert np.all(s.face_normals @ normal > 0.999)  # every triangle keeps the winding
    # each triangle's centroid lies inside the polygon (2D point-in-polygon in its plane)
    from matplotlib.path import Path as MplPath

    poly = MplPath(np.array(corners, float))
    cen = s.vertices[s.faces].mean(1)
    cen2d = np.column_stack([cen[:, 0], cen[:, 1] / c])
    assert poly.contains_points(cen2d).all()


def test_smoothing_groups_decide_computed_normals(tmp_path):
    cube_v = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1))
    faces = "f 1 2 4 3\nf 5 7 8 6\nf 1 5 6 2\nf 3 4 8 7\nf 1 3 7 5\nf 2 6 8 4\n"
    flat = _load_quiet(_write(tmp_path, "flat.obj", cube_v + "s off\n" + faces))
    smooth = _load_quiet(_write(tmp_path, "smooth.obj", cube_v + "s 1\n" + faces))
    # flat: 6 faces x 4 own corners; normals are the face normals (axis-aligned)
    assert len(flat.vertices) == 24
    assert np.allclose(np.abs(flat.normals).max(1), 1.0, atol=1e-6)
    # one smoothing group: corners shared (8 vertices), normals point along the diagonals
    assert len(smooth.vertices) == 8
    centred = smooth.vertices - 0.5
    expect = centred / np.linalg.norm(centred, axis=1, keepdims=True)
    np.testing.assert_allclose(smooth.normals, expect, atol=1e-6)
    # outward winding as written
    assert np.all(
        np.einsum("ij,ij->i", flat.face_normals, flat.vertices[flat.faces].mean(1) - 0.5) > 0
    )


# --------------------------------------------------------------------------- OBJ errors
@pytest.mark.parametrize(
    "body, line, match",
    [
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n",
            5,
            "index 9 out of range: the file has 3",
        ),
        ("v 0 0 0\nv 1 0 0\nf 1 2 -3\nv 0 1 0\n", 3, "index -3 out of range: 2 defined before"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", 4, "index 0"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2/1 3/1\n", 4, "texture index 1 out of range"),
        ("v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n", 2, "'zero' is not a number"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n", 5, "2 corner\\(s\\) \\(need >= 3\\)"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x3\n", 4, "'x3' .* is not an integer"),
        ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", 2, "vertex needs 3 coordinates"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/2/3/4 2 3\n", 4, "is not v, v/vt"),
    ],
)
def test_obj_errors_name_file_and_line(tmp_path, body, line, match):
    p = _write(tmp_path, "bad.obj", body)
    with pytest.raises(SceneError, match=match) as e:
        load(p)
    assert f"{p}:{line}:" in str(e.value)


def test_fast_and_line_readers_agree(tmp_path):
    """The vectorised reader and the line-by-line one give identical meshes."""
    files = [DATA / "cornell_style.obj"]
    text = "".join(
        f"v {i % 7} {i // 7} {(i * 3) % 5}\nvt {i / 50} 0.5\nvn 0 0 1\n" for i in range(50)
    )
    text += "usemtl a\ns 1\n" + "".join(
        f"f {i}/{i}/{i} {i + 1}/{i + 1}/{i + 1} {i + 8}/{i + 8}/{i + 8}\n" for i in range(1, 40)
    )
    text += "usemtl b\ns off\n" + "".join(
        f"f -{i} -{i + 1} -{i + 9} -{i + 8}\n" for i in range(1, 20)
    )
    files.append(_write(tmp_path, "mixed.obj", text))
    for f in files:
        a, b = parse_obj(f, fast=True), parse_obj(f, fast=False)
        for k in ("vertices", "faces", "normals", "uvs", "face_material", "face_line"):
            x, y = getattr(a, k), getattr(b, k)
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(x, y, err_msg=f"{f.name}: {k}")
        assert a.material_names == b.material_names


# --------------------------------------------------------------------------- MTL
def _quad_obj(tmp: Path, mtl: str, materials: list[str], mtllib: str = "m.mtl") -> Path:
    (tmp / "m.mtl").write_text(mtl)
    text = f"mtllib {mtllib}\n" if mtllib else ""
    for i, m in enumerate(materials):
        text += f"v {i} 0 0\nv {i + 1} 0 0\nv {i + 1} 1 0\nv {i} 1 0\nvt 0 0\nvt 1 0\nvt 1 1\n"
        text += f"vt 0 1\nusemtl {m}\nf -4/-4 -3/-3 -2/-2 -1/-1\n"
    return _write(tmp, "q.obj", text)


def test_mtl_keys_emission_texture_options(tmp_path):
    from PIL import Image

    Image.fromarray(np.full((2, 2, 3), 255, np.uint8)).save(tmp_path / "t.png")
    mtl = (
        "newmtl lamp\nKd 0.1 0.2 0.3\nKe 5 4 3\nKs 0 0 0\nNs 10\nNi 1.5\nd 1\nillum 2\n"
        "newmtl tex\nKd 1 1 1\nmap_Kd -s 1 1 1 -o 0 0 t.png\n"
        "newmtl grey\nKd 0.5\n"
    )
    s = _load_quiet(_quad_obj(tmp_path, mtl, ["lamp", "tex", "grey"]))
    m = {x.name: x for x in s.materials}
    np.testing.assert_allclose(m["lamp"].emission, [5, 4, 3])
    np.testing.assert_allclose(m["lamp"].albedo, [0.1, 0.2, 0.3])
    assert m["tex"].is_textured and m["tex"].texture_path == str(tmp_path / "t.png")
    np.testing.assert_allclose(m["grey"].albedo, [0.5, 0.5, 0.5])
    assert s.n_triangles == 6 and len(s.emissive_faces) == 2


@pytest.mark.parametrize(
    "block, albedo, words",
    [
        # a mirror with Kd = 0: Ks becomes the diffuse albedo (never black), scaled to a largest
        # channel of 0.8 (an approximation never reflects all the light)
        (
            "Kd 0 0 0\nKs 0.9 0.8 0.7\nillum 3",
            [0.8, 0.8 * 0.8 / 0.9, 0.7 * 0.8 / 0.9],
            ["mirror (illum 3)", "Ks", "scaled by 0.889"],
        ),
        # a mirror without any colour: 0.8 grey, said so
        ("Kd 0 0 0\nillum 5", [0.8, 0.8, 0.8], ["mirror (Fresnel) (illum 5)", "0.8 grey"]),
        # glass with a transmission filter: Kd + Ks + Tf
        (
            "Kd 0.01 0.01 0.01\nKs 0.3 0.3 0.3\nTf 0.1 0.2 0.3\nillum 7",
            [0.41, 0.51, 0.61],
            ["glass"],
        ),
        # glossy (Ks dominant) with illum 2
        ("Kd 0.2 0.1 0.1\nKs 0.5 0.5 0.5\nNs 200\nillum 2", [0.7, 0.6, 0.6], ["glossy", "Ns 200"]),
        # transparent: d < 1, and Tr > 0 without d
        ("Kd 0.3 0.3 0.3\nd 0.25", [0.8, 0.8, 0.8], ["transparent (opacity 0.25)"]),
        ("Kd 0.3 0.3 0.3\nTr 0.5", [0.8, 0.8, 0.8], ["transparent (opacity 0.5)"]),
    ],
)
def test_unrenderable_materials_become_nearest_diffuse_with_warning(tmp_path, block, albedo, words):
    p = _quad_obj(tmp_path, "newmtl odd\n" + block + "\n", ["odd"])
    with pytest.warns(MaterialApproximationWarning) as w:
        s = load(p)
    msg = _messages(w)
    assert "material 'odd'" in msg and "rendered as diffuse albedo" in msg
    for word in words:
        assert word in msg
    np.testing.assert_allclose(s.materials[0].albedo, albedo, atol=1e-9)


def test_missing_mtl_and_missing_material_warn(tmp_path):
    p = _quad_obj(tmp_path, "newmtl a\nKd 0.1 0.1 0.1\n", ["a", "nowhere"], mtllib="gone.mtl")
    with pytest.warns(SceneRepairWarning, match="gone.mtl not found"):
        s = load(p)
    assert [m.name for m in s.materials] == ["a", "nowhere"]
    np.testing.assert_allclose(s.materials[0].albedo, 0.8)
    p = _quad_obj(tmp_path, "newmtl a\nKd 0.1 0.1 0.1\n", ["a", "nowhere"])
    with pytest.warns(SceneRepairWarning, match=r"\['nowhere'\] not found"):
        s = load(p)
    np.testing.assert_allclose(s.materials[0].albedo, 0.1)


def test_several_mtllibs(tmp_path):
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "b.mtl").write_text("newmtl blue\nKd 0 0 1\n")
    text = "mtllib a.mtl b.mtl\n" + "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
    text += "usemtl blue\nf 1 2 3\nusemtl red\nf 1 3 4\n"
    s = _load_quiet(_write(tmp_path, "two.obj", text))
    np.testing.assert_allclose(s.materials[s.face_material[0]].albedo, [0, 0, 1])
    np.testing.assert_allclose(s.materials[s.face_material[1]].albedo, [1, 0, 0])


def test_mtl_bad_number_names_line(tmp_path):
    p = _quad_obj(tmp_path, "newmtl a\nKd 0.1 0.1 0.1\nNs lots\n", ["a"])
    with pytest.raises(SceneError, match=r"m.mtl:3: bad Ns"):
        load(p)


# --------------------------------------------------------------------------- up axis
def _floor_and_box(up: str) -> str:
    """A 4 x 4 floor with a 0.5 cube on it (14 triangles), written with the given up axis."""
    quads = [
        [(-2, 0, -2), (-2, 0, 2), (2, 0, 2), (2, 0, -2)],  # floor, normal +y
    ]
    lo, hi = -0.25, 0.25
    for axis in range(3):
        for side in (lo, hi):
            q = []
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = [0.0, 0.0, 0.0]
                others = [k for k in range(3) if k != axis]
                p[axis] = side
                p[others[0]] = (lo, hi)[a]
                p[others[1]] = (lo, hi)[b]
                p[1] += 0.25
                q.append(tuple(p))
            quads.append(q)
    text = ""
    for q in quads:
        for x, y, z in q:
            if up == "z":
                x, y, z = x, -z, y  # y-up (x, y, z) written z-up: (x, -z, y)
            text += f"v {x} {y} {z}\n"
        text += "f -4 -3 -2 -1\n"
    return text


def test_up_axis_guess_and_override(tmp_path):
    y = load(_write(tmp_path, "y.obj", _floor_and_box("y")))
    z = load(_write(tmp_path, "z.obj", _floor_and_box("z")))
    np.testing.assert_allclose(y.bounds, [[-2, 0, -2], [2, 0.5, 2]], atol=1e-6)
    np.testing.assert_allclose(z.bounds, y.bounds, atol=1e-6)  # guessed z, rotated to +y
    kept = load(tmp_path / "z.obj", up_axis="y")  # the user's word wins
    np.testing.assert_allclose(kept.bounds, [[-2, -2, 0], [2, 2, 0.5]], atol=1e-6)
    with pytest.raises(SceneError, match="up_axis"):
        load(tmp_path / "y.obj", up_axis="-z")


# --------------------------------------------------------------------------- glTF
_PNG_1x1 = None


def _png_bytes() -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def _gltf(tmp: Path, name: str, material: dict, extra: dict | None = None, glb: bool = False):
    """One triangle (0,0,0) (1,0,0) (0,1,0) with uvs and one material; ``extra`` merged into
    the document (nodes, extensions...)."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0, 0], [1, 0], [0, 1]], np.float32)
    idx = np.array([0, 1, 2], np.uint16)
    blob = pos.tobytes() + uv.tobytes() + idx.tobytes() + b"\0\0"
    png = _png_bytes()
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}
                ]
            }
        ],
        "materials": [material],
        "textures": [{"source": 0}],
        "images": [{"uri": "data:image/png;base64," + base64.b64encode(png).decode()}],
        "buffers": [
            {
                "byteLength": len(blob),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode(),
            }
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 24},
            {"buffer": 0, "byteOffset": 60, "byteLength": 6},
        ],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": 3,
                "type": "VEC3",
                "min": [0, 0, 0],
                "max": [1, 1, 0],
            },
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"},
        ],
    }
    for k, v in (extra or {}).items():
        if k == "nodes":
            doc["nodes"] = doc["nodes"] + v
            doc["scenes"][0]["nodes"] = list(range(len(doc["nodes"])))
            doc["scenes"][0]["nodes"] = [0] + [
                i
                for i in range(1, len(doc["nodes"]))
                if not any(i in n.get("children", []) for n in doc["nodes"])
            ]
        else:
            doc[k] = v
    p = tmp / name
    text = json.dumps(doc).encode()
    if glb:
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text
        p.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    else:
        p.write_bytes(text)
    return p


def test_gltf_emissive_texture_drops_emission_with_warning(tmp_path):
    mat = {
        "name": "visor",
        "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0.0},
        "emissiveFactor": [1, 1, 1],
        "emissiveTexture": {"index": 0},
    }
    p = _gltf(tmp_path, "e.gltf", mat)
    with pytest.warns(MaterialApproximationWarning) as w:
        s = load(p)
    msg = _messages(w)
    assert "material 'visor'" in msg and "emissiveTexture" in msg and "dropped" in msg
    assert not s.materials[0].is_emissive and len(s.emissive_faces) == 0
    # without the texture the emission is kept (times KHR_materials_emissive_strength)
    mat2 = {
        "name": "lamp",
        "pbrMetallicRoughness": {"metallicFactor": 0.0},
        "emissiveFactor": [1, 0.5, 0.25],
        "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4}},
    }
    s = _load_quiet(_gltf(tmp_path, "l.gltf", mat2))
    np.testing.assert_allclose(s.materials[0].emission, [4, 2, 1], atol=1e-6)


@pytest.mark.parametrize(
    "material, words",
    [
        (
            {
                "name": "gold",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 0.8, 0.3, 1],
                    "metallicFactor": 1.0,
                },
            },
            ["metal (metallicFactor 1)"],
        ),
        (
            {"name": "steel", "pbrMetallicRoughness": {"baseColorFactor": [1, 0.8, 0.3, 1]}},
            ["metal (metallicFactor 1)"],
        ),
        (
            {
                "name": "glass",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 0.8, 0.3, 1],
                    "metallicFactor": 0.0,
                },
                "extensions": {"KHR_materials_transmission": {"transmissionFactor": 0.9}},
            },
            ["transmission", "0.9"],
        ),
    ],
)
def test_gltf_metal_and_transmission_become_diffuse(tmp_path, material, words):
    with pytest.warns(MaterialApproximationWarning) as w:
        s = load(_gltf(tmp_path, "m.glb", material, glb=True))
    msg = _messages(w)
    assert f"material '{material['name']}'" in msg
    for word in words:
        assert word in msg
    # the base colour scaled to a largest channel of 0.8 (never an albedo >= 1)
    np.testing.assert_allclose(s.materials[0].albedo, [0.8, 0.64, 0.24], atol=1 / 255)
    assert s.materials[0].albedo.max() < 1


def test_gltf_dropped_normal_and_occlusion_maps_are_named(tmp_path):
    mat = {
        "name": "brick",
        "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.4, 0.3, 1], "metallicFactor": 0.0},
        "normalTexture": {"index": 0},
        "occlusionTexture": {"index": 0},
    }
    with pytest.warns(MaterialApproximationWarning) as w:
        s = load(_gltf(tmp_path, "n.gltf", mat))
    msg = _messages(w)
    assert "material 'brick'" in msg
    assert "normalTexture, occlusionTexture dropped" in msg
    np.testing.assert_allclose(s.materials[0].albedo, [0.5, 0.4, 0.3], atol=1 / 255)
    # without those maps: no warning at all
    mat = {"name": "plain", "pbrMetallicRoughness": {"metallicFactor": 0.0}}
    with warnings.catch_warnings():
        warnings.simplefilter("error", MaterialApproximationWarning)
        load(_gltf(tmp_path, "p.gltf", mat))


@pytest.mark.parametrize("glb", [False, True])
def test_gltf_punctual_lights_through_node_transforms(tmp_path, glb):
    s2 = math.sqrt(0.5)
    lights = {
        "KHR_lights_punctual": {
            "lights": [
                {"type": "point", "name": "bulb", "color": [1, 0.5, 0.25], "intensity": 683},
                {
                    "type": "spot",
                    "name": "spot",
                    "intensity": 1366,
                    "spot": {
                        "innerConeAngle": math.radians(10),
                        "outerConeAngle": math.radians(20),
                    },
                },
                {"type": "directional", "name": "sun", "intensity": 6830},
            ]
        }
    }
    nodes = [
        # parent: at (1, 2, 3), rotated +90 degrees about y (local -z -> world -x)
        {"translation": [1, 2, 3], "rotation": [0, s2, 0, s2], "children": [2, 3]},
        {"translation": [0, 0, 5], "extensions": {"KHR_lights_punctual": {"light": 0}}},
        {"translation": [0, 1, 0], "extensions": {"KHR_lights_punctual": {"light": 1}}},
        # a sun pointing straight down: rotated -90 degrees about x (local -z -> world -y)
        {"rotation": [-s2, 0, 0, s2], "extensions": {"KHR_lights_punctual": {"light": 2}}},
    ]
    p = _gltf(
        tmp_path,
        "lights.glb" if glb else "lights.gltf",
        {"name": "m", "pbrMetallicRoughness": {"metallicFactor": 0}},
        {"nodes": nodes, "extensions": lights, "extensionsUsed": ["KHR_lights_punctual"]},
        glb=glb,
    )
    s = _load_quiet(p)
    by = {lt.name: lt for lt in s.lights}
    assert sorted(by) == ["bulb", "spot", "sun"]
    # node 2: child of node 1 at local (0, 0, 5) -> rotated to (5, 0, 0) -> + (1, 2, 3)
    np.testing.assert_allclose(by["bulb"].position, [6, 2, 3], atol=1e-9)
    np.testing.assert_allclose(by["bulb"].intensity, [1, 0.5, 0.25], atol=1e-9)  # 683 cd -> 1 W/sr
    np.testing.assert_allclose(by["spot"].position, [1, 3, 3], atol=1e-9)
    np.testing.assert_allclose(by["spot"].direction, [-1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(by["spot"].intensity, [2, 2, 2], atol=1e-9)
    assert by["spot"].inner_deg == pytest.approx(10) and by["spot"].outer_deg == pytest.approx(20)
    np.testing.assert_allclose(by["sun"].direction, [0, -1, 0], atol=1e-9)
    np.testing.assert_allclose(by["sun"].irradiance, [10, 10, 10], atol=1e-9)  # 6830 lux
    assert has_light(s)
    # lights follow the loader's scale and translation like the geometry
    t = load(p, scale=2.0, translation=(0, 0, 1))
    tb = {lt.name: lt for lt in t.lights}
    np.testing.assert_allclose(tb["bulb"].position, [12, 4, 7], atol=1e-9)
    np.testing.assert_allclose(tb["spot"].direction, [-1, 0, 0], atol=1e-9)


# --------------------------------------------------------------------------- Camera.frame
@pytest.mark.parametrize("height, width", [(100, 200), (200, 100), (64, 64)])
def test_camera_frame_bounding_sphere_just_fits(height, width):
    bounds = np.array([[-1.0, 0.0, 2.0], [3.0, 2.0, 6.0]])
    centre, radius = bounds.mean(0), math.sqrt(4 * 4 + 2 * 2 + 4 * 4) / 2  # = 3
    view = np.array([1.0, -0.5, -2.0])
    cam = Camera.frame(
        bounds, up=(0, 1, 0), fov_y_deg=60, height=height, width=width, view_direction=view
    )
    np.testing.assert_allclose(cam.forward, view / np.linalg.norm(view), atol=1e-12)
    half = math.radians(min(cam.fov_y_deg, cam.fov_x_deg)) / 2
    dist = np.linalg.norm(cam.position - centre)
    assert dist == pytest.approx(radius / math.sin(half), rel=1e-12)
    # the tangent point of the sphere in the narrower image direction lands on the image edge
    narrow = cam.up if height <= width else cam.right
    tangent = cam.position + dist * math.cos(half) * (
        math.cos(half) * cam.forward + math.sin(half) * narrow
    )
    assert np.linalg.norm(tangent - centre) == pytest.approx(radius, rel=1e-9)
    uv, _ = cam.project(tangent)
    if height <= width:
        assert uv[1] == pytest.approx(0.0, abs=1e-6)  # top edge
    else:
        assert uv[0] == pytest.approx(width, abs=1e-6)  # right edge
    # every point of the sphere is inside the image
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))
    pts = centre + radius * d / np.linalg.norm(d, axis=1, keepdims=True)
    uv, depth = cam.project(pts)
    assert np.all(depth > 0)
    assert np.all((uv >= -1e-6) & (uv <= [width + 1e-6, height + 1e-6]))
    # up is up in the image
    assert cam.up @ np.array([0, 1.0, 0]) > 0.8


def test_camera_frame_sphere_and_errors():
    cam = Camera.frame((0, 0, 0, 1), fov_y_deg=90, height=10, width=10)
    assert np.linalg.norm(cam.position) == pytest.approx(1 / math.sin(math.radians(45)))
    with pytest.raises(ValueError, match="zero size"):
        Camera.frame([[1, 1, 1], [1, 1, 1]])
    with pytest.raises(ValueError, match=r"\(2, 3\) box or a \(4,\) sphere"):
        Camera.frame([1, 2, 3])
    with pytest.raises(ValueError, match="parallel"):
        Camera.frame([[0, 0, 0], [1, 1, 1]], view_direction=(0, -1, 0))


# --------------------------------------------------------------------------- default light, CLI
def test_with_default_light_only_for_unlit_scenes(tmp_path):
    lit = _load_quiet(DATA / "cornell_style.obj")  # emissive light quad
    assert has_light(lit) and with_default_light(lit) is lit
    bare = load(_write(tmp_path, "bare.obj", _floor_and_box("y")))
    assert not has_light(bare)
    h0 = bare.content_hash
    lit2 = with_default_light(bare)
    assert lit2 is not bare and not bare.lights and bare.sky is None  # original untouched
    assert bare.content_hash == h0
    (sun,) = lit2.lights
    assert sun.name == "default_sun" and sun.direction @ lit2.up < -0.5  # from above
    assert lit2.sky is not None and lit2.sky.kind == "gradient" and has_light(lit2)
    assert lit2.content_hash != h0
    np.testing.assert_array_equal(lit2.vertices, bare.vertices)


def test_select_cameras_keeps_aspect_for_render_and_trace():
    from icbtool.scene import cornell_box, select_cameras

    s = cornell_box()
    base = s.default_camera
    ((name, cam),) = select_cameras(s, "default", height=base.height // 2)
    assert name == "default" and (cam.height, cam.width) == (base.height // 2, base.width // 2)
    assert cam.fov_y_deg == pytest.approx(base.fov_y_deg)
    ((_, cam),) = select_cameras(s, "default", width=40, height=20)
    assert (cam.height, cam.width) == (20, 40)
    with pytest.raises(ValueError, match="--height"):
        select_cameras(s, "default", height=0)
    with pytest.raises(ValueError, match="no camera path"):
        select_cameras(s, "path:nope")


def _bare_mesh(tmp: Path) -> Path:
    return _write(tmp, "bare.obj", _floor_and_box("y"))


@pytest.mark.gl
def test_cli_render_bare_mesh_is_not_black(tmp_path):
    from icbtool.cli import main
    from icbtool.imageio import read_exr

    out = tmp_path / "r"
    rc = main(
        [
            "render",
            str(_bare_mesh(tmp_path)),
            "--out",
            str(out),
            "--height",
            "32",
            "--buffers",
            "dl",
            "--default-light",
        ]
    )
    assert rc == 0
    dl = read_exr(out / "dl.exr")
    assert dl.shape[:2] == (32, 32)
    mask = read_exr(out / "mask.exr") > 0
    assert mask.shape == (32, 32) and mask.mean() > 0.1  # the framed mesh is in view
    assert np.median(dl[mask].max(-1)) > 0.05  # lit by the default sun


@pytest.mark.parametrize("command", ["trace", "render", "lpm"])
def test_cli_unlit_scene_needs_default_light(tmp_path, command, capsys):
    """Without --default-light, a scene with no light is an error naming the option (no
    silent substitution of a light the file does not have)."""
    from icbtool.cli import main

    rc = main([command, str(_bare_mesh(tmp_path)), "--out", str(tmp_path / "o")])
    assert rc != 0
    err = capsys.readouterr().err
    assert "bare.obj: the scene has no light" in err and "--default-light" in err


def test_cli_trace_bare_mesh_is_not_black(tmp_path):
    from icbtool.cli import main
    from icbtool.imageio import read_exr

    out = tmp_path / "t"
    rc = main(
        [
            "trace",
            str(_bare_mesh(tmp_path)),
            "--out",
            str(out),
            "--height",
            "24",
            "--spp",
            "2",
            "--threads",
            "1",
            "--default-light",
        ]
    )
    assert rc == 0
    full = read_exr(out / "full.exr")
    assert full.shape[:2] == (24, 24)
    assert (full.max(-1) > 0.01).mean() > 0.9
    gi = read_exr(out / "gi.exr")
    assert gi.max() > 0  # the default sky lights the scene through the GI


@pytest.mark.parametrize("file_lights", [None, True, False])
def test_description_keeps_or_drops_the_files_punctual_lights(tmp_path, file_lights):
    lights = {"KHR_lights_punctual": {"lights": [{"type": "point", "name": "bulb"}]}}
    nodes = [{"translation": [0, 3, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}}]
    _gltf(
        tmp_path,
        "lit.gltf",
        {"name": "m", "pbrMetallicRoughness": {"metallicFactor": 0}},
        {"nodes": nodes, "extensions": lights, "extensionsUsed": ["KHR_lights_punctual"]},
    )
    flag = "" if file_lights is None else f"file_lights = {str(file_lights).lower()}\n"
    (tmp_path / "lit.toml").write_text(
        f'[scene]\nmesh = "lit.gltf"\n{flag}\n'
        '[[lights]]\ntype = "directional"\nname = "sun"\ndirection = [0, -1, 0]\n'
        "irradiance = [1, 1, 1]\n"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = sc.load(tmp_path / "lit.toml")
    names = sorted(lt.name for lt in s.lights)
    assert names == (["sun"] if file_lights is False else ["bulb", "sun"])
    # an explicit lights override replaces every light, the file's included
    s2 = sc.read_description(tmp_path / "lit.toml").build(lights=[])
    assert s2.lights == ()


def test_description_file_lights_must_be_boolean(tmp_path):
    (tmp_path / "d.toml").write_text('[scene]\nmesh = "x.obj"\nfile_lights = "yes"\n')
    with pytest.raises(
        sc.SceneError, match=r"d\.toml: \[scene\] file_lights must be true or false"
    ):
        sc.read_description(tmp_path / "d.toml")
