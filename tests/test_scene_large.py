"""Loading and packing large scenes: the memory-lean paths give exactly the arrays (and images)
of the straightforward ones, and loading shows its progress."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import icbtool.scene.bsdf as sb
import icbtool.scene.mitsuba as mitsuba
import icbtool.scene.types as types
from icbtool.scene import Material, SceneBuilder, Sky, load
from icbtool.scene.load import decode_texture
from icbtool.scene.types import fill_vertex_normals, vertex_normals

FIXTURE = Path(__file__).parent / "data" / "scenes" / "mitsuba" / "fixture.xml"


def _mesh(seed: int = 0, n_vertices: int = 60, n_faces: int = 150):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n_vertices, 3)).astype(np.float32)
    f = rng.integers(0, n_vertices - 3, size=(n_faces, 3))  # the last 3 vertices: unused
    return v, f


def _add_at_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The reference: np.add.at over the corners, first corners, then second, then third."""
    tri = v[f].astype(np.float64)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros((len(v), 3))
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(ln > 1e-30, vn / np.maximum(ln, 1e-300), np.array([0.0, 1.0, 0.0]))
    return vn.astype(np.float32)


def test_vertex_normals_equal_the_add_at_sums_bit_for_bit():
    v, f = _mesh()
    got = vertex_normals(v, f)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, _add_at_normals(v, f))
    np.testing.assert_array_equal(got[-3:], np.tile([0, 1, 0], (3, 1)))  # unused: +up


def test_fill_vertex_normals_equals_the_whole_mesh_values():
    v, f = _mesh(1)
    whole = vertex_normals(v, f)
    missing = np.zeros(len(v), bool)
    missing[[0, 5, 17, len(v) - 1]] = True  # the last vertex is used by no face
    n = np.full((len(v), 3), 7.0, np.float32)
    fill_vertex_normals(v, f, n, missing)
    np.testing.assert_array_equal(n[missing], whole[missing])
    assert np.all(n[~missing] == 7.0)  # the file's normals stay


def test_face_cross_in_chunks_equals_one_pass(monkeypatch):
    v, f = _mesh(2)
    tri = v[f].astype(np.float64)
    one_pass = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    monkeypatch.setattr(types, "FACE_CHUNK", 7)  # many chunks and a ragged last one
    np.testing.assert_array_equal(types._face_cross_chunked(v, f), one_pass)


def _unoptimised_merge(monkeypatch) -> None:
    """The Mitsuba reader as it was: float64 shapes merged, every vertex normal computed."""

    def keep_float64(self) -> None:
        pass

    def whole_mesh(vertices, faces, normals, missing):
        normals[missing] = vertex_normals(vertices, faces)[missing]

    monkeypatch.setattr(mitsuba._Part, "__post_init__", keep_float64)
    monkeypatch.setattr(mitsuba, "fill_vertex_normals", whole_mesh)
    monkeypatch.setattr(types, "FACE_CHUNK", 1 << 30)


def _scene_arrays(path: Path) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = load(path)
    out = {k: getattr(s, k) for k in ("vertices", "faces", "normals", "face_material", "uvs")}
    out["textures"] = [m.texture for m in s.materials]
    return out


def test_mitsuba_loader_gives_the_arrays_of_the_unoptimised_merge(monkeypatch, tmp_path):
    """The fixture (obj, ply, cube, sphere, disk, cylinder, a bitmap) and a serialized file
    whose shapes have no normals (all computed) or some."""
    from test_scene_mitsuba import _write_serialized

    v, f = _mesh(3, 40, 60)
    n = vertex_normals(v, f)
    n[::3] = np.nan  # a third of the file's normals unusable: recomputed from their faces
    _write_serialized(tmp_path / "m.serialized", [(v, f, None, None), (v, f, n, None)])
    xml = tmp_path / "s.xml"
    xml.write_text(
        '<scene version="3.0.0">'
        '<shape type="serialized"><string name="filename" value="m.serialized"/></shape>'
        '<shape type="serialized"><string name="filename" value="m.serialized"/>'
        '<integer name="shape_index" value="1"/>'
        '<transform name="to_world"><rotate y="1" angle="30"/><translate x="4"/></transform>'
        "</shape></scene>"
    )
    lean = [_scene_arrays(FIXTURE), _scene_arrays(xml)]
    _unoptimised_merge(monkeypatch)
    before = [_scene_arrays(FIXTURE), _scene_arrays(xml)]
    for a, b in zip(lean, before):
        for key in ("vertices", "faces", "normals", "face_material", "uvs"):
            assert (a[key] is None) == (b[key] is None), key
            if a[key] is not None:
                assert a[key].dtype == b[key].dtype, key
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        for ta, tb in zip(a["textures"], b["textures"]):
            assert (ta is None) == (tb is None)
            if ta is not None:
                np.testing.assert_array_equal(ta, tb)


def test_load_shows_a_bar_over_the_shapes(capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load(FIXTURE, progress=True)
        err_on = capsys.readouterr().err
        load(FIXTURE)
        err_off = capsys.readouterr().err
    n_shapes = FIXTURE.read_text().count("<shape ")
    assert f"load {FIXTURE.name}" in err_on and f"{n_shapes}/{n_shapes}" in err_on
    assert "shape" in err_on
    assert f"load {FIXTURE.name}" not in err_off


# --------------------------------------------------------------------------- tracer packing
def _reference_encode(texels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The one-pass encoding: a binary search of the whole concatenation."""
    lut = decode_texture(np.arange(256, dtype=np.uint8).reshape(1, 256))[0, :, 0]
    codes = np.clip(np.searchsorted(lut, texels), 0, 255)
    if np.array_equal(lut[codes], texels):
        return codes.astype(np.uint8), lut
    return np.zeros(0, np.uint8), texels


@pytest.mark.parametrize("kinds", [("8bit", "8bit"), ("8bit", "float"), ()])
def test_texels_encoded_in_pieces_equal_the_one_pass_encoding(monkeypatch, kinds):
    from icbtool.trace import texels

    rng = np.random.default_rng(4)
    texs = [
        decode_texture(rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)).reshape(-1)
        if k == "8bit"
        else rng.uniform(0, 1, 9 * 11 * 3).astype(np.float32)
        for k in kinds
    ]
    whole = np.concatenate(texs) if texs else np.zeros(1, np.float32)
    ref_codes, ref_lut = _reference_encode(whole)
    monkeypatch.setattr(texels, "TEXEL_PIECE", 10)  # pieces across texture boundaries
    codes, lut = texels.encode_texels(texs)
    assert codes.dtype == np.uint8 and lut.dtype == np.float32
    np.testing.assert_array_equal(codes, ref_codes)
    np.testing.assert_array_equal(lut, ref_lut)


def test_every_srgb_level_gets_its_own_code():
    from icbtool.trace import texels

    lut = decode_texture(np.arange(256, dtype=np.uint8).reshape(1, 256))[0, :, 0]
    codes, _ = texels.encode_texels([np.ascontiguousarray(lut[::-1])])
    np.testing.assert_array_equal(codes, np.arange(256)[::-1])


def test_texel_sets_code_each_texture_into_the_table_holding_it(monkeypatch):
    """sRGB-decoded and raw (code / 255) textures coded into their own table, across piece
    boundaries; a texture of neither gives the float texels."""
    from icbtool.trace import texels

    rng = np.random.default_rng(8)
    k = [rng.integers(0, 256, n, dtype=np.uint8) for n in (33, 20, 17)]
    srgb, lin = texels.srgb_levels(), texels.linear_levels()
    texs = [srgb[k[0]], lin[k[1]], srgb[k[2]]]
    monkeypatch.setattr(texels, "TEXEL_PIECE", 8)
    codes, lut, base = texels.encode_texel_sets(texs, [srgb, lin])
    np.testing.assert_array_equal(base, [0, 256, 0])
    np.testing.assert_array_equal(codes, np.concatenate(k))
    off = np.repeat(base, [33, 20, 17])
    np.testing.assert_array_equal(lut[off + codes], np.concatenate(texs))
    other = [*texs, rng.uniform(0, 1, 9).astype(np.float32)]
    codes, lut, base = texels.encode_texel_sets(other, [srgb, lin])
    assert codes.size == 0 and not base.any()
    np.testing.assert_array_equal(lut, np.concatenate(other))


def _textured_emitting_scene():
    rng = np.random.default_rng(5)
    b = SceneBuilder("packed")
    for i in range(2):
        tex = decode_texture(rng.integers(0, 256, (6, 5, 3), dtype=np.uint8))
        m = b.add_material(Material(f"t{i}", albedo=(1, 1, 1), texture=tex))
        b.add_quad((-1 + i, 0, -1), (1, 0, 0), (0, 0, 2), m)
    for i, e in enumerate(((3, 2, 1), (1, 1, 4))):
        m = b.material(f"e{i}", albedo=(0, 0, 0), emission=e)
        b.add_quad((-0.5 + i, 1.5, -0.5), (0, 0, 0.5), (0.5, 0, 0), m)
    b.sky = Sky((0.2, 0.2, 0.2))
    return b.build()


def test_packing_in_pieces_renders_the_same_image_bit_for_bit(monkeypatch):
    """The tracer's arrays packed with tiny texel pieces (many) and with the default (one)
    give identical images; the emitter pmf is the per-face power's."""
    from icbtool.camera import Camera
    from icbtool.scene.derived import forget
    from icbtool.trace import TraceConfig, render, texels, tracer

    scene = _textured_emitting_scene()
    cam = Camera.look_at((0, 3, 2), (0, 0, 0), (0, 1, 0), fov_y_deg=60, height=10, width=12)
    cfg = TraceConfig(spp=2, max_depth=3, seed=3)
    one = render(scene, cam, cfg)
    sd = tracer._SceneData.of(scene)
    lum = np.array([0.2126, 0.7152, 0.0722])
    power = (
        scene.face_areas
        * np.array([m.emission @ lum for m in scene.materials])[scene.face_material]
    )
    np.testing.assert_allclose(sd.face_light_pmf, power / power.sum(), rtol=1e-12)
    forget(scene)
    monkeypatch.setattr(texels, "TEXEL_PIECE", 7)
    many = render(scene, cam, cfg)
    for key in ("full", "gi", "direct"):
        np.testing.assert_array_equal(getattr(one, key), getattr(many, key))


def test_materials_of_one_image_share_its_texels_and_user_arrays_are_copied(tmp_path):
    """Two Mitsuba BSDFs of one bitmap file: one decoded array, held by both materials and
    their bitmaps (not a copy each); a writable array a user gives is copied and clipped."""
    from PIL import Image

    rng = np.random.default_rng(6)
    Image.fromarray(rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)).save(tmp_path / "t.png")
    quad = '<shape type="rectangle"><bsdf type="{}"><texture type="bitmap" name="{}">' \
        '<string name="filename" value="t.png"/></texture></bsdf>{}</shape>'  # fmt: skip
    xml = tmp_path / "s.xml"
    xml.write_text(
        '<scene version="3.0.0">'
        + quad.format("diffuse", "reflectance", "")
        + quad.format(
            "roughplastic",
            "diffuse_reflectance",
            '<transform name="to_world"><translate x="3"/></transform>',
        )  # fmt: skip
        + "</scene>"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load(xml)
    texs = [m.texture for m in scene.materials if m.is_textured]
    assert len(texs) == 2 and texs[0] is texs[1] and not texs[0].flags.writeable
    bitmaps = [
        m.bsdf.diffuse_reflectance for m in scene.materials if isinstance(m.bsdf, sb.RoughPlastic)
    ]
    assert bitmaps and np.shares_memory(bitmaps[0].data, texs[0])
    with Image.open(tmp_path / "t.png") as im:
        np.testing.assert_array_equal(texs[0], decode_texture(im))
    mine = np.full((2, 2, 3), 1.5, np.float32)
    m = Material("m", texture=mine)
    assert not np.shares_memory(m.texture, mine) and mine.flags.writeable
    np.testing.assert_array_equal(m.texture, 1.0)


def _general_textured_scene():
    """Three quads under a sky: a diffuse BSDF and a bump-mapped roughplastic of 8-bit sRGB
    bitmaps and a raw one, and a Lambert material of the diffuse's image."""
    rng = np.random.default_rng(7)
    a = decode_texture(rng.integers(0, 256, (6, 5, 3), dtype=np.uint8))
    c = decode_texture(rng.integers(0, 256, (4, 9, 3), dtype=np.uint8))
    b = SceneBuilder("general_textured")
    m0 = b.add_material(Material("d", bsdf=sb.Diffuse(sb.Bitmap(a))))
    raw = rng.integers(0, 256, (5, 4, 3)).astype(np.float32) / np.float32(255)  # a raw bitmap
    plastic = sb.RoughPlastic(diffuse_reflectance=sb.Bitmap(c), alpha=0.3)
    m1 = b.add_material(Material("p", bsdf=sb.BumpMap(sb.Bitmap(raw), plastic, scale=0.5)))
    m2 = b.add_material(Material("l", albedo=(1, 1, 1), texture=a))
    b.add_quad((-1.5, 0, -1), (0, 0, 2), (1, 0, 0), m0)  # facing +y
    b.add_quad((-0.5, 0, -1), (0, 0, 2), (1, 0, 0), m1)
    b.add_quad((0.5, 0, -1), (0, 0, 2), (1, 0, 0), m2)
    b.sky = Sky((0.7, 0.8, 0.9))
    return b.build()


def test_general_kernel_texel_codes_render_the_float_texels_image_bit_for_bit(monkeypatch):
    """The general (BSDF) kernel's textures stored as uint8 sRGB codes give the very image of
    the float32 texels (the codes decode to the same floats), and each image is stored once."""
    from icbtool.camera import Camera
    from icbtool.scene.derived import forget
    from icbtool.trace import TraceConfig, render, texels, tracer

    scene = _general_textured_scene()
    cam = Camera.look_at((0, 3, 2), (0, 0, 0), (0, 1, 0), fov_y_deg=60, height=10, width=14)
    cfg = TraceConfig(spp=4, max_depth=3, seed=5)
    coded = render(scene, cam, cfg)
    params = tracer._SceneData.of(scene).general.params
    n = (6 * 5 + 4 * 9 + 5 * 4) * 3  # the shared image once
    assert params.texels.dtype == np.uint8 and params.texels.size == n
    assert params.texel_lut.shape == (512,)  # sRGB levels, then code / 255 (the raw bitmap)
    assert sorted(params.ti[:, 4]) == [0, 0, 0, 256]  # the Lambert quad: its own bitmap
    forget(scene)
    for name in ("srgb_levels", "linear_levels"):
        levels = getattr(texels, name)()
        monkeypatch.setattr(texels, name, lambda lv=levels: lv[::-1].copy())  # no codes
    floats = render(scene, cam, cfg)
    params = tracer._SceneData.of(scene).general.params
    assert params.texels.size == 0 and params.texel_lut.size == n
    assert coded.full.std() > 0
    for key in ("full", "gi", "direct"):
        np.testing.assert_array_equal(getattr(coded, key), getattr(floats, key))


def test_face_normals_and_areas_from_one_pass_equal_their_formulas():
    from icbtool.scene import Scene

    v, f = _mesh(6)
    f[3] = [4, 4, 9]  # a degenerate face: zero area, zero normal
    s = Scene("m", v, f, vertex_normals(v, f), np.zeros(len(f), np.int32), [Material("m")])
    tri = v[f].astype(np.float64)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(cross, axis=1, keepdims=True)
    normals = np.where(ln > 0, cross / np.maximum(ln, 1e-300), 0).astype(np.float32)
    np.testing.assert_array_equal(s.face_areas, 0.5 * np.linalg.norm(cross, axis=1))
    np.testing.assert_array_equal(s.face_normals, normals)
    assert s.face_areas[3] == 0 and not s.face_normals[3].any()
    assert s.face_normals is s.face_normals and s.face_areas is s.face_areas  # cached


# --------------------------------------------------------------------------- binary PLY
def _write_ply(path: Path, v, faces, normals=None, uvs=None, face_colour=False, ascii_=False):
    """A PLY file: vertices (float32 x y z [nx ny nz] [u v]), faces (uchar count, int indices)."""
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    props += ["u", "v"] if uvs is not None else []
    cols = [np.asarray(v, np.float32)]
    cols += [np.asarray(normals, np.float32)] if normals is not None else []
    cols += [np.asarray(uvs, np.float32)] if uvs is not None else []
    vert = np.concatenate(cols, axis=1)
    k = len(faces[0])
    head = ["ply", f"format {'ascii' if ascii_ else 'binary_little_endian'} 1.0"]
    head += [f"element vertex {len(v)}"] + [f"property float {p}" for p in props]
    head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head += ["property uchar red"] if face_colour else []
    head += ["end_header"]
    out = ("\n".join(head) + "\n").encode()
    if ascii_:
        lines = [" ".join(f"{x:.9g}" for x in row) for row in vert]
        lines += [f"{k} " + " ".join(str(i) for i in f) for f in faces]
        out += ("\n".join(lines) + "\n").encode()
    else:
        fields = [("n", "u1"), ("i", "<i4", (k,))] + ([("c", "u1")] if face_colour else [])
        rec = np.zeros(len(faces), np.dtype(fields))
        rec["n"], rec["i"] = k, faces
        out += vert.astype("<f4").tobytes() + rec.tobytes()
    path.write_bytes(out)


@pytest.mark.parametrize("kind", ["triangles", "normals_uvs_colours", "quads"])
def test_binary_ply_reader_equals_the_general_reader(tmp_path, kind):
    from icbtool.scene.mesh import load_mesh
    from icbtool.scene.ply import read_binary_ply

    rng = np.random.default_rng(7)
    v = rng.normal(size=(30, 3))
    faces = rng.integers(0, 30, (40, 4 if kind == "quads" else 3))
    faces = faces[[len(set(f)) == len(f) for f in faces]]
    extra = {}
    if kind == "normals_uvs_colours":
        n = rng.normal(size=(30, 3))
        extra = dict(normals=n / np.linalg.norm(n, axis=1, keepdims=True), face_colour=True,
                     uvs=rng.uniform(size=(30, 2)))  # fmt: skip
    _write_ply(tmp_path / "m.ply", v, faces, **extra)
    fv, ff, fn, fuv = read_binary_ply(tmp_path / "m.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = load_mesh(tmp_path / "m.ply", up_axis="y", textures=False)
    np.testing.assert_array_equal(fv.astype(np.float32), ref.vertices)
    # the same triangles (a quad's two, each in the general reader's rotation or ours)
    canon = lambda f: np.sort([tuple(np.roll(t, -int(np.argmin(t)))) for t in f], axis=0)  # noqa: E731
    np.testing.assert_array_equal(canon(ff), canon(ref.faces))
    if kind == "normals_uvs_colours":
        np.testing.assert_allclose(fn, ref.normals, atol=1e-6)
        np.testing.assert_array_equal(fuv.astype(np.float32), ref.uvs)
    else:
        assert np.isnan(fn).all() and fuv is None


def test_binary_ply_reader_leaves_other_files_to_the_general_reader(tmp_path):
    from icbtool.scene.ply import read_binary_ply

    v, f = _mesh(8, 10, 12)
    _write_ply(tmp_path / "a.ply", v, f, ascii_=True)
    assert read_binary_ply(tmp_path / "a.ply") is None
    (tmp_path / "t.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nproperty list uchar float texcoord\n"
        b"end_header\n"
        + np.zeros(9, "<f4").tobytes()
        + b"\x03"
        + np.arange(3, dtype="<i4").tobytes()
        + b"\x06"
        + np.zeros(6, "<f4").tobytes()
    )
    assert read_binary_ply(tmp_path / "t.ply") is None  # per-corner uvs: not this reader's


def test_mitsuba_ply_shapes_read_fast_equal_the_general_reader(tmp_path, monkeypatch):
    import icbtool.scene.ply as ply

    rng = np.random.default_rng(9)
    v = rng.normal(size=(40, 3))
    f = rng.integers(0, 40, (60, 3))
    f = f[[len(set(t)) == 3 for t in f]]
    _write_ply(tmp_path / "a.ply", v, f, uvs=rng.uniform(size=(40, 2)))
    _write_ply(tmp_path / "b.ply", v + 3, f)
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0">'
        '<shape type="ply"><string name="filename" value="a.ply"/>'
        '<transform name="to_world"><scale value="2"/></transform></shape>'
        '<shape type="ply"><string name="filename" value="b.ply"/></shape></scene>'
    )
    fast = _scene_arrays(tmp_path / "s.xml")
    monkeypatch.setattr(ply, "read_binary_ply", lambda path: None)
    general = _scene_arrays(tmp_path / "s.xml")
    for key in ("vertices", "faces", "face_material", "uvs"):
        np.testing.assert_array_equal(fast[key], general[key], err_msg=key)
    np.testing.assert_allclose(fast["normals"], general["normals"], atol=2e-6)


def test_rough_tables_are_computed_once_per_parameters():
    """A scene's rough BSDFs share a few (alpha, eta): the tables are cached, read-only, and
    equal to a fresh computation."""
    from icbtool.trace import bsdfs

    a = bsdfs.rough_tables(True, 0.3, 1.5)
    assert bsdfs.rough_tables(True, 0.3, 1.5) is a
    fresh = bsdfs.rough_tables.__wrapped__(True, 0.3, 1.5)
    np.testing.assert_array_equal(a[0], fresh[0])
    assert a[1] == fresh[1] and not a[0].flags.writeable
