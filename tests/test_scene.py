"""Scenes: procedural known answers, file loaders, the description format, bad inputs, Sponza."""

from __future__ import annotations

import math
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from icbtool.imageio import srgb_decode
from icbtool.scene import (
    SceneError,
    SceneRepairWarning,
    cornell_box,
    load,
    read_description,
    white_furnace,
)

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- procedural
def test_cornell_box_known_properties():
    s = cornell_box()
    lo, hi = s.bounds
    np.testing.assert_allclose(lo, [-1.0, 0.0, -1.0], atol=0.01)
    np.testing.assert_allclose(hi, [1.0, 1.974, 1.0], atol=0.01)
    (light,) = s.lights_of("area")
    np.testing.assert_allclose(light.normal, [0, -1, 0], atol=1e-9)
    em = s.emissive_faces
    assert len(em) == 2
    assert np.all(s.face_normals[em] @ np.array([0, 1.0, 0]) < -0.999)
    # the room's walls face the inside of the box
    inside = np.array([0.0, 1.0, 0.0])
    names = [m.name for m in s.materials]
    walls = np.isin(s.face_material, [names.index("red"), names.index("green")])
    centroids = s.vertices[s.faces[walls]].mean(1)
    assert np.all(np.einsum("ij,ij->i", s.face_normals[walls], inside - centroids) > 0)
    assert {"train", "test"} <= set(s.paths)


def test_white_furnace_faces_inward():
    s = white_furnace()
    c = s.vertices[s.faces].mean(1)
    assert np.all(np.einsum("ij,ij->i", s.face_normals, -c) > 0)
    assert np.all(np.einsum("ij,ij->i", s.normals, -s.vertices) > 0)


# --------------------------------------------------------------------------- loaders
def _png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(rgb.astype(np.uint8)).save(path)


def _texture_rgb() -> np.ndarray:
    """A 4 x 6 image: top-left texel red, bottom-left green, the rest grey."""
    t = np.full((4, 6, 3), 128, np.uint8)
    t[0, 0] = (255, 0, 0)
    t[-1, 0] = (0, 255, 0)
    return t


def _write_obj(tmp: Path, name="m.obj", kd="0.5 0.25 1.0", ke=None, texture="tex.png") -> Path:
    _png(tmp / "tex.png", _texture_rgb())
    mtl = f"newmtl mat\nKd {kd}\n" + (f"Ke {ke}\n" if ke else "")
    if texture:
        mtl += f"map_Kd {texture}\n"
    mtl += "newmtl plain\nKd 0.2 0.3 0.4\n"
    (tmp / "m.mtl").write_text(mtl)
    obj = textwrap.dedent(
        """\
        mtllib m.mtl
        v 0 0 0
        v 1 0 0
        v 1 1 0
        v 0 1 0
        v 0 0 1
        vt 0 0
        vt 1 0
        vt 1 1
        vt 0 1
        usemtl mat
        f 1/1 2/2 3/3 4/4
        usemtl plain
        f 1/1 5/2 2/3
        """
    )
    (tmp / name).write_text(obj)
    return tmp / name


def test_obj_mtl_texture_round_trip(tmp_path):
    s = load(_write_obj(tmp_path, ke="2 1 0"))
    assert s.n_triangles == 3
    names = [m.name for m in s.materials]
    assert sorted(names) == ["mat", "plain"]  # order: trimesh's grouping
    im = names.index("mat")
    mat, plain = s.materials[im], s.materials[names.index("plain")]
    np.testing.assert_allclose(mat.albedo, [0.5, 0.25, 1.0])
    np.testing.assert_allclose(mat.emission, [2, 1, 0])
    np.testing.assert_allclose(plain.albedo, [0.2, 0.3, 0.4])
    assert mat.is_textured and not plain.is_textured
    # decoded sRGB -> linear; texel (0, 0) is the top-left of the file
    np.testing.assert_allclose(mat.texture[0, 0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(mat.texture[-1, 0], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(mat.texture[1, 1], srgb_decode(np.full(3, 128 / 255)), atol=1e-6)
    assert mat.texture.dtype == np.float32
    # uvs kept per vertex as written (OBJ: v = 0 is the bottom of the image)
    corners = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    for p, uv in zip(corners, [(0, 0), (1, 0), (1, 1), (0, 1)]):
        i = np.flatnonzero(np.all(s.vertices == p, axis=1))
        assert any(np.allclose(s.uvs[j], uv) for j in i)
    # no normals in the file: area-weighted unit normals (the quad faces +z)
    quad_v = np.unique(s.faces[s.face_material == im])
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1, atol=1e-6)
    assert np.all(s.normals[quad_v] @ np.array([0, 0, 1.0]) > 0.5)
    assert s.source == str(tmp_path / "m.obj")


def test_obj_overrides_scale_up_axis_flip_v(tmp_path):
    p = _write_obj(tmp_path)
    s = load(p, scale=2.0, up_axis="z", translation=(1, 2, 3), flip_v=True, name="x")
    assert s.name == "x"
    base = load(p)
    # z-up -> y-up: (x, y, z) -> (x, z, -y), then scale, then translate
    expect = 2.0 * base.vertices[:, [0, 2, 1]] * [1, 1, -1] + [1, 2, 3]
    np.testing.assert_allclose(s.vertices, expect, atol=1e-6)
    np.testing.assert_allclose(s.uvs[:, 1], 1 - base.uvs[:, 1], atol=1e-6)
    np.testing.assert_allclose(
        s.face_normals, base.face_normals[:, [0, 2, 1]] * [1, 1, -1], atol=1e-6
    )
    with pytest.raises(TypeError, match="bogus"):
        load(p, bogus=1)
    with pytest.raises(SceneError, match="up_axis"):
        load(p, up_axis="w")


def test_ply_round_trip(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    m.export(tmp_path / "s.ply")
    s = load(tmp_path / "s.ply")
    np.testing.assert_allclose(s.vertices, m.vertices, atol=1e-6)
    np.testing.assert_array_equal(s.faces, m.faces)
    assert len(s.materials) == 1 and s.uvs is None
    np.testing.assert_allclose(s.materials[0].albedo, 0.8)
    # computed normals of a sphere point outwards
    assert np.all(np.einsum("ij,ij->i", s.normals, s.vertices) / 2.0 > 0.98)


def test_glb_round_trip(tmp_path):
    import trimesh
    from PIL import Image

    m = trimesh.creation.box()
    uv = np.random.default_rng(0).random((len(m.vertices), 2))
    mat = trimesh.visual.material.PBRMaterial(
        baseColorFactor=[0.5, 0.25, 1.0, 1.0],
        emissiveFactor=[0.1, 0.2, 0.3],
        baseColorTexture=Image.fromarray(_texture_rgb()),
        metallicFactor=0.0,  # a dielectric: its base colour is the albedo (metals: approximated)
    )
    m.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    m.export(tmp_path / "b.glb")
    s = load(tmp_path / "b.glb")
    np.testing.assert_allclose(s.vertices, m.vertices, atol=1e-6)
    np.testing.assert_allclose(s.uvs, uv, atol=1e-6)
    (sm,) = s.materials
    np.testing.assert_allclose(sm.albedo, [0.5, 0.25, 1.0], atol=1 / 255)
    np.testing.assert_allclose(sm.emission, [0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(sm.texture[0, 0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(sm.texture[-1, 0], [0, 1, 0], atol=1e-6)


# --------------------------------------------------------------------------- bad inputs
def _tri_obj(tmp_path: Path, body: str, name="bad.obj") -> Path:
    p = tmp_path / name
    p.write_text(body)
    return p


TRI = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(
    "body, match",
    [
        (TRI + "f 1 2 7\n", "index 7 out of range"),
        (TRI + "f 1 2 -4\n", "index -4 out of range"),
        (TRI + "f 1 2 3\nf 1 2", "truncated"),
        ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n", "NaN or Inf"),
        ("v 0 0 0\nv 1 0 inf\nv 0 1 0\nf 1 2 3\n", "NaN or Inf"),
        ("# nothing here\n", "empty mesh"),
        (TRI, "empty mesh"),
        (TRI + "f 1 2 x\n", "not an integer"),
        ("v 0 0 0\nv 1e-9 0 0\nv 0 1e-9 0\nf 1 2 3\n", "absurd scale"),
        ("v 0 0 0\nv 1e8 0 0\nv 0 1e8 0\nf 1 2 3\n", "absurd scale"),
        (TRI + "f 1 2 2\n", "degenerate"),
    ],
)
def test_bad_obj_raises_naming_file(tmp_path, body, match):
    p = _tri_obj(tmp_path, body)
    with pytest.raises(SceneError, match=match) as e:
        load(p)
    assert str(p) in str(e.value)


def test_binary_junk_obj(tmp_path):
    p = tmp_path / "junk.obj"
    p.write_bytes(b"\x00\x01\x02garbage" * 10)
    with pytest.raises(SceneError, match="NUL bytes"):
        load(p)


def test_missing_empty_unknown_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        load(tmp_path / "nope.obj")
    (tmp_path / "x.stl").write_text("solid x\n")
    with pytest.raises(SceneError, match="unknown scene file type '.stl'"):
        load(tmp_path / "x.stl")
    (tmp_path / "e.obj").write_text("")
    with pytest.raises(SceneError, match="empty"):
        load(tmp_path / "e.obj")


def test_degenerate_faces_dropped_with_warning(tmp_path):
    body = TRI + "v 2 0 0\nf 1 2 3\nf 1 2 4\nf 3 3 1\n"  # face 2 is collinear, face 3 repeats
    with pytest.warns(SceneRepairWarning, match="dropped 2 degenerate"):
        s = load(_tri_obj(tmp_path, body))
    assert s.n_triangles == 1


def test_nan_normals_recomputed_with_warning(tmp_path):
    body = TRI + "vn 0 0 0\nvn 0 0 1\nvn nan 0 1\nf 1//1 2//2 3//3\n"
    with pytest.warns(SceneRepairWarning, match="2 vertex normal"):
        s = load(_tri_obj(tmp_path, body))
    np.testing.assert_allclose(s.normals, np.tile([0, 0, 1.0], (3, 1)), atol=1e-6)


def test_missing_texture_uses_base_colour(tmp_path):
    p = _write_obj(tmp_path, texture="missing.png")
    with pytest.warns(SceneRepairWarning, match="missing.png not found"):
        s = load(p)
    mat = next(m for m in s.materials if m.name == "mat")
    assert not mat.is_textured
    np.testing.assert_allclose(mat.albedo, [0.5, 0.25, 1.0])


def test_corrupt_texture_and_bright_albedo_repaired(tmp_path):
    p = _write_obj(tmp_path, kd="1.5 0.5 0.5")
    (tmp_path / "tex.png").write_bytes(b"not a png at all")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        s = load(p)
    msgs = " | ".join(str(x.message) for x in w if issubclass(x.category, SceneRepairWarning))
    assert "unreadable" in msgs and "clipped" in msgs
    mat = next(m for m in s.materials if m.name == "mat")
    np.testing.assert_allclose(mat.albedo, [1.0, 0.5, 0.5])


def test_truncated_binary_files(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    for ext, kw in ((".glb", {}), (".ply", {}), (".ply", {"encoding": "ascii"})):
        full = tmp_path / f"full{ext}"
        m.export(full, **kw)
        data = full.read_bytes()
        cut = tmp_path / f"cut{ext}"
        cut.write_bytes(data[: int(len(data) * 0.9)])
        with pytest.raises(SceneError, match="truncated|corrupt") as e:
            load(cut)
        assert str(cut) in str(e.value)
    (tmp_path / "fake.glb").write_bytes(b"hello world, not a glb")
    with pytest.raises(SceneError, match="magic"):
        load(tmp_path / "fake.glb")


# --------------------------------------------------------------------------- descriptions
def _desc(tmp_path: Path, text: str, name="scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def test_description_full(tmp_path):
    _write_obj(tmp_path)
    p = _desc(
        tmp_path,
        """
        [scene]
        name = "demo"
        mesh = "m.obj"
        scale = 2.0
        [camera]
        fov_y_deg = 50.0
        height = 24
        width = 32
        [[lights]]
        type = "directional"
        direction = [0.0, -1.0, 0.0]
        irradiance = [3.0, 3.0, 3.0]
        [[lights]]
        type = "area"
        name = "panel"
        corner = [0.0, 1.9, 0.0]
        edge_u = [0.5, 0.0, 0.0]
        edge_v = [0.0, 0.0, 0.5]
        radiance = [5.0, 5.0, 5.0]
        [[lights]]
        type = "spot"
        position = [0.0, 2.0, 0.0]
        direction = [0.0, -1.0, 0.0]
        intensity = [1.0, 1.0, 1.0]
        [sky]
        type = "gradient"
        zenith = [0.1, 0.2, 0.4]
        horizon = [0.3, 0.3, 0.3]
        [default_camera]
        eye = [0.0, 0.5, 5.0]
        target = [0.0, 0.5, 0.0]
        [paths.a]
        type = "orbit"
        center = [0.0, 0.0, 0.0]
        radius = 4.0
        height = 1.0
        n = 12
        [paths.b]
        type = "flythrough"
        waypoints = [[0.0, 1.0, 5.0], [1.0, 1.0, 4.0], [2.0, 1.0, 5.0]]
        n = 20
        image_width = 16
        """,
    )
    s = load(p)
    assert s.name == "demo" and s.source == str(p.resolve())
    assert [lt.kind for lt in s.lights] == ["directional", "area", "spot"]
    assert s.n_triangles == 3 + 2  # the area light's quad joins the mesh
    assert s.materials[-1].name == "emitter:panel" and s.materials[-1].is_emissive
    assert s.sky.kind == "gradient"
    np.testing.assert_allclose(s.bounds[1], [2.0, 2.0, 2.0])  # scaled mesh, light at y 1.9
    assert s.default_camera.height == 24 and s.default_camera.fov_y_deg == pytest.approx(50)
    assert len(s.paths["a"]) == 12 and s.paths["b"].intrinsics.width == 16
    s2 = load(p, height=12, width=12, with_paths=False, scale=1.0)
    assert s2.default_camera.width == 12 and not s2.paths
    np.testing.assert_allclose(s2.bounds[1], [1.0, 1.9, 1.0])
    assert s.default_camera.aperture_radius == 0 and s.default_camera.is_pinhole


def test_description_thin_lens_focuses_on_the_target_by_default(tmp_path):
    _write_obj(tmp_path)
    cams = []
    for lens in ("aperture_radius = 0.05", "aperture_radius = 0.05\nfocus_distance = 2.5"):
        text = '[scene]\nmesh = "m.obj"\n[default_camera]\neye = [0, 3, 4]\ntarget = [0, 0, 0]\n'
        cams.append(load(_desc(tmp_path, text + lens + "\n")).default_camera)
    assert cams[0].aperture_radius == 0.05 and cams[0].focus_distance == pytest.approx(5.0)
    assert cams[1].focus_distance == 2.5 and cams[1].pinhole().is_pinhole


@pytest.mark.parametrize(
    "text, match",
    [
        ('[scene]\nmesh = "m.obj"\nscael = 1.0\n', r"unknown key\(s\) \['scael'\] in \[scene\]"),
        ('[scene]\nmesh = "m.obj"\n[extra]\na = 1\n', r"\['extra'\] in \[top level\]"),
        ('[scene]\nmesh = "m.obj"\n[camera]\nfov = 3\n', r"\['fov'\] in \[camera\]"),
        (
            '[scene]\nmesh = "m.obj"\n[[lights]]\ntype = "directional"\ndirection = [0, -1, 0]\n'
            "irradiance = [1, 1, 1]\ncolour = 1\n",
            r"\['colour'\] in \[lights 0",
        ),
        ('[scene]\nmesh = "m.obj"\n[[lights]]\ntype = "laser"\n', "unknown type 'laser'"),
        ('[scene]\nmesh = "m.obj"\n[paths.x]\ntype = "orbit"\nradius = 1\n', "missing"),
        ('[scene]\nmesh = "m.obj"\n[paths.x]\ntype = "teleport"\n', "needs a 'type'"),
        ("[scene]\nscale = 1.0\n", r"no mesh: give \[scene\] mesh"),
        ('[scene]\nmesh = "m.obj"\n[sky]\nzenith = [-1, 0, 0]\n', r"\[sky\]"),
        (
            '[scene]\nmesh = "m.obj"\n[default_camera]\neye = [0, 0, 5]\ntarget = [0, 0, 0]\n'
            "aperture_radius = -0.1\n",
            r"\[default_camera\]: Camera aperture_radius must be >= 0",
        ),
        ("[scene\nmesh = 1\n", "not valid TOML"),
        ('[scene]\nmesh = "${ICBTOOL_TEST_UNSET_VAR}/m.obj"\n', "ICBTOOL_TEST_UNSET_VAR"),
    ],
)
def test_description_errors_name_key_and_file(tmp_path, monkeypatch, text, match):
    monkeypatch.delenv("ICBTOOL_TEST_UNSET_VAR", raising=False)
    _write_obj(tmp_path)
    p = _desc(tmp_path, text)
    with pytest.raises(SceneError, match=match) as e:
        load(p)
    assert str(p.resolve()) in str(e.value)


def test_description_env_expansion(tmp_path, monkeypatch):
    mesh_dir = tmp_path / "meshes"
    mesh_dir.mkdir()
    _write_obj(mesh_dir)
    sub = tmp_path / "descs"
    sub.mkdir()
    p = _desc(sub, '[scene]\nmesh = "${ICBTOOL_TEST_MESHES:-../meshes}/m.obj"\n')
    monkeypatch.delenv("ICBTOOL_TEST_MESHES", raising=False)
    assert read_description(p).mesh == (mesh_dir / "m.obj").resolve()  # default, relative
    other = tmp_path / "elsewhere"
    other.mkdir()
    _write_obj(other)
    monkeypatch.setenv("ICBTOOL_TEST_MESHES", str(other))
    assert read_description(p).mesh == (other / "m.obj").resolve()
    assert load(p).n_triangles == 3
    monkeypatch.setenv("ICBTOOL_TEST_MESHES", str(tmp_path / "void"))
    with pytest.raises(FileNotFoundError, match="void"):
        load(p)


def test_description_random_walk_path(tmp_path):
    import trimesh

    # a closed box room 8 x 3 x 8 with inward faces
    room = trimesh.creation.box(extents=(8, 3, 8))
    room.vertices += [0, 1.5, 0]
    room.faces = room.faces[:, ::-1]
    room.export(tmp_path / "room.ply")
    p = _desc(
        tmp_path,
        """
        [scene]
        mesh = "room.ply"
        [camera]
        height = 8
        width = 8
        [paths.w]
        type = "random_walk"
        n = 30
        seed = 1
        height_range = [1.5, 1.7]
        """,
    )
    s = load(p)
    pos = s.paths["w"].world_from_cam[:, :3, 3]
    assert len(pos) == 30 and np.all(np.abs(pos[:, [0, 2]]) < 4 - 0.4)
    assert np.all((pos[:, 1] > 1.5 - 1e-6) & (pos[:, 1] < 1.7 + 1e-6))


def test_shipped_descriptions_parse():
    for p in sorted((REPO / "data" / "scenes").glob("*.toml")):
        d = read_description(p)
        assert d.mesh.name and d.paths


# --------------------------------------------------------------------------- Sponza
@pytest.mark.sponza
def test_sponza_obj(sponza_path):
    s = load(sponza_path, textures=False)
    assert s.n_triangles == 66_445
    assert len(s.materials) == 19


@pytest.mark.sponza
def test_sponza_description(sponza_path, monkeypatch):
    monkeypatch.setenv("ICBTOOL_SPONZA", str(sponza_path.parent))
    s = load(REPO / "data" / "scenes" / "sponza.toml")
    assert s.n_triangles == 66_445
    assert len(s.materials) == 19 and sum(m.is_textured for m in s.materials) == 17
    np.testing.assert_allclose(s.bounds, [[-17.40, -0.91, -7.80], [17.42, 15.65, 7.80]], atol=0.01)
    assert s.lights_of("directional") and s.sky is not None and s.default_camera is not None
    train, test = s.paths["train"], s.paths["test"]
    assert len(train) >= 120 and len(test) >= 120
    for p in (train, test):
        steps = np.linalg.norm(np.diff(p.world_from_cam[:, :3, 3], axis=0), axis=1)
        np.testing.assert_allclose(steps / np.diff(p.times), 1.4, rtol=0.03)
    pt, pv = train.world_from_cam[:, :3, 3], test.world_from_cam[:, :3, 3]
    # different routes: no test camera within 0.5 m of a train camera
    dmin = np.min(np.linalg.norm(pt[:, None] - pv[None], axis=-1))
    assert dmin > 0.5
    # the relief's inscription is right way up: its texture's top row maps to the top of the
    # geometry (flip_v); i.e. v grows with height on that material
    mi = [m.name for m in s.materials].index("sp_02_reljef")
    vids = np.unique(s.faces[s.face_material == mi])
    corr = np.corrcoef(s.vertices[vids, 1], s.uvs[vids, 1])[0, 1]
    assert corr > 0.9
    # the sun reaches part of the atrium floor through the roof opening
    from icbtool.scene.raycast import EmbreeScene

    es = EmbreeScene.from_scene(s)
    xs, zs = np.meshgrid(np.linspace(-10, 10, 41), np.linspace(-2, 2, 9))
    pts = np.stack([xs.ravel(), np.full(xs.size, 0.2), zs.ravel()], 1)
    sun = s.lights_of("directional")[0]
    lit = ~es.occluded(pts, np.tile(-sun.direction, (len(pts), 1)), np.inf)
    assert 0.1 < lit.mean() < 0.9
    assert math.isclose(float(np.linalg.norm(sun.direction)), 1.0)
