"""The lightweight progressive mesh: levels, uv transfer, wire chunks, client-side error."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace

import numpy as np
import pytest

from icbtool import lpm
from icbtool.lpm.build import decode_texture_bytes
from icbtool.lpm.chunks import chunk_header
from icbtool.scene import SceneBuilder, cornell_box, light_faces
from icbtool.scene.load import decode_texture

pytest.importorskip("open3d")

SIZE = 2.0
N = 24  # grid cells per side: 2 * 24 * 24 = 1152 triangles per plane


def _grid(n: int = N, size: float = SIZE) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) vertices of an n x n grid on y = 0, x and z in [-size/2, size/2], and (F, 3)
    faces facing +y."""
    t = np.linspace(-size / 2, size / 2, n + 1)
    x, z = np.meshgrid(t, t, indexing="xy")
    v = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], 1)
    i = np.arange(n * n)
    r, c = i // n, i % n
    a = r * (n + 1) + c
    faces = np.concatenate(
        [np.stack([a, a + n + 1, a + 1], 1), np.stack([a + 1, a + n + 1, a + n + 2], 1)]
    )
    return v, faces


def _uv_of(p: np.ndarray) -> np.ndarray:
    """The plane's uv: linear in position (u along x, v along -z), in [0, 1]."""
    return np.stack([p[:, 0] / SIZE + 0.5, 0.5 - p[:, 2] / SIZE], 1)


def _texture(h: int = 64, w: int = 48) -> np.ndarray:
    """A linear texture decoded from 8-bit sRGB (so it survives PNG exactly)."""
    rng = np.random.default_rng(3)
    return decode_texture(rng.integers(0, 256, (h, w, 3), dtype=np.uint8))


def textured_plane(two_materials: bool = False):
    v, f = _grid()
    b = SceneBuilder("plane")
    m0 = b.material("tex", texture=_texture())
    if not two_materials:
        b.add_mesh(v, f, m0, np.tile([0, 1, 0], (len(v), 1)), _uv_of(v))
        return b.build()
    m1 = b.material("white", albedo=(0.7, 0.7, 0.7))
    cx = v[f].mean(1)[:, 0]
    b.add_mesh(v, f[cx < 0], m0, np.tile([0, 1, 0], (len(v), 1)), _uv_of(v))
    b.add_mesh(v, f[cx >= 0], m1, np.tile([0, 1, 0], (len(v), 1)), _uv_of(v))
    return b.build()


CFG = lpm.LPMConfig(ratios=(0.1, 0.4, 1.0), texture_max=(16, 32, 0))


@pytest.fixture(scope="module")
def plane_lpm():
    return lpm.build(textured_plane(), CFG)


# --------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"ratios": (0.5, 0.2, 1.0), "texture_max": (0, 0, 0)}, "increase"),
        ({"ratios": (0.1, 0.5), "texture_max": (0, 0)}, "end with 1.0"),
        ({"ratios": (0.1, 1.0), "texture_max": (0,)}, "one size per level"),
        ({"texture_format": "webp"}, "texture_format"),
        ({"max_chunk_bytes": 10}, "max_chunk_bytes"),
    ],
)
def test_config_rejects_bad_values(kw, msg):
    with pytest.raises(ValueError, match=msg):
        lpm.LPMConfig(**kw)


# --------------------------------------------------------------------------- levels
@pytest.mark.parametrize("budget", ["global", "per_group"])
def test_triangle_counts_follow_the_ratios(plane_lpm, budget):
    lp = (
        plane_lpm
        if budget == "global"
        else lpm.build(plane_lpm.source, replace(CFG, budget=budget))
    )
    n = lp.source.n_triangles
    counts = [lv.n_triangles for lv in lp.levels]
    assert counts[-1] == n
    for ratio, c in zip(CFG.ratios[:-1], counts):
        # open3d stops at the target or just under it (one collapse removes 1-2 triangles)
        assert ratio * n - 4 <= c <= ratio * n + 1, (ratio, c)
    assert counts == sorted(counts)


def test_finest_level_is_the_input(plane_lpm):
    src, fine = plane_lpm.source, plane_lpm.levels[-1].scene
    for k in ("vertices", "faces", "normals", "uvs", "face_material"):
        assert np.array_equal(getattr(fine, k), getattr(src, k)), k
    assert np.array_equal(fine.materials[0].texture, src.materials[0].texture)


def test_decimated_plane_uvs_are_the_planes_linear_map(plane_lpm):
    """Known answer: the plane's uv is linear in position, so every vertex of every level must
    carry exactly that uv (the same point maps to the same texel)."""
    for lv in plane_lpm.levels[:-1]:
        s = lv.scene
        np.testing.assert_allclose(s.uvs, _uv_of(s.vertices.astype(np.float64)), atol=2e-6)
        np.testing.assert_allclose(s.normals, np.tile([0, 1, 0], (len(s.normals), 1)), atol=1e-6)


def test_uv_error_metric_is_zero_on_the_plane(plane_lpm):
    e = lpm.metrics.uv_error(plane_lpm.levels[0].scene, plane_lpm.source, n_samples=5000)
    assert e["mean_abs_255"] == 0.0
    assert e["p95_texel_distance"] < 1e-3


def test_uv_seam_is_not_interpolated_across():
    """Two uv charts meeting at x = 0 (split vertices): every decimated triangle must take the
    uv map of one chart for all three corners, never a mix (which would smear the texture)."""
    v, f = _grid()
    cx = v[f].mean(1)[:, 0]
    b = SceneBuilder("seam")
    m = b.material("tex", texture=_texture())
    n = np.tile([0, 1, 0], (len(v), 1))
    b.add_mesh(v, f[cx < 0], m, n, _uv_of(v))
    b.add_mesh(v, f[cx >= 0], m, n, _uv_of(v) + [0.25, 0.1])  # second chart: shifted
    scene = b.build()
    level = lpm.build(scene, lpm.LPMConfig(ratios=(0.05, 1.0), texture_max=(0, 0))).levels[0]
    s = level.scene
    p = s.vertices[s.faces].astype(np.float64).reshape(-1, 3)
    uv = s.uvs[s.faces].reshape(-1, 2)
    left = np.abs(uv - _uv_of(p)).max(1).reshape(-1, 3) < 1e-5
    right = np.abs(uv - _uv_of(p) - [0.25, 0.1]).max(1).reshape(-1, 3) < 1e-5
    assert (left.all(1) | right.all(1)).all()
    assert left.all(1).any() and right.all(1).any()
    # and it was decimated across the seam (welded), not kept as two separate meshes
    assert s.n_triangles < 0.1 * scene.n_triangles


def test_flat_plane_hausdorff_is_zero(plane_lpm):
    for lv in plane_lpm.levels:
        e = lpm.metrics.geometric_error(lv.scene, plane_lpm.source, n_samples=20_000)
        assert e["hausdorff"] < 1e-6 and e["rms"] < 1e-6


def test_geometric_error_known_offset():
    """A level moved by d along the plane's normal is d away everywhere."""
    src = textured_plane()
    moved = dataclasses.replace(src, vertices=src.vertices + np.float32([0, 0.01, 0]))
    e = lpm.metrics.geometric_error(moved, src, n_samples=5000)
    d = 0.01 / src.diagonal
    assert e["rms"] == pytest.approx(d, rel=1e-3)
    assert e["hausdorff"] == pytest.approx(d, rel=1e-3)


def test_materials_per_triangle_preserved():
    """Left half textured, right half white: every decimated triangle keeps its side's
    material (groups are decimated apart, so no face crosses x = 0)."""
    scene = textured_plane(two_materials=True)
    level = lpm.build(scene, lpm.LPMConfig(ratios=(0.1, 1.0), texture_max=(0, 0))).levels[0]
    s = level.scene
    cx = s.vertices[s.faces].astype(np.float64).mean(1)[:, 0]
    assert s.n_triangles < 0.2 * scene.n_triangles
    assert np.all(s.face_material[cx < 0] == 0) and np.all(s.face_material[cx > 0] == 1)
    assert [m.name for m in s.materials] == [m.name for m in scene.materials]
    # the two halves still cover the plane (areas add up to the full plane's)
    assert s.face_areas.sum() == pytest.approx(SIZE * SIZE, rel=1e-5)


def test_textures_shrink_per_level(plane_lpm):
    sides = [max(lv.scene.materials[0].texture.shape[:2]) for lv in plane_lpm.levels]
    assert sides == [16, 32, 64]


def test_cornell_box_light_geometry_and_counts():
    box = cornell_box()
    lp = lpm.build(box, lpm.LPMConfig(ratios=(0.02, 1.0), texture_max=(0, 0)))
    coarse = lp.levels[0].scene
    # every group of the box is a few quads: kept whole, and the area light's faces are exact
    assert coarse.n_triangles == box.n_triangles
    assert light_faces(coarse).sum() == light_faces(box).sum() == 2
    emit = coarse.emissive_faces
    np.testing.assert_array_equal(
        np.sort(coarse.vertices[coarse.faces[emit]].reshape(-1, 3), 0),
        np.sort(box.vertices[box.faces[box.emissive_faces]].reshape(-1, 3), 0),
    )
    assert coarse.light_hash == box.light_hash


# --------------------------------------------------------------------------- chunks
def _assert_scene_equal(a, b):
    for k in ("vertices", "faces", "normals", "uvs", "face_material"):
        x, y = getattr(a, k), getattr(b, k)
        assert (x is None and y is None) or (x.dtype == y.dtype and np.array_equal(x, y)), k
    assert len(a.materials) == len(b.materials)
    for ma, mb in zip(a.materials, b.materials):
        assert ma.name == mb.name and ma.texture_path == mb.texture_path
        assert np.array_equal(ma.albedo, mb.albedo) and np.array_equal(ma.emission, mb.emission)
        assert (ma.texture is None) == (mb.texture is None)
        if ma.texture is not None:
            assert np.array_equal(ma.texture, mb.texture)


@pytest.mark.parametrize("max_bytes", [None, 4096, 5001, 65536])
def test_chunk_round_trip_is_exact(plane_lpm, max_bytes):
    for lv in plane_lpm.levels:
        chunks = lv.to_chunks(max_bytes)
        assert max(len(c[2]) for c in chunks) <= (max_bytes or CFG.max_chunk_bytes)
        assert [c[1] for c in chunks][0] == "materials"
        got = lpm.assemble(chunks, base=plane_lpm.source)
        _assert_scene_equal(got, lv.scene)


def test_assemble_picks_the_finest_complete_level(plane_lpm):
    c0 = plane_lpm.levels[0].to_chunks()
    c1 = plane_lpm.levels[1].to_chunks()
    partial = c1[:-1]  # level 1 misses a chunk
    got = lpm.assemble(c0 + partial)
    assert got.n_triangles == plane_lpm.levels[0].n_triangles
    assert lpm.levels_in(c0 + c1) == [0, 1]
    assert lpm.levels_in(plane_lpm.chunks()) == [0, 1, 2]
    assert lpm.assemble(c0 + c1).n_triangles == plane_lpm.levels[1].n_triangles
    with pytest.raises(ValueError, match="lacks 1 chunk"):
        lpm.assemble(c0 + partial, level=1)


def test_chunk_size_bound_respected():
    scene = textured_plane()
    big = dataclasses.replace(
        scene,
        materials=(dataclasses.replace(scene.materials[0], texture=_texture(256, 256)),),
    )
    lp = lpm.build(big, lpm.LPMConfig(ratios=(0.5, 1.0), texture_max=(0, 0)))
    for lv in lp.levels:
        chunks = lv.to_chunks(max_chunk_bytes=4096)
        assert max(len(c[2]) for c in chunks) <= 4096
        assert sum(c[1] == "texture" for c in chunks) > 1  # the PNG was split
        _assert_scene_equal(lpm.assemble(chunks[::-1]), lv.scene)  # any order
    # 625 vertices x 12 bytes do not fit one chunk of the full level
    assert sum(c[0].startswith("L1/geometry/vertices") for c in chunks) > 1


def test_corrupt_and_truncated_chunks_raise_clear_errors(plane_lpm):
    chunks = plane_lpm.levels[0].to_chunks()
    name, part, data = chunks[2]

    def with_chunk(d):
        return [*chunks[:2], (name, part, d), *chunks[3:]]

    flipped = bytearray(data)
    flipped[-1] ^= 0xFF
    with pytest.raises(ValueError, match=rf"'{name}'.*CRC-32"):
        lpm.assemble(with_chunk(bytes(flipped)))
    with pytest.raises(ValueError, match=rf"'{name}'.*truncated"):
        lpm.assemble(with_chunk(data[:-10]))
    with pytest.raises(ValueError, match=rf"'{name}'.*truncated"):
        lpm.assemble(with_chunk(data[:5]))
    with pytest.raises(ValueError, match=rf"'{name}'.*bad magic"):
        lpm.assemble(with_chunk(b"XXXX" + data[4:]))
    with pytest.raises(ValueError, match="not UTF-8 JSON"):
        lpm.assemble(with_chunk(data[:8] + b"{" * (len(data) - 8)))
    with pytest.raises(ValueError, match=r"'L0/other'.*header names it"):
        lpm.assemble([*chunks[:2], ("L0/other", part, data), *chunks[3:]])
    with pytest.raises(ValueError, match="no complete level"):
        lpm.assemble(chunks[1:])


def test_chunk_header_layout(plane_lpm):
    """The documented layout: magic, uint32 LE header length, JSON header, payload."""
    name, part, data = plane_lpm.levels[0].to_chunks()[1]
    assert data[:4] == b"ICBL"
    hlen = int.from_bytes(data[4:8], "little")
    header = json.loads(data[8 : 8 + hlen])
    assert header["name"] == name and header["part"] == part == "geometry"
    rows = np.frombuffer(data[8 + hlen :], "<f4").reshape(header["rows"], -1)
    arr = getattr(plane_lpm.levels[0].scene, header["array"])
    np.testing.assert_array_equal(rows, arr[header["row0"] : header["row0"] + header["rows"]])
    assert chunk_header(data, name)[0] == header


def test_scene_info_round_trip():
    box = cornell_box()
    info = lpm.scene_info(box)
    json.loads(info)  # plain JSON
    fields = lpm.read_scene_info(info)
    assert dataclasses.replace(box, **fields).light_hash == box.light_hash
    level = lpm.build(box, lpm.LPMConfig(ratios=(1.0,), texture_max=(0,))).levels[0]
    got = lpm.assemble(level.to_chunks(), base=info)
    assert got.light_hash == box.light_hash
    with pytest.raises(ValueError, match="scene info"):
        lpm.read_scene_info(b'{"lights": [{"kind": "nope"}]}')


def test_jpeg_textures_round_trip():
    scene = textured_plane()
    lp = lpm.build(scene, lpm.LPMConfig(ratios=(1.0,), texture_max=(0,), texture_format="jpeg"))
    lv = lp.levels[0]
    assert lv.texture_bytes[0][:2] == b"\xff\xd8"
    _assert_scene_equal(lpm.assemble(lv.to_chunks()), lv.scene)
    assert np.array_equal(decode_texture_bytes(lv.texture_bytes[0]), lv.scene.materials[0].texture)


# --------------------------------------------------------------------------- client
@pytest.mark.gl
def test_cornell_coarsest_level_renders_like_the_full_box():
    from icbtool.raster import RasterConfig
    from icbtool.scene import cornell_camera

    box = cornell_box()
    coarse = lpm.build(box, lpm.LPMConfig(ratios=(0.02, 1.0), texture_max=(0, 0))).levels[0]
    cams = [cornell_camera(48, 48)]
    cfg = RasterConfig(shadow_map_size=256, area_shadow_map_size=64, area_samples=2)
    e = lpm.metrics.client_error(lpm.assemble(coarse.to_chunks(), base=box), box, cams, cfg)
    assert e["depth_rel_p95"] < 1e-5
    assert e["depth_bad_fraction"] == 0.0
    assert e["dl_ssim"] > 0.999


@pytest.mark.gl
def test_cli_writes_stats_previews_and_chunks(tmp_path):
    from icbtool.cli import main

    out = tmp_path / "lpm"
    rc = main(["lpm", "cornell_box", "--out", str(out), "--cameras", "1", "--height", "24",
               "--width", "24", "--ratios", "0.5,1", "--chunks"])  # fmt: skip
    assert rc == 0
    data = json.loads((out / "lpm.json").read_text())
    assert [r["triangles"] for r in data["levels"]] == [32, 32]
    assert data["levels"][0]["client"]["depth_bad_fraction"] == 0.0
    for f in ("lpm.csv", "lpm_levels.png", "lpm_dl.png", "chunks/scene_info.json"):
        assert (out / f).is_file(), f
    chunks = [
        (str(p.relative_to(out / "chunks").with_suffix("")), None, p.read_bytes())
        for p in sorted((out / "chunks").rglob("L0/**/*.bin"))
    ]
    chunks = [(n, chunk_header(d, n)[0]["part"], d) for n, _, d in chunks]
    got = lpm.assemble(chunks, base=(out / "chunks" / "scene_info.json").read_bytes())
    assert got.n_triangles == 32 and len(got.lights) == 1


def test_eval_config_rejects_a_bad_latency():
    from icbtool.lpm.evaluate import EvalConfig

    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="EvalConfig.latency_s must be finite and >= 0"):
            EvalConfig(latency_s=bad)
