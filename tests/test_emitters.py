"""Emissive geometry as light (icbtool.scene.emitters): promotion, raster DL and the tracer's
DL/GI split on the classic Cornell box written as a glTF in millimetres."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

import icbtool.scene as sc  # noqa: E402
from benchmarks.cornell_gltf import (
    LIGHT_RADIANCE,
    LIGHT_X,
    LIGHT_Y,
    LIGHT_Z,
    TALL_TOP,
    cornell_camera_m,
    write_cornell_gltf,
)
from icbtool.camera import Camera  # noqa: E402
from icbtool.scene.emitters import light_faces, promote_emitters  # noqa: E402

L = np.array(LIGHT_RADIANCE)
QUAD_AREA = (LIGHT_X[1] - LIGHT_X[0]) * (LIGHT_Z[1] - LIGHT_Z[0]) * 1e-6  # m^2


@pytest.fixture(scope="module")
def cornell(tmp_path_factory) -> sc.Scene:
    return sc.load(write_cornell_gltf(tmp_path_factory.mktemp("cb") / "cornell_mm.gltf"))


@pytest.fixture(scope="module")
def cornell_empty(tmp_path_factory) -> sc.Scene:
    p = write_cornell_gltf(tmp_path_factory.mktemp("cb") / "cornell_empty.gltf", blocks=False)
    return sc.load(p)


# ------------------------------------------------------------------------- analytic references
def _corner_form_factor(a: float, b: float, c: float) -> float:
    """Form factor from a point to a parallel a x b rectangle at height c with one corner above
    the point (the classic closed form)."""
    A, B = a / c, b / c
    sa, sb = math.sqrt(1 + A * A), math.sqrt(1 + B * B)
    return (A / sa * math.atan(B / sa) + B / sb * math.atan(A / sb)) / (2 * math.pi)


def rect_form_factor(x: float, z: float, height: float) -> float:
    """Form factor from a floor point (x, z) (m, facing up) to the Cornell light rectangle at
    ``height`` above it, by superposition of corner rectangles (signed)."""
    total = 0.0
    for xe, sx in ((LIGHT_X[1] * 1e-3, 1), (LIGHT_X[0] * 1e-3, -1)):
        for ze, sz in ((LIGHT_Z[1] * 1e-3, 1), (LIGHT_Z[0] * 1e-3, -1)):
            dx, dz = xe - x, ze - z
            f = _corner_form_factor(abs(dx), abs(dz), height) if dx and dz else 0.0
            total += sx * sz * math.copysign(1, dx) * math.copysign(1, dz) * f
    return total


def test_rect_form_factor_known_values():
    # far away: F -> A cos^2 / (pi r^2); under the centre of a huge rectangle: F -> 1
    x, z = np.mean(LIGHT_X) * 1e-3, np.mean(LIGHT_Z) * 1e-3
    assert rect_form_factor(x, z, 100.0) == pytest.approx(QUAD_AREA / (math.pi * 1e4), rel=1e-6)
    assert _corner_form_factor(1e6, 1e6, 1.0) == pytest.approx(0.25, rel=1e-5)


# ------------------------------------------------------------------------- promotion
def test_cornell_gltf_emitter_promoted(cornell):
    lf = light_faces(cornell)
    assert lf.sum() == 2  # the two triangles of the ceiling quad
    assert np.array_equal(np.flatnonzero(lf), cornell.emissive_faces)
    (light,) = cornell.lights  # no punctual lights in the file: only the promoted quad
    assert light.kind == "area" and light.shape == "parallelogram"  # exact pair merged
    assert light.area == pytest.approx(QUAD_AREA, rel=1e-6)
    assert cornell.face_areas[lf].sum() == pytest.approx(QUAD_AREA, rel=1e-6)
    assert np.allclose(light.normal, [0, -1, 0])
    assert np.allclose(light.radiance, LIGHT_RADIANCE, rtol=1e-6)
    assert len(cornell.faces) == 32  # the faces stay in the mesh (the camera sees them)


def test_budget_zero_keeps_seen_emission(tmp_path):
    s = sc.load(write_cornell_gltf(tmp_path / "c.gltf"), emitter_budget=0)
    assert s.lights == () and light_faces(s).sum() == 0 and len(s.emissive_faces) == 2
    with pytest.raises(sc.SceneError, match="emitter_budget"):
        sc.load(tmp_path / "c.gltf", emitter_budget=-1)


def _emissive_grid(n_quads: int, cut: str = "diagonal") -> sc.Scene:
    """A floor and a row of ``n_quads`` emissive 0.1 m quads (2 triangles each) above it."""
    b = sc.SceneBuilder("grid")
    white = b.material("white", albedo=(0.5, 0.5, 0.5))
    lamp = b.material("lamp", albedo=(0, 0, 0), emission=(2.0, 2.0, 2.0))
    b.add_quad((-5, 0, -5), (0, 0, 10), (10, 0, 0), white)
    for i in range(n_quads):
        b.add_quad((0.1 * i, 1.0, 0), (0.1, 0, 0), (0, 0, 0.1), lamp)  # faces down
    return b.build()


def test_budget_exceeded_logs_and_keeps(caplog):
    s = _emissive_grid(50)  # 100 emissive triangles
    with caplog.at_level(logging.INFO, logger="icbtool.scene.emitters"):
        out = promote_emitters(s, max_triangles=64)
    assert out is s and out.lights == ()
    msgs = [r.getMessage() for r in caplog.records if r.name == "icbtool.scene.emitters"]
    assert any("100 emissive triangles" in m and "64" in m for m in msgs), msgs
    out = promote_emitters(s, max_triangles=100)
    assert len(out.lights) == 50 and light_faces(out).sum() == 100
    assert sum(lt.area for lt in out.lights) == pytest.approx(50 * 0.01, rel=1e-6)
    with pytest.raises(ValueError, match="max_triangles"):
        promote_emitters(s, max_triangles=-3)


def test_triangles_not_merged_unless_parallelogram():
    b = sc.SceneBuilder("tris")
    white = b.material("white")
    lamp = b.material("lamp", albedo=(0, 0, 0), emission=(1.0, 1.0, 1.0))
    b.add_quad((-5, 0, -5), (0, 0, 10), (10, 0, 0), white)
    # a kite (two triangles sharing an edge, not a parallelogram) and a lone triangle
    b.add_mesh(
        [[0, 1, 0], [0.2, 1, 0.1], [0, 1, 0.3], [-0.1, 1, 0.1]], [[0, 2, 1], [0, 3, 2]], lamp
    )
    b.add_mesh([[1, 1, 0], [1.2, 1, 0], [1, 1, 0.2]], [[0, 2, 1]], lamp)
    s = promote_emitters(b.build())
    assert [lt.shape for lt in s.lights] == ["triangle"] * 3
    assert light_faces(s).sum() == 3
    for lt, f in zip(s.lights, s.emissive_faces):
        assert lt.area == pytest.approx(s.face_areas[f], rel=1e-6)
        assert np.allclose(lt.normal, s.face_normals[f], atol=1e-6)


def test_promote_leaves_existing_area_lights_alone():
    s = sc.cornell_box()  # procedural: its light is already an AreaLight
    assert promote_emitters(s) is s


@pytest.mark.parametrize("shape", ["parallelogram", "triangle"])
def test_sample_points_stratified(shape):
    lt = sc.AreaLight((0, 1, 0), (0.3, 0, 0), (0.1, 0, 0.2), (1, 1, 1), shape=shape)
    for k in (1, 2, 4):
        pts = lt.sample_points(k)
        assert pts.shape == (k * k, 3)
        assert lt.contains(pts).all()
        assert np.allclose(pts.mean(0), lt.vertices.mean(0), atol=1e-12)  # equal cells
        assert len(np.unique(np.round(pts, 9), axis=0)) == k * k


# ------------------------------------------------------------------------- raster DL (GL)
def _down_camera(x: float, z: float, size: int = 9) -> Camera:
    """A camera 0.3 m above the floor point (x, 0, z) looking straight down at it."""
    return Camera.look_at((x, 0.3, z), (x, 0.0, z), (0, 0, 1), 20.0, size, size)


def _raster_dl(scene: sc.Scene, cam: Camera, **cfg) -> np.ndarray:
    from icbtool.raster import RasterConfig, render

    return render(scene, cam, ("dl",), RasterConfig(**cfg)).dl


@pytest.mark.gl
@pytest.mark.parametrize("xz", [(0.278, 0.2795), (0.12, 0.45), (0.5, 0.1)])
def test_raster_dl_equals_rectangle_irradiance(cornell_empty, xz):
    white = next(m for m in cornell_empty.materials if m.name == "white").albedo
    x, z = xz
    dl = _raster_dl(cornell_empty, _down_camera(x, z))[4, 4]
    expect = white * L * rect_form_factor(x, z, LIGHT_Y * 1e-3)  # albedo/pi * (pi L F)
    np.testing.assert_allclose(dl, expect, rtol=0.015)


@pytest.mark.gl
def test_raster_64_triangle_lights_and_limit_error(cornell_empty):
    """The light quad as 64 triangle AreaLights (4 x 8 cells, 2 triangles each): same DL."""
    from icbtool.raster import RasterConfig, RasterError, Rasterizer

    b = sc.SceneBuilder("tiles")
    white = b.material("white", albedo=(0.73, 0.73, 0.73))
    w, d = 0.556, 0.5592
    b.add_quad((0, 0, 0), (0, 0, d), (w, 0, 0), white)  # floor only
    (x0, x1), (z0, z1), y = np.array(LIGHT_X) / 1e3, np.array(LIGHT_Z) / 1e3, LIGHT_Y / 1e3
    dx, dz = (x1 - x0) / 4, (z1 - z0) / 8
    for i in range(4):
        for j in range(8):
            c = np.array([x0 + i * dx, y, z0 + j * dz])
            for corner, eu, ev in (
                (c, (dx, 0, 0), (0, 0, dz)),  # normals down: cross(eu, ev) = -y
                (c + (dx, 0, dz), (-dx, 0, 0), (0, 0, -dz)),
            ):
                b.add_area_light(sc.AreaLight(corner, eu, ev, L, f"t{i}{j}", shape="triangle"))
    s = b.build()
    assert len(s.lights_of("area")) == 64
    x, z = 0.2, 0.35
    cfg = dict(area_samples=2, area_shadow_map_size=64)
    dl = _raster_dl(s, _down_camera(x, z), **cfg)[4, 4]
    np.testing.assert_allclose(dl, 0.73 * L * rect_form_factor(x, z, y), rtol=0.015)
    with pytest.raises(RasterError, match="GL_MAX_ARRAY_TEXTURE_LAYERS"):
        Rasterizer(s, RasterConfig(area_samples=8))  # 64 x 64 shadow maps > 2048 layers


@pytest.mark.gl
def test_raster_dl_umbra_of_a_block(cornell):
    """A floor point that sees none of the light (checked by Embree rays to 16x16 points on
    the light) gets (near) zero DL; one that sees all of it gets the unshadowed value."""
    from icbtool.scene.raycast import EmbreeScene

    emb = EmbreeScene.from_scene(cornell)
    light = cornell.lights[0]
    targets = light.sample_points(16)

    def seen_fraction(p: np.ndarray) -> float:
        d = targets - p
        dist = np.linalg.norm(d, axis=1)
        occ = emb.occluded(np.tile(p + [0, 1e-5, 0], (len(d), 1)), d / dist[:, None], dist * 0.999)
        return 1.0 - float(np.mean(occ))

    # search the floor behind the tall block (seen from the light) for a point in its umbra:
    # outside the block's footprint (>= 1.5 cm) and with its neighbours 1 cm away in the umbra
    foot = np.array(TALL_TOP, np.float64)[:, [0, 2]] / 1e3

    def outside_by(x: float, z: float) -> float:  # signed distance outside the convex footprint
        d = -np.inf
        for i in range(4):
            a, b = foot[i], foot[(i + 1) % 4]
            e = (b - a) / np.linalg.norm(b - a)
            out = np.array([e[1], -e[0]])
            if out @ (foot.mean(0) - a) > 0:
                out = -out
            d = max(d, out @ (np.array([x, z]) - a))
        return d

    umbra = None
    for x in np.linspace(0.30, 0.54, 25):
        for z in np.linspace(0.40, 0.55, 16):
            if umbra is None and outside_by(x, z) > 0.015:
                ring = [(x + dx, z + dz) for dx in (-0.01, 0, 0.01) for dz in (-0.01, 0, 0.01)]
                if all(seen_fraction(np.array([a, 0.0, c])) == 0.0 for a, c in ring):
                    umbra = np.array([x, 0.0, z])
    assert umbra is not None, "no floor point in the tall block's umbra"
    # the camera must see that floor point (not the block): look down from close above
    x, z = umbra[0], umbra[2]
    cam = Camera.look_at((x, 0.02, z), (x, 0.0, z), (0, 0, 1), 20.0, 9, 9)
    dl = _raster_dl(cornell, cam)[4, 4]
    open_dl = 0.73 * L * rect_form_factor(x, z, LIGHT_Y * 1e-3)
    assert np.all(dl <= 0.02 * open_dl), (dl, open_dl)
    lit = np.array([0.278, 0.0, 0.2795])
    assert seen_fraction(lit) > 0.5  # partly lit reference: DL in proportion
    dl_lit = _raster_dl(cornell, _down_camera(lit[0], lit[2]))[4, 4]
    assert dl_lit[0] > 0.3 * 0.73 * L[0] * rect_form_factor(lit[0], lit[2], LIGHT_Y * 1e-3)


# ------------------------------------------------------------------------- tracer split
def _trace(scene: sc.Scene, cam: Camera, spp: int, **kw):
    from icbtool.trace import TraceConfig, render

    return render(scene, cam, TraceConfig(spp=spp, seed=3, threads=2, aux=False, **kw))


@pytest.mark.gl
def test_tracer_direct_matches_raster_dl(cornell):
    cam = cornell_camera_m(24, 24)
    dl = _raster_dl(cornell, cam)
    # pixel centres, as the raster samples them (no pixel-area jitter)
    tr = _trace(cornell, cam, 256, max_depth=2, pixel_jitter=False)
    em = np.all(np.isclose(tr.direct, L, rtol=1e-3), axis=2)  # the emitter seen
    assert em.sum() >= 1 and np.allclose(dl[em], L, rtol=1e-3)
    lit = ~em
    rel = tr.direct[lit].mean(0) / dl[lit].mean(0) - 1.0
    assert np.all(np.abs(rel) < 0.03), rel
    # with max_depth=2 all light is direct: nothing left in gi
    assert np.abs(tr.gi).max() < 1e-6


def test_gi_split_against_brute_force(cornell, tmp_path):
    """GI (full - direct) with the promoted emitter equals a brute-force indirect reference:
    the emitter as plain emissive geometry (budget 0), full (depth -1) - depth-2 image."""
    plain = sc.load(write_cornell_gltf(tmp_path / "c.gltf"), emitter_budget=0)
    cam = cornell_camera_m(24, 24)
    kw = dict(pixel_jitter=False)  # pixel centres: some pixels see only the emitter
    spp = 256
    prom = _trace(cornell, cam, spp, max_depth=-1, **kw)
    full = _trace(plain, cam, spp, max_depth=-1, **kw)
    d2 = _trace(plain, cam, spp, max_depth=2, **kw)
    ref = full.full - d2.full
    # the plain scene keeps the emitter's light in gi; the promoted one in direct
    assert prom.gi.mean() < 0.8 * full.gi.mean()
    bias = prom.gi.mean((0, 1)) / ref.mean((0, 1)) - 1.0
    assert np.all(np.abs(bias) < 0.03), bias
    # emitter pixels: direct = its emission, gi = only light bounced onto its albedo
    em = np.all(np.isclose(prom.direct, L, rtol=1e-3), axis=2)
    assert em.sum() >= 1
    assert np.all(prom.gi[em] < 0.05 * L)
    np.testing.assert_allclose(prom.full.mean((0, 1)), full.full.mean((0, 1)), rtol=0.03)


def test_light_faces_of_many_lights_match_each_lights_own_test():
    """light_faces tests each light only against faces near it: the answer is still every
    emissive face whose corners all lie in some light (checked light by light here), for a
    sphere promoted to one light per triangle, with half of those lights dropped."""
    import dataclasses

    from icbtool.scene import white_furnace

    sphere = promote_emitters(white_furnace(subdivisions=2), max_triangles=10_000)
    half = dataclasses.replace(sphere, lights=sphere.lights[::2])
    for scene, n_lights in ((sphere, 320), (half, 160)):
        lights = scene.lights_of("area")
        assert len(lights) == n_lights
        tri = scene.vertices[scene.faces[scene.emissive_faces]]
        want = np.zeros(len(scene.faces), bool)
        for light in lights:
            want[scene.emissive_faces[light.contains(tri).all(axis=1)]] = True
        got = light_faces(scene)
        assert got.sum() == n_lights and np.array_equal(got, want)
