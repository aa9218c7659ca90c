"""Known-answer tests of icbtool.raster (GL tests use $ICBTOOL_GL_BACKEND; osmesa in `make test`).

Tolerances (float32 buffers):
* depth / position / normals vs analytic values: 1e-5 relative (interpolation in float32);
* DL of analytic lights vs closed forms: 1e-4 relative;
* raster vs Embree primary hits (Cornell box): depth 1e-4 relative, normals 1e-4, away from
  silhouettes (pixels whose 3x3 neighbourhood sees more than one triangle plane in Embree);
* shadow masks vs Embree occlusion: exact away from a 1-pixel band around the true shadow edge;
* area-light irradiance vs a 96x96 midpoint quadrature of the light: 2e-3 relative.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import icbtool as icb
from icbtool.raster import RasterConfig, Rasterizer
from icbtool.scene import (
    AreaLight,
    DirectionalLight,
    PointLight,
    SceneBuilder,
    Sky,
    SpotLight,
)

gl = pytest.mark.gl


def _cfg(**kw) -> RasterConfig:
    return RasterConfig(backend="auto", **kw)


def _floor_scene(lights, size=10.0, albedo=(0.5, 0.4, 0.3), sky=None):
    b = SceneBuilder("floor")
    m = b.material("floor", albedo=albedo)
    h = size / 2
    b.add_quad((-h, 0, h), (size, 0, 0), (0, 0, -size), m)
    b.lights.extend(lights)
    b.sky = sky
    return b.build()


def _down_camera(height=64, width=64, y=2.0):
    return icb.Camera.look_at(
        (0, y, 0), (0, 0, 0), (0, 0, -1), fov_y_deg=60, height=height, width=width
    )


def _dilate(m: np.ndarray) -> np.ndarray:
    """3x3 binary dilation (edge-padded)."""
    p = np.pad(m, 1, mode="edge")
    h, w = m.shape
    return np.any([p[i : i + h, j : j + w] for i in range(3) for j in range(3)], axis=0)


# --------------------------------------------------------------------------- config (no GL)
def test_config_validation():
    with pytest.raises(ValueError, match="backend"):
        RasterConfig(backend="vulkan")
    with pytest.raises(ValueError, match="area_samples"):
        RasterConfig(area_samples=0)
    with pytest.raises(ValueError, match="near < far"):
        RasterConfig(near=2.0, far=1.0)
    with pytest.raises(ValueError, match="unknown raster buffer"):
        icb.raster.check_buffers(("dl", "gi"))
    assert icb.raster.check_buffers("depth, dl") == ("dl", "depth")


def test_bogus_backend_names():
    from icbtool.raster.context import create_context, resolve_backend

    with pytest.raises(ValueError, match="unknown GL backend 'bogus'"):
        create_context("bogus")
    old = os.environ.get("ICBTOOL_GL_BACKEND")
    os.environ["ICBTOOL_GL_BACKEND"] = "nonsense"
    try:
        with pytest.raises(ValueError, match="ICBTOOL_GL_BACKEND='nonsense'"):
            resolve_backend("auto")
    finally:
        if old is None:
            del os.environ["ICBTOOL_GL_BACKEND"]
        else:
            os.environ["ICBTOOL_GL_BACKEND"] = old


def test_provoking_vertices_are_unique_and_keep_winding():
    from icbtool.raster.renderer import _provoking

    rng = np.random.default_rng(0)
    faces = rng.integers(0, 40, size=(300, 3))  # many faces per vertex: duplicates needed
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])]
    faces = faces[faces[:, 0] != faces[:, 2]]
    out, src = _provoking(faces, 40)
    assert len(np.unique(out[:, 2])) == len(out)  # every face has its own last vertex
    np.testing.assert_array_equal(src[:40], np.arange(40))
    orig = src[out]  # back to original vertices: a cyclic rotation of each face
    rot = [np.roll(faces, k, axis=1) for k in range(3)]
    assert np.all(np.any([np.all(orig == r, axis=1) for r in rot], axis=0))
    assert len(src) < 40 + len(faces)


# --------------------------------------------------------------------------- G-buffers
@gl
def test_plane_depth_position_normals():
    scene = icb.scene.plane()
    cam = scene.default_camera
    buf = icb.raster.render(scene, cam, config=_cfg())
    assert buf.valid.all()
    for n in icb.raster.BUFFER_NAMES:
        x = getattr(buf, n)
        assert x.dtype == np.float32 and x.shape[:2] == (cam.height, cam.width), n
    np.testing.assert_allclose(buf.depth[..., 0], 2.0, rtol=1e-5)
    expect = cam.unproject(cam.pixel_centers(), buf.depth[..., 0].astype(np.float64))
    np.testing.assert_allclose(buf.position, expect, atol=2e-5)
    np.testing.assert_allclose(buf.position[..., 1], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(buf.normal_world, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(
        buf.normal_world, np.broadcast_to([0, 1, 0], buf.normal_world.shape), atol=1e-6
    )
    # view normals: world normals rotated into OpenCV camera axes; facing the camera (z < 0)
    nv = buf.normal_world @ cam.cam_from_world[:3, :3].T
    np.testing.assert_allclose(buf.normal_view, nv, atol=1e-6)
    assert (buf.normal_view[..., 2] < 0).all()


@gl
def test_point_projects_to_same_pixel():
    """A tiny emissive quad around a 3D point lights exactly the pixel Camera.project names."""
    cam = icb.Camera.look_at(
        (0.3, 1.5, 2.0), (0, 0, 0), (0, 1, 0), fov_y_deg=50, height=48, width=80
    )
    uv_target = np.array([57.5 + 0.13, 11.5 - 0.21])  # off-centre, top-right: catches flips
    p = cam.unproject(uv_target, 1.7)
    (u, v), _ = cam.project(p)
    half = 0.3 * 1.7 / cam.fx  # 0.3 px at depth 1.7
    b = SceneBuilder("dot")
    m = b.material("dot", albedo=(0, 0, 0), emission=(5, 5, 5))
    r, up = cam.right, cam.up
    b.add_quad(p - half * (r + up), 2 * half * r, 2 * half * up, m)
    buf = icb.raster.render(b.build(), cam, ("dl",), config=_cfg())
    rows, cols = np.nonzero(buf.valid)
    assert list(zip(rows, cols)) == [(int(np.floor(v)), int(np.floor(u)))]
    np.testing.assert_allclose(buf.dl[rows[0], cols[0]], 5.0, rtol=1e-6)


@gl
def test_only_requested_buffers_and_determinism():
    scene = icb.scene.cornell_box()
    cam = icb.scene.cornell_camera(48, 48)
    with Rasterizer(scene, _cfg(area_samples=2, area_shadow_map_size=128)) as r:
        full = r.render(cam)
        some = r.render(cam, buffers=("dl", "depth"))
        again = r.render(cam, buffers=("dl", "depth"))
        mask_only = r.render(cam, buffers=("mask",))
    assert some.names == ("dl", "depth", "mask")
    for n in ("albedo", "normal_world", "normal_view", "position"):
        assert getattr(some, n) is None
    assert mask_only.names == ("mask",)
    np.testing.assert_array_equal(some.dl, again.dl)
    np.testing.assert_array_equal(some.depth, again.depth)
    np.testing.assert_array_equal(some.depth, full.depth)
    np.testing.assert_allclose(some.dl, full.dl, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(mask_only.mask, full.mask)
    assert set(full.timings) >= {"draw", "readback", "total"}


@gl
def test_clusters_and_culling_change_nothing(monkeypatch):
    """Tiny culling clusters (many draw calls, u_prim_base offsets, clusters outside the view
    skipped) give exactly the single-draw image."""
    from icbtool.raster import renderer

    scene = icb.scene.cornell_box()
    cam = icb.Camera.look_at(
        (0.5, 1.2, 1.5), (-0.6, 0.4, -1), (0, 1, 0), fov_y_deg=40, height=40, width=48
    )
    cfg = _cfg(area_samples=2, area_shadow_map_size=128)
    ref = icb.raster.render(scene, cam, ("dl", "albedo", "depth", "normal_world"), config=cfg)
    monkeypatch.setattr(renderer, "CLUSTER_FACES", 2)
    with Rasterizer(scene, cfg) as r:
        assert len(r._cluster_start) == scene.n_triangles // 2
        buf = r.render(cam, ("dl", "albedo", "depth", "normal_world"))
        assert r.last_drawn_fraction < 1.0  # some clusters were culled
    for n in ("dl", "albedo", "depth", "normal_world"):
        np.testing.assert_array_equal(getattr(buf, n), getattr(ref, n), err_msg=n)


@gl
def test_cornell_matches_embree_primary_rays():
    from icbtool.scene.raycast import EmbreeScene

    scene = icb.scene.cornell_box()
    # from outside and above: background, two-sided walls seen from behind, both blocks
    cam = icb.Camera.look_at(
        (2.2, 3.2, 4.5), (0, 0.8, 0), (0, 1, 0), fov_y_deg=45, height=96, width=128
    )
    buf = icb.raster.render(
        scene, cam, ("depth", "normal_world", "position"), config=_cfg(shadows=False)
    )
    o, d, dpd = cam.rays()
    hits = EmbreeScene.from_scene(scene).intersect(o.reshape(-1, 3), d.reshape(-1, 3))
    prim = hits.prim.reshape(cam.height, cam.width)
    hit = prim >= 0
    plane_id = np.round(
        np.concatenate(
            [
                scene.face_normals,
                np.einsum("ij,ij->i", scene.face_normals, scene.vertices[scene.faces[:, 0]])[
                    :, None
                ],
            ],
            1,
        ),
        4,
    )
    key = np.where(
        hit,
        np.unique(plane_id, axis=0, return_inverse=True)[1].reshape(-1)[np.maximum(prim, 0)],
        -1,
    )
    # silhouette / crease pixels: the 3x3 neighbourhood sees more than one plane (or background)
    edge = np.zeros_like(hit)
    for val in np.unique(key):
        m = key == val
        edge |= _dilate(m) & _dilate(~m)
    interior = ~edge
    assert interior.sum() > 0.6 * hit.size
    assert np.array_equal(buf.valid[interior], hit[interior])
    assert (buf.valid != hit)[edge].mean() < 0.2
    h = interior & hit
    depth = (hits.t.reshape(prim.shape) * dpd)[h]
    np.testing.assert_allclose(buf.depth[..., 0][h], depth, rtol=1e-4)
    # the shading normal (interpolated vertex normals) at Embree's hit, turned to face the camera
    # like the geometric normal (the box's quads are not exactly planar: ng != shading normal)
    vn = scene.normals[scene.faces[np.maximum(hits.prim, 0)]].astype(np.float64)
    bu, bv = hits.u[:, None], hits.v[:, None]
    ns = (1 - bu - bv) * vn[:, 0] + bu * vn[:, 1] + bv * vn[:, 2]
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-12)
    ns *= -np.sign(np.einsum("ij,ij->i", hits.ng, d.reshape(-1, 3)))[:, None]
    np.testing.assert_allclose(
        buf.normal_world[h], ns.reshape(buf.normal_world.shape)[h], atol=1e-4
    )
    pos = (o + d * hits.t.reshape(prim.shape)[..., None])[h]
    np.testing.assert_allclose(buf.position[h], pos, atol=1e-4 * scene.diagonal)


@gl
def test_textured_albedo_follows_uv_and_mip_footprint():
    """A ramp texture (R = u, G = v) seen obliquely: albedo equals the uv of the pixel's surface
    point (perspective-correct interpolation, texture orientation); a fine checkerboard far away
    averages to grey (the mip level follows the pixel footprint) but stays sharp nearby."""
    n = 64
    ramp = np.zeros((n, n, 3), np.float32)
    ramp[..., 0] = (np.arange(n) + 0.5)[None, :] / n  # u grows along columns
    ramp[..., 1] = 1.0 - (np.arange(n) + 0.5)[:, None] / n  # image row 0 is the top: v = 1
    checker = (np.indices((n, n)) // 4).sum(0) % 2  # cells of 4x4 texels
    checker = np.repeat(checker[..., None], 3, -1).astype(np.float32)
    b = SceneBuilder("textured")
    b.add_quad(
        (-2, 0, 2), (4, 0, 0), (0, 0, -4), b.material("ramp", albedo=(1, 1, 1), texture=ramp)
    )
    b.add_quad(
        (-2, 0.01, -2.5),
        (4, 0, 0),
        (0, 0, -20),
        b.material("checker", albedo=(1, 1, 1), texture=checker),
    )
    scene = b.build()
    cam = icb.Camera.look_at(
        (0.2, 1.2, 3.0), (0, 0, -2), (0, 1, 0), fov_y_deg=60, height=96, width=96
    )
    buf = icb.raster.render(scene, cam, ("albedo", "position"), config=_cfg(texture_size=n))
    p = buf.position.astype(np.float64)
    u = (p[..., 0] + 2) / 4
    v = (2 - p[..., 2]) / 4
    on_ramp = buf.valid & (p[..., 2] > -2.0) & (np.abs(p[..., 1]) < 1e-4)
    inner = on_ramp & (np.minimum(u, v) > 0.15) & (np.maximum(u, v) < 0.85)
    assert inner.sum() > 1500
    # sRGB8 storage quantises by < 0.005; filtering a linear ramp keeps it linear
    np.testing.assert_allclose(buf.albedo[inner][:, 0], u[inner], atol=0.01)
    np.testing.assert_allclose(buf.albedo[inner][:, 1], v[inner], atol=0.01)
    on_checker = buf.valid & (np.abs(p[..., 1] - 0.01) < 1e-4)
    far = on_checker & (p[..., 2] < -14)
    near = on_checker & (p[..., 2] > -3.5) & (p[..., 2] < -2.6)
    assert far.sum() > 20 and near.sum() > 50
    assert np.abs(buf.albedo[far][:, 0] - 0.5).max() < 0.05  # averaged by the mip chain
    assert buf.albedo[near][:, 0].std() > 0.3  # texels still resolved


@gl
def test_depth_prepass_changes_nothing():
    scene = icb.scene.cornell_box()
    cam = icb.scene.cornell_camera(40, 48)
    cfg = dict(area_samples=2, area_shadow_map_size=128)
    a = icb.raster.render(scene, cam, config=_cfg(depth_prepass=False, **cfg))
    b = icb.raster.render(scene, cam, config=_cfg(depth_prepass=True, **cfg))
    for n in icb.raster.BUFFER_NAMES:
        np.testing.assert_array_equal(getattr(a, n), getattr(b, n), err_msg=n)


@gl
def test_frames_do_not_share_memory():
    """Each frame's buffers are its own (readback staging memory is reused between frames)."""
    scene = icb.scene.cornell_box()
    cams = [icb.scene.cornell_camera(32, 32), icb.scene.cornell_camera(32, 32).resized(1, 1)]
    with Rasterizer(scene, _cfg(area_samples=2, area_shadow_map_size=128)) as r:
        for cam in cams:
            first = r.render(cam)
            kept = {n: getattr(first, n).copy() for n in first.names}
            moved = icb.Camera.look_at(
                (0.3, 0.2, 1.0),
                (0, 1.5, -1),
                (0, 1, 0),
                fov_y_deg=50,
                height=cam.height,
                width=cam.width,
            )
            second = r.render(moved)
            assert not np.array_equal(second.position, kept["position"])
            for n, x in kept.items():
                np.testing.assert_array_equal(getattr(first, n), x, err_msg=n)


# --------------------------------------------------------------------------- lighting
@gl
def test_directional_light_lambert():
    sun = DirectionalLight((0.3, -1.0, 0.2), (3.0, 2.0, 1.0))
    scene = _floor_scene([sun])
    buf = icb.raster.render(scene, _down_camera(), ("dl", "albedo"), config=_cfg())
    cos = float(-sun.direction[1])
    expect = np.array([0.5, 0.4, 0.3]) * sun.irradiance * cos / np.pi
    np.testing.assert_allclose(
        buf.albedo[buf.valid], np.broadcast_to([0.5, 0.4, 0.3], (buf.valid.sum(), 3)), rtol=1e-6
    )
    np.testing.assert_allclose(
        buf.dl[buf.valid], np.broadcast_to(expect, (buf.valid.sum(), 3)), rtol=1e-4
    )


@gl
def test_point_and_spot_lights():
    light_pos = np.array([0.4, 1.0, -0.3])
    point = PointLight(light_pos, (2.0, 2.0, 2.0))
    buf = icb.raster.render(
        _floor_scene([point]), _down_camera(), ("dl", "position"), config=_cfg()
    )
    p = buf.position[buf.valid].astype(np.float64)
    dvec = light_pos - p
    r2 = (dvec**2).sum(1)
    cos = dvec[:, 1] / np.sqrt(r2)
    expect = (np.array([0.5, 0.4, 0.3]) / np.pi)[None] * 2.0 * (cos / r2)[:, None]
    np.testing.assert_allclose(buf.dl[buf.valid], expect, rtol=1e-4)

    spot = SpotLight(light_pos, (0.2, -1.0, 0.1), (3.0, 3.0, 3.0), inner_deg=15, outer_deg=35)
    buf = icb.raster.render(_floor_scene([spot]), _down_camera(), ("dl", "position"), config=_cfg())
    p = buf.position[buf.valid].astype(np.float64)
    dvec = light_pos - p
    r2 = (dvec**2).sum(1)
    ldir = dvec / np.sqrt(r2)[:, None]
    fall = spot.falloff(-ldir @ spot.direction)
    expect = (np.array([0.5, 0.4, 0.3]) / np.pi)[None] * 3.0 * (fall * ldir[:, 1] / r2)[:, None]
    np.testing.assert_allclose(buf.dl[buf.valid], expect, rtol=1e-4, atol=1e-6)
    assert (fall == 0).mean() > 0.2 and (fall == 1).mean() > 0.02  # both outside and inside


@gl
def test_sky_background():
    scene = _floor_scene(
        [], size=6.0, sky=Sky((0.2, 0.3, 0.9), (0.8, 0.7, 0.6), (0.1, 0.1, 0.1), kind="gradient")
    )
    cam = icb.Camera.look_at((0, 0.5, 3), (0, 0.4, 0), (0, 1, 0), fov_y_deg=70, height=48, width=64)
    buf = icb.raster.render(scene, cam, ("dl",), config=_cfg())
    bg = ~buf.valid
    assert 0.3 < bg.mean() < 0.95
    _, d, _ = cam.rays()
    expect = scene.sky.radiance(d)
    np.testing.assert_allclose(buf.dl[bg], expect[bg], rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(buf.dl[buf.valid], 0.0)  # no lights: the floor is black


@gl
def test_scene_behind_the_camera_renders_only_background():
    """A camera far from the scene looking away (the whole scene behind it) sees nothing: an
    empty mask and the sky, never a near/far plane error."""
    sky = Sky((0.2, 0.3, 0.9))
    scene = _floor_scene([], size=6.0, sky=sky)
    cam = icb.Camera.look_at((0, 1, 20), (0, 1, 40), (0, 1, 0), fov_y_deg=40, height=16, width=16)
    buf = icb.raster.render(scene, cam, ("dl", "depth"), config=_cfg())
    assert not buf.valid.any()
    np.testing.assert_allclose(buf.dl.reshape(-1, 3), np.tile([0.2, 0.3, 0.9], (256, 1)), rtol=1e-5)


@gl
def test_sun_shadow_matches_embree_occlusion():
    from icbtool.scene.raycast import EmbreeScene

    b = SceneBuilder("box_on_floor")
    b.add_quad((-5, 0, 5), (10, 0, 0), (0, 0, -10), b.material("floor", albedo=(0.6, 0.6, 0.6)))
    b.add_box(
        (0.3, 0.75, -0.2),
        (1.0, 1.5, 0.7),
        b.material("box", albedo=(0.3, 0.5, 0.7)),
        rotation_y_deg=25,
    )
    b.lights.append(DirectionalLight((-0.9, -0.8, -0.5), (4.0, 4.0, 4.0)))
    scene = b.build()
    cam = icb.Camera.look_at(
        (-2.5, 5, 3.5), (-0.8, 0, -0.8), (0, 1, 0), fov_y_deg=50, height=128, width=128
    )
    buf = icb.raster.render(scene, cam, ("dl", "albedo", "normal_world", "position"), config=_cfg())
    sun = scene.lights[0]
    lvec = -sun.direction
    cos = buf.normal_world @ lvec
    unshadowed = buf.albedo * sun.irradiance * np.maximum(cos, 0)[..., None] / np.pi
    sel = buf.valid & (cos > 0.2)
    vis = buf.dl[..., 0] / np.maximum(unshadowed[..., 0], 1e-12)
    lit_raster = vis > 0.5
    # geometric truth: an occlusion ray per pixel from the raster's own hit point
    p = buf.position.reshape(-1, 3).astype(np.float64)
    n = buf.normal_world.reshape(-1, 3)
    origins = p + 1e-4 * scene.diagonal * n
    occ = (
        EmbreeScene.from_scene(scene)
        .occluded(origins, np.broadcast_to(lvec, origins.shape), np.inf)
        .reshape(cam.height, cam.width)
    )
    lit_true = ~occ
    band = _dilate(lit_true & sel) & _dilate(~lit_true & sel)  # 1-pixel band at shadow edges
    check = sel & ~band
    assert (~lit_true & check).sum() > 300 and (lit_true & check).sum() > 300
    bad = check & (lit_raster != lit_true)
    assert bad.sum() == 0, f"{bad.sum()} pixels disagree outside the 1-px band"
    # away from edges, lit pixels are exactly unshadowed (no acne) and shadowed ones exactly 0
    np.testing.assert_allclose(vis[check & lit_true], 1.0, rtol=1e-4)
    np.testing.assert_allclose(buf.dl[check & ~lit_true], 0.0, atol=1e-7)


def _polygon_irradiance_quadrature(light: AreaLight, p: np.ndarray, n: np.ndarray, k=96):
    """Irradiance / radiance at p (N, 3) with normals n (N, 3): midpoint rule on the light."""
    s = (np.arange(k) + 0.5) / k
    pts = light.corner + s[:, None, None] * light.edge_u + s[None, :, None] * light.edge_v
    pts = pts.reshape(-1, 3)
    da = light.area / len(pts)
    out = np.zeros(len(p))
    for i in range(0, len(p), 256):
        d = pts[None] - p[i : i + 256, None]
        r2 = (d**2).sum(-1)
        r = np.sqrt(r2)
        cos_r = np.maximum((d * n[i : i + 256, None]).sum(-1) / r, 0)
        cos_l = np.maximum(-(d @ light.normal) / r, 0)
        out[i : i + 256] = (cos_r * cos_l / r2).sum(1) * da
    return out


@gl
def test_cornell_area_light_matches_quadrature():
    scene = icb.scene.cornell_box(with_blocks=False)
    light = scene.lights_of("area")[0]
    cam = icb.Camera.look_at(
        (0, 1.0, 3.5), (0, 0.2, 0), (0, 1, 0), fov_y_deg=45, height=64, width=64
    )
    buf = icb.raster.render(
        scene,
        cam,
        ("dl", "albedo", "normal_world", "position"),
        config=_cfg(area_samples=3, area_shadow_map_size=256),
    )
    floor = buf.valid & (buf.normal_world[..., 1] > 0.999) & (np.abs(buf.position[..., 1]) < 1e-4)
    assert floor.sum() > 500
    p = buf.position[floor].astype(np.float64)
    n = buf.normal_world[floor].astype(np.float64)
    e = _polygon_irradiance_quadrature(light, p, n)
    expect = buf.albedo[floor] / np.pi * light.radiance * e[:, None]
    # nothing stands between the floor and the light: the whole floor is exact (no acne)
    np.testing.assert_allclose(buf.dl[floor], expect, rtol=2e-3)


# --------------------------------------------------------------------------- backends
@gl
def test_backend_already_bound_error():
    """Once OpenGL is bound to one platform, asking for the other names the problem."""
    from icbtool.raster.context import GLBackendError, create_context

    with Rasterizer(icb.scene.plane(), _cfg()) as r:
        other = "egl" if r.backend == "osmesa" else "osmesa"
    with pytest.raises(GLBackendError, match="already imported"):
        create_context(other)


_EGL_SCRIPT = """
import json, numpy as np, icbtool as icb
from icbtool.raster import RasterConfig, GLBackendError
try:
    buf = icb.raster.render(icb.scene.plane(), icb.scene.plane().default_camera, ("depth", "dl"),
                            config=RasterConfig(backend="egl"))
except GLBackendError as e:
    print(json.dumps({"error": str(e)}))
else:
    print(json.dumps({"depth_err": float(np.abs(buf.depth - 2).max()), "dl": float(buf.dl.mean()),
                      "valid": float(buf.valid.mean())}))
"""


@gl
def test_egl_backend_in_subprocess():
    env = {
        k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM", "ICBTOOL_GL_BACKEND")
    }
    res = subprocess.run(
        [sys.executable, "-c", _EGL_SCRIPT], capture_output=True, text=True, timeout=120, env=env
    )
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if "error" in out:
        pytest.skip(f"EGL unavailable on this machine: {out['error']}")
    assert out["valid"] == 1.0
    assert out["depth_err"] < 2e-5
    scene = icb.scene.plane()
    sun = scene.lights[0]
    expect = 0.5 * 3.0 * float(-sun.direction[1]) / np.pi
    assert abs(out["dl"] - expect) < 1e-4 * expect


@gl
def test_cli_render(tmp_path):
    from icbtool.cli import main
    from icbtool.imageio import read_exr

    out = tmp_path / "r"
    argv = [
        "render",
        "plane",
        "--out",
        str(out),
        "--buffers",
        "dl,depth",
        "--height",
        "24",
        "--width",
        "32",
        "--backend",
        os.environ.get("ICBTOOL_GL_BACKEND", "auto"),
    ]
    assert main(argv) == 0
    depth = read_exr(out / "depth.exr")
    assert depth.shape == (24, 32)
    np.testing.assert_allclose(depth, 2.0, rtol=1e-5)
    assert (out / "dl.png").is_file() and (out / "mask.exr").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["buffers"] == ["dl", "depth", "mask"] and "run_info" in summary
    assert main(["render", "plane", "--out", str(out), "--camera", "path:nope"]) == 1


# --------------------------------------------------------------------------- Sponza
@gl
@pytest.mark.sponza
@pytest.mark.slow
def test_sponza_renders(sponza_path):
    from icbtool.scene.load import load

    toml = os.path.join(os.path.dirname(__file__), "..", "data", "scenes", "sponza.toml")
    scene = load(toml)
    cam = scene.default_camera
    with Rasterizer(scene, _cfg()) as r:
        buf = r.render(cam, ("dl", "albedo", "normal_world", "depth"))
    assert buf.valid.mean() > 0.5
    for n in buf.names:
        assert np.isfinite(getattr(buf, n)).all(), n
    v = buf.valid
    assert (buf.depth[v] > 0).all()
    np.testing.assert_allclose(np.linalg.norm(buf.normal_world[v], axis=-1), 1, atol=1e-4)
    lum = buf.dl[v].mean(-1)
    assert (lum > 0.05 * lum.max()).mean() > 0.02  # the sun lights a part of what is seen
    assert (lum < 1e-6).mean() > 0.1  # and shadows exist
    assert buf.albedo[v].std(0).max() > 0.02  # textures, not flat colours


# ------------------------------------------------------------------------------ DL supersampling
@gl
def test_dl_supersample_is_the_tracers_pixel_filter():
    """dl_supersample = k shades k x k points per pixel (box filter), as the tracer's jittered
    pixels do: against the traced direct light (box-filtered), k = 3 halves the error of pixel
    centres on the Cornell box's edges and penumbrae; the other buffers stay pixel centres."""
    from icbtool.trace import TraceConfig, render

    scene = icb.scene.cornell_box()
    cam = scene.default_camera.resized(32, 32)
    from scipy.ndimage import binary_dilation

    ref = render(scene, cam, TraceConfig(spp=256, max_depth=2, seed=2)).direct
    out = {}
    for k in (1, 3):
        with Rasterizer(scene, RasterConfig(dl_supersample=k)) as r:
            out[k] = r.render(cam)
    # not the light itself (a sliver 1-2 pixels tall whose coverage is a matter of subsample
    # positions) nor its neighbours
    sel = (out[1].mask[..., 0] > 0) & ~binary_dilation(ref.mean(-1) > 2.0, iterations=2)
    err = {k: float(np.abs(out[k].dl - ref)[sel].mean()) for k in out}
    assert err[3] < 0.5 * err[1], err  # measured 0.0031 -> 0.0009
    # k x k points of one pixel = the same view at k times the size, box-filtered
    with Rasterizer(scene) as r:
        big = r.render(cam.resized(96, 96), "dl").dl.reshape(32, 3, 32, 3, 3).mean((1, 3))
    np.testing.assert_allclose(out[3].dl, big, rtol=1e-5, atol=1e-6)
    for name in ("albedo", "normal_world", "depth", "position", "mask"):
        np.testing.assert_array_equal(getattr(out[3], name), getattr(out[1], name))
    with pytest.raises(ValueError, match="dl_supersample"):
        RasterConfig(dl_supersample=0)


# ------------------------------------------------------------------------------ soft shadows
@gl
def test_soft_shadows_match_the_tracers_direct_light():
    """At default settings the area light's penumbrae and fully lit surfaces agree with the
    tracer's direct light (the independent peer; box-filtered pixels, 256 spp) within 2 % and
    1 % per channel: a view inside the Cornell box of the tall block's soft shadow on the red
    wall (grazing incidence) and the floor. Measured: penumbra -0.2 / +0.2 / +0.3 %, lit
    +0.0 / -0.1 / -0.1 %; with the former normal offset at the area lookups and one point per
    pixel the penumbra was -3.0 / -2.3 / -2.1 %."""
    from scipy.ndimage import binary_dilation

    from icbtool.raster.accuracy import interior_pixels, shadow_bias
    from icbtool.trace import TraceConfig, render

    scene = icb.scene.cornell_box()
    cam = icb.Camera.look_at(
        (0.4, 0.9, 0.6), (-1.0, 0.5, -0.4), (0, 1, 0), fov_y_deg=60, height=48, width=48
    )
    ref = render(scene, cam, TraceConfig(spp=256, max_depth=2, seed=3)).direct
    with Rasterizer(scene, _cfg(shadows=False)) as r:
        fine = r.render(cam.resized(192, 192), ("normal_world", "albedo", "position", "dl"))
        free = fine.dl.reshape(48, 4, 48, 4, 3).mean((1, 3))  # the unshadowed light, box filter
    with Rasterizer(scene, _cfg()) as r:
        dl = r.render(cam, "dl").dl
    # not the light seen nor the 2 pixels around it (the ceiling beside it is in its plane)
    seen_light = binary_dilation(free.mean(-1) > 0.5 * free.mean(-1).max(), iterations=2)
    b = shadow_bias(dl, ref, free, interior_pixels(fine, 4) & ~seen_light)
    assert b.penumbra_pixels > 150 and b.lit_pixels > 1000, b
    assert np.all(np.abs(b.penumbra) <= 0.02), b
    assert np.all(np.abs(b.lit) <= 0.01), b


def test_shadow_bias_classifies_and_sums():
    """Known answer: a penumbra pixel 10 % dark and a lit pixel 1 % bright; edges and unlit
    pixels do not count."""
    from icbtool.raster.accuracy import shadow_bias

    ref = np.ones((1, 4, 3), np.float32)
    free = np.array([1.0, 2.0, 1.0, 0.0], np.float32)[None, :, None].repeat(3, -1)
    dl = np.array([1.01, 0.9, 5.0, 0.0], np.float32)[None, :, None].repeat(3, -1)
    select = np.array([[True, True, False, True]])
    b = shadow_bias(dl, ref, free, select)
    assert (b.penumbra_pixels, b.lit_pixels) == (1, 1)
    np.testing.assert_allclose(b.penumbra, -0.1, rtol=1e-5)
    np.testing.assert_allclose(b.lit, 0.01, rtol=1e-4)
    with pytest.raises(ValueError, match="select"):
        shadow_bias(dl, ref, free, select[0])


def test_interior_pixels_are_footprints_on_one_plane():
    """Known answer: two planes meeting at fine column 6 of an 8x8 fine image (k = 4): pixel
    column 0 (fine 0-3, margin to 4) sees one plane, column 1 (fine 4-7) both; background rows
    are never interior."""
    from icbtool.raster import RasterBuffers
    from icbtool.raster.accuracy import interior_pixels

    n = np.zeros((8, 8, 3), np.float32)
    n[..., 2] = 1.0
    pos = np.zeros((8, 8, 3), np.float32)
    pos[:, 6:, 2] = 0.5  # a parallel plane farther along z
    mask = np.ones((8, 8, 1), np.float32)
    cam = icb.Camera.from_fov(60.0, 8, 8)
    fine = RasterBuffers(camera=cam, mask=mask, normal_world=n, position=pos)
    np.testing.assert_array_equal(interior_pixels(fine, 4), [[True, False], [True, False]])
    mask[4:] = 0.0
    np.testing.assert_array_equal(interior_pixels(fine, 4), [[False, False], [False, False]])
    with pytest.raises(ValueError, match="multiple"):
        interior_pixels(fine, 3)
