"""Scene states in the store and the invalidation rule (icbtool.store.invalidation)."""

from __future__ import annotations

import numpy as np
import pytest

import icbtool.scene as sc
from icbtool import store as st
from icbtool.camera import Camera
from icbtool.scene.animation import MeshTrack, Track, animate
from icbtool.store import invalidation as inv


@pytest.fixture(scope="module")
def moving():
    return sc.PROCEDURAL["cornell_box_moving_light"](height=16, width=16)


# ------------------------------------------------------------------------------------ states
def test_state_ids_follow_the_animated_parameters(moving):
    static = sc.PROCEDURAL["cornell_box"](height=16, width=16)
    assert inv.state_id(static) == inv.STATIC_STATE
    ids = {t: inv.state_id(moving.at(t)) for t in (0.0, 0.5, 1.0, 4.0, 9.0)}
    assert len({ids[0.0], ids[0.5], ids[1.0]}) == 3  # the light is elsewhere at each
    assert ids[4.0] == ids[9.0] == ids[0.0]  # home at 4 s, held after: the same state as at 0
    assert len(ids[0.0]) == 16


def test_all_states_share_group_keys_that_no_static_scene_has(moving):
    keys = {inv.group_keys(moving.at(t)) for t in (0.0, 0.7, 2.5)}
    assert len(keys) == 1
    (sh, _lh), static = keys.pop(), sc.PROCEDURAL["cornell_box"](height=16, width=16)
    assert sh not in (moving.content_hash, static.content_hash)
    assert inv.group_keys(static) == (static.content_hash, static.light_hash)


def test_the_state_tags_survive_the_store_and_its_check(moving, tmp_path):
    cam = Camera.look_at((0, 1, 3), (0, 1, 0), (0, 1, 0), fov_y_deg=40, height=4, width=4)
    now = moving.at(0.5)
    sh, lh = inv.group_keys(now)
    meta = st.RecordMeta(now.name, sh, lh, spp=2, tags=inv.state_tags(now))
    old = st.RecordMeta("cornell_box", "a" * 64, "b" * 16, spp=2)  # a record from before states
    gi = np.ones((4, 4, 3), np.float32)
    with st.open(tmp_path / "s") as s:
        new_id = s.put(st.CRTBuffer(cam, meta, gi=gi))
        old_id = s.put(st.CRTBuffer(cam, old, gi=gi))
    with st.open(tmp_path / "s") as s:
        assert inv.record_state(s.info(new_id).meta) == (inv.state_id(now), 0.5)
        assert inv.record_state(s.get(new_id).meta) == (inv.state_id(now), 0.5)
        assert inv.record_state(s.info(old_id).meta) == (inv.STATIC_STATE, None)
        assert s.check().ok
    report = st.rebuild(tmp_path / "s")  # the state is in the self-describing payload too
    assert new_id in report.recovered
    with st.open(tmp_path / "s") as s:
        assert inv.record_state(s.info(new_id).meta) == (inv.state_id(now), 0.5)


# ------------------------------------------------------------------------------------ changes
def test_a_moved_area_light_changes_the_box_of_its_old_and_new_polygon(moving):
    a, b = moving.at(0.0), moving.at(1.0)
    ch = inv.scene_change(a, b)
    assert ch.lights == (0,) and ch.meshes == () and not ch.everywhere
    pts = np.concatenate([a.lights[0].vertices, b.lights[0].vertices]).astype(np.float64)
    np.testing.assert_allclose(ch.region, [pts.min(0), pts.max(0)])
    assert ch.region[1, 0] - ch.region[0, 0] == pytest.approx(
        np.ptp(a.lights[0].vertices[:, 0]) + 0.45
    )
    assert inv.scene_change(a, moving.at(4.0)).empty  # home again: nothing to invalidate
    static = sc.PROCEDURAL["cornell_box"](height=16, width=16)
    assert inv.scene_change(static, b).everywhere  # not one animation: nothing to bound it by
    assert inv.scene_change(static, a).empty  # ... but the same contents are no change


def test_a_moved_mesh_changes_the_box_of_its_old_and_new_bounds():
    floor = sc.PROCEDURAL["boxes_on_floor"](n_boxes=2, height=8, width=8)
    start, stop = 4, 4 + 24  # the first box after the floor quad
    track = MeshTrack(
        "box0", start, stop, np.zeros(3), translate=Track([0.0, 1.0], [[0, 0, 0], [2, 0, 0]])
    )
    s = animate(floor, meshes=[track])
    ch = inv.scene_change(s, s.at(1.0))
    v0 = s.vertices[start:stop].astype(np.float64)
    assert ch.meshes == ("box0",) and ch.lights == ()
    np.testing.assert_allclose(ch.region[0], v0.min(0), atol=1e-6)
    np.testing.assert_allclose(ch.region[1], v0.max(0) + [2, 0, 0], atol=1e-6)


def test_a_turned_sun_reaches_everything():
    from icbtool.scene.animation import LightTrack

    floor = sc.PROCEDURAL["boxes_on_floor"](n_boxes=1, height=8, width=8)
    sun = floor.lights[0]
    tr = LightTrack(
        0, sun, {"direction": Track([0.0, 1.0], [sun.direction, [0.3, -1.0, 0.0]], "direction")}
    )
    s = animate(floor, [tr])
    ch = inv.scene_change(s, s.at(1.0))
    assert ch.everywhere and ch.region is None
    assert inv.is_affected(ch, np.array([[50.0, 0, 50], [51, 1, 51]]), reach_m=0.1)


# ------------------------------------------------------------------------------------ the rule
def test_seen_bounds_of_a_camera_facing_a_wall_at_known_depth():
    cam = Camera.look_at((0, 0, 0), (0, 0, -1), (0, 1, 0), fov_y_deg=90, height=4, width=4)
    depth = np.full((4, 4, 1), 2.0, np.float32)
    mask = np.ones((4, 4, 1), np.float32)
    b = inv.seen_bounds(cam, depth, mask)
    # fov 90: the outermost pixel centres are at +-0.75 of the half-width, at depth 2: +-1.5
    np.testing.assert_allclose(b, [[-1.5, -1.5, -2.0], [1.5, 1.5, -2.0]], atol=1e-9)
    mask[:, :2] = 0  # only the right half seen
    assert inv.seen_bounds(cam, depth, mask)[0, 0] == pytest.approx(0.5)
    assert inv.seen_bounds(cam, depth, np.zeros_like(mask)) is None


def test_the_rule_reaches_what_lies_within_reach_and_everything_without_one():
    ch = inv.Change(lights=(0,), region=np.array([[0.0, 0, 0], [1, 1, 1]]))
    near = np.array([[1.5, 0, 0], [2, 1, 1]])  # 0.5 from the region
    far = np.array([[4.0, 0, 0], [5, 1, 1]])  # 3 from it
    assert inv.is_affected(ch, near, reach_m=1.0)
    assert not inv.is_affected(ch, far, reach_m=1.0)
    assert inv.is_affected(ch, far)  # no reach given: conservative
    assert not inv.is_affected(inv.Change(), near)  # nothing changed
    assert not inv.is_affected(ch, None)  # a record that sees nothing has no GI
    assert inv.box_distance(far, ch.region) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="reach_m"):
        inv.is_affected(ch, near, reach_m=-1.0)
