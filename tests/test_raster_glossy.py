"""The client's direct light on glossy materials (icbtool.raster.glossy, resolve.frag's GLOSSY).

Known answers are written here from the formulas (Walter et al.'s GGX D and Smith G1, the
conductor Fresnel at normal incidence), independently of the shader; the Cornell box with glossy
materials is compared with the tracer's direct light (the peer that evaluates the same BSDFs).
Tolerances: float32 buffers against closed forms 1e-4 relative (as tests/test_raster.py); the
raster against the tracer, see the test.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import icbtool as icb
from icbtool.raster import RasterConfig, Rasterizer
from icbtool.scene import PointLight, SceneBuilder
from icbtool.scene.bsdf import CONDUCTOR_ETA_K, RoughConductor, RoughPlastic

pytestmark = pytest.mark.gl


def _cfg(**kw) -> RasterConfig:
    return RasterConfig(backend="auto", **kw)


def _plane(bsdf, light: PointLight):
    b = SceneBuilder("glossy_plane")
    m = b.material("plane", albedo=(0.5, 0.5, 0.5), bsdf=bsdf)
    b.add_quad((-5, 0, 5), (10, 0, 0), (0, 0, -10), m)
    b.lights.append(light)
    return b.build()


def _ggx_d(a: float, cos_m: np.ndarray) -> np.ndarray:
    c2 = cos_m * cos_m
    return a * a / (np.pi * (c2 * (a * a - 1.0) + 1.0) ** 2)


def _ggx_g1(a: float, cos_v: np.ndarray) -> np.ndarray:
    tan2 = (1.0 - cos_v**2) / cos_v**2
    return 2.0 / (1.0 + np.sqrt(1.0 + a * a * tan2))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_ggx_highlight_of_a_point_light_on_a_plane_is_the_formula():
    """A perfect-mirror GGX conductor (material "none": F = 1), alpha 0.3, a point light and an
    oblique camera: the DL at the mirror pixel and at off-peak pixels (the highlight's flank and
    its tail) is I / r^2 D(h) G1(wi) G1(wo) / (4 cos_i), from the pixels' own positions."""
    a = 0.3
    light = PointLight((0.6, 1.0, 0.0), (5.0, 4.0, 3.0))
    scene = _plane(RoughConductor(material="none", distribution="ggx", alpha_u=a, alpha_v=a), light)
    cam = icb.Camera.look_at(
        (-0.6, 1.0, 0.0), (0, 0, 0), (0, 1, 0), fov_y_deg=70, height=48, width=48
    )
    with Rasterizer(scene, _cfg()) as r:
        buf = r.render(cam, ("dl", "position"))
    p = buf.position.astype(np.float64)
    wi = _unit(cam.position - p)
    d = light.position - p
    wo = _unit(d)
    h = _unit(wi + wo)
    expect = (
        light.intensity
        / (d**2).sum(-1, keepdims=True)
        * (
            _ggx_d(a, h[..., 1])
            * _ggx_g1(a, wi[..., 1])
            * _ggx_g1(a, wo[..., 1])
            / (4 * wi[..., 1])
        )[..., None]
    )
    on = buf.mask[..., 0] > 0
    peak = np.unravel_index(np.argmax(np.where(on, expect[..., 0], 0)), on.shape)
    # the mirror point of the light seen from the camera is (0, 0, 0): the peak is near it (1 / r^2
    # and G move it a little towards the light)
    assert np.linalg.norm(p[peak]) < 0.1, p[peak]
    y, x = peak
    pixels = [peak, (y, x + 4), (y + 6, x), (y - 10, x + 3), (min(y + 20, 47), x - 12)]
    for px in pixels:
        np.testing.assert_allclose(buf.dl[px], expect[px], rtol=1e-4, err_msg=str(px))
    # the flank and the tail are well below the peak: these are off-peak pixels
    assert expect[pixels[-1]][0] < 0.5 * expect[peak][0]
    np.testing.assert_allclose(buf.dl[on], expect[on], rtol=1e-4)


def test_conductor_fresnel_at_normal_incidence():
    """Gold, camera and point light straight above the plane: at the centre pixel h = n, so the
    value is I / r^2 F(0) D(n) / 4 with F(0) = ((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2) per
    channel and D(n) = 1 / (pi alpha^2) (GGX; G1 = 1 at normal incidence)."""
    a = 0.2
    light = PointLight((0.0, 2.0, 0.0), (3.0, 3.0, 3.0))
    scene = _plane(RoughConductor(material="Au", distribution="ggx", alpha_u=a, alpha_v=a), light)
    cam = icb.Camera.look_at((0, 2.0, 0), (0, 0, 0), (0, 0, -1), fov_y_deg=60, height=33, width=33)
    with Rasterizer(scene, _cfg()) as r:
        dl = r.render(cam, "dl").dl
    eta, k = (np.asarray(x) for x in CONDUCTOR_ETA_K["Au"])
    f0 = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
    expect = 3.0 / 4.0 * f0 / (np.pi * a * a) / 4.0
    np.testing.assert_allclose(dl[16, 16], expect, rtol=1e-4)
    assert dl[16, 16, 0] > 1.5 * dl[16, 16, 2]  # gold: red over blue


def test_lambertian_scenes_keep_the_lambert_shader():
    """Without a glossy material no BSDF table is uploaded (the Lambert path is unchanged), and a
    plastic's Lambert stand-in differs from its BSDF."""
    light = PointLight((0.3, 1.0, 0.2), (2.0, 2.0, 2.0))
    cam = icb.Camera.look_at((0, 2.0, 0), (0, 0, 0), (0, 0, -1), fov_y_deg=60, height=16, width=16)
    lam = _plane(None, light)
    plastic = _plane(RoughPlastic(distribution="beckmann", alpha=0.1), light)
    with Rasterizer(lam, _cfg()) as r:
        assert r._bsdf_tex is None
        a = r.render(cam, "dl").dl
    with Rasterizer(plastic, _cfg()) as r:
        assert r._bsdf_tex is not None
        b = r.render(cam, "dl").dl
    assert np.abs(a - b).max() > 0.05 * a.max()


def test_glossy_cornell_box_matches_the_tracers_direct_light():
    """cornell_box_glossy at 32^2 from its camera, against the tracer's direct light (512 spp,
    box-filtered pixels): over the interior pixels where the BSDF matters (the raster's glossy
    DL and its Lambert stand-in differ by > 1 %; not the light seen) the bias per channel is
    within 2 %, and in the highlights (the brightest fifth of them) within 2 % too, where the
    Lambert-only raster is off by more than 5 %. The tolerance: the area light's glossy
    integral is an 8 x 8 midpoint rule times the light's visibility fraction (exact when fully
    lit), plus the tracer's noise over these ~200 pixels (< 0.5 %). Measured: +0.3 % over the
    glossy pixels and +0.6 % in the highlights; Lambert-only +3.9 % and -7.4 %."""
    from scipy.ndimage import binary_dilation

    from icbtool.raster.accuracy import interior_pixels
    from icbtool.trace import TraceConfig, render

    n = 32
    scene = icb.scene.PROCEDURAL["cornell_box_glossy"](n, n)
    cam = scene.default_camera
    ref = render(scene, cam, TraceConfig(spp=512, max_depth=2, seed=3)).direct
    lambert = dataclasses.replace(
        scene, materials=[dataclasses.replace(m, bsdf=None) for m in scene.materials]
    )
    with Rasterizer(scene, _cfg()) as r:
        dl = r.render(cam, "dl").dl
        fine = r.render(cam.resized(4 * n, 4 * n), ("normal_world", "position"))
    with Rasterizer(lambert, _cfg()) as r:
        dl_lambert = r.render(cam, "dl").dl
    seen_light = binary_dilation(dl.mean(-1) > 5.0, iterations=2)
    diff = np.abs(dl - dl_lambert).mean(-1)
    glossy = interior_pixels(fine, 4) & ~seen_light & (diff > 0.01 * dl_lambert.mean(-1) + 1e-4)
    assert glossy.sum() > 150, glossy.sum()
    top = glossy & (dl.mean(-1) > np.percentile(dl[glossy].mean(-1), 80))

    def bias(img: np.ndarray, sel: np.ndarray) -> np.ndarray:
        return img[sel].astype(np.float64).sum(0) / ref[sel].astype(np.float64).sum(0) - 1.0

    assert np.all(np.abs(bias(dl, glossy)) <= 0.02), bias(dl, glossy)
    assert np.all(np.abs(bias(dl, top)) <= 0.02), bias(dl, top)
    assert np.all(np.abs(bias(dl_lambert, top)) > 0.05), bias(dl_lambert, top)


def test_glossy_cornell_box_scene():
    """The built-in scene: three glossy materials (rough plastic, rough gold, smooth-ish
    plastic at alpha 0.1) and the Cornell box's paths."""
    scene = icb.scene.PROCEDURAL["cornell_box_glossy"](16, 16)
    kinds = sorted(type(m.bsdf).__name__ for m in scene.materials if m.bsdf is not None)
    assert kinds == ["RoughConductor", "RoughPlastic", "RoughPlastic"]
    assert (
        min(float(m.bsdf.alpha) for m in scene.materials if isinstance(m.bsdf, RoughPlastic)) == 0.1
    )
    assert set(scene.paths) == {"train", "test"}
