"""Tests for icbtool.warp: known-answer warps, hole causes, round trips, gradients, filling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import icbtool as icb
from icbtool.camera import Camera
from icbtool.warp import WarpConfig, backward, combine, forward, inpaint
from icbtool.warp.functional import BackwardWarp, warp_backward

# --------------------------------------------------------------------------- a tiny ray caster
# Scene: a wall (plane z = WALL_Z, facing the camera) and a box front (the square |x - BOX_X|,
# |y| <= BOX_HALF at z = BOX_Z), cameras near the origin looking down +z.
WALL_Z, BOX_Z, BOX_X, BOX_HALF = 5.0, 3.0, 0.0, 0.5


def _colour(p: np.ndarray, on_box: np.ndarray) -> np.ndarray:
    """A smooth colour of world position; the box is saturated red-ish, the wall is not."""
    x, y = p[..., 0], p[..., 1]
    wall = np.stack([0.5 + 0.2 * np.sin(0.7 * x), 0.5 + 0.2 * np.cos(0.9 * y), 0.4 + 0.1 * x], -1)
    box = np.stack([np.full_like(x, 3.0), 0.1 + 0.05 * x, 0.1 + 0.05 * y], -1)
    return np.where(on_box[..., None], box, wall).astype(np.float32)


def render(cam: Camera, with_box: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image (H,W,3), depth (H,W,1), on_box (H,W)) of the wall-and-box scene."""
    o, d, cosz = cam.rays()
    t_wall = (WALL_Z - o[..., 2]) / d[..., 2]
    t = t_wall
    on_box = np.zeros(t.shape, bool)
    if with_box:
        t_box = (BOX_Z - o[..., 2]) / d[..., 2]
        pb = o + t_box[..., None] * d
        on_box = (np.abs(pb[..., 0] - BOX_X) <= BOX_HALF) & (np.abs(pb[..., 1]) <= BOX_HALF)
        on_box &= t_box > 0
        t = np.where(on_box, t_box, t_wall)
    p = o + t[..., None] * d
    depth = (t * cosz)[..., None].astype(np.float32)
    return _colour(p, on_box), depth, on_box


def cam_at(x: float = 0.0, y: float = 0.0, z: float = 0.0, rotvec=(0, 0, 0), fov=50.0, h=48, w=64):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = (x, y, z)
    return Camera.from_fov(fov, h, w, pose)


# --------------------------------------------------------------------------- known answers
BACKENDS = pytest.mark.parametrize("backend", ["numba", "torch"])


@BACKENDS
def test_identity_warp_is_exact(rng, backend):
    cam = cam_at()
    img = rng.random((48, 64, 3)).astype(np.float32)
    depth = (2.0 + rng.random((48, 64, 1))).astype(np.float32)
    res = backward(img, depth, cam, depth, cam, config=WarpConfig(dtype="float64", backend=backend))
    assert not res.holes.any()
    np.testing.assert_allclose(res.image, img, atol=1e-6)
    assert np.all(res.weight > 1 - 1e-6)
    # float32 geometry: (u * d) / d is not always u, so taps are off by ~1e-5 px
    res = backward(img, depth, cam, depth, cam, config=WarpConfig(backend=backend))
    assert not res.holes.any()
    np.testing.assert_allclose(res.image, img, atol=1e-4)


@BACKENDS
def test_one_pixel_shift_of_a_plane(rng, backend):
    src = cam_at()
    z = 4.0
    tx = z / src.fx  # moves a point at depth z by exactly one pixel
    dst = cam_at(x=tx)
    img = rng.random((48, 64, 3)).astype(np.float32)
    depth = np.full((48, 64, 1), z, np.float32)
    res = backward(img, depth, src, depth, dst, config=WarpConfig(dtype="float64", backend=backend))
    # the target camera moved right: the image moves left by one pixel
    np.testing.assert_allclose(res.image[:, :-1], img[:, 1:], atol=1e-6)
    assert not res.holes[:, :-1].any()
    assert res.outside[:, -1].all() and res.holes[:, -1].all()
    assert not res.disoccluded.any() and not res.no_geometry.any()
    # the forward warp agrees exactly on this integer shift
    fwd = forward(img, depth, src, dst, config=WarpConfig(dtype="float64"))
    np.testing.assert_allclose(fwd.image[:, :-1], img[:, 1:], atol=1e-6)
    assert fwd.holes[:, -1].all() and not fwd.holes[:, :-1].any()
    np.testing.assert_allclose(fwd.depth[:, :-1], z, rtol=1e-6)


@BACKENDS
def test_disoccluded_wall_is_not_filled_with_the_box(backend):
    src, dst = cam_at(x=-0.4), cam_at(x=0.4)
    s_img, s_depth, _ = render(src)
    d_img, d_depth, d_box = render(dst)
    res = backward(s_img, s_depth, src, d_depth, dst, config=WarpConfig(backend=backend))
    # pixels seeing the wall in the target whose wall point the reference's box hides
    p = dst.unproject(dst.pixel_centers(), d_depth[..., 0])
    uv, _ = src.project(p)
    o, dirs, _ = src.rays(uv)  # rays of the reference towards those wall points
    t_box = (BOX_Z - o[..., 2]) / dirs[..., 2]
    pb = o + t_box[..., None] * dirs
    margin = 0.1  # 2 px at the box: keep the bilinear footprint off its edge
    hidden = np.abs(pb[..., 0] - BOX_X) < BOX_HALF - margin
    hidden &= np.abs(pb[..., 1]) < BOX_HALF - margin
    hidden &= ~d_box
    assert hidden.sum() > 30
    assert res.disoccluded[hidden].all()
    assert not res.outside[hidden].any()
    # no ghosts anywhere: no wall pixel of the target is given the box colour (red = 3)
    assert np.all(res.image[~d_box, 0] < 1.0)
    # valid pixels reproduce the target's own rendering (smooth colours, bilinear error only)
    ok = ~res.holes
    assert ok.mean() > 0.7
    np.testing.assert_allclose(res.image[ok], d_img[ok], atol=0.02)
    assert np.array_equal(res.holes, res.outside | res.disoccluded | res.no_geometry)


@BACKENDS
def test_different_resolution_and_fov(backend):
    cfg = WarpConfig(backend=backend)
    dst = cam_at(x=0.1, fov=45.0, h=48, w=64)
    wide = cam_at(fov=70.0, h=96, w=120)  # wider and finer reference
    narrow = cam_at(fov=30.0, h=30, w=40)
    d_img, d_depth, d_box = render(dst, with_box=False)
    for ref in (wide, narrow):
        s_img, s_depth, _ = render(ref, with_box=False)
        res = backward(s_img, s_depth, ref, d_depth, dst, config=cfg)
        assert res.image.shape == (48, 64, 3)
        ok = ~res.holes
        np.testing.assert_allclose(res.image[ok], d_img[ok], atol=0.01)
        # outside exactly where the target point projects outside the reference image
        uv, _ = ref.project(dst.unproject(dst.pixel_centers(), d_depth[..., 0]))
        out = (uv[..., 0] < 0) | (uv[..., 0] > ref.width) | (uv[..., 1] < 0)
        out |= uv[..., 1] > ref.height
        assert np.array_equal(res.outside, out)
        assert not res.disoccluded.any()
    assert not backward(*render(wide, False)[:2], wide, d_depth, dst, config=cfg).holes.any()


@BACKENDS
def test_masks_and_errors(rng, backend):
    cfg = WarpConfig(backend=backend)
    cam = cam_at()
    img = rng.random((48, 64, 3)).astype(np.float32)
    depth = np.full((48, 64, 1), 3.0, np.float32)
    mask = np.ones((48, 64, 1), np.float32)
    mask[:10] = 0
    res = backward(img, depth, cam, depth, cam, dst_mask=mask, config=cfg)
    assert res.no_geometry[:10].all() and not res.no_geometry[10:].any()
    assert np.array_equal(res.holes, res.no_geometry)
    # a source pixel without geometry is not used: those target pixels are disoccluded
    res = backward(img, depth, cam, depth, cam, src_mask=mask, config=cfg)
    assert res.disoccluded[:9].all() and not res.holes[11:].any()
    bad = depth.copy()
    bad[5, 5:8] = 0.0
    with pytest.raises(ValueError, match="3 pixel"):
        backward(img, depth, cam, bad, cam, dst_mask=np.ones_like(mask), config=cfg)
    # without a mask, zero depth is simply no geometry
    res = backward(img, depth, cam, bad, cam, config=cfg)
    assert res.no_geometry.sum() == 3
    with pytest.raises(ValueError, match="src_image"):
        backward(img[:-1], depth, cam, depth, cam, config=cfg)
    with pytest.raises(ValueError, match="dst_depth"):
        backward(img, depth, cam, depth[..., 0:1, None], cam, config=cfg)
    with pytest.raises(ValueError, match="src_depth"):
        warp_backward(
            torch.zeros(1, 3, 4, 4),
            torch.ones(1, 1, 4, 5),
            torch.ones(1, 1, 4, 4),
            torch.eye(3),
            torch.eye(3),
            torch.eye(4),
        )


# --------------------------------------------------------------------------- round trip
def _inner(uv: np.ndarray, cam: Camera) -> np.ndarray:
    u, v = uv[..., 0], uv[..., 1]
    return (u >= 1) & (u <= cam.width - 1) & (v >= 1) & (v <= cam.height - 1)


@settings(max_examples=20, deadline=None)
@given(
    t=st.tuples(*[st.floats(-0.25, 0.25)] * 3),
    r=st.tuples(*[st.floats(-0.05, 0.05)] * 3),
)
def test_round_trip_on_covisible_pixels(t, r):
    a = cam_at()
    b = cam_at(*t, rotvec=r)
    _, da, _ = render(a)
    _, db, _ = render(b)
    # the image to carry: A's own pixel coordinates (a linear field, so bilinear taps are exact)
    coords = a.pixel_centers().astype(np.float32)
    cfg = WarpConfig(dtype="float64")
    ab = backward(coords, da, a, db, b, config=cfg)
    # B pixels carry exact coordinates where all four taps agreed and none was clamped at A's
    # border (the outer half pixel replicates the border, which is not linear)
    exact = (ab.weight > 1 - 1e-6) & _inner(ab.image, a)
    ba = backward(ab.image, db, b, da, a, src_mask=exact, config=cfg)
    uv_in_b, _ = b.project(a.unproject(coords, da[..., 0]))
    co = ~ba.holes & (ba.weight > 1 - 1e-6) & _inner(uv_in_b, b)
    assert co.mean() > 0.3
    err = np.abs(ba.image[co] - coords[co]).max()
    assert err < 0.05, err


# --------------------------------------------------------------------------- gradients
def _tiny_problem():
    g = torch.Generator().manual_seed(0)
    src = torch.rand(1, 2, 4, 5, generator=g, dtype=torch.float64)
    src_depth = torch.full((1, 1, 4, 5), 2.0, dtype=torch.float64)
    dst_depth = 2.0 + 0.05 * torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64)
    K = torch.tensor([[4.0, 0, 2.5], [0, 4.0, 2.0], [0, 0, 1]], dtype=torch.float64)[None]
    pose = torch.eye(4, dtype=torch.float64)[None].clone()
    pose[0, 0, 3] = 0.13  # a fractional-pixel shift (0.26 px)
    pose[0, 1, 3] = -0.07
    return src, src_depth, dst_depth, K, pose


def test_gradcheck_image_and_target_depth():
    src, sd, dd, K, pose = _tiny_problem()
    src.requires_grad_(True)
    dd.requires_grad_(True)

    def f(img, ddepth):
        return warp_backward(img, sd, ddepth, K, K, pose, rel_depth_tol=0.2).image

    assert torch.autograd.gradcheck(f, (src, dd), eps=1e-6, atol=1e-5)


def test_gradcheck_source_depth_soft():
    src, sd, dd, K, pose = _tiny_problem()
    sd = sd + 0.1 * torch.rand(
        sd.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    sd.requires_grad_(True)
    mod = BackwardWarp(rel_depth_tol=0.05, soft_depth=0.05)

    def f(sdepth):
        return mod(src, sdepth, dd, K, K, pose).image

    assert torch.autograd.gradcheck(f, (sd,), eps=1e-6, atol=1e-5)
    out = f(sd)
    out.sum().backward()
    assert sd.grad is not None and sd.grad.abs().sum() > 0


def test_batched_matches_single(rng):
    src, sd, dd, K, pose = _tiny_problem()
    pose2 = pose.clone()
    pose2[0, 0, 3] = -0.2
    batch = warp_backward(
        torch.cat([src, src.flip(-1)]),
        sd.expand(2, -1, -1, -1),
        dd.expand(2, -1, -1, -1),
        K.expand(2, 3, 3),
        K,
        torch.cat([pose, pose2]),
    )
    one = warp_backward(src.flip(-1), sd, dd, K, K, pose2)
    torch.testing.assert_close(batch.image[1:], one.image)
    torch.testing.assert_close(batch.holes[1:], one.holes)


# --------------------------------------------------------------------------- forward warp
def test_forward_agrees_with_backward_on_covisible_pixels():
    src, dst = cam_at(), cam_at(0.15, -0.05, 0.1, rotvec=(0.01, -0.02, 0.0))
    s_img, s_depth, _ = render(src)
    _, d_depth, _ = render(dst)
    bw = backward(s_img, s_depth, src, d_depth, dst)
    fw = forward(s_img, s_depth, src, dst)
    # away from depth edges (a nearest splat is off by up to half a pixel)
    import cv2

    z = d_depth[..., 0]
    k = np.ones((5, 5), np.uint8)
    edge = cv2.dilate(z, k) > 1.05 * cv2.erode(z, k)
    both = ~bw.holes & ~fw.holes & (bw.weight > 0.999) & ~edge
    assert both.mean() > 0.6
    # nearest splat: up to ~0.7 px position error on a smooth image (gradient < 0.02 / px)
    np.testing.assert_allclose(fw.image[both], bw.image[both], atol=0.03)
    np.testing.assert_allclose(fw.depth[both], d_depth[both], rtol=0.01)
    # a wide disocclusion (sideways move) is a hole in the forward warp too
    side = cam_at(0.5)
    _, side_depth, _ = render(side)
    bw = backward(s_img, s_depth, src, side_depth, side)
    fw = forward(s_img, s_depth, src, side)
    assert bw.disoccluded.sum() > 30
    assert fw.holes[bw.disoccluded].mean() > 0.8


# --------------------------------------------------------------------------- combine, inpaint
def test_combine_picks_the_valid_reference():
    dst = cam_at()
    left, right = cam_at(x=-0.5), cam_at(x=0.5)
    _, d_depth, _ = render(dst)
    d_img = render(dst)[0]
    rl = backward(*render(left)[:2], left, d_depth, dst)
    rr = backward(*render(right)[:2], right, d_depth, dst)
    assert rl.disoccluded.sum() > 20 and rr.disoccluded.sum() > 20
    both = combine([rl, rr])
    assert both.holes.sum() < min(rl.holes.sum(), rr.holes.sum())
    only_r = rl.holes & ~rr.holes
    assert only_r.any()
    assert np.all(both.source[only_r] == 1)
    np.testing.assert_array_equal(both.image[only_r], rr.image[only_r])
    assert np.all(both.source[~rl.holes] >= 0)
    ok = ~both.holes
    np.testing.assert_allclose(both.image[ok], d_img[ok], atol=0.02)
    assert np.array_equal(both.holes, rl.holes & rr.holes)
    assert np.array_equal(both.holes, both.outside | both.disoccluded | both.no_geometry)


def test_combine_prefers_the_denser_reference():
    dst = cam_at()
    near, far = cam_at(fov=40, h=96, w=128), cam_at(z=-1.0, fov=70)  # far: pulled back, coarse
    _, d_depth, _ = render(dst, False)
    r_far = backward(*render(far, False)[:2], far, d_depth, dst)
    r_near = backward(*render(near, False)[:2], near, d_depth, dst)
    both = combine([r_far, r_near])
    common = ~r_far.holes & ~r_near.holes
    assert common.sum() > 100 and np.all(both.source[common] == 1)


def test_inpaint_fills_and_masks_still_report():
    src, dst = cam_at(x=-0.4), cam_at(x=0.4)
    s_img, s_depth, _ = render(src)
    d_img, d_depth, _ = render(dst)
    res = backward(s_img, s_depth, src, d_depth, dst)
    filled = inpaint(res, d_depth)
    assert np.array_equal(filled.holes, res.holes)
    assert np.array_equal(filled.disoccluded, res.disoccluded)
    assert np.array_equal(filled.inpainted, res.holes & ~res.no_geometry)
    np.testing.assert_array_equal(filled.image[~res.holes], res.image[~res.holes])
    h = res.disoccluded
    assert np.all(filled.image[h] > 0.1)  # filled from the surrounding wall colours
    err_before = np.abs(res.image[h] - d_img[h]).mean()
    err_after = np.abs(filled.image[h] - d_img[h]).mean()
    assert err_after < 0.3 * err_before


def test_lazy_attribute_and_config_validation():
    assert icb.warp.backward is backward
    with pytest.raises(ValueError, match="rel_depth_tol"):
        WarpConfig(rel_depth_tol=0)
    with pytest.raises(ValueError, match="splat"):
        WarpConfig(splat="gauss")  # type: ignore[arg-type]
    assert math.isfinite(WarpConfig().min_weight)


# --------------------------------------------------------------------------- cross-module
@pytest.mark.gl
def test_raster_buffers_warp_between_cornell_cameras():
    """Raster depth warps camera A's albedo and DL to camera B; on co-visible pixels they equal
    B's own raster buffers (albedo exactly up to edge pixels; DL is view-independent diffuse)."""
    from icbtool.raster import RasterConfig, Rasterizer

    scene = icb.scene.cornell_box()
    a = icb.scene.cornell_camera(96, 96)
    pose = a.world_from_cam.copy()
    pose[:3, :3] = pose[:3, :3] @ Rotation.from_rotvec([0.0, 0.06, 0.0]).as_matrix()
    pose[:3, 3] += 0.25 * a.right + 0.4 * a.forward
    b = Camera.from_fov(40.0, 80, 112, pose)  # another pose, FOV and size
    with Rasterizer(scene, RasterConfig(backend="auto")) as r:
        ra, rb = r.render(a), r.render(b)
    img_a = np.concatenate([ra.albedo, ra.dl], -1)
    res = backward(img_a, ra.depth, a, rb.depth, b, src_mask=ra.mask, dst_mask=rb.mask)
    assert np.array_equal(res.no_geometry, ~rb.valid)
    ok = ~res.holes & (res.weight > 0.999)
    assert ok.sum() > 0.85 * rb.valid.sum()
    # away from material edges (bilinear taps straddle two albedos there)
    import cv2

    alb = rb.albedo.sum(-1)
    k = np.ones((3, 3), np.uint8)
    flat = (cv2.dilate(alb, k) - cv2.erode(alb, k)) < 1e-3
    sel = ok & flat
    np.testing.assert_allclose(res.image[sel][:, :3], rb.albedo[sel], atol=2e-3)
    dl = rb.dl[sel]
    rel = np.abs(res.image[sel][:, 3:] - dl) / (np.abs(dl) + 0.05)
    assert np.median(rel) < 0.02 and np.mean(rel < 0.1) > 0.95


def test_slope_aware_depth_test_keeps_grazing_surfaces():
    """A plane at ~60 deg (up to ~85 deg at the image edge) to the view: raw tap depths differ
    by > 2 % per pixel, extrapolated ones agree, so the slope-aware test keeps all four taps
    (test_disoccluded_wall_is_not_filled_with_the_box checks that edges still fail)."""

    def plane_depth(cam: Camera) -> np.ndarray:
        # plane z = 4 + 1.8 * x (world), cameras looking down +z near the origin
        o, d, cosz = cam.rays()
        t = (4.0 + 1.8 * o[..., 0] - o[..., 2]) / (d[..., 2] - 1.8 * d[..., 0])
        return (t * cosz)[..., None].astype(np.float32)

    src = cam_at(fov=40)
    dst = cam_at(x=0.013, y=0.007, fov=40)
    ds, dd = plane_depth(src), plane_depth(dst)
    assert (ds > 0).all() and (dd > 0).all()
    rel_step = np.abs(np.diff(ds[..., 0], axis=1)) / ds[:, 1:, 0]
    assert np.median(rel_step) > 0.025
    img = src.pixel_centers().astype(np.float32)
    raw = backward(img, ds, src, dd, dst, config=WarpConfig(slope_limit=0.0))
    aware = backward(img, ds, src, dd, dst)
    inner = ~aware.outside
    assert (raw.weight[inner] < 0.999).mean() > 0.5
    assert (aware.weight[inner] > 0.999).mean() > 0.95


def test_precomputed_slopes_give_the_same_warp():
    from icbtool.warp.functional import inverse_depth_slopes

    src, dst = cam_at(x=-0.3), cam_at(x=0.2, rotvec=(0, 0.03, 0))
    s_img, s_depth, _ = render(src)
    _, d_depth, _ = render(dst)
    t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None]  # noqa: E731
    K_s, K_d = torch.from_numpy(src.K)[None].float(), torch.from_numpy(dst.K)[None].float()
    pose = torch.from_numpy(src.cam_from_world @ dst.world_from_cam)[None].float()
    a = warp_backward(t(s_img), t(s_depth), t(d_depth), K_s, K_d, pose)
    slopes = inverse_depth_slopes(t(s_depth))
    b = warp_backward(t(s_img), t(s_depth), t(d_depth), K_s, K_d, pose, src_slopes=slopes)
    torch.testing.assert_close(a.image, b.image)
    assert torch.equal(a.holes, b.holes)
    with pytest.raises(ValueError, match="src_slopes"):
        warp_backward(t(s_img), t(s_depth), t(d_depth), K_s, K_d, pose, src_slopes=slopes[:, :1])


# --------------------------------------------------------------------------- numba vs torch
def _scene_case(seed: int):
    """A random pose/size pair of cameras in the wall-and-box scene, the target wider than the
    reference (so some target pixels are outside it) and often disoccluding."""
    r = np.random.default_rng(seed)
    sizes = [(48, 64), (40, 40), (60, 90), (33, 47)]
    cams = []
    for i, fov in enumerate((r.uniform(35, 55), r.uniform(60, 80))):
        h, w = sizes[(seed + i) % 4]
        pose = r.uniform(-0.4, 0.4, 3)
        cams.append(cam_at(*pose, rotvec=r.uniform(-0.1, 0.1, 3), fov=fov, h=h, w=w))
    return cams[0], cams[1]


def _assert_backends_agree(a, b, atol=1e-5):
    for name in ("holes", "outside", "disoccluded", "no_geometry", "source"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(a.image, b.image, atol=atol, rtol=0)
    np.testing.assert_allclose(a.weight, b.weight, atol=atol, rtol=0)
    np.testing.assert_allclose(a.density, b.density, atol=atol, rtol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_numba_and_torch_backends_agree_on_random_scenes(seed):
    src, dst = _scene_case(seed)
    r = np.random.default_rng(100 + seed)
    _, s_depth, _ = render(src)
    _, d_depth, _ = render(dst)
    # a random image (each tap's value is visible), 1 to 4 channels
    img = r.random((src.height, src.width, 1 + seed % 4)).astype(np.float32)
    kw = {}
    if seed % 3 == 1:  # masks with holes (source and target)
        kw = dict(
            src_mask=(r.random((src.height, src.width, 1)) > 0.1).astype(np.float32),
            dst_mask=r.random((dst.height, dst.width)) > 0.1,
        )
    opts = [
        dict(),
        dict(slope_limit=0.0),
        dict(soft_depth=0.05, rel_depth_tol=0.05),
        dict(min_weight=0.3, slope_limit=0.5),
    ][seed % 4]
    res = {
        be: backward(
            img,
            s_depth,
            src,
            d_depth,
            dst,
            **kw,
            config=WarpConfig(dtype="float64", backend=be, **opts),
        )
        for be in ("numba", "torch")
    }
    _assert_backends_agree(res["numba"], res["torch"])
    # each case exercises valid pixels and holes outside the reference
    assert (~res["numba"].holes).sum() > 50 and res["numba"].outside.any()


def test_numba_and_torch_backends_agree_on_disocclusion_and_fov_change():
    """The disocclusion case, a wide fine reference and a narrow coarse one, in float64 (exact
    masks) and float32 (the kernel computes in float64, torch in float32: a tap whose depth test
    is decided by the last bits may differ, on a tiny fraction of pixels)."""
    dst = cam_at(x=0.4)
    refs = [cam_at(x=-0.4), cam_at(fov=70.0, h=96, w=120), cam_at(x=0.2, fov=30.0, h=30, w=40)]
    _, d_depth, _ = render(dst)
    for ref in refs:
        s_img, s_depth, _ = render(ref)
        for dt in ("float64", "float32"):
            a, b = (
                backward(s_img, s_depth, ref, d_depth, dst, config=WarpConfig(dtype=dt, backend=be))
                for be in ("numba", "torch")
            )
            if dt == "float64":
                _assert_backends_agree(a, b)
            else:
                assert (a.holes != b.holes).mean() < 1e-3
                same = (a.holes == b.holes) & (np.abs(a.weight - b.weight) < 1e-4)
                assert same.mean() > 0.995
                np.testing.assert_allclose(a.image[same], b.image[same], atol=1e-4)
    res = backward(*render(refs[0])[:2], refs[0], d_depth, dst)
    assert res.disoccluded.sum() > 30  # the case does disocclude


def test_numba_threads_give_identical_results():
    """Large enough to be split into row blocks over threads: the result does not depend on the
    number of threads (nor on which thread did which block)."""
    src, dst = cam_at(x=-0.3, h=150, w=240), cam_at(x=0.25, rotvec=(0, 0.04, 0), h=160, w=240)
    s_img, s_depth, _ = render(src)
    _, d_depth, _ = render(dst)
    one = backward(s_img, s_depth, src, d_depth, dst, config=WarpConfig(threads=1))
    for threads in (2, 3):
        many = backward(s_img, s_depth, src, d_depth, dst, config=WarpConfig(threads=threads))
        _assert_backends_agree(one, many, atol=0.0)
    ref = backward(
        s_img, s_depth, src, d_depth, dst, config=WarpConfig(dtype="float64", backend="torch")
    )
    num = backward(s_img, s_depth, src, d_depth, dst, config=WarpConfig(dtype="float64"))
    _assert_backends_agree(num, ref)


def test_backend_choice_is_explicit(monkeypatch):
    with pytest.raises(ValueError, match="backend"):
        WarpConfig(backend="cuda")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="threads"):
        WarpConfig(threads=0)
    cam = cam_at()
    img = np.ones((48, 64, 3), np.float32)
    depth = np.full((48, 64, 1), 3.0, np.float32)
    # numba missing: 'auto' and 'numba' fail loudly (no silent fall back to torch); 'torch' works
    monkeypatch.setitem(__import__("sys").modules, "icbtool.warp._numba", None)
    for be in ("auto", "numba"):
        with pytest.raises(ImportError, match="backend='torch'"):
            backward(img, depth, cam, depth, cam, config=WarpConfig(backend=be))
    res = backward(img, depth, cam, depth, cam, config=WarpConfig(backend="torch"))
    assert not res.holes.any()


@pytest.mark.parametrize("splat", ["nearest", "footprint2"])
def test_numba_and_torch_forward_warps_agree(splat):
    """Rotated cameras (no two points land on one pixel at exactly the same depth, where the
    winner is arbitrary), with a source mask, in float64: the same z-buffer, holes and colours."""
    src = cam_at(-0.2, 0.05, 0.0, rotvec=(0.02, -0.03, 0.01), h=40, w=56)
    dst = cam_at(0.2, -0.05, 0.15, rotvec=(-0.01, 0.04, 0.02), fov=55.0, h=48, w=64)
    s_img, s_depth, _ = render(src)
    r = np.random.default_rng(7)
    mask = r.random((40, 56)) > 0.05
    res = {
        be: forward(
            s_img,
            s_depth,
            src,
            dst,
            src_mask=mask,
            config=WarpConfig(dtype="float64", splat=splat, backend=be),
        )
        for be in ("numba", "torch")
    }
    a, b = res["numba"], res["torch"]
    np.testing.assert_array_equal(a.holes, b.holes)
    np.testing.assert_allclose(a.depth, b.depth, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.holes.any() and (~a.holes).mean() > 0.5
