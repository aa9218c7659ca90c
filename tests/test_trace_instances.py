"""Mitsuba instances traced by Embree instancing (one BVH per shapegroup, placed copies): the same
hits and images as the flattened copies, and Mitsuba 3's images."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from icbtool.scene import load
from icbtool.scene.instancing import Instancing, instanced
from icbtool.trace import kernels as K
from icbtool.trace.rtc import RtcScene

# a floor, a ceiling light and three instances of a two-shape group: a non-uniformly scaled
# cube and a rotated rectangle; the instances rotated, scaled non-uniformly and moved
_XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective"><float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="0, 5, 9" target="0, 0.6, 0" up="0, 1, 0"/>
    </transform>
    <sampler type="independent"/>
    <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="32"/>
      <rfilter type="box"/></film></sensor>
  <shape type="rectangle"><transform name="to_world"><scale value="8"/>
    <rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.6, 0.6"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="1.5"/>
    <rotate x="1" angle="90"/><translate y="5"/></transform>
    <emitter type="area"><rgb name="radiance" value="6, 6, 6"/></emitter></shape>
  <shape type="shapegroup" id="thing">
    <shape type="cube"><transform name="to_world"><scale x="0.8" y="0.3" z="0.5"/>
      <rotate y="1" angle="20"/><translate y="0.3"/></transform>
      <bsdf type="BSDF_A</bsdf></shape>
    <shape type="rectangle"><transform name="to_world"><scale x="0.6" y="0.4"/>
      <rotate x="1" angle="-60"/><translate y="1.1" z="0.3"/></transform>
      <bsdf type="twosided"><bsdf type="diffuse">
        <rgb name="reflectance" value="0.2, 0.7, 0.3"/></bsdf></bsdf></shape>
  </shape>
  <shape type="instance"><ref id="thing"/></shape>
  <shape type="instance"><ref id="thing"/>
    <transform name="to_world"><scale x="1.6" y="0.7" z="1.1"/><rotate y="1" angle="55"/>
      <translate x="-2.6" z="-0.8"/></transform></shape>
  <shape type="instance"><ref id="thing"/>
    <transform name="to_world"><rotate z="1" angle="25"/><scale x="0.8" y="1.5" z="0.9"/>
      <translate x="2.5" y="0.4" z="0.5"/></transform></shape>
</scene>
"""
_DIFFUSE = 'diffuse"><rgb name="reflectance" value="0.7, 0.4, 0.2"/>'
_GLOSSY = (
    'roughplastic"><rgb name="diffuse_reflectance" value="0.7, 0.4, 0.2"/>'
    '<float name="alpha" value="0.2"/>'
)


def _scene_file(tmp_path, bsdf: str = _DIFFUSE):
    path = tmp_path / "instances.xml"
    path.write_text(_XML.replace("BSDF_A", bsdf))
    return path


def _load(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load(path)


def test_reader_keeps_each_instance_as_a_placed_prototype(tmp_path):
    scene = _load(_scene_file(tmp_path))
    inst = scene.instancing
    assert isinstance(inst, Instancing)
    assert len(inst.protos) == 1 and len(inst.protos[0][1]) == 12 + 2
    assert inst.proto.tolist() == [0, 0, 0]
    assert inst.n_faces == 3 * 14
    assert inst.matches(scene.vertices, scene.faces)
    # the placed prototype is the flattened copy, corner by corner
    pv, pf = inst.protos[0]
    for i in range(3):
        x = inst.xform[i].astype(np.float64)
        world = pv[pf].astype(np.float64) @ x[:, :3].T + x[:, 3]
        a = int(inst.face0[i])
        got = scene.vertices[scene.faces[a : a + len(pf)]]
        np.testing.assert_allclose(got, world, atol=1e-5)
    # a moved mesh no longer matches: the tracer then builds a flat BVH
    moved = scene.vertices.copy()
    moved[scene.faces[int(inst.face0[1])]] += 0.5
    assert not inst.matches(moved, scene.faces)


def test_auto_instancing_threshold_and_forcing(tmp_path):
    inst = _load(_scene_file(tmp_path)).instancing
    assert not instanced(inst, "auto")  # 42 faces: copies are cheaper
    assert instanced(inst, "always")
    assert not instanced(inst, "never")
    assert not instanced(None, "always")
    with pytest.raises(ValueError, match="always or never"):
        instanced(inst, "sometimes")


def test_instanced_bvh_hits_the_faces_the_flat_bvh_hits(tmp_path):
    """Rays from all around: the two-level BVH names the same scene face at the same distance
    as the flat BVH of every copy (the prototype's u, v too)."""
    scene = _load(_scene_file(tmp_path))
    flat = RtcScene(scene.vertices, scene.faces)
    two = RtcScene(scene.vertices, scene.faces, instancing=scene.instancing)
    assert two.n_instances == 3 and two.n_bvh_triangles == len(scene.faces) - 2 * 14
    rng = np.random.default_rng(5)
    n = 4000
    o = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    o[:, 1] = rng.uniform(0.01, 4.5, n)
    target = rng.uniform(-3, 3, (n, 3))
    target[:, 1] = rng.uniform(0, 1.6, n)
    d = target - o
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    out = []
    for rs in (flat, two):
        t, u, v = (np.zeros(n, np.float32) for _ in range(3))
        prim = np.zeros(n, np.int64)
        K.rtc_intersect_mapped(rs.ptr, rs.fn_intersect, o, d, t, prim, u, v, 0, n, rs.prim_map)
        out.append((t, prim, u, v))
    (t0, p0, u0, v0), (t1, p1, u1, v1) = out
    covered = np.zeros(len(scene.faces), bool)
    for a in scene.instancing.face0:
        covered[a : a + 14] = True
    assert covered[p0[p0 >= 0]].sum() > 300  # many rays hit the instances
    same = p0 == p1
    assert same.mean() > 0.998, same.mean()  # (a ray through a shared edge may pick either)
    hit = same & (p0 >= 0)
    np.testing.assert_allclose(t1[hit], t0[hit], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(u1[hit], u0[hit], atol=1e-3)
    np.testing.assert_allclose(v1[hit], v0[hit], atol=1e-3)


@pytest.mark.parametrize("bsdf", [_DIFFUSE, _GLOSSY], ids=["lambert", "general"])
def test_instanced_and_flattened_renders_agree(tmp_path, monkeypatch, bsdf):
    """Same seed, same paths: the instanced BVH changes no hit beyond float rounding, so the
    images agree far below their noise (both kernels)."""
    from icbtool.trace import TraceConfig, render

    scene = _load(_scene_file(tmp_path, bsdf))
    imgs = []
    for how in ("never", "always"):
        monkeypatch.setenv("ICBTOOL_INSTANCING", how)
        r = render(scene, scene.default_camera, TraceConfig(spp=8, max_depth=4, seed=2))
        imgs.append(r.direct + r.gi)
    a, b = imgs
    assert RtcScene.of(scene).n_instances == 3  # (the env still says always)
    assert abs(b.mean() / a.mean() - 1) < 1e-3, (a.mean(), b.mean())
    assert np.mean(np.abs(a - b)) < 1e-3 * a.mean()


@pytest.mark.parametrize("bsdf", [_DIFFUSE, _GLOSSY], ids=["lambert", "general"])
def test_instanced_scene_matches_mitsuba(tmp_path, monkeypatch, bsdf):
    """Rotated, non-uniformly scaled instances (normals through the inverse transpose), traced
    by Embree instancing, against Mitsuba 3's instances: mean bias < 2 % per channel, blurred
    relative RMSE below max(5 %, twice Mitsuba's own seed-to-seed difference)."""
    from test_trace_bsdf import peer_compare_file

    monkeypatch.setenv("ICBTOOL_INSTANCING", "always")
    path = _scene_file(tmp_path, bsdf)
    assert RtcScene.of(_load(path)).n_instances == 3
    bias, rmse, own = peer_compare_file(path, spp=64, max_depth=4)
    assert np.all(np.abs(bias) < 0.02), bias
    assert rmse < max(0.05, 2 * own), (rmse, own)
