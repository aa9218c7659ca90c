"""The cloud and the client of an animated scene: states, stale records, cheap renders that
refine (the moving-light Cornell box at tiny sizes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import icbtool as icb
from icbtool.store import invalidation as inv
from icbtool.system import Client, Cloud, CloudConfig, GIRequest

H = W = 24


@pytest.fixture(scope="module")
def moving():
    return icb.scene.PROCEDURAL["cornell_box_moving_light"](height=H, width=W)


def _cfg(**kw):
    return CloudConfig(prefetch=False, spp=16, cheap_spp=2, denoise=False, max_depth=3, **kw)


def _req(cam, t, seq=0):
    return GIRequest(cam, time_s=t, seq=seq, depth_range=(0.5, 10.0))


def _stored(cloud):
    return [cloud.store.info(i) for i in cloud.store.ids()]


def test_a_record_made_before_the_move_is_stale_after_it_then_cheap_then_refined(moving, tmp_path):
    cam = icb.scene.cornell_camera(H, W)
    with Cloud(moving, tmp_path / "c", _cfg()) as cloud:
        first = cloud.request(_req(cam, 0.0))
        assert not first.cache_hit and not first.stale
        assert first.reference.meta.spp == 16
        assert inv.record_state(first.reference.meta) == (inv.state_id(moving.at(0.0)), 0.0)
        home = cloud.request(_req(cam, 4.0, 1))  # the light is home again: the same state
        assert home.cache_hit and not home.stale and cloud.renders == 1
        moved = cloud.request(_req(cam, 1.0, 2))  # the light moved: the rule reaches it
        assert moved.cache_hit and moved.stale and cloud.stale_served == 1
        np.testing.assert_array_equal(moved.reference.gi, first.reference.gi)  # served stale...
        (rec,) = _stored(cloud)  # ...while a cheap render at the new state replaced it
        assert rec.meta.spp == 2 and inv.record_state(rec.meta)[0] == inv.state_id(moving.at(1.0))
        cheap = cloud.request(_req(cam, 1.0, 3))  # the same state: fresh, and refined
        assert cheap.cache_hit and not cheap.stale and cheap.reference.meta.spp == 2
        (rec,) = _stored(cloud)
        assert rec.meta.spp == 16 and cloud.refinements == 1 and cloud.invalidated == 1
        refined = cloud.request(_req(cam, 1.0, 4)).reference
        assert refined.meta.spp == 16 and cloud.renders == 3
        # the refined record is a render at the new state, to the tracer's noise: the light went
        # +x, so the right half of the box gains GI over the left; on that contrast an
        # independent render (another seed) at the new state is much closer to the refined
        # record than to the record from before the move
        fresh = cloud.render(cam, 99, scene=moving.at(1.0))

        def contrast(rec):
            g, m = rec.gi.mean(-1), rec.mask[..., 0] > 0
            return g[:, W // 2 :][m[:, W // 2 :]].mean() - g[:, : W // 2][m[:, : W // 2]].mean()

        noise = abs(contrast(refined) - contrast(fresh))
        change = abs(contrast(first.reference) - contrast(fresh))
        assert noise < 0.3 * change, (noise, change)


def test_a_record_beyond_the_reach_of_the_change_keeps_serving(moving, tmp_path):
    b = moving.bounds
    centre = 0.5 * (b[0] + b[1])
    # one camera sees only the floor (far below the ceiling light), one the ceiling
    floor = icb.Camera.look_at(
        centre + [0, -0.2, 0], centre + [0, -1.0, 0], (0, 0, 1), fov_y_deg=30, height=H, width=W
    )
    ceiling = icb.Camera.look_at(
        centre + [0, 0.2, 0], centre + [0, 1.0, 0], (0, 0, 1), fov_y_deg=30, height=H, width=W
    )
    with Cloud(moving, tmp_path / "c", _cfg(reach_m=0.5)) as cloud:
        for k, cam in enumerate((floor, ceiling)):
            cloud.request(_req(cam, 0.0, k))
        assert cloud.renders == 2
        far = cloud.request(_req(floor, 1.0, 2))
        near = cloud.request(_req(ceiling, 1.0, 3))
        assert far.cache_hit and not far.stale
        assert near.cache_hit and near.stale
        assert cloud.renders == 3  # only the ceiling's record was rendered again


@pytest.mark.parametrize(
    ("mode", "hit", "stale", "renders"), [("all", False, False, 2), ("none", True, True, 1)]
)
def test_the_baselines_rerender_everything_or_nothing(moving, tmp_path, mode, hit, stale, renders):
    cam = icb.scene.cornell_camera(H, W)
    with Cloud(moving, tmp_path / "c", _cfg(invalidation=mode)) as cloud:
        cloud.request(_req(cam, 0.0))
        after = cloud.request(_req(cam, 1.0, 1))
        assert (after.cache_hit, after.stale, cloud.renders) == (hit, stale, renders)
        spp = {r.meta.spp for r in _stored(cloud)}
        assert spp == {16} and len(cloud.store) == 1  # full invalidation renders at full spp


def test_the_client_rasterizes_the_current_state_and_marks_stale_frames(moving, tmp_path):
    cam = icb.scene.cornell_camera(H, W)
    with (
        Cloud(moving, tmp_path / "c", _cfg()) as cloud,
        Client(moving, cloud) as client,
        icb.raster.Rasterizer(moving.at(1.0)) as rz1,
    ):
        f0 = client.frame(cam, _req(cam, 0.0), time_s=0.0)
        f1 = client.frame(cam, _req(cam, 1.0, 1), time_s=1.0)
        assert not f0.stale and f1.stale and f1.time_s == 1.0
        np.testing.assert_array_equal(f1.wrt.dl, rz1.render(cam).dl)  # DL at the new state
        assert not np.array_equal(f0.wrt.dl, f1.wrt.dl)
        f2 = client.frame(cam, _req(cam, 1.0, 2), time_s=1.0)
        assert not f2.stale  # the cheap render at t = 1 answers now
        # the previous reference (of another state) is not combined with the current one
        np.testing.assert_array_equal(f2.gi, f2.combined.image)
        assert f2.hole_ratio_combined == f2.warped.hole_ratio


def test_bad_invalidation_settings_are_refused():
    with pytest.raises(ValueError, match="invalidation"):
        CloudConfig(invalidation="some")
    with pytest.raises(ValueError, match="reach_m"):
        CloudConfig(reach_m=-1.0)
    with pytest.raises(ValueError, match="cheap_spp"):
        CloudConfig(cheap_spp=0)
    assert dataclasses.replace(CloudConfig(), reach_m=2.0).reach_m == 2.0
