"""Tests for icbtool.prefetch: FOV growth, clamp, containment of the predicted frusta."""

from __future__ import annotations

import math

import numpy as np
import pytest

from icbtool.camera import Camera
from icbtool.prefetch import (
    LatencyModel,
    PrefetchConfig,
    depth_range_from_depth,
    predicted_cameras,
    prefetch_camera,
)

CLIENT = Camera.look_at((0.3, 1.0, 3.0), (0.0, 0.8, -1.0), fov_y_deg=45.0, height=96, width=128)
DR = (0.8, 6.0)


def fov(v_t, v_r, **kw) -> float:
    return prefetch_camera(CLIENT, v_t, v_r, PrefetchConfig(**kw), depth_range=DR).fov_y_deg


def test_rest_and_zero_latency_keep_the_client_camera():
    r = prefetch_camera(CLIENT, np.zeros(3), np.zeros(3), PrefetchConfig(), DR)
    assert r.fov_y_deg == pytest.approx(CLIENT.fov_y_deg, abs=1e-9)
    assert r.fov_x_deg == pytest.approx(CLIENT.fov_x_deg, abs=1e-9)
    assert r.pullback == 0 and not r.clamped
    assert (r.camera.height, r.camera.width) == (96, 128)
    np.testing.assert_allclose(r.camera.world_from_cam, CLIENT.world_from_cam)
    moving = PrefetchConfig(latency_s=0.0)
    r0 = prefetch_camera(CLIENT, [1.4, 0.3, -1.0], [0.5, 1.0, 0.2], moving, DR)
    assert r0.fov_y_deg == pytest.approx(CLIENT.fov_y_deg, abs=1e-9)
    assert fov([0, 0, 0], [0, 0, 0], margin_deg=4.0) == pytest.approx(CLIENT.fov_y_deg + 4.0)


def test_fov_grows_with_speed_and_latency_and_is_clamped():
    speeds = [0.2, 0.5, 1.0, 1.4, 3.0]
    f_speed = [fov([s, 0, 0], [0, 0, 0], latency_s=0.1) for s in speeds]
    assert all(b > a for a, b in zip(f_speed, f_speed[1:]))
    f_lat = [fov([1.4, 0, 0], [0, 0, 0], latency_s=t) for t in (0.02, 0.05, 0.1, 0.2)]
    assert all(b > a for a, b in zip(f_lat, f_lat[1:]))
    f_rot = [fov([0, 0, 0], [0, w, 0], latency_s=0.1) for w in (0.5, 1.0, 2.0)]
    assert all(b > a for a, b in zip(f_rot, f_rot[1:]))
    # yaw alone without pull-back: the horizontal half-FOV grows by exactly the yaw angle
    r = prefetch_camera(
        CLIENT, [0, 0, 0], [0, 1.0, 0], PrefetchConfig(latency_s=0.1, motion_model="velocity"), DR
    )
    assert r.fov_x_deg >= CLIENT.fov_x_deg + 2 * math.degrees(0.1) - 1e-6
    for kw in ({"latency_s": 0.5}, {"latency_s": 0.3, "max_fov_deg": 100.0}):
        r = prefetch_camera(CLIENT, [0.5, 0, 0], [3, 3, 3], PrefetchConfig(**kw), DR)
        assert r.fov_y_deg <= PrefetchConfig(**kw).max_fov_deg + 1e-9
        assert r.clamped and r.required_fov_y_deg > r.fov_y_deg


@pytest.mark.parametrize("model", ["axes", "velocity"])
@pytest.mark.parametrize(
    "v_t,v_r",
    [
        ([1.4, 0.0, 0.0], [0, 0, 0]),
        ([0.3, -0.5, 1.2], [0.4, 1.1, 0.2]),
        ([0.0, 0.0, -1.4], [0.0, 0.0, 0.0]),
        ([0, 0, 0], [0.0, 2.0, 0.5]),
    ],
)
def test_prefetched_frustum_contains_the_predicted_frusta(model, v_t, v_r, rng):
    cfg = PrefetchConfig(latency_s=0.1, motion_model=model)
    res = prefetch_camera(CLIENT, v_t, v_r, cfg, DR)
    assert not res.clamped
    ref = res.camera
    for cam in predicted_cameras(CLIENT, v_t, v_r, cfg):
        uv = rng.random((400, 2)) * [cam.width, cam.height]
        z = rng.uniform(*DR, size=400)
        z[:4] = DR[0]  # include the corners at near and far
        z[4:8] = DR[1]
        uv[:8] = [[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]] * 2
        p = cam.unproject(uv, z)
        q, d = ref.project(p)
        assert np.all(d > 0)
        eps = 1e-6
        assert np.all((q[:, 0] >= -eps) & (q[:, 0] <= ref.width + eps))
        assert np.all((q[:, 1] >= -eps) & (q[:, 1] <= ref.height + eps))
    # and it is tight: the FOV cannot be 2 % narrower (some predicted corner touches the border)
    if res.fov_y_deg > CLIENT.fov_y_deg + 0.5:
        narrower = ref.with_fov(res.fov_y_deg * 0.98)
        outside = 0
        for cam in predicted_cameras(CLIENT, v_t, v_r, cfg):
            for z in DR:
                uv = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]])
                q, _ = narrower.project(cam.unproject(uv.astype(float), np.full(4, z)))
                outside += np.sum(
                    (q[:, 0] < 0)
                    | (q[:, 0] > narrower.width)
                    | (q[:, 1] < 0)
                    | (q[:, 1] > narrower.height)
                )
        assert outside > 0


def test_pullback_and_resolution_rules():
    v = [0.0, 0.0, -1.4]
    r = prefetch_camera(CLIENT, v, [0, 0, 0], PrefetchConfig(latency_s=0.1), DR)
    assert r.pullback == pytest.approx(0.14)
    np.testing.assert_allclose(r.camera.position, CLIENT.position - 0.14 * CLIENT.forward)
    np.testing.assert_allclose(r.camera.forward, CLIENT.forward)
    v = [1.4, 0.0, 0.0]
    same = prefetch_camera(CLIENT, v, [0, 0, 0], PrefetchConfig(resolution_rule="same"), DR)
    centre = prefetch_camera(CLIENT, v, [0, 0, 0], PrefetchConfig(resolution_rule="center"), DR)
    near = prefetch_camera(CLIENT, v, [0, 0, 0], PrefetchConfig(resolution_rule="near"), DR)
    assert (same.camera.height, same.camera.width) == (96, 128)
    assert centre.camera.fy == pytest.approx(CLIENT.fy, rel=0.02)  # same centre pixel density
    assert near.camera.fy >= centre.camera.fy * (DR[0] + near.pullback) / DR[0] * 0.98
    capped = prefetch_camera(
        CLIENT, [5, 0, 0], [0, 0, 0], PrefetchConfig(latency_s=0.3, max_pixels=20000), DR
    )
    assert capped.camera.height * capped.camera.width <= 20000
    assert capped.camera.width / capped.camera.height == pytest.approx(128 / 96, rel=0.05)


def test_latency_model_and_validation():
    lm = LatencyModel(render_s=0.05, encode_s=0.01, transfer_s=0.04)
    assert lm.total_s == pytest.approx(0.1)
    with pytest.raises(ValueError, match="render_s"):
        LatencyModel(render_s=-1)
    with pytest.raises(ValueError, match="max_fov_deg"):
        PrefetchConfig(max_fov_deg=180)
    with pytest.raises(ValueError, match="v_t"):
        prefetch_camera(CLIENT, [np.nan, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="z_near"):
        prefetch_camera(CLIENT, [0, 0, 0], [0, 0, 0], depth_range=(0.0, 1.0))
    d = np.full((4, 5, 1), 2.0)
    d[0, 0] = 0.5
    m = np.ones((4, 5, 1))
    assert depth_range_from_depth(d, m) == (0.5, 2.0)
    with pytest.raises(ValueError, match="no valid"):
        depth_range_from_depth(np.zeros((2, 2, 1)))
