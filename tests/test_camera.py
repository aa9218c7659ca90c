"""Camera model, camera paths, the scene-aware random walk and the camera placement check."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from icbtool.camera import (
    Camera,
    CameraPath,
    CameraPlacementError,
    look_at_pose,
)
from icbtool.scene import SceneBuilder, check_camera, random_walk

# --------------------------------------------------------------------------- Camera: known answers


def test_look_at_axes():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), (0, 1, 0))
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(cam.right, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(cam.up, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(cam.position, [0, 0, 5])
    # OpenCV axes: +y (down in the image) is world -y here
    np.testing.assert_allclose(cam.world_from_cam[:3, 1], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(cam.cam_from_world @ cam.world_from_cam, np.eye(4), atol=1e-12)


def test_look_at_rejects_degenerate():
    with pytest.raises(ValueError, match="coincide"):
        look_at_pose((1, 2, 3), (1, 2, 3))
    with pytest.raises(ValueError, match="parallel"):
        look_at_pose((0, 0, 0), (0, 5, 0), (0, 1, 0))


def test_project_known_point():
    cam = Camera(96, 128, 100.0, 100.0, 64.0, 48.0)
    uv, depth = cam.project([1.0, 0.5, 2.0])
    np.testing.assert_allclose(uv, [100 * 0.5 + 64, 100 * 0.25 + 48])
    assert depth == pytest.approx(2.0)
    uv, depth = cam.project([0.0, 0.0, -1.0])  # behind
    assert np.all(np.isnan(uv)) and depth < 0


def test_fov_from_K_and_kornia_shift():
    h, w = 120, 160
    f = 0.5 * h / math.tan(math.radians(50.0) / 2)
    cam = Camera.from_K([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], h, w)
    assert cam.fov_y_deg == pytest.approx(50.0)
    assert cam.fov_x_deg == pytest.approx(math.degrees(2 * math.atan(0.5 * w / f)))
    kk = cam.K_kornia()
    np.testing.assert_allclose(kk[:2, 2], [w / 2 - 0.5, h / 2 - 0.5])
    np.testing.assert_allclose(kk[[0, 1], [0, 1]], [f, f])


def test_pixel_centres_and_rays():
    cam = Camera(4, 6, 3.0, 3.0, 3.0, 2.0)
    c = cam.pixel_centers()
    np.testing.assert_allclose(c[0, 0], [0.5, 0.5])
    np.testing.assert_allclose(c[3, 5], [5.5, 3.5])
    o, d, dpd = cam.rays()
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    # a point at distance t along a ray has depth t * depth_per_distance and projects back
    p = o + 2.5 * d
    uv, depth = cam.project(p)
    np.testing.assert_allclose(uv, c, atol=1e-9)
    np.testing.assert_allclose(depth, 2.5 * dpd, atol=1e-9)


def test_gl_projection_maps_pixel_centres():
    cam = Camera(48, 64, 70.0, 65.0, 30.0, 26.0, look_at_pose((1, 2, 3), (0, 0, 0)))
    znear, zfar = 0.1, 100.0
    proj = cam.gl_projection_matrix(znear, zfar)
    view = cam.gl_view_matrix()
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [64, 48], (20, 2))
    depth = rng.uniform(0.5, 50, 20)
    pw = cam.unproject(uv, depth)
    clip = (proj @ view @ np.c_[pw, np.ones(20)].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    # hand computation: x_ndc = 2u/W - 1, y_ndc = 1 - 2v/H (window origin bottom-left)
    np.testing.assert_allclose(ndc[:, 0], 2 * uv[:, 0] / 64 - 1, atol=1e-9)
    np.testing.assert_allclose(ndc[:, 1], 1 - 2 * uv[:, 1] / 48, atol=1e-9)
    # the OpenGL depth mapping: z_ndc = (f + n)/(f - n) - 2 f n / ((f - n) z)
    zn = (zfar + znear) / (zfar - znear) - 2 * zfar * znear / ((zfar - znear) * depth)
    np.testing.assert_allclose(ndc[:, 2], zn, atol=1e-9)
    assert clip[0, 3] == pytest.approx(depth[0])
    with pytest.raises(ValueError):
        cam.gl_projection_matrix(1.0, 0.5)


def test_camera_rejects_bad_input():
    with pytest.raises(ValueError):
        Camera(0, 10, 1, 1, 5, 5)
    with pytest.raises(ValueError):
        Camera(10, 10, -1, 1, 5, 5)
    with pytest.raises(ValueError, match="rotation"):
        Camera(10, 10, 1, 1, 5, 5, np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError):
        Camera.from_fov(180.0, 10, 10)
    with pytest.raises(ValueError, match="unknown"):
        Camera.from_dict({**Camera.from_fov(40, 8, 8).to_dict(), "extra": 1})


# --------------------------------------------------------------------------- Camera: properties
_vec = st.tuples(*[st.floats(-10, 10, allow_nan=False)] * 3)


def _pose(eye, target):
    if np.linalg.norm(np.subtract(target, eye)) < 1e-2:
        target = np.add(eye, (0.0, 0.0, 1.0))
    d = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.99 else (1.0, 0.0, 0.0)
    return look_at_pose(eye, target, up)


@settings(max_examples=60, deadline=None)
@given(
    eye=_vec,
    target=_vec,
    fov=st.floats(10, 150),
    h=st.integers(1, 2000),
    w=st.integers(1, 2000),
    uv=st.tuples(st.floats(0, 1), st.floats(0, 1)),
    depth=st.floats(0.01, 1e3),
)
def test_project_unproject_identity(eye, target, fov, h, w, uv, depth):
    cam = Camera.from_fov(fov, h, w, _pose(eye, target))
    pix = np.array([uv[0] * w, uv[1] * h])
    p = cam.unproject(pix, depth)
    pix2, d2 = cam.project(p)
    assert d2 == pytest.approx(depth, rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(pix2, pix, atol=1e-6 * max(h, w))


@settings(max_examples=40, deadline=None)
@given(
    eye=_vec,
    target=_vec,
    fov=st.floats(10, 150),
    h=st.integers(1, 999),
    w=st.integers(1, 999),
    h2=st.integers(1, 999),
)
def test_dict_round_trip_and_resize_keeps_fov(eye, target, fov, h, w, h2):
    cam = Camera.from_fov(fov, h, w, _pose(eye, target))
    assert Camera.from_dict(cam.to_dict()) == cam
    w2 = max(1, round(h2 * w / h))
    if w2 > 32768:  # an extreme aspect ratio scaled up: refused, with the size in the message
        with pytest.raises(ValueError, match="width"):
            cam.resized(h2, w2)
        return
    r = cam.resized(h2, w2)
    assert r.fov_y_deg == pytest.approx(fov, rel=1e-9)
    assert r.fov_x_deg == pytest.approx(
        math.degrees(2 * math.atan(math.tan(math.radians(cam.fov_x_deg) / 2))), rel=1e-9
    )
    np.testing.assert_array_equal(r.world_from_cam, cam.world_from_cam)


# --------------------------------------------------------------------------- CameraPath
INTR = Camera.from_fov(60, 32, 48)


def test_orbit_radius_and_look_direction():
    c = np.array([1.0, 0.5, -2.0])
    p = CameraPath.orbit(c, 3.0, 1.2, INTR, n=24, duration_s=6.0, look_height=0.3)
    assert len(p) == 24 and p.duration == pytest.approx(6.0)
    target = c + [0, 0.3, 0]
    for cam in p:
        rel = cam.position - c
        assert math.hypot(rel[0], rel[2]) == pytest.approx(3.0)
        assert rel[1] == pytest.approx(1.2)
        d = (target - cam.position) / np.linalg.norm(target - cam.position)
        np.testing.assert_allclose(cam.forward, d, atol=1e-9)
    # a full orbit does not repeat its first camera
    assert np.linalg.norm(p[0].position - p[-1].position) > 0.5


def test_flythrough_through_waypoints_at_constant_speed():
    wp = np.array([[0.0, 1, 0], [4, 1, 1], [6, 2, -2], [10, 1, 0]])
    p = CameraPath.flythrough(wp, INTR, n=200, speed=1.4)
    pos = p.world_from_cam[:, :3, 3]
    np.testing.assert_allclose(pos[0], wp[0], atol=1e-9)
    np.testing.assert_allclose(pos[-1], wp[-1], atol=1e-9)
    dense = np.stack([p.pose_at(t)[:3, 3] for t in np.linspace(0, p.duration, 1000)])
    for w in wp[1:-1]:
        assert np.min(np.linalg.norm(dense - w, axis=1)) < 0.02
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    dt = np.diff(p.times)
    np.testing.assert_allclose(steps / dt, 1.4, rtol=0.02)
    # cameras look along the path
    tang = np.diff(pos, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", tang, p.world_from_cam[:-1, :3, 2])
    assert np.all(cos > 0.95)


def test_velocity_matches_finite_differences():
    wp = np.array([[0.0, 1, 0], [3, 1, 1], [5, 1.5, -1]])
    p = CameraPath.flythrough(wp, INTR, n=40, speed=1.0, targets=wp + [5, 0, 0])
    for t in (0.3 * p.duration, 0.55 * p.duration, 0.8 * p.duration):
        h = 1e-4
        fd = (p.pose_at(t + h)[:3, 3] - p.pose_at(t - h)[:3, 3]) / (2 * h)
        v, w = p.velocity(t)
        np.testing.assert_allclose(v, fd, atol=1e-5)
        r0, r1 = p.pose_at(t - h)[:3, :3], p.pose_at(t + h)[:3, :3]
        from scipy.spatial.transform import Rotation

        w_fd = Rotation.from_matrix(r0.T @ r1).as_rotvec() / (2 * h)
        np.testing.assert_allclose(w, w_fd, atol=1e-4)


def test_path_bad_inputs():
    with pytest.raises(ValueError):
        CameraPath.flythrough([[0, 0, 0]], INTR)
    with pytest.raises(ValueError, match="repeat"):
        CameraPath.flythrough([[0, 0, 0], [0, 0, 0], [1, 0, 0]], INTR)
    with pytest.raises(ValueError):
        CameraPath.flythrough([[0, 0, 0], [1, 0, 0]], INTR, speed=0)
    with pytest.raises(ValueError):
        CameraPath.orbit((0, 0, 0), -1.0, 1.0, INTR)
    with pytest.raises(ValueError, match="increasing"):
        CameraPath(np.array([0.0, 0.0]), np.stack([np.eye(4)] * 2), INTR)
    with pytest.raises(ValueError, match="pose 1"):
        CameraPath(np.array([0.0, 1.0]), np.stack([np.eye(4), np.diag([1, 1, -1, 1.0])]), INTR)
    p = CameraPath.orbit((0, 0, 0), 2.0, 1.0, INTR, n=5)
    q = CameraPath.from_dict(p.to_dict())
    np.testing.assert_array_equal(q.world_from_cam, p.world_from_cam)


# --------------------------------------------------------------------------- scene-aware
def _room():
    """A closed 10 x 3 x 8 room (inward faces), a 2 x 2 x 2 box (outward faces) in the middle."""
    b = SceneBuilder("room")
    m = b.material("white", albedo=(0.7, 0.7, 0.7))
    x0, x1, y0, y1, z0, z1 = -5.0, 5.0, 0.0, 3.0, -4.0, 4.0
    b.add_quad((x0, y0, z0), (0, 0, z1 - z0), (x1 - x0, 0, 0), m)  # floor, normal +y
    b.add_quad((x0, y1, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), m)  # ceiling, -y
    b.add_quad((x0, y0, z0), (x1 - x0, 0, 0), (0, y1 - y0, 0), m)  # back wall z0, +z
    b.add_quad((x0, y0, z1), (0, y1 - y0, 0), (x1 - x0, 0, 0), m)  # front wall z1, -z
    b.add_quad((x0, y0, z0), (0, y1 - y0, 0), (0, 0, z1 - z0), m)  # wall x0, +x
    b.add_quad((x1, y0, z0), (0, 0, z1 - z0), (0, y1 - y0, 0), m)  # wall x1, -x
    b.add_box((0.0, 1.0, 0.0), (2.0, 2.0, 2.0), m)
    return b.build()


def test_room_faces_point_inwards():
    s = _room()
    centre = np.array([0.0, 1.5, 3.0])
    tri = s.vertices[s.faces[:12]].mean(1)
    assert np.all(np.einsum("ij,ij->i", s.face_normals[:12], centre - tri) > 0)


def test_random_walk_stays_clear_and_is_deterministic():
    s = _room()
    intr = Camera.from_fov(60, 16, 16)
    kw = dict(n=150, seed=3, speed=1.4, dt=0.1, height_range=(1.4, 1.8), clearance=0.4)
    p = random_walk(s, intr, **kw)
    q = random_walk(s, intr, **kw)
    np.testing.assert_array_equal(p.world_from_cam, q.world_from_cam)
    r = random_walk(s, intr, **{**kw, "seed": 4})
    assert not np.allclose(r.world_from_cam, p.world_from_cam)
    pos = p.world_from_cam[:, :3, 3]
    assert len(p) == 150 and np.allclose(np.diff(p.times), 0.1)
    # inside the room, clear of the walls and ceiling
    assert np.all(pos[:, 0] > -5 + 0.4) and np.all(pos[:, 0] < 5 - 0.4)
    assert np.all(pos[:, 2] > -4 + 0.4) and np.all(pos[:, 2] < 4 - 0.4)
    assert np.all(pos[:, 1] >= 1.4 - 1e-6) and np.all(pos[:, 1] <= 1.8 + 1e-6)
    # never inside (or within clearance of) the box; the box top is at y = 2 > eye height
    outside = np.maximum(np.abs(pos[:, 0]), np.abs(pos[:, 2])) > 1.0 + 0.4 - 1e-3
    assert np.all(outside)
    # walking speed, smooth heading (bounded yaw rate)
    steps = np.linalg.norm(np.diff(pos[:, [0, 2]], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.14, rtol=1e-6)
    fwd = p.world_from_cam[:, :3, 2]
    yaw = np.unwrap(np.arctan2(fwd[:, 2], fwd[:, 0]))
    assert np.max(np.abs(np.diff(yaw))) <= math.radians(9.0) + 1e-6
    assert np.all(np.abs(fwd[:, 1]) < math.sin(math.radians(10.0)) + 1e-9)
    # it actually explores
    assert np.ptp(pos[:, 0]) > 2.0 or np.ptp(pos[:, 2]) > 2.0


def test_random_walk_bad_inputs():
    s = _room()
    with pytest.raises(ValueError, match="start"):
        random_walk(s, INTR, 10, 0, start=(0.0, 1.5, 0.0))  # inside the box
    with pytest.raises(ValueError, match="n >= 2"):
        random_walk(s, INTR, 1, 0)
    with pytest.raises(ValueError):
        random_walk(s, INTR, 10, 0, height_range=(2.0, 1.0))


def test_check_camera():
    s = _room()
    ok = Camera.look_at((3.0, 1.5, 2.0), (0, 1, 0))
    sur = check_camera(s, ok)
    assert sur.back_fraction == 0.0 and sur.hit_fraction == 1.0
    with pytest.raises(CameraPlacementError, match="inside geometry"):
        check_camera(s, Camera.look_at((0.0, 1.0, 0.2), (3, 1, 0)))
    with pytest.raises(CameraPlacementError, match="from a surface"):
        check_camera(s, Camera.look_at((4.999, 1.5, 0.0), (0, 1, 0)))


#: The walks of tests/data/random_walk_ref.npz: poses written by random_walk before it was split
#: into named steps (_Probe, _Walker, _View); the same seed must still give the same path (the
#: scene descriptions' random_walk paths, Sponza's "walk" included, depend on it). Bit for bit on
#: the host that wrote the file; on another host the float32 ray casts (Embree, numpy) may round
#: a last bit otherwise (6e-8 to 4e-7 on these walks). A change to the walk itself
#: moves poses by far more (a step here is 0.14-0.3 m).
WALK_ATOL = 1e-6
REF_WALKS = {
    "seed3": dict(n=150, seed=3, height_range=(1.4, 1.8), clearance=0.4),
    "seed11_start": dict(n=120, seed=11, start=(-3.0, 1.6, -2.5), turn_rate_deg=90.0),
    "seed5_tight": dict(n=200, seed=5, clearance=0.9, lookahead=0.5, speed=3.0),
}


@pytest.mark.parametrize("key", sorted(REF_WALKS))
def test_random_walk_matches_the_stored_paths(key):
    ref = np.load(Path(__file__).parent / "data" / "random_walk_ref.npz")[key]
    p = random_walk(_room(), Camera.from_fov(60, 16, 16), **REF_WALKS[key])
    np.testing.assert_allclose(p.world_from_cam, ref, rtol=0, atol=WALK_ATOL)


@settings(max_examples=40, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.1, 20), st.floats(0.5, 40), st.floats(0, 1))
def test_orthographic_and_thin_lens_project_unproject_round_trip(x, y, z, f, near):
    """An orthographic camera's project/unproject invert each other (u = fx x + cx, depth
    kept) and a thin lens's are its pinhole's; sample_rays at the lens centre is ``rays``.
    A point on the near plane itself is left out: rounding in the pose decides its side."""
    assume(abs(z - near) > 1e-9)
    pose = look_at_pose((0.5, 1, 6), (0, 0, 0))
    ortho = Camera(30, 40, f, f, 20, 15, pose, projection="orthographic", near_clip=near)
    p = np.array([x, y, z]) @ pose[:3, :3].T + pose[:3, 3]
    uv, depth = ortho.project(p)
    assert depth == pytest.approx(z)
    if z >= near:
        np.testing.assert_allclose(uv, [f * x + 20, f * y + 15], atol=1e-9)
        np.testing.assert_allclose(ortho.unproject(uv, depth), p, atol=1e-9)
    else:
        assert np.isnan(uv).all()
    lens = Camera(30, 40, f, f, 20, 15, pose, aperture_radius=0.2, focus_distance=3)
    np.testing.assert_allclose(lens.project(p)[0], lens.pinhole().project(p)[0], atol=1e-9)
    o, d = lens.sample_rays([[x + 20, y + 15]], [0.5, 0.5])
    o2, d2, _ = lens.rays(np.array([[x + 20, y + 15]]))
    np.testing.assert_allclose(d, d2, atol=1e-12)
    np.testing.assert_allclose(o, o2, atol=1e-12)  # no near clip: from the centre
