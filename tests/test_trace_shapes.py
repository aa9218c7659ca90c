"""Exact emitters in the path tracer: analytic spheres, disks and cylinders, and mesh lights seen
at grazing angles, against known answers (irradiance of a sphere or disk light) and against
Monte Carlo ray casting of the same shapes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from icbtool.camera import Camera
from icbtool.scene import AnalyticShape, Material, Scene, SceneBuilder
from icbtool.trace import TraceConfig, render

ALBEDO = 0.5
RADIANCE = 4.0


def _similarity(center, scale, rot=None) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = (np.eye(3) if rot is None else np.asarray(rot)) * scale
    m[:3, 3] = center
    return m


def _uv_sphere(seg: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit UV sphere (outward faces)."""
    th = np.linspace(0, np.pi, seg // 2 + 1)
    ph = np.linspace(0, 2 * np.pi, seg + 1)
    t, p = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    w = seg + 1
    f = []
    for i in range(seg // 2):
        for j in range(seg):
            a, b, c, d = i * w + j, (i + 1) * w + j, (i + 1) * w + j + 1, i * w + j + 1
            if i > 0:
                f.append([a, d, b])
            if i < seg // 2 - 1:
                f.append([d, c, b])
    return v, np.array(f)


def _floor_scene(light: str, d: float, r: float, exact: bool = True) -> Scene:
    """A large grey floor (y = 0, facing +y) under one light: a sphere of radius r centred at
    height d, or a disk of radius r at height d facing down; ``exact``: as an AnalyticShape
    (else its tessellation alone, a mesh light)."""
    b = SceneBuilder(f"{light}-over-floor")
    floor = b.material("floor", albedo=(ALBEDO,) * 3)
    b.add_quad((-50, 0, 50), (100, 0, 0), (0, 0, -100), floor)
    em = b.material("light", albedo=(0.0,) * 3, emission=(RADIANCE,) * 3)
    if light == "sphere":
        v, f = _uv_sphere(48)
        m = _similarity((0, d, 0), r)
        b.add_mesh(v * r + (0, d, 0), f, em)
    else:  # a disk facing -y: local z -> world -y
        rot = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
        m = _similarity((0, d, 0), r, rot)
        t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        ring = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1) @ m[:3, :3].T + (0, d, 0)
        v = np.vstack([[0, d, 0], ring])
        f = np.array([[0, 1 + i, 1 + (i + 1) % 64] for i in range(64)])
        b.add_mesh(v, f, em)
    scene = b.build()
    if not exact:
        return scene
    n = len(scene.faces)
    shape = AnalyticShape(light, m, len(scene.materials) - 1, (2, n), name=light)
    return dataclasses.replace(scene, shapes=[shape])


def _floor_radiance(scene: Scene, spp: int = 1024, seed: int = 0) -> float:
    """Traced radiance (direct + gi, red) of the floor point (0, 0, 0), seen at a grazing angle
    from beside the light (one pixel, its centre), with paths of two segments (direct light)."""
    cam = Camera.look_at((4.0, 0.02, 0.0), (0, 0, 0), up=(0, 1, 0), fov_y_deg=1.0,
                         height=1, width=1)  # fmt: skip
    cfg = TraceConfig(spp=spp, max_depth=2, pixel_jitter=False, seed=seed, spp_per_pass=spp)
    res = render(scene, cam, cfg)
    return float(res.direct[0, 0, 0] + res.gi[0, 0, 0])


@pytest.mark.parametrize("d", [1.05, 1.6, 4.0])
def test_sphere_light_irradiance_is_exact_at_every_distance(d):
    """A sphere light of radius r at height d over a Lambertian floor: the irradiance below it
    is pi L (r / d)^2 (the sphere wholly above the horizon), so the floor's radiance there is
    albedo L (r / d)^2; the traced direct light matches within 0.5 %, close up too."""
    got = _floor_radiance(_floor_scene("sphere", d, 1.0))
    want = ALBEDO * RADIANCE / d**2
    assert got == pytest.approx(want, rel=5e-3)


@pytest.mark.parametrize("d", [0.25, 1.0, 3.0])
def test_disk_light_on_axis_irradiance_is_exact(d):
    """A disk light of radius r facing the floor from height d: on its axis the irradiance is
    pi L r^2 / (r^2 + d^2)."""
    got = _floor_radiance(_floor_scene("disk", d, 1.0))
    want = ALBEDO * RADIANCE / (1.0 + d * d)
    assert got == pytest.approx(want, rel=5e-3)


def _polygon_irradiance(scene: Scene, p: np.ndarray, normal: np.ndarray) -> float:
    """Exact integral of cos over the solid angle of the emissive faces facing p (Lambert's
    polygon formula; the faces of a convex mesh do not hide each other)."""
    tri = scene.vertices[scene.faces[scene.emissive_faces]].astype(np.float64) - p
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tri = tri[np.einsum("ij,ij->i", n, tri[:, 0]) < 0]
    u = tri / np.linalg.norm(tri, axis=2, keepdims=True)
    total = 0.0
    for k in range(3):
        a, b = u[:, k], u[:, (k + 1) % 3]
        c = np.cross(a, b)
        s = np.linalg.norm(c, axis=1)
        total += float((np.arctan2(s, np.einsum("ij,ij->i", a, b)) * (c @ normal) / s).sum())
    return 0.5 * abs(total)


@pytest.mark.parametrize("d", [1.05, 1.6])
def test_a_mesh_light_seen_at_grazing_angles_is_not_hidden_by_itself(d):
    """A tessellated sphere light (emissive triangles, no analytic shape) over a floor: its rim
    is seen at grazing angles, where shadow rays aimed along the unoffset direction met the
    light's own plane before the sampled point (10-18 % of the light lost). The traced
    radiance equals the exact polygon irradiance of the mesh (Lambert's formula) within 0.5 %."""
    scene = _floor_scene("sphere", d, 1.0, exact=False)
    want = (
        ALBEDO / math.pi * RADIANCE * _polygon_irradiance(scene, np.zeros(3), np.array([0, 1, 0]))
    )
    assert _floor_radiance(scene) == pytest.approx(want, rel=5e-3)


# ----------------------------------------------------------------------------- hooks, directly
def _shape(kind: str) -> AnalyticShape:
    rot = np.linalg.qr(np.array([[0.3, -0.5, 0.8], [0.9, 0.1, -0.2], [0.1, 0.8, 0.5]]))[0]
    if kind == "sphere":
        m = _similarity((0.2, 1.5, -0.3), 0.7, rot)
    elif kind == "disk":  # an ellipse: exact too
        m = _similarity((0.2, 1.5, -0.3), 1.0, rot) @ np.diag([0.8, 0.4, 1.0, 1.0])
    else:
        m = _similarity((0.2, 1.5, -0.3), 1.0, rot) @ np.diag([0.5, 0.5, 1.2, 1.0])
    return AnalyticShape(kind, m, 0, (0, 1), name=kind)


@pytest.mark.parametrize("kind", ["sphere", "disk", "cylinder"])
def test_shape_samples_cover_the_solid_angle_that_rays_hit(kind):
    """For each shape, the emitter sampler's estimate of the solid angle of the shape's emitting
    side seen from a point (mean of usable / pdf) equals the fraction of uniform random rays
    whose first hit is that side (times 4 pi), and the density it reports is
    :func:`shape_pdf`'s for the same direction: sampler, pdf and intersection agree."""
    from icbtool.trace import shapes as S

    shp = S.pack_shapes([_shape(kind)])
    rng = np.random.default_rng(3)
    p = np.array([0.1, 0.2, 0.4])
    n = 400_000
    u = rng.random((n, 2))
    d = np.empty((n, 3))
    dist, pdf, ok, y = np.empty(n), np.empty(n), np.empty(n, bool), np.empty((n, 3))
    S.sample_batch(shp, 0, np.tile(p, (n, 1)), u, d, dist, pdf, ok, y)
    omega_sampled = float(np.where(ok, 1.0 / pdf, 0.0).mean())
    # the sampled points lie on the shape: a ray towards each hits it at that distance
    t, k = np.empty(n), np.empty(n, np.int64)
    sel = np.flatnonzero(ok)[:2000]
    S.intersect_batch(shp, np.tile(p, (len(sel), 1)), d[sel], np.full(len(sel), np.inf),
                      t[: len(sel)], k[: len(sel)])  # fmt: skip
    assert np.all(k[: len(sel)] == 0)
    np.testing.assert_allclose(t[: len(sel)], dist[sel], rtol=1e-9, atol=1e-12)
    # and shape_pdf gives the sampler's density
    q = np.empty(len(sel))
    cos = np.abs(np.einsum("ij,ij->i", d[sel], _normals(shp, y[sel], kind)))
    S.pdf_batch(shp, 0, np.tile(p, (len(sel), 1)), d[sel], dist[sel], cos, q)
    np.testing.assert_allclose(q, pdf[sel], rtol=1e-6)
    # uniform directions: the hits on the emitting side
    w = rng.normal(size=(n, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    S.intersect_batch(shp, np.tile(p, (n, 1)), w, np.full(n, np.inf), t, k)
    hit = k == 0
    front = np.einsum("ij,ij->i", w[hit], _normals(shp, p + t[hit, None] * w[hit], kind)) < 0
    omega_hit = 4 * np.pi * front.sum() / n
    se = 4 * np.pi * math.sqrt(front.mean() * (1 - front.mean()) * hit.mean() / n) + 1e-3
    assert abs(omega_sampled - omega_hit) < 4 * se + 2e-3 * omega_hit, (omega_sampled, omega_hit)


def _normals(shp: np.ndarray, pts: np.ndarray, kind: str) -> np.ndarray:
    """Outward (disk: +z image) unit normals of the packed shape 0 at surface points."""
    c, a = shp[0, 3:6], shp[0, 6:9]
    v = pts - c
    if kind == "sphere":
        n = v
    elif kind == "disk":
        n = np.tile(a, (len(pts), 1))
    else:
        n = v - (v @ a)[:, None] * a
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_analytic_shape_validation_names_the_problem():
    with pytest.raises(ValueError, match="similarity"):
        AnalyticShape("sphere", np.diag([1.0, 2.0, 1.0, 1.0]), 0, (0, 1), name="s")
    with pytest.raises(ValueError, match="cross-section a circle"):
        AnalyticShape("cylinder", np.diag([1.0, 2.0, 1.0, 1.0]), 0, (0, 1), name="c")
    with pytest.raises(ValueError, match="kind"):
        AnalyticShape("cone", np.eye(4), 0, (0, 1))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="singular"):
        AnalyticShape("disk", np.diag([1.0, 0.0, 1.0, 1.0]), 0, (0, 1))
    b = SceneBuilder("s")
    b.add_quad((0, 0, 0), (1, 0, 0), (0, 0, 1), b.material("m"))
    sc = b.build()
    with pytest.raises(ValueError, match="beyond the 2 faces"):
        dataclasses.replace(sc, shapes=[AnalyticShape("disk", np.eye(4), 0, (0, 3))])
    tex = Material("t", texture=np.ones((2, 2, 3)))
    with pytest.raises(ValueError, match="textured"):
        dataclasses.replace(sc, materials=[tex], uvs=np.zeros((4, 2)),
                            shapes=[AnalyticShape("disk", np.eye(4), 0, (0, 2))])  # fmt: skip


# ----------------------------------------------------------------------------- peer: Mitsuba 3
_VEACH_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world">
      <lookat origin="0, 2.2, 4.2" target="0, 0.35, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="32"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.5, 0.4"/></bsdf>
  </shape>
  <shape type="sphere">
    <point name="center" x="-1.5" y="0.6" z="0"/><float name="radius" value="0.05"/>
    <emitter type="area"><rgb name="radiance" value="80, 60, 40"/></emitter></shape>
  <shape type="sphere">
    <point name="center" x="-0.5" y="0.42" z="0"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="6, 6, 8"/></emitter></shape>
  <shape type="sphere">
    <point name="center" x="0.6" y="0.4" z="0"/><float name="radius" value="0.38"/>
    <emitter type="area"><rgb name="radiance" value="1.5, 2, 2"/></emitter></shape>
  <shape type="disk">
    <transform name="to_world">
      <scale value="0.3"/><rotate x="1" angle="90"/><translate x="1.6" y="0.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="3, 2, 2"/></emitter></shape>
</scene>"""


def test_sphere_and_disk_lights_over_a_floor_match_mitsuba(tmp_path):
    """Veach-style sphere lights (tiny to large, the largest almost touching the floor) and a
    disk light over a floor, read from one Mitsuba file by both renderers: the traced image
    matches Mitsuba 3's, mean bias < 2 % per channel and blurred (sigma 1.5 px) relative RMSE
    below max(5 %, twice Mitsuba's own seed-to-seed difference)."""
    mi = pytest.importorskip("mitsuba")
    from scipy.ndimage import gaussian_filter

    from icbtool.scene import load

    mi.set_variant("scalar_rgb")
    path = tmp_path / "veach.xml"
    path.write_text(_VEACH_XML)
    scene = load(path)
    assert sorted(s.kind for s in scene.shapes) == ["disk", "sphere", "sphere", "sphere"]
    assert scene.max_depth == 3  # the file's integrator, as Mitsuba renders it
    res = render(scene, scene.default_camera, TraceConfig(spp=256, seed=1, max_depth=3))
    ours = res.direct + res.gi
    msc = mi.load_file(str(path))
    ref_a = np.asarray(mi.render(msc, spp=256, seed=11), np.float64)[..., :3]
    ref_b = np.asarray(mi.render(msc, spp=256, seed=12), np.float64)[..., :3]
    ref = 0.5 * (ref_a + ref_b)

    def blur(img):
        return gaussian_filter(img, sigma=(1.5, 1.5, 0), mode="nearest")

    def rel_rmse(a, b):
        return float(np.sqrt(np.mean((blur(a) - blur(b)) ** 2)) / np.mean(blur(b)))

    floor = rel_rmse(ref_a, ref_b)
    bias = ours.mean((0, 1)) / ref.mean((0, 1)) - 1.0
    assert np.all(np.abs(bias) < 0.02), bias
    assert rel_rmse(ours, ref) < max(0.05, 2.0 * floor), (rel_rmse(ours, ref), floor)


_SPOT_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="2"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="70"/>
    <transform name="to_world">
      <lookat origin="0, 3, 0.01" target="0, 0, 0" up="0, 0, 1"/></transform>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="40"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
  </shape>
  <emitter type="spot">
    <transform name="to_world"><lookat origin="-0.6, 1.5, 0" target="-0.4, 0, 0"/></transform>
    <rgb name="intensity" value="6, 5, 4"/>
    <float name="cutoff_angle" value="35"/><float name="beam_width" value="15"/>
  </emitter>
  <emitter type="point"><point name="position" x="1.0" y="0.8" z="0.5"/>
    <rgb name="intensity" value="1, 2, 3"/></emitter>
</scene>"""


def test_spot_and_point_lights_match_mitsuba(tmp_path):
    """A Mitsuba spot light (cutoff_angle, beam_width: linear falloff in the angle) and a point
    light over a floor: the traced direct light matches Mitsuba 3's image (intensity in W/sr,
    the falloff's ramp and edge): mean bias < 2 % per channel, and its per-pixel difference
    from a Mitsuba render no larger than Mitsuba's own seed-to-seed difference (Mitsuba picks
    one of the two lights per sample: its noise is the floor; the traced image has none to
    speak of)."""
    mi = pytest.importorskip("mitsuba")
    from icbtool.scene import load

    mi.set_variant("scalar_rgb")
    path = tmp_path / "spot.xml"
    path.write_text(_SPOT_XML)
    scene = load(path)
    (spot,) = scene.lights_of("spot")
    assert spot.profile == "linear" and (spot.inner_deg, spot.outer_deg) == (15.0, 35.0)
    ours = render(scene, scene.default_camera, TraceConfig(spp=64, seed=1, max_depth=2)).direct
    msc = mi.load_file(str(path))
    ref = np.asarray(mi.render(msc, spp=64, seed=3), np.float64)[..., :3]
    ref_b = np.asarray(mi.render(msc, spp=64, seed=4), np.float64)[..., :3]
    bias = ours.mean((0, 1)) / ref.mean((0, 1)) - 1.0
    assert np.all(np.abs(bias) < 0.02), bias

    def rel_rmse(a, b):
        return float(np.sqrt(np.mean((a - b) ** 2)) / b.mean())

    assert rel_rmse(ours, ref) < rel_rmse(ref_b, ref), (rel_rmse(ours, ref), rel_rmse(ref_b, ref))


def test_linear_spot_profile_is_mitsubas():
    """SpotLight(profile="linear"): 1 inside beam_width, (cutoff - angle) / (cutoff - beam)
    between, 0 outside (Mitsuba 3's falloff_curve)."""
    from icbtool.scene import SpotLight

    s = SpotLight((0, 0, 0), (0, 0, 1), (1, 1, 1), 15.0, 35.0, profile="linear")
    ang = np.array([0.0, 10.0, 15.0, 20.0, 30.0, 35.0, 50.0])
    want = np.clip((35.0 - ang) / 20.0, 0, 1)
    np.testing.assert_allclose(s.falloff(np.cos(np.radians(ang))), want, atol=1e-9)
    with pytest.raises(ValueError, match="profile"):
        SpotLight((0, 0, 0), (0, 0, 1), (1, 1, 1), profile="cubic")  # type: ignore[arg-type]


def test_the_kernels_record_the_shapes_source_they_inline():
    """numba caches the kernels by their own file's text: icbtool.trace.kernels.SHAPES_SOURCE
    must name the current icbtool/trace/shapes.py (its SHA-256 prefix), so that a change to the
    shapes hooks also changes kernels.py and no stale cached kernel keeps the old hooks."""
    import hashlib
    from pathlib import Path

    from icbtool.trace import kernels, shapes

    digest = hashlib.sha256(Path(shapes.__file__).read_bytes()).hexdigest()[:16]
    assert kernels.SHAPES_SOURCE == digest


# ----------------------------------------------------------------------- the general (BSDF) kernel
@pytest.mark.parametrize("d", [1.05, 4.0])
def test_sphere_light_over_a_declared_bsdf_floor_is_exact(d):
    """The floor of :func:`test_sphere_light_irradiance_is_exact_at_every_distance` given a
    declared diffuse BSDF, so that the general kernel traces it: the exact sphere light is
    sampled by its cone and weighted by the density it used (a tessellated one loses light at
    its rim), and the floor's radiance is albedo L (r / d)^2 within 0.5 %."""
    import icbtool.scene.bsdf as sb

    scene = _floor_scene("sphere", d, 1.0)
    floor = dataclasses.replace(scene.materials[0], bsdf=sb.Diffuse(ALBEDO))
    scene = dataclasses.replace(scene, materials=[floor, *scene.materials[1:]])
    got = _floor_radiance(scene)
    assert got == pytest.approx(ALBEDO * RADIANCE / d**2, rel=5e-3)


_GLOSSY_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="6"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world">
      <lookat origin="0, 1.6, 3.6" target="0, 0.2, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="32"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="rectangle">
    <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/></transform>
    <bsdf type="roughconductor"><string name="material" value="Cu"/>
      <float name="alpha" value="0.3"/></bsdf>
  </shape>
  <shape type="sphere">
    <point name="center" x="-0.6" y="0.7" z="0"/><float name="radius" value="0.25"/>
    <emitter type="area"><rgb name="radiance" value="12, 10, 8"/></emitter></shape>
  <shape type="sphere">
    <point name="center" x="0.5" y="0.45" z="0.2"/><float name="radius" value="0.45"/>
    <bsdf type="roughplastic"><rgb name="diffuse_reflectance" value="0.2, 0.4, 0.7"/>
      <float name="alpha" value="0.15"/></bsdf></shape>
  <emitter type="constant"><rgb name="radiance" value="0.1"/></emitter>
</scene>"""


def test_sphere_light_on_a_glossy_floor_and_glossy_sphere_match_mitsuba(tmp_path):
    """A sphere light and a rough-plastic sphere, both exact, over a rough copper floor (the
    general kernel): the light's reflection, the sphere's highlight and shadow as Mitsuba 3
    renders them, mean bias < 2 % per channel and blurred relative RMSE below max(5 %, twice
    Mitsuba's own seed-to-seed difference)."""
    from test_trace_bsdf import peer_compare_file

    from icbtool.scene import load

    path = tmp_path / "glossy.xml"
    path.write_text(_GLOSSY_XML)
    assert [s.kind for s in load(path).shapes] == ["sphere", "sphere"]
    bias, rmse, own = peer_compare_file(path, spp=128, max_depth=6)
    assert np.all(np.abs(bias) < 0.02), bias
    assert rmse < max(0.05, 2 * own), (rmse, own)
