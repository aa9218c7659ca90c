"""Mitsuba 3's BSDFs in the tracer: known answers, sampling/evaluation consistency, and a peer
suite against Mitsuba 3 itself on small material-preview scenes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from icbtool.scene import Material
from icbtool.scene import bsdf as sb

BSDFS = {
    "diffuse": sb.Diffuse((0.2, 0.5, 0.8)),
    "plastic": sb.Plastic(diffuse_reflectance=(0.6, 0.2, 0.1)),
    "plastic_nonlinear": sb.Plastic(diffuse_reflectance=(0.6, 0.2, 0.1), nonlinear=True),
    "roughplastic": sb.RoughPlastic(diffuse_reflectance=(0.1, 0.3, 0.6), alpha=0.2),
    "roughplastic_ggx": sb.RoughPlastic(distribution="ggx", alpha=0.3),
    "conductor_au": sb.Conductor(material="Au"),
    "roughconductor_cu": sb.RoughConductor(material="Cu", alpha_u=0.2, alpha_v=0.2),
    "roughconductor_aniso": sb.RoughConductor(distribution="ggx", alpha_u=0.15, alpha_v=0.4),
    "dielectric": sb.Dielectric(),
    "thindielectric": sb.ThinDielectric(),
    "roughdielectric": sb.RoughDielectric(distribution="ggx", alpha_u=0.2, alpha_v=0.2),
    "blend": sb.BlendBSDF(sb.Diffuse(0.8), sb.RoughConductor(alpha_u=0.2, alpha_v=0.2), 0.3),
    "twosided": sb.TwoSided(sb.RoughPlastic(alpha=0.1)),
}


def test_conductor_table_equals_mitsubas_rgb_values():
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is the tracer's peer (make install)")
    mi.set_variant("scalar_rgb")
    for name in ("Au", "Cu", "Ag", "Al", "Cr", "none"):
        p = mi.traverse(mi.load_dict({"type": "conductor", "material": name}))
        eta, k = sb.CONDUCTOR_ETA_K[name]
        np.testing.assert_allclose(np.resize(np.array(p["eta.value"]), 3), eta, rtol=1e-6)
        np.testing.assert_allclose(np.resize(np.array(p["k.value"]), 3), k, rtol=1e-6)


def test_named_ior_and_bad_parameters_are_clear_errors():
    assert sb.Plastic().int_ior == sb.NAMED_IOR["polypropylene"]
    assert sb.Dielectric().eta == pytest.approx(1.5046 / 1.000277)
    with pytest.raises(ValueError, match="unknown IOR name 'unobtainium'"):
        sb.Dielectric(int_ior="unobtainium")
    with pytest.raises(ValueError, match="unknown material 'Xx'"):
        sb.Conductor(material="Xx")
    with pytest.raises(ValueError, match="distribution"):
        sb.RoughConductor(distribution="phong")
    with pytest.raises(ValueError, match="bsdf must be"):
        Material("m", bsdf="plastic")


def test_fresnel_at_normal_incidence_and_total_internal_reflection():
    from icbtool.trace import bsdfs as bs

    for eta in (1.33, 1.5, 2.4):
        f0 = ((eta - 1) / (eta + 1)) ** 2
        assert bs.fresnel(1.0, eta)[0] == pytest.approx(f0, rel=1e-12)
        assert sb.fresnel_dielectric(1.0, eta) == pytest.approx(f0, rel=1e-12)
        assert bs.fresnel(-0.1, eta)[0] == 1.0  # inside, beyond the critical angle
    # a conductor with k = 0 is a dielectric; eta 0, k 1 ("none") reflects everything
    assert bs.fresnel_conductor(0.7, 1.5, 0.0) == pytest.approx(bs.fresnel(0.7, 1.5)[0])
    assert bs.fresnel_conductor(0.3, 0.0, 1.0) == pytest.approx(1.0)


def test_microfacet_sampling_is_mitsubas_visible_normal_sampling():
    """Beckmann normals equal Mitsuba 3's ``sample_visible`` draws sample for sample (the same
    inversion), and both distributions' densities equal Mitsuba's ``pdf`` (GGX is drawn by a
    different mapping of the same distribution)."""
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is the tracer's peer (make install)")
    from icbtool.trace import bsdfs as bs

    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(1)
    for kind, ggx in ((mi.MicrofacetType.Beckmann, False), (mi.MicrofacetType.GGX, True)):
        for au, av in ((0.3, 0.3), (0.1, 0.5)):
            d = mi.MicrofacetDistribution(kind, au, av, True)
            for _ in range(100):
                ct = rng.uniform(0.05, 1.0)
                ph = rng.uniform(0, 2 * math.pi)
                st = math.sqrt(1 - ct * ct)
                wi = (st * math.cos(ph), st * math.sin(ph), ct)
                u = rng.random(2)
                mx, my, mz, pdf = bs.mf_sample(ggx, au, av, *wi, *u)
                if not ggx:
                    m_ref, _ = d.sample(mi.Vector3f(wi), mi.Point2f(u))
                    np.testing.assert_allclose([mx, my, mz], np.array(m_ref), atol=1e-5)
                ref = float(d.pdf(mi.Vector3f(wi), mi.Vector3f(mx, my, mz)))
                assert pdf == pytest.approx(ref, rel=1e-3), (kind, au, av, wi, u)
    assert bs.erfinv(0.5) == pytest.approx(0.4769362762044699, rel=1e-14)
    assert bs.erfinv(-(1 - 1e-12)) == pytest.approx(-5.042031898572696, rel=1e-10)


def _batch(name, wi_z, n=200_000, seed=0):
    from icbtool.trace import bsdfs as bs

    t = bs.pack([Material("m", bsdf=BSDFS[name])])
    rng = np.random.default_rng(seed)
    roots = np.zeros(n, np.int64)
    uv = rng.random((n, 2))
    wi = np.tile([math.sqrt(1 - wi_z**2), 0.0, wi_z], (n, 1))
    wo, w = np.zeros((n, 3)), np.zeros((n, 3))
    pdf, fl = np.zeros(n), np.zeros(n, np.int64)
    bs.sample_batch(t.params, roots, uv, wi, rng.random((n, 3)), wo, w, pdf, fl)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ev = np.zeros((n, 4))
    bs.eval_batch(t.params, roots, uv, wi, d, ev)
    at = np.zeros((n, 4))
    bs.eval_batch(t.params, roots, uv, wi, wo, at)
    return w, pdf, fl, ev, at


@pytest.mark.parametrize("name", [k for k in BSDFS if "dielectric" not in k or "rough" in k])
@pytest.mark.parametrize("wi_z", [0.9, 0.4])
def test_sampling_weights_average_to_the_evaluated_albedo(name, wi_z):
    """E[weight] of the sampler = the integral of eval over the sphere (non-delta BSDFs; the
    delta lobes of plastic are added back from their Fresnel), and the sampler's density is
    the one pdf() reports."""
    w, pdf, fl, ev, at = _batch(name, wi_z)
    delta = (fl & 2) != 0
    sampled = w[~delta].sum(0) / len(w)
    evaluated = ev[:, :3].mean(0) * 4 * math.pi
    np.testing.assert_allclose(sampled, evaluated, rtol=0.03, atol=3e-3)
    ok = ((fl & 1) != 0) & ~delta
    np.testing.assert_allclose(at[ok, 3], pdf[ok], rtol=1e-9)


def test_smooth_bsdfs_conserve_what_they_do_not_absorb():
    """A white mirror reflects all; a dielectric's reflected + refracted weights (radiance
    scaled by 1 / eta^2 on entering) average to R + (1 - R) / eta^2."""
    from icbtool.trace import bsdfs as bs

    w, _, fl, _, _ = _batch("dielectric", 1.0)
    eta = sb.Dielectric().eta
    r = bs.fresnel(1.0, eta)[0]
    assert w[:, 0].mean() == pytest.approx(r + (1 - r) / eta**2, rel=0.01)
    w, _, _, _, _ = _batch("thindielectric", 0.7)
    assert w[:, 0].mean() == pytest.approx(1.0, abs=1e-12)


# ---------------------------------------------------------------------------------- renders
def _sphere_scene(bsdf, sky=1.0, size=24):
    import trimesh

    from icbtool.camera import Camera
    from icbtool.scene import SceneBuilder, Sky

    b = SceneBuilder("bsdf")
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    m = b.add_material(Material("m", bsdf=bsdf))
    b.add_mesh(np.asarray(s.vertices), np.asarray(s.faces), m)
    b.sky = Sky(kind="uniform", zenith=(sky, sky, sky))
    cam = Camera.look_at((0, 0, 4), (0, 0, 0), (0, 1, 0), fov_y_deg=30, height=size, width=size)
    return b.build(default_camera=cam), cam


def test_smooth_mirror_reflects_a_uniform_sky_exactly():
    from icbtool.trace.tracer import TraceConfig, render

    scene, cam = _sphere_scene(sb.Conductor(), sky=0.7)
    r = render(scene, cam, TraceConfig(spp=4, max_depth=16))
    # the middle of the sphere (at its rim the tessellation's smooth normals send some mirror
    # rays into the sphere, as they would in Mitsuba on the same mesh)
    img = (r.gi + r.direct)[8:16, 8:16]
    np.testing.assert_allclose(img, 0.7, rtol=1e-5)
    assert any("general kernel" in s for s in r.stats.skipped)


def test_white_furnace_rough_dielectric_sphere_conserves_energy():
    """A non-absorbing rough dielectric sphere under a uniform sky: every path leaves it again
    (radiance scaling cancels between entering and leaving), so it looks like the sky."""
    from icbtool.trace.tracer import TraceConfig, render

    scene, cam = _sphere_scene(sb.RoughDielectric(distribution="ggx", alpha_u=0.05, alpha_v=0.05))
    r = render(scene, cam, TraceConfig(spp=64, max_depth=64, rr_depth=64, seed=1))
    img = (r.gi + r.direct)[6:18, 6:18]
    assert img.mean() == pytest.approx(1.0, abs=0.03)


def test_blend_of_a_delta_and_a_rough_bsdf_is_the_mix_of_their_images():
    """On a convex sphere (one bounce on it) the image is linear in the BSDF, so a blendbsdf's
    image is the weighted mix of its two BSDFs' images: here a smooth gold mirror (a delta lobe)
    and GGX rough plastic, under a sky with a bright patch (light sampling and MIS at work).
    Mitsuba 3.7-3.9 renders this blend about 18 % darker: its blendbsdf::sample adds the
    rough lobe's density to the delta lobe's unit "pdf" (docs/mitsuba.md)."""
    from icbtool.scene import Sky
    from icbtool.trace.tracer import TraceConfig, render

    env = np.full((32, 64, 3), 0.3, np.float32)
    env[6:10, 20:26] = 40.0  # a small bright patch above the horizon
    env[16:, :, 1] = 0.05  # a darker, coloured lower half
    rough = sb.RoughPlastic(diffuse_reflectance=0.0, distribution="ggx", alpha=0.3)
    gold = sb.Conductor(material="Au")
    means = {}
    for name, bsdf in (("rough", rough), ("gold", gold), ("blend", sb.BlendBSDF(rough, gold, 0.3))):
        scene, cam = _sphere_scene(bsdf)
        scene = dataclasses.replace(scene, sky=Sky(kind="envmap", envmap=env))
        r = render(scene, cam, TraceConfig(spp=512, max_depth=8, seed=3))
        means[name] = (r.gi + r.direct)[8:16, 8:16].mean((0, 1))
    mix = 0.7 * means["rough"] + 0.3 * means["gold"]
    np.testing.assert_allclose(means["blend"], mix, rtol=0.02)


def test_lambert_scene_keeps_the_lambert_kernel():
    from icbtool.scene import cornell_box, cornell_camera
    from icbtool.trace.tracer import TraceConfig, render

    scene = cornell_box()
    cam = cornell_camera(16, 16)
    r = render(scene, cam, TraceConfig(spp=1))
    assert any("general BSDF kernel: every material is Lambertian" in s for s in r.stats.skipped)


# ---------------------------------------------------------------------------------- peer suite
_PEER_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="16"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="35"/>
    <transform name="to_world">
      <lookat origin="0, 1.2, 4" target="0, 0.1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/>
      <integer name="height" value="{size}"/><rfilter type="box"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.8, 0.85, 0.9"/></emitter>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.8"/><rotate x="1" angle="90"/>
      <translate y="2.5" z="0.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="4, 4, 4"/></emitter>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
      <translate y="-1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.4, 0.4, 0.4"/></bsdf>
  </shape>
  <shape type="sphere">{bsdf}</shape>
</scene>"""

PEER_BSDFS = {
    "roughplastic": '<bsdf type="roughplastic"><rgb name="diffuse_reflectance" '
    'value="0.1, 0.3, 0.6"/><float name="alpha" value="0.2"/></bsdf>',
    "plastic": '<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.6, 0.2, 0.1"/>'
    "</bsdf>",
    "roughconductor": '<bsdf type="roughconductor"><string name="material" value="Au"/>'
    '<string name="distribution" value="ggx"/><float name="alpha" value="0.25"/></bsdf>',
    "conductor": '<bsdf type="conductor"><string name="material" value="Cu"/></bsdf>',
    "dielectric": '<bsdf type="dielectric"/>',
    "roughdielectric": '<bsdf type="roughdielectric"><float name="alpha" value="0.15"/></bsdf>',
    "thindielectric": '<bsdf type="thindielectric"/>',
    "blendbsdf": '<bsdf type="blendbsdf"><float name="weight" value="0.4"/>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.2, 0.2"/></bsdf>'
    '<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></bsdf>',
    "twosided_roughconductor_aniso": '<bsdf type="twosided"><bsdf type="roughconductor">'
    '<string name="material" value="Al"/><float name="alpha_u" value="0.05"/>'
    '<float name="alpha_v" value="0.3"/></bsdf></bsdf>',
    "mask": '<bsdf type="mask"><float name="opacity" value="0.5"/>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.6, 0.2"/></bsdf></bsdf>',
}


def _blur(img, sigma=1.5):
    from scipy.ndimage import gaussian_filter

    return np.stack([gaussian_filter(img[..., c], sigma) for c in range(3)], -1)


def peer_compare(tmp_path, name, size=48, spp=64):
    """(bias (3,), blurred relative RMSE, Mitsuba's own seed-to-seed blurred relative RMSE)."""
    xml = tmp_path / f"{name}.xml"
    xml.write_text(_PEER_XML.format(size=size, bsdf=PEER_BSDFS[name]))
    return peer_compare_file(xml, spp)


def peer_compare_file(xml, spp=64, max_depth=16):
    """:func:`peer_compare` of any scene file: icbtool against Mitsuba 3 (``scalar_rgb``, seeds 1
    and 2) at equal spp and depth."""
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is the tracer's peer (make install)")
    import warnings

    from icbtool.scene import load
    from icbtool.trace.tracer import TraceConfig, render

    mi.set_variant("scalar_rgb")
    ref = [np.array(mi.render(mi.load_file(str(xml)), spp=spp, seed=s))[..., :3] for s in (1, 2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load(xml)
    r = render(scene, scene.default_camera, TraceConfig(spp=spp, max_depth=max_depth, seed=3))
    ours = r.gi + r.direct
    mean_ref = ref[0].reshape(-1, 3).mean(0)
    bias = ours.reshape(-1, 3).mean(0) / mean_ref - 1
    scale = max(float(_blur(ref[0]).mean()), 1e-6)
    rmse = float(np.sqrt(np.mean((_blur(ours) - _blur(ref[0])) ** 2))) / scale
    own = float(np.sqrt(np.mean((_blur(ref[1]) - _blur(ref[0])) ** 2))) / scale
    return bias, rmse, own


@pytest.mark.parametrize("name", list(PEER_BSDFS))
def test_peer_mitsuba_material_preview(tmp_path, name):
    bias, rmse, own = peer_compare(tmp_path, name)
    assert np.all(np.abs(bias) < 0.02), (name, bias)
    assert rmse < max(0.05, 2 * own), (name, rmse, own)


def test_material_preview_light_without_a_bsdf_reflects_nothing_as_in_mitsuba(tmp_path):
    """The material-preview scene's area light has no BSDF: Mitsuba makes it black, so light
    bouncing between the floor and the light's face is not reflected there. At 256 spp the
    mean of the whole image matches Mitsuba's to 0.3 % per channel (a reflecting light, the
    shapes' default diffuse 0.5, made it 0.4-0.8 % too bright)."""
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is the tracer's peer (make install)")
    import warnings

    from icbtool.scene import load
    from icbtool.trace.tracer import TraceConfig, render

    mi.set_variant("scalar_rgb")
    xml = tmp_path / "preview.xml"
    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.3, 0.2"/></bsdf>'
    xml.write_text(_PEER_XML.format(size=32, bsdf=diffuse))
    ref = np.array(mi.render(mi.load_file(str(xml)), spp=512, seed=1))[..., :3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load(xml)
    r = render(scene, scene.default_camera, TraceConfig(spp=256, max_depth=16, seed=3))
    bias = (r.gi + r.direct).reshape(-1, 3).mean(0) / ref.reshape(-1, 3).mean(0) - 1
    assert np.all(np.abs(bias) < 0.003), bias
