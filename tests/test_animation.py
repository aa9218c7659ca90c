"""Time in scenes: keyframe tracks, the scene at a time, descriptions with keys, --time."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import icbtool.scene as sc
from icbtool.scene.animation import (
    LightTrack,
    Track,
    animate,
    quaternion_from_axis_angle,
    rotation_matrix,
)


# --------------------------------------------------------------------------- tracks
def test_linear_track_interpolates_and_holds_outside_its_keys():
    tr = Track([0.0, 2.0, 3.0], [[0.0, 0, 0], [2.0, 4, -2], [2.0, 4, 0]])
    np.testing.assert_allclose(tr.at(1.0), [1.0, 2.0, -1.0])
    np.testing.assert_allclose(tr.at(2.5), [2.0, 4.0, -1.0])
    np.testing.assert_allclose(tr.at(-5.0), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(tr.at(99.0), [2.0, 4.0, 0.0])


def test_direction_track_turns_at_constant_angular_speed():
    tr = Track([0.0, 1.0], [[1.0, 0, 0], [0.0, 0, 3.0]], kind="direction")  # normalised on input
    for a in (0.25, 0.5, 0.8):
        d = tr.at(a)
        assert np.linalg.norm(d) == pytest.approx(1.0)
        assert math.degrees(math.acos(d[0])) == pytest.approx(90 * a)


def test_rotation_track_slerps_along_the_shorter_arc():
    q0 = quaternion_from_axis_angle([0, 1, 0], 10.0)
    q1 = -quaternion_from_axis_angle([0, 1, 0], 50.0)  # the same rotation, other hemisphere
    tr = Track([0.0, 1.0], [q0, q1], kind="rotation")
    r = rotation_matrix(tr.at(0.5))
    np.testing.assert_allclose(r, rotation_matrix(quaternion_from_axis_angle([0, 1, 0], 30.0)))


@pytest.mark.parametrize(
    "times, values, kind, message",
    [
        ([0.0, 0.0], [[0.0], [1.0]], "linear", "strictly increasing"),
        ([1.0, 0.5], [[0.0], [1.0]], "linear", "strictly increasing"),
        ([0.0, 1.0], [[0.0], [math.nan]], "linear", "finite"),
        ([0.0, 1.0], [[1.0, 0, 0], [-1.0, 0, 0]], "direction", "opposite"),
        ([0.0], [[0.0, 0, 0]], "direction", "must not be zero"),
    ],
)
def test_bad_tracks_are_refused(times, values, kind, message):
    with pytest.raises(ValueError, match=message):
        Track(times, values, kind)


# --------------------------------------------------------------------------- scene.at
def test_a_static_scene_is_itself_at_every_time():
    s = sc.cornell_box(height=16, width=16)
    assert not s.is_animated and s.at(12.5) is s and s.time == 0.0
    with pytest.raises(ValueError, match="finite"):
        s.at(math.inf)


def test_the_built_in_moving_light_moves_its_polygon_and_its_light_together():
    s = sc.PROCEDURAL["cornell_box_moving_light"](height=16, width=16)
    base = sc.cornell_box(height=16, width=16)
    assert s.is_animated and s.content_hash == base.content_hash  # t = 0: the published box
    half = s.at(0.5)
    light = half.lights[0]
    np.testing.assert_allclose(light.corner, base.lights[0].corner + [0.225, 0, 0])
    emitter = [i for i, m in enumerate(half.materials) if m.name == "emitter:ceiling_light"][0]
    corners = half.vertices[np.unique(half.faces[half.face_material == emitter])]
    np.testing.assert_allclose(corners, light.vertices, atol=1e-6)
    assert np.all(light.contains(corners))
    assert half.time == 0.5 and half.content_hash != s.content_hash
    # the scene at a time depends on the time alone, not on the time it was reached from
    assert half.at(3.7).content_hash == s.at(3.7).content_hash
    assert s.at(3.7).at(0.0).content_hash == s.content_hash


def test_keyed_area_radiance_changes_the_emitter_faces_too():
    s = sc.cornell_box(height=16, width=16)
    light = s.lights[0]
    track = LightTrack(0, light, {"radiance": Track([0.0, 2.0], [light.radiance, [0.0, 0, 0]])})
    a = animate(s, [track], t=1.0)
    emitter = [m for m in a.materials if m.name == "emitter:ceiling_light"][0]
    np.testing.assert_allclose(emitter.emission, light.radiance / 2)
    np.testing.assert_allclose(a.lights[0].radiance, light.radiance / 2)


# --------------------------------------------------------------------------- descriptions
_BOX = """\
v -0.5 0 -0.5
v 0.5 0 -0.5
v 0.5 1 -0.5
v -0.5 1 -0.5
v -0.5 0 0.5
v 0.5 0 0.5
v 0.5 1 0.5
v -0.5 1 0.5
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 4 8 7 3
f 1 5 8 4
f 2 3 7 6
"""
_FLOOR = """\
v -3 0 -3
v 3 0 -3
v 3 0 3
v -3 0 3
f 1 4 3 2
"""


def _description(tmp_path: Path, lights: str, box_keys: str = "", extra: str = "") -> Path:
    (tmp_path / "box.obj").write_text(_BOX)
    (tmp_path / "floor.obj").write_text(_FLOOR)
    text = textwrap.dedent(
        f"""\
        [scene]
        name = "moving"

        [[meshes]]
        path = "floor.obj"

        [[meshes]]
        path = "box.obj"
        translation = [0.0, 0.0, 0.0]
        {box_keys}

        [camera]
        fov_y_deg = 50.0
        height = 24
        width = 32

        [default_camera]
        eye = [0.0, 2.5, 5.0]
        target = [0.0, 0.3, 0.0]
        {extra}
        """
    )
    p = tmp_path / "moving.toml"
    p.write_text(text + lights)
    return p


_POINT = """
[[lights]]
type = "point"
position = [0.0, 3.0, 0.0]
intensity = [8.0, 8.0, 8.0]
name = "lamp"
keyframes = [{t = 0.0, position = [-1.0, 3.0, 0.0]}, {t = 2.0, position = [1.0, 3.0, 1.0]}]
"""


def test_a_moving_mesh_moves_rigidly_about_its_pivot(tmp_path):
    keys = (
        "pivot = [0.0, 0.0, 0.0]\n"
        "keyframes = [{t = 0.0}, {t = 2.0, translate = [1.0, 0.0, 0.0], rotate = [0, 1, 0, 90]}]"
    )
    p = _description(tmp_path, _POINT, keys)
    s0 = sc.load(p)
    replaced = sc.load(p, lights=list(s0.lights))  # new lights drop the light's keys, not the box's
    assert replaced.is_animated and replaced.at(1.0).lights[0].position.tolist() == [-1.0, 3.0, 0.0]
    s1 = s0.at(1.0)
    n_floor = 4
    box0, box1 = s0.vertices[n_floor:].astype(np.float64), s1.vertices[n_floor:].astype(np.float64)
    rot = rotation_matrix(quaternion_from_axis_angle([0, 1, 0], 45.0))
    np.testing.assert_allclose(box1, box0 @ rot.T + [0.5, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(s1.vertices[:n_floor], s0.vertices[:n_floor])  # the floor stays
    np.testing.assert_allclose(
        s1.normals[n_floor:], s0.normals[n_floor:].astype(np.float64) @ rot.T, atol=1e-6
    )
    np.testing.assert_allclose(s1.lights[0].position, [0.0, 3.0, 0.5])
    assert s0.lights[0].position.tolist() == [-1.0, 3.0, 0.0]  # loaded at t = 0: the first key


def test_a_keyed_light_renders_as_the_same_light_placed_statically(tmp_path):
    """The traced scene at t equals a static description with the interpolated light (bit for
    bit: same seed, same geometry)."""
    from icbtool.trace import TraceConfig, render

    p = _description(tmp_path, _POINT)
    at = sc.load(p).at(1.5)
    still = tmp_path / "still"
    still.mkdir()
    q = _description(
        still,
        _POINT.split("keyframes")[0].replace("[0.0, 3.0, 0.0]", "[0.5, 3.0, 0.75]"),
    )
    ref = sc.load(q)
    cam = ref.default_camera
    cfg = TraceConfig(spp=2, seed=3)
    a, b = render(at, cam, cfg), render(ref, cam, cfg)
    assert np.array_equal(a.direct, b.direct) and np.array_equal(a.gi, b.gi)
    assert float(a.direct.mean()) > 0
    assert not np.array_equal(a.direct, render(sc.load(p), cam, cfg).direct)  # t = 0 differs


@pytest.mark.parametrize(
    "lights, box_keys, message",
    [
        (_POINT.replace("t = 2.0", "t = -1.0"), "", r"keyframes\[1\].*strictly increasing"),
        (_POINT.replace("position = [1.0", "colour = [1.0"), "", r"unknown field.*colour"),
        (_POINT.replace("t = 2.0", "t = nan"), "", r"keyframes\[1\].*finite"),
        (_POINT.replace("[8.0, 8.0, 8.0]", "[8.0, 8.0, 8.0]\nnope = 1"), "", "nope"),
        ("", "keyframes = [{t = 0.0, rotate = [0, 0, 0, 30]}]", r"box.*rotate.*non-zero"),
        ("", "keyframes = [{t = 0.0, scale = 2.0}]", r"box.*unknown field.*scale"),
        ("", "keyframes = {t = 0.0}", r"box.*non-empty array of tables"),
        ("", "pivot = [0, nan, 0]\nkeyframes = [{t = 0.0}]", r"box.*pivot must be 3 finite"),
    ],
)
def test_bad_keys_are_one_line_errors_naming_the_file_and_the_key(
    tmp_path, lights, box_keys, message
):
    p = _description(tmp_path, lights, box_keys)
    with pytest.raises(sc.SceneError, match=message) as e:
        sc.read_description(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_a_moving_emissive_mesh_is_refused(tmp_path):
    p = _description(tmp_path, _POINT, "keyframes = [{t = 0.0}, {t = 1.0, translate = [1, 0, 0]}]")
    (tmp_path / "lamp.mtl").write_text("newmtl glow\nKd 0 0 0\nKe 5 5 5\n")
    (tmp_path / "box.obj").write_text("mtllib lamp.mtl\nusemtl glow\n" + _BOX)
    with pytest.raises(sc.SceneError, match="emissive faces cannot move"):
        sc.load(p)


# --------------------------------------------------------------------------- command line
def _icbtool(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "icbtool", *args], capture_output=True, text=True, cwd=cwd
    )


def test_trace_takes_the_scene_time(tmp_path):
    out = tmp_path / "t"
    r = _icbtool(
        "trace", "cornell_box_moving_light", "--time", "1", "--height", "8", "--width", "8",
        "--spp", "1", "--out", str(out), cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "summary.json").read_text())["scene_time"] == 1.0
    bad = _icbtool(
        "trace", "cornell_box", "--time", "nan", "--out", str(tmp_path / "x"), cwd=tmp_path
    )
    assert bad.returncode == 2 and "--time" in bad.stderr and "finite" in bad.stderr
    assert not (tmp_path / "x").exists()
