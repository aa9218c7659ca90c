"""Environment maps (Sky kind 'envmap'): Mitsuba 3's lat-long convention, the kernels' lookup and
importance table, known answers in the tracer, the raster background, TOML and file reading."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sstats

import icbtool as icb
from icbtool.camera import Camera
from icbtool.imageio import read_hdr, write_exr
from icbtool.scene import SceneBuilder, Sky
from icbtool.scene.description import SceneError, read_description
from icbtool.trace import SkyTable, TraceConfig, render


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _mitsuba_dir(u: float, v: float) -> np.ndarray:
    """Mitsuba 3 envmap's uv_to_direction (map space)."""
    th, ph = v * math.pi, u * 2 * math.pi
    return np.array([math.sin(ph) * math.sin(th), math.cos(th), -math.cos(ph) * math.sin(th)])


def _unit_dirs(n: int, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _sky_map(h: int = 32, w: int = 64) -> np.ndarray:
    """A sky-like map: a bright sun blob, a blue dome, a dark ground (all > 0)."""
    v, u = (np.mgrid[0:h, 0:w] + np.array([0.0, 0.5])[:, None, None]) / np.array([h - 1, w])[
        :, None, None
    ]
    th, ph = v * np.pi, u * 2 * np.pi
    d = np.stack([np.sin(ph) * np.sin(th), np.cos(th), -np.cos(ph) * np.sin(th)], -1)
    sun = np.array([0.5, 0.7, 0.3]) / np.linalg.norm([0.5, 0.7, 0.3])
    blob = 400.0 * np.exp((d @ sun - 1) / 0.002)
    dome = np.where(d[..., 1:2] > 0, [0.3, 0.45, 0.8], [0.08, 0.07, 0.06])
    return (dome + blob[..., None] * [1.0, 0.9, 0.8]).astype(np.float32)


# ------------------------------------------------------------------------------ convention
def test_texel_centres_are_mitsubas_and_the_map_is_bilinear():
    m = np.random.default_rng(0).random((8, 16, 3)).astype(np.float32)
    sky = Sky.from_envmap(m)
    for j, i in [(1, 0), (3, 5), (6, 15), (4, 0)]:  # (at the poles every u is one direction)
        d = _mitsuba_dir((i + 0.5) / 16, j / 7)
        np.testing.assert_allclose(sky.radiance(d), m[j, i], rtol=1e-5)
    # halfway between texel centres: the mean of the two; across u = 0 (periodic)
    d = _mitsuba_dir(2.0 / 16, 3 / 7)
    np.testing.assert_allclose(sky.radiance(d), 0.5 * (m[3, 1] + m[3, 2]), rtol=1e-5)
    d = _mitsuba_dir(0.0, 3 / 7)
    np.testing.assert_allclose(sky.radiance(d), 0.5 * (m[3, 15] + m[3, 0]), rtol=1e-5)
    # row 0 is straight up (map +y), the last row straight down
    poles = np.zeros((8, 16, 3), np.float32)
    poles[0], poles[-1] = 5.0, 2.0
    np.testing.assert_allclose(Sky.from_envmap(poles).radiance(np.eye(3)[[1]]), 5.0)
    np.testing.assert_allclose(Sky.from_envmap(poles).radiance(-np.eye(3)[[1]]), 2.0)
    # a rotation moves the map with it
    r = _rotation(1)
    rot = Sky.from_envmap(m, scale=2.0, world_from_map=r)
    dirs = _unit_dirs(100, 2)
    np.testing.assert_allclose(rot.radiance(dirs @ r.T), 2.0 * sky.radiance(dirs), rtol=1e-5)
    np.testing.assert_allclose(rot.up, r[:, 1])


def test_kernel_lookup_equals_sky_radiance():
    from icbtool.trace import kernels as K

    m = _sky_map(16, 32) * np.random.default_rng(3).random((16, 32, 1)).astype(np.float32)
    sky = Sky.from_envmap(m, scale=1.7, world_from_map=_rotation(4))
    d = _unit_dirs(5000, 5)
    out = np.empty((len(d), 3))
    K.sky_radiance_batch(SkyTable.of(sky).params(sky), d, out)
    np.testing.assert_allclose(out, sky.radiance(d), rtol=2e-6, atol=1e-6)


def test_mean_radiance_and_hash_cover_the_content():
    m = np.full((9, 18, 3), 0.7, np.float32)
    sky = Sky.from_envmap(m)
    np.testing.assert_allclose(sky.zenith, np.float32(0.7), rtol=1e-12)  # a constant map: itself
    base = icb.scene.plane(sun_direction=None)
    a = replace(base, sky=sky)
    m2 = m.copy()
    m2[4, 7, 1] += 1e-4
    b = replace(base, sky=Sky.from_envmap(m2))
    c = replace(base, sky=Sky.from_envmap(m.copy()))
    assert a.light_hash != b.light_hash and a.content_hash != b.content_hash
    assert a.light_hash == c.light_hash
    assert replace(base, sky=Sky.from_envmap(m, scale=2.0)).light_hash != a.light_hash


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(path_or_array=np.zeros((2, 8, 3))), "at least 3 x 2"),
        (dict(path_or_array=np.zeros((4, 8, 2))), r"\(H, W, 3\)"),
        (dict(path_or_array=np.full((4, 8, 3), np.nan)), "NaN/Inf texels .*row 0, column 0"),
        (dict(path_or_array=-np.ones((4, 8, 3))), "negative radiance"),
        (dict(path_or_array=np.ones((4, 8, 3)), scale=-1.0), "envmap_scale"),
        (dict(path_or_array=np.ones((4, 8, 3)), world_from_map=2 * np.eye(3)), "rotation"),
    ],
)
def test_bad_maps_are_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Sky.from_envmap(**kwargs)


def test_hdr_files_read_exr_and_radiance(tmp_path):
    import cv2

    m = _sky_map(8, 16)
    write_exr(tmp_path / "a.exr", m)
    np.testing.assert_array_equal(read_hdr(tmp_path / "a.exr"), m)
    cv2.imwrite(str(tmp_path / "a.hdr"), np.ascontiguousarray(m[..., ::-1]))
    err = np.abs(read_hdr(tmp_path / "a.hdr") - m)
    assert np.all(err <= m.max(-1, keepdims=True) / 128)  # RGBE: 8-bit mantissas, one exponent
    sky = Sky.from_envmap(tmp_path / "a.hdr")
    assert sky.envmap.shape == (8, 16, 3)
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        Sky.from_envmap(tmp_path / "nope.exr")
    (tmp_path / "a.png").write_bytes(b"x")
    with pytest.raises(ValueError, match="unsupported HDR image type '.png'"):
        read_hdr(tmp_path / "a.png")


# ------------------------------------------------------------------------------ sampling
def test_envmap_table_is_normalised_and_sampling_follows_its_pdf():
    sky = Sky.from_envmap(_sky_map(16, 32), world_from_map=_rotation(6))
    tab = SkyTable.of(sky)
    nc, nphi = tab.pdf.shape
    assert (nc, nphi) == (15, 32) and tab.rows == 1
    th = np.arange(nc + 1) * np.pi / nc
    solid = (np.cos(th[:-1]) - np.cos(th[1:]))[:, None] * (2 * np.pi / nphi)
    assert (tab.pdf * solid).sum() == pytest.approx(1.0, abs=1e-12)
    n = 200_000
    d, p = tab.sample(np.random.default_rng(0).random((n, 2)))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.all(p > 0)
    assert np.mean(np.isclose(tab.pdf_of(d), p, rtol=1e-12)) > 0.999  # but at cell borders
    # counts per cell (from the direction alone, in map space) follow the table
    local = d @ sky.world_from_map
    row = np.minimum((np.arccos(np.clip(local[:, 1], -1, 1)) / (np.pi / nc)).astype(int), nc - 1)
    u = np.mod(np.arctan2(local[:, 0], -local[:, 2]) / (2 * np.pi) - 0.5 / nphi, 1.0)
    col = np.minimum((u * nphi).astype(int), nphi - 1)
    counts = np.bincount(row * nphi + col, minlength=nc * nphi).reshape(nc, nphi)
    expect = tab.pdf * solid * n
    big = expect > 20
    z = (counts - expect) / np.sqrt(np.maximum(expect, 1.0))
    chi2, dof = float(np.sum(z[big] ** 2)), int(big.sum()) - 1
    assert sstats.chi2.sf(chi2, dof) > 1e-4 and sstats.chi2.cdf(chi2, dof) > 1e-4, (chi2, dof)
    assert tab.peak > 20  # the sun blob


# ------------------------------------------------------------------------------ tracer
def test_constant_map_is_the_uniform_sky():
    """A constant map gives the uniform sky's images (same random numbers, BSDF sampling) and,
    with importance sampling, the plane's known answer GI = albedo * L (furnace-like)."""
    base = icb.scene.plane(sun_direction=None, albedo=(0.5, 0.6, 0.7))
    cam = base.default_camera.resized(12, 12)
    L = np.array([0.8, 1.0, 1.3])
    uni = replace(base, sky=Sky(L))
    env = replace(base, sky=Sky.from_envmap(np.broadcast_to(L, (9, 20, 3)), 1.0, _rotation(7)))
    cfg = TraceConfig(spp=8, sampler="independent", sky_sampling="bsdf", seed=3)
    a, b = render(uni, cam, cfg), render(env, cam, cfg)
    np.testing.assert_allclose(b.gi, a.gi, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(b.direct, a.direct, rtol=1e-5)
    res = render(env, cam, replace(cfg, sky_sampling="mis", spp=32))
    assert res.stats.rays["shadow"] > 0
    expect = np.array([0.5, 0.6, 0.7]) * L
    mean = res.gi.reshape(-1, 3).mean(0)
    se = np.sqrt(res.variance.reshape(-1, 3).sum(0)) / res.gi[..., 0].size
    assert np.all(np.abs(mean - expect) < 5 * se + 1e-6), (mean, expect, se)


def _quad_facing(n: np.ndarray, albedo: float = 0.5):
    """A 2 x 2 quad through the origin facing n, and a camera in front of it that it fills."""
    n = n / np.linalg.norm(n)
    a = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    sb = SceneBuilder("quad")
    m = sb.material("grey", albedo=(albedo,) * 3)
    sb.add_quad(-a - b, 2 * a, 2 * b, m)  # normal = cross(2a, 2b) = n
    up = b
    cam = Camera.look_at(tuple(2 * n), (0, 0, 0), tuple(up), fov_y_deg=20, height=8, width=8)
    return sb.build(default_camera=cam), cam


@pytest.mark.parametrize("normal", [(0, 1, 0), (1, 0, 0), (-1, 0, 0), (0, 0, 1), (0.3, 0.2, -1)])
def test_one_bright_texel_lights_a_plane_like_a_directional_light(normal):
    """A map black but for one texel: a quad facing n receives E = Phi * max(n . d, 0) from the
    texel's direction d (Mitsuba's convention), Phi = the texel's integral over solid angle."""
    h, w, j, i, V = 32, 64, 9, 13, 5000.0
    m = np.zeros((h, w, 3), np.float32)
    m[j, i] = V
    r = _rotation(8)
    sky = Sky.from_envmap(m, world_from_map=r)
    d = r @ _mitsuba_dir((i + 0.5) / w, j / (h - 1))
    # Phi: the bilinear hat's integral (2 pi / w) * int hat(theta) sin(theta) dtheta
    t = np.linspace(-1, 1, 20001)
    dth = np.pi / (h - 1)
    phi = V * (2 * np.pi / w) * np.trapezoid((1 - np.abs(t)) * np.sin(j * dth + t * dth), t) * dth
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    scene, cam = _quad_facing(n)
    scene = replace(scene, sky=sky)
    res = render(scene, cam, TraceConfig(spp=16, sky_sampling="mis", seed=1))
    expect = 0.5 / np.pi * phi * max(float(n @ d), 0.0)
    mean = res.gi.reshape(-1, 3).mean(0)
    assert np.allclose(mean, expect, rtol=0.03, atol=1e-3 * phi), (mean, expect, n @ d)


def test_importance_sampling_is_unbiased_and_less_noisy():
    """Boxes under a sun-like map: the map's importance sampling (MIS with the BSDF) and BSDF
    sampling alone agree on the mean (z-test) and MIS has far less variance."""
    scene = icb.scene.boxes_on_floor(n_boxes=5, seed=2, sun_irradiance=0.0)
    scene = replace(scene, sky=Sky.from_envmap(_sky_map(32, 64)))
    cam = scene.default_camera.resized(20, 20)
    base = TraceConfig(spp=32, sampler="independent", seed=4)
    a = render(scene, cam, replace(base, sky_sampling="bsdf"))
    b = render(scene, cam, replace(base, sky_sampling="mis"))
    n = a.gi[..., 0].size
    diff = b.gi.reshape(-1, 3).mean(0) - a.gi.reshape(-1, 3).mean(0)
    se = np.sqrt(a.variance.reshape(-1, 3).sum(0) + b.variance.reshape(-1, 3).sum(0)) / n
    assert np.all(np.abs(diff) < 5 * se), (diff, se)
    ratio = b.variance.mean() / a.variance.mean()
    assert ratio < 0.5, ratio
    auto = render(scene, cam, replace(base, spp=2))
    assert auto.stats.rays["shadow"] > 0  # 'auto' samples a peaked map


# ------------------------------------------------------------------------------ raster
@pytest.mark.gl
def test_raster_background_shows_the_map():
    from icbtool.raster import Rasterizer

    sky = Sky.from_envmap(_sky_map(16, 32), scale=1.5, world_from_map=_rotation(9))
    scene = replace(icb.scene.plane(sun_direction=None), sky=sky)
    cam = Camera.look_at((0, 1, 0), (1, 1.3, 0.2), (0, 1, 0), 100, 24, 32)
    with Rasterizer(scene) as r:
        buf = r.render(cam)
    bg = buf.mask[..., 0] < 0.5
    assert bg.sum() > 100
    v, u = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    dc = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    d = dc @ cam.world_from_cam[:3, :3].T
    expect = sky.radiance(d / np.linalg.norm(d, axis=-1, keepdims=True))
    np.testing.assert_allclose(buf.dl[bg], expect[bg], rtol=2e-3, atol=1e-4)
    # surfaces: the map's light is GI (the cloud's), not the client's DL
    assert np.all(buf.dl[~bg] == 0)


# ------------------------------------------------------------------------------ TOML
def _toml(tmp_path, sky: str):
    (tmp_path / "p.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 0 -1\nf 1 2 3\n")
    p = tmp_path / "s.toml"
    p.write_text(f'[scene]\nmesh = "p.obj"\n[sky]\n{sky}\n')
    return p


def test_toml_envmap_sky(tmp_path):
    m = _sky_map(8, 16)
    write_exr(tmp_path / "sky.exr", m)
    p = _toml(tmp_path, 'type = "envmap"\nmap = "sky.exr"\nscale = 2.0\nrotation = [0, 1, 0, 90]')
    sky = read_description(p).sky
    assert sky.kind == "envmap" and sky.envmap_scale == 2.0
    np.testing.assert_array_equal(sky.envmap, m)
    np.testing.assert_allclose(sky.world_from_map, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    mat = "[[1, 0, 0], [0, 0, -1], [0, 1, 0]]"
    p = _toml(tmp_path, f'type = "envmap"\nmap = "sky.exr"\nrotation = {mat}')
    np.testing.assert_allclose(read_description(p).sky.world_from_map, np.array(eval(mat)))


@pytest.mark.parametrize(
    ("sky", "match"),
    [
        ('type = "envmap"', r"missing required key\(s\) \['map'\]"),
        ('type = "envmap"\nmap = "none.exr"', "none.exr' not found"),
        ('type = "envmap"\nmap = "sky.exr"\nzenith = [1, 1, 1]', r"unknown key\(s\) \['zenith'\]"),
        ('type = "envmap"\nmap = "sky.exr"\nrotation = [0, 0, 0, 90]', "axis must not be zero"),
        ('type = "envmap"\nmap = "sky.exr"\nrotation = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]',
         "rotation"),
        ('type = "envmap"\nmap = "sky.exr"\nscale = -2', "envmap_scale"),
    ],
)  # fmt: skip
def test_toml_envmap_errors_name_the_problem(tmp_path, sky, match):
    write_exr(tmp_path / "sky.exr", _sky_map(8, 16))
    with pytest.raises(SceneError, match=match):
        read_description(_toml(tmp_path, sky))


def test_skies_without_a_map_keep_the_light_hash_stores_were_written_with(tmp_path):
    """Adding environment maps must not change the hash of a uniform or gradient sky: records are
    looked up by it, so a changed hash would silently turn every stored record of such a scene
    into a miss. The values are the hashes before environment maps existed."""
    assert icb.scene.boxes_on_floor().light_hash == "12f0bc78b0d32112"  # uniform sky
    repo = Path(__file__).resolve().parents[1]
    (tmp_path / "s.toml").write_text(
        f'[scene]\nname = "s"\nmesh = "{repo}/tests/data/scenes/cornell_style.obj"\n'
        '[sky]\ntype = "gradient"\nzenith = [0.3, 0.45, 0.8]\nhorizon = [0.7, 0.75, 0.8]\n'
        "ground = [0.2, 0.18, 0.15]\n"
    )
    assert icb.scene.load(tmp_path / "s.toml").light_hash == "1f1dafc0bc58cfb1"  # gradient
