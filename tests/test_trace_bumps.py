"""Mitsuba 3's ``normalmap`` and ``bumpmap`` in the tracer: known answers (a flat map changes
nothing, the bump gradient is the bilinear interpolant's), the reader, and peer renders of a
bumpy floor against Mitsuba 3 itself."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_trace_bsdf import peer_compare_file

from icbtool.scene import Material
from icbtool.scene import bsdf as sb


# ---------------------------------------------------------------------------------- known answers
def _floor_scene(bsdf, size=16):
    """A 2 x 2 floor (uvs over it) of ``bsdf`` under a uniform sky and a square area light."""
    from icbtool.camera import Camera
    from icbtool.scene import AreaLight, SceneBuilder, Sky

    b = SceneBuilder("floor")
    m = b.add_material(Material("floor", bsdf=bsdf))
    b.add_quad((-1, 0, 1), (2, 0, 0), (0, 0, -2), m)
    b.add_area_light(
        AreaLight((0.5, 1.5, -0.5), (0.4, 0, 0), (0, 0, 0.4), radiance=(6, 6, 6), name="lamp")
    )
    b.sky = Sky(kind="uniform", zenith=(0.3, 0.3, 0.3))
    cam = Camera.look_at((0, 2, 2), (0, 0, 0), (0, 1, 0), fov_y_deg=50, height=size, width=size)
    return b.build(default_camera=cam), cam


def _render(bsdf, spp=4):
    from icbtool.trace.tracer import TraceConfig, render

    scene, cam = _floor_scene(bsdf)
    r = render(scene, cam, TraceConfig(spp=spp, max_depth=4, seed=7))
    return r.direct + r.gi, r


def test_flat_normal_map_renders_exactly_as_no_map():
    """A normal map of (0.5, 0.5, 1) everywhere is the unperturbed frame: the same image, to
    float precision, as the nested BSDF alone (same seed)."""
    inner = sb.RoughPlastic(diffuse_reflectance=(0.2, 0.5, 0.7), alpha=0.2)
    flat = sb.Bitmap(np.tile(np.float32([0.5, 0.5, 1.0]), (4, 4, 1)))
    plain, _ = _render(inner)
    mapped, r = _render(sb.NormalMap(flat, inner))
    assert plain.max() > 0.05
    np.testing.assert_allclose(mapped, plain, rtol=1e-6, atol=1e-7)
    assert any("normalmap" in s and "general kernel" in s for s in r.stats.skipped)


def test_tilted_normal_map_and_constant_bump_map():
    """A constant bump map has no gradient: the image equals the nested BSDF's (the frame turns
    about the normal only; roughplastic is isotropic). A tilted normal map changes it."""
    inner = sb.RoughPlastic(diffuse_reflectance=(0.6, 0.4, 0.2), alpha=0.3)
    plain, _ = _render(inner)
    const = sb.Bitmap(np.full((3, 5, 3), 0.7, np.float32))
    bumped, _ = _render(sb.BumpMap(const, inner, scale=3.0))
    np.testing.assert_allclose(bumped, plain, rtol=1e-5, atol=1e-6)
    n = np.float32([0.8, 0.5, 0.8])  # encoded (0.6, 0, 0.6): tilted 45 degrees along +u
    tilted, _ = _render(sb.NormalMap(sb.Bitmap(np.tile(n, (2, 2, 1))), inner))
    assert np.abs(tilted - plain).mean() > 0.05 * plain.mean()


def test_bump_gradient_is_the_bilinear_interpolants():
    """tex_grad1 = the finite difference of the bilinear lookup's luminance in Mitsuba's uv
    (v = 1 - scene v), through a to_uv scale; a nearest bitmap has none."""
    from icbtool.trace import bsdfs as bs

    rng = np.random.default_rng(3)
    data = rng.random((5, 7, 3)).astype(np.float32)
    to_uv = np.diag([2.0, 3.0, 1.0])
    t = bs.pack([Material("m", bsdf=sb.BumpMap(sb.Bitmap(data, to_uv=to_uv), sb.Diffuse()))])
    B = t.params
    tex = int(B.ntex[t.mat_root[0], 0])

    def lum(u, v):  # u, v: Mitsuba's
        r, g, b = bs.tex_eval(B.tk, B.tf, B.ti, B.texels, B.texel_lut, tex, u, 1.0 - v, 0)
        return 0.212671 * r + 0.715160 * g + 0.072169 * b

    h = 1e-6
    for u, v in rng.random((20, 2)):
        gu, gv = bs.tex_grad1(B.tk, B.tf, B.ti, B.texels, B.texel_lut, tex, u, 1.0 - v)
        fu = (lum(u + h, v) - lum(u - h, v)) / (2 * h)
        fv = (lum(u, v + h) - lum(u, v - h)) / (2 * h)
        assert gu == pytest.approx(fu, rel=1e-4, abs=1e-4)
        assert gv == pytest.approx(fv, rel=1e-4, abs=1e-4)
    near = bs.pack([Material("m", bsdf=sb.BumpMap(sb.Bitmap(data, "nearest"), sb.Diffuse()))])
    P = near.params
    assert bs.tex_grad1(P.tk, P.tf, P.ti, P.texels, P.texel_lut, 0, 0.3, 0.6) == (0.0, 0.0)


def test_map_declarations_and_nestings_are_checked():
    d = sb.Diffuse()
    with pytest.raises(ValueError, match="bumpmap texture must be a bitmap"):
        sb.BumpMap(sb.Checkerboard(), d)
    with pytest.raises(ValueError, match="nested BSDF must be a BSDF"):
        sb.NormalMap(0.5, "diffuse")
    assert sb.approximate_albedo(sb.NormalMap((0.5, 0.5, 1.0), sb.Diffuse(0.3))) == (0.3,) * 3
    from icbtool.trace import bsdfs as bs

    nm = sb.NormalMap((0.5, 0.5, 1.0), d)
    for bad, msg in (
        (sb.BlendBSDF(nm, d), "inside a blendbsdf"),
        (sb.NormalMap((0.5, 0.5, 1.0), sb.TwoSided(nm)), "one normalmap or bumpmap"),
        (sb.NormalMap((0.5, 0.5, 1.0), sb.Mask(d)), "a mask inside"),
    ):
        with pytest.raises(ValueError, match=msg):
            bs.pack([Material("m", bsdf=bad)])
    t = bs.pack([Material("m", bsdf=sb.TwoSided(nm))], maps=False)  # no uvs: the map is dropped
    assert bs.NORMALMAP not in t.params.nt


# ---------------------------------------------------------------------------------- reader
def test_reader_builds_maps_and_names_a_missing_map(tmp_path):
    from icbtool.scene import load
    from icbtool.scene.validate import SceneError

    _write_maps(tmp_path)
    xml = tmp_path / "s.xml"
    xml.write_text(_xml(PEER_MAPS["twosided_bumpmap_roughplastic"]))
    s = load(xml)
    b = s.materials[-1].bsdf
    assert isinstance(b, sb.TwoSided) and isinstance(b.front, sb.BumpMap)
    assert b.front.scale == pytest.approx(0.15) and isinstance(b.front.bsdf, sb.RoughPlastic)
    xml.write_text(_xml(PEER_MAPS["normalmap_diffuse"].replace("normal.png", "gone.png")))
    with pytest.raises((SceneError, FileNotFoundError), match=r"s\.xml:\d+.*gone\.png"):
        load(xml)
    xml.write_text(_xml('<bsdf type="normalmap"><bsdf type="diffuse"/></bsdf>'))
    with pytest.raises(SceneError, match=r"s\.xml:\d+.*texture named 'normalmap'"):
        load(xml)


def test_reader_folds_a_scale_texture_and_drops_a_map_without_gradient(tmp_path):
    """Mitsuba 0.6 files (Bitterli's bedroom) scale a bump map's bitmap with a ``scale``
    texture, which Mitsuba 3 lacks: its factor multiplies the bump scale. A texture without a
    gradient (a checkerboard) drops the map, with a warning naming file:line, and keeps the
    nested BSDF exact."""
    from icbtool.scene import load
    from icbtool.scene.validate import SceneRepairWarning

    _write_maps(tmp_path)
    xml = tmp_path / "s.xml"
    scaled = (
        '<bsdf type="bumpmap"><float name="scale" value="2"/><texture type="scale">'
        '<float name="scale" value="0.2"/><texture type="bitmap">'
        f'<string name="filename" value="height.png"/></texture></texture>{_ROUGH}</bsdf>'
    )
    xml.write_text(_xml(scaled))
    b = load(xml).materials[-1].bsdf
    assert isinstance(b, sb.BumpMap) and b.scale == pytest.approx(0.4)
    xml.write_text(_xml(f'<bsdf type="bumpmap"><texture type="checkerboard"/>{_ROUGH}</bsdf>'))
    with pytest.warns(SceneRepairWarning, match=r"s\.xml:\d+.*no gradient.*bump map is dropped"):
        b = load(xml).materials[-1].bsdf
    assert isinstance(b, sb.RoughPlastic)


# ---------------------------------------------------------------------------------- peer suite
_MAP_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="8"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 2.2, 2.6" target="0, 0, 0.1" up="0, 1, 0"/>
    </transform>
    <film type="hdrfilm"><integer name="width" value="48"/>
      <integer name="height" value="36"/><rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.4"/><rotate x="1" angle="90"/>
      <translate x="1.0" y="1.6" z="-0.6"/></transform>
    <emitter type="area"><rgb name="radiance" value="12, 12, 12"/></emitter>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="1.5"/>{turn}<rotate x="1" angle="-90"/>
      </transform>
    {bsdf}
  </shape>
</scene>"""

_NORMAL = (
    '<texture type="bitmap" name="normalmap"><string name="filename" value="normal.png"/>'
    '<boolean name="raw" value="true"/></texture>'
)
_HEIGHT = (
    '<texture type="bitmap" name="height"><string name="filename" value="height.png"/></texture>'
    '<float name="scale" value="0.15"/>'
)
_ROUGH = (
    '<bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.35, 0.6"/>'
    '<float name="alpha" value="0.15"/></bsdf>'
)
PEER_MAPS = {
    "normalmap_diffuse": f'<bsdf type="normalmap">{_NORMAL}<bsdf type="diffuse">'
    '<rgb name="reflectance" value="0.7, 0.55, 0.4"/></bsdf></bsdf>',
    "normalmap_roughplastic": f'<bsdf type="normalmap">{_NORMAL}{_ROUGH}</bsdf>',
    "bumpmap_textured_diffuse": f'<bsdf type="bumpmap">{_HEIGHT}<bsdf type="diffuse">'
    '<texture type="bitmap" name="reflectance"><string name="filename" value="albedo.png"/>'
    "</texture></bsdf></bsdf>",
    "twosided_bumpmap_roughplastic": f'<bsdf type="twosided"><bsdf type="bumpmap">{_HEIGHT}'
    f"{_ROUGH}</bsdf></bsdf>",
    # the tangent frame's orientation matters to an anisotropic BSDF only
    "bumpmap_anisotropic_roughconductor": f'<bsdf type="bumpmap">{_HEIGHT}'
    '<bsdf type="roughconductor"><string name="material" value="Al"/><string '
    'name="distribution" value="ggx"/><float name="alpha_u" value="0.03"/>'
    '<float name="alpha_v" value="0.4"/></bsdf></bsdf>',
}


#: cases on a floor turned in its plane (uv axes unaligned with the world's)
TURNED = {"bumpmap_anisotropic_roughconductor"}


def _xml(bsdf: str, turned: bool = False) -> str:
    turn = '<rotate z="1" angle="60"/>' if turned else ""
    return _MAP_XML.format(bsdf=bsdf, turn=turn)


def _write_maps(folder) -> None:
    """normal.png (a raw normal map of sinusoidal bumps), height.png (the same bumps as an
    sRGB height field) and albedo.png (colour stripes), small 8-bit images."""
    from PIL import Image

    n = 64
    u = (np.arange(n) + 0.5) / n
    uu, vv = np.meshgrid(u, u)
    k = 2 * math.pi * 3
    h = np.sin(k * uu) * np.sin(k * vv)
    dhdu = k * np.cos(k * uu) * np.sin(k * vv)
    dhdv = k * np.sin(k * uu) * np.cos(k * vv)
    nrm = np.stack([-0.04 * dhdu, -0.04 * dhdv, np.ones_like(h)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    img = np.round((nrm + 1) / 2 * 255).astype(np.uint8)
    Image.fromarray(img).save(folder / "normal.png")
    Image.fromarray(np.round((0.5 + 0.5 * h) * 255).astype(np.uint8)).save(folder / "height.png")
    stripes = np.zeros((8, 8, 3), np.uint8)
    stripes[:, :4] = (200, 120, 60)
    stripes[:, 4:] = (60, 140, 200)
    Image.fromarray(stripes).save(folder / "albedo.png")


@pytest.mark.parametrize("name", list(PEER_MAPS))
def test_peer_mitsuba_bumpy_floor(tmp_path, name):
    """A floor with a normal or bump map under a square light: icbtool's render against
    Mitsuba 3's at equal spp (mean bias < 2 % per channel, blurred relative RMSE under
    max(5 %, twice Mitsuba's own seed-to-seed figure))."""
    _write_maps(tmp_path)
    xml = tmp_path / f"{name}.xml"
    xml.write_text(_xml(PEER_MAPS[name], name in TURNED))
    bias, rmse, own = peer_compare_file(xml, spp=64, max_depth=8)
    assert np.all(np.abs(bias) < 0.02), (name, bias)
    assert rmse < max(0.05, 2 * own), (name, rmse, own)


def test_face_tangents_known_answer_and_same_bits_in_chunks(monkeypatch):
    """dp/du and dp/dv (Mitsuba's v) of a quad are its edges; every face's tangents lie in its
    plane (degenerate uvs: the normal's coordinate system); chunks change no bit."""
    from icbtool.scene import SceneBuilder
    from icbtool.trace import tracer

    rng = np.random.default_rng(3)
    b = SceneBuilder("tangents")
    flat = sb.Bitmap(np.tile(np.float32([0.5, 0.5, 1.0]), (2, 2, 1)))
    m = b.add_material(Material("m", bsdf=sb.NormalMap(flat, sb.RoughPlastic(alpha=0.2))))
    b.add_quad((0, 0, 0), (2, 0, 0), (0, 0, -3), m)
    uv = rng.uniform(-2, 2, (600, 2))
    uv[:30] = uv[0]  # ten faces with degenerate uvs
    b.add_mesh(rng.normal(size=(600, 3)), np.arange(600).reshape(200, 3), m, uvs=uv)
    scene = b.build()
    face_uv = scene.uvs[scene.faces]
    whole = tracer._general_data(scene, face_uv)
    monkeypatch.setattr(tracer, "TANGENT_CHUNK", 7)
    parts = tracer._general_data(scene, face_uv)
    np.testing.assert_array_equal(parts.face_t, whole.face_t)
    np.testing.assert_array_equal(parts.face_b, whole.face_b)
    np.testing.assert_allclose(whole.face_t[:2], [[2, 0, 0]] * 2, atol=1e-6)
    np.testing.assert_allclose(whole.face_b[:2], [[0, 0, 3]] * 2, atol=1e-6)
    n = scene.face_normals
    scale = np.linalg.norm(whole.face_t, axis=1) * np.linalg.norm(whole.face_b, axis=1)
    assert scale.min() > 0
    for x in (whole.face_t, whole.face_b):
        cos = np.abs((x * n).sum(1)) / np.linalg.norm(x, axis=1)
        assert cos.max() < 1e-4
