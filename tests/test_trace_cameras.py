"""Thin-lens and orthographic cameras: Mitsuba 3's ``thinlens`` and ``orthographic`` sensors.

Known answers (the rays Mitsuba's own sensors cast, the thin-lens circle of confusion, the
aperture's uniform disk) and peer renders against Mitsuba 3 (Lambert and general kernels).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np
import pytest

from icbtool.camera import Camera
from icbtool.scene import SceneBuilder, SceneError, load
from tests.test_trace_bsdf import PEER_BSDFS, peer_compare_file


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - the install puts it there
        pytest.fail(f"Mitsuba 3 is the tracer's peer, installed by `make install` ({e})")
    mi.set_variant("scalar_rgb")
    return mi


def _sensor_xml(kind, extra="", to_world="", film=(48, 36), crop=None, body=""):
    w, h = film
    film_xml = f'<integer name="width" value="{w}"/><integer name="height" value="{h}"/>'
    if crop is not None:
        film_xml += "".join(
            f'<integer name="crop_{k}" value="{v}"/>'
            for k, v in zip(("offset_x", "offset_y", "width", "height"), crop)
        )
    body = body or '<shape type="cube"/>'
    return (
        f'<scene version="3.0.0"><sensor type="{kind}">{extra}<transform name="to_world">'
        f'{to_world}<lookat origin="0.3, 0.2, 4" target="0, 0, 0" up="0, 1, 0"/></transform>'
        f'<film type="hdrfilm">{film_xml}<rfilter type="box"/></film></sensor>{body}</scene>'
    )


def _load(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load(path)
    return scene, [str(w.message) for w in caught]


# --------------------------------------------------------------- the rays of Mitsuba's sensors
@pytest.mark.parametrize(
    "kind, extra, to_world, crop",
    [
        (
            "thinlens",
            '<float name="aperture_radius" value="0.2"/><float name="focus_distance" value="3.5"/>'
            '<float name="fov" value="40"/>',
            "",
            None,
        ),
        (
            "thinlens",
            '<float name="aperture_radius" value="0.05"/><string name="focal_length" value="35mm"/>'
            '<float name="near_clip" value="0.5"/>',
            "",
            (6, 4, 30, 20),
        ),
        ("orthographic", "", '<scale x="1.5" y="0.75" z="2"/>', None),
        (
            "orthographic",
            '<float name="near_clip" value="0.3"/>',
            '<scale value="2"/>',
            (8, 2, 32, 30),
        ),
        ("perspective", '<float name="near_clip" value="0.7"/>', "", (4, 4, 40, 28)),
    ],
)
def test_camera_rays_equal_mitsubas_sensor(tmp_path, kind, extra, to_world, crop):
    """Every (image point, lens sample) casts Mitsuba's ray: same origin (aperture point, near
    clip, orthographic extent = the to_world scale, crop) and direction (focus plane)."""
    mi = _mitsuba()
    path = tmp_path / "c.xml"
    path.write_text(_sensor_xml(kind, extra, to_world, crop=crop))
    scene, msgs = _load(path)
    cam = scene.default_camera
    if kind != "perspective":
        assert sum(f"{kind} sensor" in m for m in msgs) == 1, msgs
    sensor = mi.load_file(str(path)).sensors()[0]
    rng = np.random.default_rng(0)
    for pos, lens in zip(rng.random((12, 2)), rng.random((12, 2))):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.ScalarPoint2f(*pos), mi.ScalarPoint2f(*lens))
        o, d = cam.sample_rays(pos * [cam.width, cam.height], lens)
        np.testing.assert_allclose(o, np.array(ray.o), atol=2e-5)
        np.testing.assert_allclose(d, np.array(ray.d), atol=2e-6)


def test_sensor_errors_name_the_line(tmp_path):
    bad = {
        '<float name="aperture_radius" value="-0.1"/>': "aperture_radius must be >= 0",
        '<float name="aperture_radius" value="0.1"/><float name="focus_distance" value="0"/>': (
            "focus_distance must be > 0"
        ),
        "": "needs 'aperture_radius'",
        '<float name="aperture_radius" value="0.1"/><float name="near_clip" value="0"/>': (
            "near_clip must be > 0"
        ),
    }
    for extra, why in bad.items():
        path = tmp_path / "c.xml"
        path.write_text(_sensor_xml("thinlens", extra))
        with pytest.raises(SceneError, match=f"c.xml:1: .*{why}"):
            _load(path)
    with pytest.raises(ValueError, match="aperture_radius must be >= 0"):
        Camera(8, 8, 10, 10, 4, 4, aperture_radius=-1)
    with pytest.raises(ValueError, match="orthographic Camera has no lens"):
        Camera(8, 8, 10, 10, 4, 4, projection="orthographic", aperture_radius=0.1)


def test_pipeline_gets_the_pinhole_and_dicts_round_trip():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), height=30, width=40)
    lens = replace(cam, aperture_radius=0.1, focus_distance=4.0, near_clip=0.01)
    assert lens.pinhole() == cam and cam.pinhole() is cam
    assert Camera.from_dict(lens.to_dict()) == lens and set(cam.to_dict()) == {
        "height", "width", "fx", "fy", "cx", "cy", "world_from_cam"
    }  # fmt: skip
    ortho = replace(cam, projection="orthographic", fx=10.0, fy=10.0, near_clip=0.5)
    assert Camera.from_dict(ortho.to_dict()) == ortho
    with pytest.raises(ValueError, match="orthographic camera has no pinhole intrinsics"):
        _ = ortho.K
    # the pinhole sees the orthographic camera's near plane at the same pixels
    p = np.array([[0.7, -0.4, 5.0 - 0.5]])  # on the near plane (the camera looks down -z)
    np.testing.assert_allclose(ortho.pinhole().project(p)[0], ortho.project(p)[0], atol=1e-9)
    np.testing.assert_allclose(ortho.project(p)[0], [[20 + 7, 15 + 4]], atol=1e-9)


# ------------------------------------------------------------------ the tracer's camera rays
@pytest.mark.parametrize("sampler", ["independent", "sobol", "zsobol"])
def test_traced_lens_rays_fill_the_aperture_uniformly(sampler):
    """The kernel's camera rays (ray log): start on the near plane, come from the aperture disk
    (uniform: E|a|^2 = r^2 / 2), aim at the focus plane inside the image, and the aperture
    point is uncorrelated with the position in the pixel."""
    from icbtool.trace import TraceConfig, ray_log_buffers, render

    b = SceneBuilder("wall")
    b.add_quad((-5, -5, -3), (10, 0, 0), (0, 10, 0), b.material("grey", albedo=(0.5,) * 3))
    scene = b.build()
    r, fd, near = 0.3, 2.5, 0.05
    cam = replace(
        Camera.look_at((0.2, 0.1, 2), (0, 0, 0), height=24, width=32),
        aperture_radius=r,
        focus_distance=fd,
        near_clip=near,
    )
    log = ray_log_buffers(4000)
    render(scene, cam, TraceConfig(spp=8, max_depth=1, sampler=sampler, seed=5), ray_log=log)
    cam_rays = log["kind"][: int(log["n"][0])] == 0
    o = log["o"][: len(cam_rays)][cam_rays].astype(np.float64)
    d = log["d"][: len(cam_rays)][cam_rays].astype(np.float64)
    assert len(o) > 2000
    m = cam.cam_from_world
    oc = o @ m[:3, :3].T + m[:3, 3]
    dc = d @ m[:3, :3].T
    np.testing.assert_allclose(oc[:, 2], near, atol=1e-6)
    a = oc - dc * (near / dc[:, 2])[:, None]  # back to the lens plane z = 0
    rho2 = (a[:, 0] ** 2 + a[:, 1] ** 2) / r**2
    assert rho2.max() <= 1 + 1e-4
    assert abs(rho2.mean() - 0.5) < 4 * math.sqrt(1 / 12 / len(a)) + 1e-3
    f = a + dc * (fd / dc[:, 2])[:, None]  # the focus point
    u = cam.fx * f[:, 0] / fd + cam.cx
    v = cam.fy * f[:, 1] / fd + cam.cy
    assert u.min() >= -1e-3 and u.max() <= cam.width + 1e-3
    assert v.min() >= -1e-3 and v.max() <= cam.height + 1e-3
    for lens_axis, jitter in ((a[:, 0], u % 1.0), (a[:, 1], v % 1.0), (a[:, 0], v % 1.0)):
        assert abs(np.corrcoef(lens_axis, jitter)[0, 1]) < 4 / math.sqrt(len(a))


def test_out_of_focus_point_blurs_to_the_thin_lens_circle_of_confusion():
    """A small emissive square out of focus images as itself convolved with the thin lens's
    blur disk and the pixel's box: the image's second moment along x is a^2 / 12 + D^2 / 16 +
    1 / 12 (square of side a pixels, disk of diameter D = 2 r fx |z - f| / (f z) pixels)."""
    from icbtool.trace import TraceConfig, render

    b = SceneBuilder("dot")
    lamp = b.material("lamp", albedo=(0.0,) * 3, emission=(1.0,) * 3)
    s, z = 0.04, 1.5  # side and depth of the square
    b.add_quad((-s / 2, -s / 2, -z), (s, 0, 0), (0, s, 0), lamp)
    scene = b.build()
    base = Camera.look_at((0, 0, 0), (0, 0, -1), height=48, width=48, fov_y_deg=30.0)
    for fd, radius in ((4.0, 0.1), (0.8, 0.08)):
        cam = replace(base, aperture_radius=radius, focus_distance=fd)
        img = render(scene, cam, TraceConfig(spp=256, max_depth=1, seed=2)).direct[..., 0]
        coc = float(cam.circle_of_confusion(z))
        assert coc == pytest.approx(2 * radius * cam.fx * abs(z - fd) / (fd * z))
        side = s * cam.fx / z
        xs = np.arange(cam.width) + 0.5 - cam.cx
        wx = img.sum(0)
        var_x = float((wx * xs**2).sum() / wx.sum())
        assert var_x == pytest.approx(side**2 / 12 + coc**2 / 16 + 1 / 12, rel=0.06), (fd, coc)
    # in focus, the same square stays as sharp as a pinhole's
    sharp = render(
        scene, replace(base, aperture_radius=0.05, focus_distance=z), TraceConfig(spp=64, seed=2)
    ).direct[..., 0]
    wx = sharp.sum(0)
    assert float((wx * xs**2).sum() / wx.sum()) == pytest.approx(side**2 / 12 + 1 / 12, abs=0.15)


# ------------------------------------------------------------------ peer renders (Mitsuba 3)
_BODY = """
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <emitter type="constant"><rgb name="radiance" value="0.9, 0.9, 1.0"/></emitter>
  <shape type="rectangle">
    <transform name="to_world"><scale value="3"/><translate z="-2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.08, 0.08, 0.08"/></bsdf>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.5"/><translate x="-0.6" y="0.1"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.15, 0.1"/></bsdf>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.2"/><translate x="0.5" y="-0.3" z="2.3"/>
    </transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.1, 0.3, 0.8"/></bsdf>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.08"/><translate x="0.3" y="0.35" z="1.0"/>
    </transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.9, 0.9, 0.2"/></bsdf>
  </shape>
  {extra}
"""
#: A thin lens focused on the red square; on this scene the same comparison fails by far when
#: the lens is rendered as its pinhole (blurred RMSE 0.24) or with 0.8 times its radius (0.067).
_THINLENS = (
    '<float name="fov" value="40"/><float name="aperture_radius" value="0.3"/>'
    '<float name="focus_distance" value="4.0"/>'
)


def _peer(tmp_path, name, kind, sensor, to_world="", extra=""):
    xml = tmp_path / f"{name}.xml"
    xml.write_text(_sensor_xml(kind, sensor, to_world, body=_BODY.format(extra=extra)))
    bias, rmse, own = peer_compare_file(xml, spp=64, max_depth=3)
    assert np.all(np.abs(bias) < 0.02), (name, bias)
    assert rmse < max(0.05, 2 * own), (name, rmse, own)


def test_peer_thinlens_in_and_out_of_focus(tmp_path):
    """The red square is in focus (depth 4); the blue one, 2.3 units nearer, blurs to a disk of
    about 13 pixels, the yellow one (3 units nearer) to about 30, the dark wall behind to 3."""
    _peer(tmp_path, "thinlens", "thinlens", _THINLENS)


def test_peer_orthographic_with_a_scaled_to_world(tmp_path):
    _peer(tmp_path, "ortho", "orthographic", "", '<scale x="1.6" y="1.6" z="1"/>')


def test_peer_thinlens_general_kernel(tmp_path):
    """A rough plastic sphere (the general BSDF kernel) seen through the thin lens."""
    sphere = (
        '<shape type="sphere"><float name="radius" value="0.35"/><point name="center" '
        f'x="0.1" y="0.4" z="1.2"/>{PEER_BSDFS["roughplastic"]}</shape>'
    )
    _peer(tmp_path, "thinlens_general", "thinlens", _THINLENS, extra=sphere)


def test_trace_skips_edge_samples_for_a_thin_lens_and_warns_nothing_else():
    from icbtool.trace import TraceConfig, render

    b = SceneBuilder("lamp")
    b.add_quad((-0.2, -0.2, -2), (0.4, 0, 0), (0, 0.4, 0), b.material("l", emission=(1,) * 3))
    scene = b.build()
    cam = replace(Camera.look_at((0, 0, 0), (0, 0, -1), height=16, width=16), aperture_radius=0.1)
    st = render(scene, cam, TraceConfig(spp=2)).stats
    assert any("edge samples: a thin lens" in s for s in st.skipped)
