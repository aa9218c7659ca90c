"""Mitsuba 3 scene files, multi-mesh descriptions, first views of interiors, loader messages.

The hand-written fixture tests/data/scenes/mitsuba/fixture.xml states its known answers next to
each element (areas, transforms, camera, lights).
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

import icbtool.scene as sc
from icbtool.camera import Camera
from icbtool.scene import SceneError, SceneRepairWarning, load, spectra
from icbtool.scene.mitsuba import read_mitsuba
from icbtool.scene.obj import MAX_APPROXIMATED_ALBEDO, MaterialApproximationWarning
from icbtool.scene.types import Sky

DATA = Path(__file__).parent / "data" / "scenes" / "mitsuba"
FIXTURE = DATA / "fixture.xml"
SEG = sc.mitsuba.SPHERE_SEGMENTS


def _mitsuba(variant: str = "scalar_rgb"):
    """Mitsuba 3, the reader's peer (``make install`` installs it): missing is a failure."""
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - the install puts it there
        pytest.fail(f"Mitsuba 3 is the Mitsuba reader's peer, installed by `make install` ({e})")
    mi.set_variant(variant)
    return mi


def _load(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load(path, **kw)
    return scene, [str(w.message) for w in caught], [w.category for w in caught]


def _area(scene, name: str) -> float:
    i = [m.name for m in scene.materials].index(name)
    return float(scene.face_areas[scene.face_material == i].sum())


def _polygon_area(n: int) -> float:
    """Area of the regular n-gon inscribed in the unit circle."""
    return 0.5 * n * math.sin(2 * math.pi / n)


# --------------------------------------------------------------------------- the fixture
def test_fixture_shapes_areas_and_transforms():
    s, _, _ = _load(FIXTURE)
    assert _area(s, "white") == pytest.approx(80.0, rel=1e-6)
    assert _area(s, "plastic") == pytest.approx(6.0, rel=1e-6)
    assert _area(s, "checker") == pytest.approx(4.0, rel=1e-6)
    assert _area(s, "bumpy") == pytest.approx(0.5, rel=1e-6)
    assert _area(s, "gold") == pytest.approx(0.25 * _polygon_area(SEG), rel=1e-6)
    tube = SEG * 2 * 0.25 * math.sin(math.pi / SEG) * 2  # the 64-gon's perimeter x height
    assert _area(s, "masked") == pytest.approx(tube, rel=1e-6)
    assert _area(s, "glass") == pytest.approx(math.pi, rel=1e-2)  # tessellated sphere
    # counts: 2 + 2 (rectangles) + 12 (cube) + sphere + disk + tube + quad + triangle
    n_sphere = SEG * (2 + 2 * (SEG // 2 - 2))
    assert s.n_triangles == 2 + 2 + 12 + n_sphere + SEG + 2 * SEG + 2 + 1

    def bounds(name):
        i = [m.name for m in s.materials].index(name)
        v = s.vertices[np.unique(s.faces[s.face_material == i])]
        return v.min(0), v.max(0)

    lo, hi = bounds("white")  # scale (5, 4) then -90 degrees about x: the xz plane
    np.testing.assert_allclose(lo, [-5, 0, -4], atol=1e-5)
    np.testing.assert_allclose(hi, [5, 0, 4], atol=1e-5)
    lo, hi = bounds("plastic")  # the matrix: a unit cube centred at (2, 0.5, 0)
    np.testing.assert_allclose(lo, [1.5, 0, -0.5], atol=1e-6)
    np.testing.assert_allclose(hi, [2.5, 1, 0.5], atol=1e-6)
    lo, hi = bounds("glass")
    np.testing.assert_allclose((lo + hi) / 2, [-2, 1, 0], atol=1e-6)
    np.testing.assert_allclose(hi - lo, [1, 1, 1], atol=2e-3)
    lo, hi = bounds("checker")  # the OBJ quad, moved to z = -3
    np.testing.assert_allclose(lo, [-1, 0, -3], atol=1e-6)
    np.testing.assert_allclose(hi, [1, 2, -3], atol=1e-6)
    lo, hi = bounds("masked")  # the tube from p0 to p1
    np.testing.assert_allclose(lo, [2.75, 0, -2.25], atol=1e-6)
    np.testing.assert_allclose(hi, [3.25, 2, -1.75], atol=1e-6)
    # the floor faces +y, the disk too; the PLY triangle is flat shaded (+y)
    fn = s.face_normals
    for name in ("white", "gold", "bumpy"):
        i = [m.name for m in s.materials].index(name)
        n = fn[s.face_material == i]
        np.testing.assert_allclose(n, np.tile([0, 1, 0], (len(n), 1)), atol=1e-6)


def test_fixture_camera_lights_sky_depth():
    s, _, _ = _load(FIXTURE)
    cam = s.default_camera
    assert (cam.height, cam.width) == (48, 64)
    assert cam.fx == pytest.approx(32 / math.tan(math.radians(30)))
    assert cam.fov_x_deg == pytest.approx(60.0)
    np.testing.assert_allclose(cam.position, [0, 1, 6])
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(cam.right, [1, 0, 0], atol=1e-12)  # Mitsuba's +x is left
    np.testing.assert_allclose(cam.up, [0, 1, 0], atol=1e-12)
    # the point the camera looks at lands on the image centre
    uv, depth = cam.project(np.array([[0.0, 1.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-9)
    assert depth[0] == pytest.approx(6.0)
    assert s.max_depth == 5
    np.testing.assert_allclose(s.up, [0, 1, 0])
    kinds = sorted(lt.kind for lt in s.lights)
    assert kinds == ["area", "directional", "point", "spot"]
    (area,) = s.lights_of("area")
    assert area.area == pytest.approx(0.25)
    np.testing.assert_allclose(area.normal, [0, -1, 0], atol=1e-9)
    np.testing.assert_allclose(area.radiance, [10, 8, 6])
    (pt,) = s.lights_of("point")
    np.testing.assert_allclose(pt.position, [1, 2, 3])
    np.testing.assert_allclose(pt.intensity, [5, 5, 5])
    (spot,) = s.lights_of("spot")
    np.testing.assert_allclose(spot.position, [0, 4, 0])
    np.testing.assert_allclose(spot.direction, [0, -1, 0], atol=1e-12)
    assert (spot.inner_deg, spot.outer_deg) == (22.5, 30.0)
    (sun,) = s.lights_of("directional")
    np.testing.assert_allclose(sun.direction, [0, -math.sqrt(0.5), -math.sqrt(0.5)])
    assert s.sky.kind == "uniform"
    np.testing.assert_allclose(s.sky.zenith, [0.1, 0.2, 0.3])


def test_fixture_bsdfs_are_declared_or_follow_the_one_rule_with_one_warning():
    s, msgs, cats = _load(FIXTURE)
    m = {x.name: x for x in s.materials}
    np.testing.assert_allclose(m["white"].albedo, [0.7, 0.6, 0.5])
    f = ((1.5 - 1) / (1.5 + 1)) ** 2  # plastic: int_ior 1.5, ext_ior 1.0
    np.testing.assert_allclose(m["plastic"].albedo, f + (1 - f) * np.array([0.5, 0.1, 0.1]))
    np.testing.assert_allclose(m["glass"].albedo, [0.8, 0.8, 0.8])  # 1.0 capped
    au = np.array(sc.mitsuba.METAL_F0["Au"])
    np.testing.assert_allclose(m["gold"].albedo, au * MAX_APPROXIMATED_ALBEDO / au.max())
    np.testing.assert_allclose(m["masked"].albedo, [0.2, 0.4, 0.6])
    assert m["checker"].is_textured
    np.testing.assert_allclose(m["checker"].texture[0, 0], [1, 1, 1])
    for mat in s.materials:
        assert mat.albedo.max() < 1 or mat.name in ("checker",)
    approx = [x for x, c in zip(msgs, cats) if c is MaterialApproximationWarning]
    # the tracer evaluates these exactly (albedo above: the raster's stand-in), no warning
    from icbtool.scene import bsdf as sb

    for name in ("plastic", "glass", "gold", "masked", "bumpy"):
        assert m[name].bsdf is not None, name
        assert not any(f"material '{name}'" in x for x in approx), name
    assert isinstance(m["gold"].bsdf, sb.Conductor | sb.TwoSided)
    assert isinstance(m["masked"].bsdf, sb.Mask)
    assert isinstance(m["bumpy"].bsdf, sb.BumpMap)
    assert isinstance(m["bumpy"].bsdf.bsdf, sb.RoughPlastic)
    assert m["bumpy"].bsdf.texture.path.endswith("checker.png")
    assert m["white"].bsdf is None  # diffuse stays icbtool's Lambert (the fast kernel)


def test_fixture_unsupported_elements_are_named_with_their_line():
    ms = read_mitsuba(FIXTURE)
    text = FIXTURE.read_text().splitlines()
    line_curve = next(i for i, t in enumerate(text, 1) if 'type="bsplinecurve"' in t)
    line_medium = next(i for i, t in enumerate(text, 1) if "<medium" in t)
    assert f"<shape bsplinecurve> ({FIXTURE}:{line_curve})" in ms.skipped
    assert f"<medium homogeneous> ({FIXTURE}:{line_medium})" in ms.skipped
    assert ms.shapes == 8
    _, msgs, _ = _load(FIXTURE)
    assert any(f"fixture.xml:{line_curve}: <shape bsplinecurve>" in x for x in msgs)


def test_params_override_defaults():
    s, _, _ = _load(FIXTURE, params={"depth": 3, "res": 32})
    assert s.max_depth == 3 and s.default_camera.height == 32
    assert s.default_camera.fx == pytest.approx(32 / math.tan(math.radians(30)))
    with pytest.raises(SceneError, match=r"up_axis applies to mesh files"):
        load(FIXTURE, up_axis="z")
    with pytest.raises(TypeError, match=r"unknown override\(s\) \['scale'\]"):
        load(FIXTURE, scale=2.0)


def test_shapes_without_a_bsdf_reflect_as_mitsubas_default(tmp_path):
    """A shape without a BSDF gets Mitsuba's default diffuse: reflectance 0.5, and 0 (black)
    when the shape is an area emitter; each albedo equals the one Mitsuba 3 builds."""
    mi = _mitsuba()
    p = tmp_path / "s.xml"
    p.write_text(
        '<scene version="3.0.0">\n'
        '  <shape type="rectangle" id="plain"/>\n'
        '  <shape type="rectangle" id="light"><transform name="to_world">'
        '<translate z="1"/></transform>\n'
        '    <emitter type="area"><rgb name="radiance" value="2"/></emitter></shape>\n'
        "</scene>\n"
    )
    s, _, _ = _load(p)
    theirs = {
        sh.id(): float(mi.traverse(sh.bsdf())["reflectance.value"])
        for sh in mi.load_file(str(p)).shapes()
    }
    ours = {("light" if np.any(m.emission > 0) else "plain"): m.albedo for m in s.materials}
    assert theirs == {"plain": 0.5, "light": 0.0}
    for k, v in theirs.items():
        np.testing.assert_allclose(ours[k], v)


def test_unknown_property_and_missing_parameter(tmp_path):
    p = tmp_path / "s.xml"
    p.write_text(
        '<scene version="3.0.0">\n'
        '  <shape type="rectangle">\n'
        '    <float name="wobble" value="2"/>\n'
        '    <bsdf type="diffuse"><rgb name="reflectance" value="$albedo"/></bsdf>\n'
        "  </shape>\n"
        "</scene>\n"
    )
    with pytest.raises(SceneError, match=r"s.xml:4: <rgb reflectance> uses parameter \$albedo"):
        load(p)
    s, msgs, _ = _load(p, params={"albedo": "0.25"})
    np.testing.assert_allclose(s.materials[0].albedo, 0.25)
    assert any("s.xml:3: <shape rectangle> property 'wobble' is not supported" in x for x in msgs)


@pytest.mark.parametrize(
    "text, match",
    [
        ("<scene><shape type='rectangle'>", r"x.xml:1: not valid XML"),
        ('<!DOCTYPE s [<!ENTITY a "b">]><scene/>', r"x.xml:1: DTD or entity"),
        ("<scene><shape type='cube'><ref id='nope'/></shape></scene>", r"names no element"),
        ("<scene><emitter type='point'/></scene>", r"no shape icbtool can read"),
        ("<shape type='cube'/>", r"root element must be <scene>"),
        (
            "<scene><shape type='cube'><transform name='to_world'><matrix value='1 2 3'/>"
            "</transform></shape></scene>",
            r"<matrix> needs 16 or 9 numbers",
        ),
        ("<scene><include filename='x.xml'/></scene>", r"includes nested deeper than 16"),
        (
            "<scene><integrator type='path'><integer name='max_depth' value='0'/></integrator>"
            "<shape type='cube'/></scene>",
            r"max_depth must be >= 1 or -1",
        ),
    ],
)
def test_bad_files_name_file_and_line(tmp_path, text, match):
    p = tmp_path / "x.xml"
    p.write_text(text)
    with pytest.raises(SceneError, match=match):
        load(p)


def test_envmap_goes_through_sky_from_envmap(tmp_path, monkeypatch):
    import icbtool.imageio as iio

    img = np.full((8, 16, 3), 0.5, np.float32)
    iio.write_exr(tmp_path / "sky.exr", img)
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><shape type="cube"/>'
        '<emitter type="envmap"><string name="filename" value="sky.exr"/>'
        '<float name="scale" value="2"/><transform name="to_world">'
        '<rotate y="1" angle="90"/></transform></emitter></scene>'
    )
    if not hasattr(Sky, "from_envmap"):
        with pytest.raises(SceneError, match=r"s.xml:1: environment maps need Sky.from_envmap"):
            load(tmp_path / "s.xml")
        pytest.skip("Sky.from_envmap is not in this icbtool yet (the envmap branch adds it)")
    calls = []
    original = Sky.from_envmap

    def spy(path, **kw):
        calls.append((Path(path), kw))
        return original(path, **kw)

    monkeypatch.setattr(Sky, "from_envmap", staticmethod(spy))
    s = load(tmp_path / "s.xml")
    ((path, kw),) = calls
    assert path == tmp_path / "sky.exr" and kw["scale"] == 2.0
    c, si = math.cos(math.radians(90)), math.sin(math.radians(90))
    np.testing.assert_allclose(
        kw["world_from_map"], [[c, 0, si], [0, 1, 0], [-si, 0, c]], atol=1e-12
    )
    assert s.sky is not None


def test_envmap_without_sky_from_envmap_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delattr(Sky, "from_envmap", raising=False)
    (tmp_path / "sky.hdr").write_bytes(b"#?RADIANCE\n")
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><shape type="cube"/><emitter type="envmap">'
        '<string name="filename" value="sky.hdr"/></emitter></scene>'
    )
    with pytest.raises(SceneError, match=r"s.xml:1: environment maps need Sky.from_envmap"):
        load(tmp_path / "s.xml")


_SPECTRA = """<scene version="3.0.0">
  <shape type="rectangle" id="pairs">
    <bsdf type="diffuse"><spectrum name="reflectance" value="400:0.1, 500:0.5, 600:0.8, 700:0.3"/>
    </bsdf>
    <emitter type="area"><spectrum name="radiance" value="400:2, 500:9, 600:5, 700:3"/></emitter>
  </shape>
  <shape type="rectangle" id="uniform">
    <bsdf type="diffuse"><spectrum name="reflectance" value="0.5"/></bsdf>
    <emitter type="area"><spectrum name="radiance" value="4"/></emitter>
  </shape>
  <shape type="rectangle" id="file">
    <bsdf type="diffuse"><spectrum name="reflectance" filename="refl.spd"/></bsdf>
    <emitter type="area"><spectrum name="radiance" filename="rad.spd"/></emitter>
  </shape>
  <shape type="rectangle" id="gamut">
    <bsdf type="diffuse"><spectrum name="reflectance" value="580:0, 620:1.6, 700:1.6"/></bsdf>
    <emitter type="area"><spectrum name="radiance" value="380:7, 420:7, 440:0"/></emitter>
  </shape>
  <emitter type="point" id="lamp"><spectrum name="intensity" value="3"/></emitter>
  <emitter type="directional" id="sun">
    <spectrum name="irradiance" value="450:1, 550:2, 650:3"/>
  </emitter>
</scene>
"""


def test_spectra_equal_mitsubas_own_conversion(tmp_path):
    """Every spectrum form (pairs, one value, a .spd file, out of gamut) for reflectances and
    emitters: the linear sRGB icbtool reads is the one Mitsuba's RGB variant prints."""
    mi = _mitsuba()
    (tmp_path / "refl.spd").write_text("# wavelength value\n420 0.9\n520 0.2\n\n690 0.6\n")
    (tmp_path / "rad.spd").write_text("400 1.0\n550 4.0  # peak\n800 2.0\n")
    (tmp_path / "s.xml").write_text(_SPECTRA)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ours = read_mitsuba(tmp_path / "s.xml").scene
    params = mi.traverse(mi.load_file(str(tmp_path / "s.xml")))
    mats = {m.name.split("@")[0]: m for m in ours.materials}
    for i, shape in enumerate(("pairs", "uniform", "file", "gamut")):
        m = ours.materials[i]
        theirs_refl = np.resize(np.array(params[f"{shape}.bsdf.reflectance.value"]), 3)
        theirs_rad = np.resize(np.array(params[f"{shape}.emitter.radiance.value"]), 3)
        np.testing.assert_allclose(m.albedo, theirs_refl, rtol=2e-5, atol=1e-6, err_msg=shape)
        np.testing.assert_allclose(m.emission, theirs_rad, rtol=2e-5, atol=1e-6, err_msg=shape)
    assert mats  # names as read
    lamp = ours.lights_of("point")[0]
    np.testing.assert_allclose(lamp.intensity, np.array(params["lamp.intensity.value"]), rtol=2e-5)
    sun = ours.lights_of("directional")[0]
    np.testing.assert_allclose(sun.irradiance, np.array(params["sun.irradiance.value"]), rtol=2e-5)
    # a flat reflectance stays grey; a one-value emitted spectrum is purplish, as in Mitsuba
    np.testing.assert_allclose(ours.materials[1].albedo, 0.5)
    assert ours.materials[1].emission[0] > ours.materials[1].emission[1]
    # the out-of-gamut reflectance is clipped with a warning naming its line
    line = next(i for i, t in enumerate(_SPECTRA.splitlines(), 1) if "580:0" in t)
    assert any(f"s.xml:{line}: spectrum out of the sRGB gamut" in str(w.message) for w in caught)


def test_conductor_eta_and_k_spectra_equal_mitsubas_and_are_not_clipped(tmp_path):
    """A conductor's eta and k given as spectra (gold's, from Mitsuba's own documentation
    scene) read as Mitsuba's RGB variant reads them: above 1 where they are, no gamut warning."""
    mi = _mitsuba()
    (tmp_path / "g.xml").write_text(
        '<scene version="3.0.0"><shape type="rectangle" id="g"><bsdf type="conductor">'
        '<spectrum name="eta" value="300:1.8, 400:1.65, 500:0.9, 600:0.2, 700:0.16, 800:0.18"/>'
        '<spectrum name="k" value="300:1.92, 400:1.95, 500:1.95, 600:2.97, 700:3.8, 800:5.12"/>'
        "</bsdf></shape></scene>"
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bsdf = read_mitsuba(tmp_path / "g.xml").scene.materials[0].bsdf
    params = mi.traverse(mi.load_file(str(tmp_path / "g.xml")))
    np.testing.assert_allclose(bsdf.eta, np.array(params["g.bsdf.eta.value"]), rtol=2e-5)
    np.testing.assert_allclose(bsdf.k, np.array(params["g.bsdf.k.value"]), rtol=2e-5)
    assert max(bsdf.k) > 3 and not [w for w in caught if "gamut" in str(w.message)]


def test_blackbody_equals_mitsubas_spectral_render(tmp_path):
    """A black body seen directly: icbtool's load-time RGB is what Mitsuba's spectral variant
    renders (4 pixels x 4096 spp of wavelength sampling: within 2 %)."""
    mi = _mitsuba("scalar_spectral")
    for temp in (2700, 6500):
        xml = (
            '<scene version="3.0.0"><integrator type="path"/>'
            '<sensor type="perspective"><float name="fov" value="5"/>'
            '<sampler type="independent"><integer name="sample_count" value="4096"/></sampler>'
            '<film type="hdrfilm"><integer name="width" value="2"/>'
            '<integer name="height" value="2"/><rfilter type="box"/></film></sensor>'
            '<shape type="rectangle"><boolean name="flip_normals" value="true"/>'
            '<transform name="to_world"><translate z="10"/></transform>'
            '<emitter type="area"><spectrum name="radiance" type="blackbody">'
            f'<float name="temperature" value="{temp}"/></spectrum></emitter></shape></scene>'
        )
        (tmp_path / "bb.xml").write_text(xml)
        img = np.array(mi.render(mi.load_file(str(tmp_path / "bb.xml")), seed=1))
        ours = read_mitsuba(tmp_path / "bb.xml").scene.materials[0].emission
        np.testing.assert_allclose(ours, img.reshape(-1, 3).mean(0), rtol=0.02, err_msg=temp)
    # Mitsuba 0.6's <blackbody> property (temperature with a K, scale) reads the same, scaled
    (tmp_path / "old.xml").write_text(
        '<scene version="0.6.0"><shape type="rectangle"><emitter type="area">'
        '<blackbody name="radiance" temperature="6500K" scale="0.5"/></emitter></shape></scene>'
    )
    old = read_mitsuba(tmp_path / "old.xml").scene.materials[0].emission
    np.testing.assert_allclose(old, 0.5 * spectra.blackbody_to_rgb(6500), rtol=1e-12)


@pytest.mark.parametrize(
    "spectrum, match",
    [
        ('value="400:0.1, 300:0.2"', r"s.xml:1: <spectrum reflectance>: wavelengths must be"),
        ('value="400:0.1:3"', r"s.xml:1: <spectrum reflectance>: not 'wavelength:value'"),
        ('filename="x.txt"', r"spectrum file not found"),
        ('value="1" filename="x.spd"', r"s.xml:1: <spectrum> needs a value or a filename"),
        ('type="d65"', r"s.xml:1: <spectrum type='d65'> is not supported"),
    ],
)
def test_bad_spectra_name_file_and_line(tmp_path, spectrum, match):
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><shape type="rectangle"><bsdf type="diffuse">'
        f'<spectrum name="reflectance" {spectrum}/></bsdf></shape></scene>'
    )
    with pytest.raises((SceneError, FileNotFoundError), match=match):
        load(tmp_path / "s.xml")


def test_camelcase_names_of_old_scene_versions(tmp_path):
    (tmp_path / "old.xml").write_text(
        '<scene version="0.6.0"><sensor type="perspective"><float name="fov" value="90"/>'
        '<string name="fovAxis" value="y"/><transform name="toWorld">'
        '<lookat origin="0,0,0" target="1,0,0" up="0,1,0"/></transform>'
        '<film type="hdrfilm"><integer name="width" value="20"/>'
        '<integer name="height" value="10"/></film></sensor>'
        '<shape type="cube"><transform name="toWorld"><translate x="5"/></transform></shape>'
        "</scene>"
    )
    s, msgs, _ = _load(tmp_path / "old.xml")
    assert s.default_camera.fov_y_deg == pytest.approx(90)
    np.testing.assert_allclose(s.default_camera.forward, [1, 0, 0], atol=1e-12)
    assert s.bounds[0][0] == pytest.approx(4.0)
    assert not any("not supported" in x for x in msgs)


V06 = Path(__file__).parent / "data" / "scenes" / "mitsuba06"


def test_mitsuba06_file_is_upgraded_as_mitsuba_upgrades_it(caplog):
    """A 0.6 scene (camelCase names, a diffuse BSDF's
    diffuseReflectance, a bitmap's uscale/vscale): what icbtool reads equals what Mitsuba 3
    reads after its own in-memory upgrade, with one info line and no unsupported-name warning
    (but icbtool's own: a bitmap's to_uv, the upgraded uscale/vscale, is not rendered)."""
    mi = _mitsuba()
    with caplog.at_level(logging.INFO, logger="icbtool.scene.mitsuba"):
        s, msgs, _ = _load(V06 / "scene.xml")
    assert sum("upgraded on load" in r.message for r in caplog.records) == 1
    unsupported = [x for x in msgs if "not supported" in x]
    assert len(unsupported) == 1 and "bitmap 'to_uv'" in unsupported[0], msgs  # icbtool's own
    theirs = mi.load_file(str(V06 / "scene.xml"))
    assert s.max_depth == 4  # maxDepth
    m = {x.name: x for x in s.materials}
    bsdfs = {sh.bsdf().id(): mi.traverse(sh.bsdf()) for sh in theirs.shapes()}
    # diffuseReflectance of a diffuse BSDF is its reflectance
    np.testing.assert_allclose(m["_floor"].albedo, bsdfs["_floor"]["reflectance.value"])
    np.testing.assert_allclose(m["_floor"].albedo, [0.6, 0.5, 0.4])
    assert "diffuse_reflectance.value" in bsdfs["shiny"].keys()
    np.testing.assert_allclose(
        np.array(bsdfs["shiny"]["diffuse_reflectance.value"]), [0.1, 0.2, 0.5]
    )
    f = ((1.5 - 1) / (1.5 + 1)) ** 2  # intIOR/extIOR read: the plastic's coating
    np.testing.assert_allclose(m["shiny"].albedo, f + (1 - f) * np.array([0.1, 0.2, 0.5]))
    np.testing.assert_allclose(
        np.array(bsdfs["tiled"]["reflectance.to_uv"].matrix)[:3, :3],
        [[4, 0, 0], [0, 2, 0], [0, 0, 1]],
    )
    assert m["tiled"].is_textured
    cam = s.default_camera
    sensor = theirs.sensors()[0]
    for fx, fy in [(0.5, 0.5), (0.0, 0.0), (1.0, 0.7)]:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.ScalarPoint2f(fx, fy), mi.ScalarPoint2f(0.5, 0.5))
        _, d, _ = cam.rays(np.array([[fx * 48, fy * 32]]))
        np.testing.assert_allclose(d[0], np.array(ray.d), atol=2e-6)
    (light,) = s.lights_of("area")
    np.testing.assert_allclose(light.radiance, [10, 9, 8])
    np.testing.assert_allclose(light.normal, [0, -1, 0], atol=1e-9)
    lo, hi = np.array(theirs.bbox().min), np.array(theirs.bbox().max)
    np.testing.assert_allclose(s.bounds[0], lo, atol=2e-3)
    np.testing.assert_allclose(s.bounds[1], hi, atol=2e-3)


def test_mitsuba06_srgb_blackbody_and_lookat_are_read_as_06_wrote_them():
    """0.6 elements Mitsuba 3.9 refuses: <srgb> (sRGB-decoded), <blackbody> (Planck's law at
    the temperature, in kelvin with a K, times scale) and <lookAt> (Mitsuba 3.0-3.5 upgraded
    it to <lookat>)."""
    from icbtool.imageio import srgb_decode

    s, _, _ = _load(V06 / "extras.xml")
    cube, lamp = s.materials
    want = srgb_decode(np.array([1.0, 128 / 255, 0.0], np.float32))
    np.testing.assert_allclose(cube.albedo, want, rtol=1e-6)
    np.testing.assert_allclose(lamp.emission, 0.01 * spectra.blackbody_to_rgb(3000), rtol=1e-9)
    np.testing.assert_allclose(s.default_camera.position, [0, 0, 5])
    np.testing.assert_allclose(s.default_camera.forward, [0, 0, -1], atol=1e-12)


def test_xml_on_the_cli(tmp_path):
    from icbtool.cli import main

    rc = main(["trace", str(FIXTURE), "--out", str(tmp_path), "--spp", "1", "--height", "12"])
    assert rc == 0
    import json

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["config"]["max_depth"] == 5  # the file's integrator


@pytest.mark.skipif(
    not os.environ.get("ICBTOOL_MITSUBA_SCENES"),
    reason="third-party Mitsuba scenes: set ICBTOOL_MITSUBA_SCENES to a folder of .xml files",
)
def test_third_party_mitsuba_files_load():
    """Every scene file of the folder loads, or fails with one clear error where Mitsuba 3
    itself cannot load it either (a missing asset, an unknown plugin)."""
    mi = _mitsuba()
    root = Path(os.environ["ICBTOOL_MITSUBA_SCENES"])
    files = sorted(root.rglob("*.xml"))
    assert files
    loaded = 0
    for f in files:
        if "fragments" in f.parts or "include" in f.parts:
            continue
        try:
            s, _, _ = _load(f)
        except (SceneError, FileNotFoundError) as e:
            assert str(f.parent) in str(e) or f.name in str(e), e  # names the file
            with pytest.raises(Exception):  # noqa: B017 - Mitsuba's own refusal, any type
                mi.load_file(str(f))
            continue
        assert s.n_triangles > 0
        loaded += 1
    assert loaded >= 2


# --------------------------------------------------------------------------- descriptions
def _obj_quad(path: Path, material: str, z: float = 0.0) -> Path:
    path.write_text(
        f"mtllib {path.stem}.mtl\nv 0 0 {z}\nv 1 0 {z}\nv 1 1 {z}\nv 0 1 {z}\n"
        f"usemtl {material}\nf 1 2 3 4\n"
    )
    path.with_suffix(".mtl").write_text(f"newmtl {material}\nKd 0.5 0.5 0.5\n")
    return path


def test_description_with_several_meshes(tmp_path):
    _obj_quad(tmp_path / "a.obj", "wood")
    _obj_quad(tmp_path / "b.obj", "wood")
    (tmp_path / "d.toml").write_text(
        '[scene]\nname = "two"\nmesh = "a.obj"\n\n'
        '[[meshes]]\npath = "b.obj"\nname = "copy"\nscale = 2.0\n'
        "transform = [[1, 0, 0, 10], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"
        "materials = { wood = { albedo = [0.1, 0.2, 0.3] } }\n\n"
        '[[meshes]]\npath = "b.obj"\nname = "lamp"\n'
        "transform = [1, 0, 0, 0, 0, 1, 0, 5, 0, 0, 1, 0, 0, 0, 0, 1]\n"
        "material = { emission = [1, 1, 1] }\n"
    )
    s, _, _ = _load(tmp_path / "d.toml")
    assert s.name == "two" and s.n_triangles == 6
    names = [m.name for m in s.materials]
    assert names == ["wood", "copy:wood", "lamp:wood"]
    np.testing.assert_allclose(s.materials[1].albedo, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(s.materials[0].albedo, [0.5, 0.5, 0.5])
    assert s.materials[2].is_emissive and len(s.lights) == 1  # promoted area light
    second = s.vertices[np.unique(s.faces[s.face_material == 1])]
    np.testing.assert_allclose(second.min(0), [10, 0, 0])  # scaled by 2 then moved by 10
    np.testing.assert_allclose(second.max(0), [12, 2, 0])
    third = s.vertices[np.unique(s.faces[s.face_material == 2])]
    np.testing.assert_allclose(third.min(0), [0, 5, 0])


def test_description_of_meshes_only_and_its_errors(tmp_path):
    _obj_quad(tmp_path / "a.obj", "wood")
    (tmp_path / "d.toml").write_text('[scene]\nname = "m"\n[[meshes]]\npath = "a.obj"\n')
    s, _, _ = _load(tmp_path / "d.toml")
    assert s.name == "m" and s.n_triangles == 2
    bad = {
        "materials = { stone = { albedo = [0.1, 0.1, 0.1] } }": r"no material\(s\) \['stone'\]",
        "transform = [[1, 0, 0], [0, 1, 0]]": r"transform must be 4x4 numbers",
        "transform = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]": r"invertible",
        "colour = 1": r"unknown key\(s\) \['colour'\] in \[meshes 0\]",
        "material = { albedo = [2, 0, 0] }": r"material 'wood'.*albedo must be in \[0, 1\]",
    }
    for line, match in bad.items():
        (tmp_path / "e.toml").write_text(f'[scene]\n[[meshes]]\npath = "a.obj"\n{line}\n')
        with pytest.raises(SceneError, match=match):
            load(tmp_path / "e.toml")
    (tmp_path / "e.toml").write_text('[scene]\nmesh = ["a.obj", "b.obj"]\n')
    with pytest.raises(SceneError, match=r"several meshes: \[\[meshes\]\] tables"):
        load(tmp_path / "e.toml")


def test_description_no_longer_imports_load():
    import ast

    src = (Path(sc.__file__).parent / "description.py").read_text()
    mods = {
        n.module
        for n in ast.walk(ast.parse(src))
        if isinstance(n, ast.ImportFrom) and n.module is not None
    }
    assert "icbtool.scene.load" not in mods and "icbtool.scene.mesh" in mods


# --------------------------------------------------------------------------- first views
def _room(with_pillar: bool = True):
    """A closed 10 x 3 x 8 room (faces inward) with a pillar: an interior."""
    b = sc.SceneBuilder("room")
    w = b.material("w", albedo=(0.7, 0.7, 0.7))
    X, Y, Z = 10.0, 3.0, 8.0
    quads = [  # (corner, u, v) with cross(u, v) pointing into the room
        ((0, 0, 0), (0, 0, Z), (X, 0, 0)),  # floor, +y
        ((0, Y, 0), (X, 0, 0), (0, 0, Z)),  # ceiling, -y
        ((0, 0, 0), (X, 0, 0), (0, Y, 0)),  # z = 0 wall, +z
        ((0, 0, Z), (0, Y, 0), (X, 0, 0)),  # z = Z wall, -z
        ((0, 0, 0), (0, Y, 0), (0, 0, Z)),  # x = 0 wall, +x
        ((X, 0, 0), (0, 0, Z), (0, Y, 0)),  # x = X wall, -x
    ]
    for c, u, v in quads:
        b.add_quad(c, u, v, w)
    if with_pillar:
        b.add_box((7.0, 1.5, 2.0), (0.5, 3.0, 0.5), w)
    return b.build(), (X, Y, Z)


def test_default_view_inside_an_interior(caplog):
    room, (X, Y, Z) = _room()
    outside = Camera.frame(room.bounds, up=room.up)
    assert not np.all((outside.position > 0) & (outside.position < [X, Y, Z]))  # the old view
    with caplog.at_level(logging.INFO, logger="icbtool.scene.view"):
        cam = sc.default_view(room, height=32, width=48)
    p = cam.position
    assert np.all(p > 0) and np.all(p < [X, Y, Z]), p
    sc.check_camera(room, cam)  # not in a wall
    assert abs(cam.forward[1]) < 0.3  # looks across the room, not at the floor
    assert "interior view" in caplog.text and "enclosed" in caplog.text
    assert (cam.height, cam.width) == (32, 48)


_SAMPLES = [(0.5, 0.5), (0.2, 0.2), (0.8, 0.2), (0.2, 0.8), (0.8, 0.8)]


@pytest.mark.parametrize("open_wall", [2, 3, 4, 5])
def test_default_view_of_an_open_box_looks_in_through_the_opening(caplog, open_wall):
    """A Cornell box without its camera (five walls, one open side, two blocks inside): the
    default camera stands outside the opening and looks in; every wall's centre is in view and
    nothing hides it (the whole box is shown). The same box closed is still an interior."""
    from icbtool.scene.raycast import EmbreeScene

    b = sc.SceneBuilder("open_box")
    w = b.material("w", albedo=(0.7, 0.7, 0.7))
    X, Y, Z = 2.0, 2.0, 2.0
    quads = [
        ((0, 0, 0), (0, 0, Z), (X, 0, 0)),
        ((0, Y, 0), (X, 0, 0), (0, 0, Z)),
        ((0, 0, 0), (X, 0, 0), (0, Y, 0)),
        ((0, 0, Z), (0, Y, 0), (X, 0, 0)),
        ((0, 0, 0), (0, Y, 0), (0, 0, Z)),
        ((X, 0, 0), (0, 0, Z), (0, Y, 0)),
    ]
    for i, (c, u, v) in enumerate(quads):
        if i != open_wall:
            b.add_quad(c, u, v, w)
    b.add_box((0.6, 0.3, 0.7), (0.5, 0.6, 0.5), w)
    b.add_box((1.4, 0.6, 1.2), (0.5, 1.2, 0.5), w)
    box = b.build()
    with caplog.at_level(logging.INFO, logger="icbtool.scene.view"):
        cam = sc.default_view(box, height=64, width=64)
    assert "open box view" in caplog.text
    axis = {2: 2, 3: 2, 4: 0, 5: 0}[open_wall]
    side = 0.0 if open_wall in (2, 4) else (X, Y, Z)[axis]
    inward = 1.0 if open_wall in (2, 4) else -1.0
    assert (cam.position[axis] - side) * inward < 0  # outside, beyond the opening
    assert cam.forward[axis] * inward > 0.99  # looking in
    es = EmbreeScene.from_scene(box)
    for i, (c, u, v) in enumerate(quads):
        if i == open_wall:
            continue
        pts = np.array([np.add(c, a * np.asarray(u) + b * np.asarray(v)) for a, b in _SAMPLES])
        uv, depth = cam.project(pts)
        assert np.all(depth > 0) and np.all((uv >= 0) & (uv <= 64)), i  # the wall is in view
        d = pts - cam.position
        dist = np.linalg.norm(d, axis=1)
        hit = es.intersect(np.tile(cam.position, (len(d), 1)), d / dist[:, None])
        assert np.any(np.abs(hit.t - dist) < 1e-4 * dist), i  # and seen, not hidden
    room, _ = _room()
    assert sc.view.open_box_view(room) is None


def test_default_view_of_a_mcguire_style_cornell_obj_looks_in_from_the_front():
    """The McGuire-style Cornell box OBJ (open at +z): the camera stands in front of the
    opening (z > 1) and looks along -z, the room centred in the image."""
    s, _, _ = _load(DATA.parent / "cornell_style.obj")
    cam = sc.default_view(s, height=64, width=64)
    assert cam.position[2] > 1.0
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-9)
    uv, _ = cam.project(np.array([[0.0, 1.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [32, 32], atol=1.5)


@pytest.mark.skipif(
    not os.environ.get("ICBTOOL_MITSUBA_SCENES"),
    reason="third-party Mitsuba scenes: set ICBTOOL_MITSUBA_SCENES to a folder of .xml files",
)
def test_third_party_cornell_box_without_its_sensor_is_seen_from_its_opening(tmp_path):
    """mitsuba-data's Cornell box (integrator_depth_1.xml) with its sensor removed: the default
    camera looks in along the file's own camera's direction, from outside the opening."""
    import re

    src = Path(os.environ["ICBTOOL_MITSUBA_SCENES"]) / "docs" / "scenes" / "integrator_depth_1.xml"
    text = re.sub(r"<sensor.*?</sensor>", "", src.read_text(), flags=re.DOTALL)
    text = text.replace('value="../../common"', f'value="{src.parent.parent.parent / "common"}"')
    (tmp_path / "cbox.xml").write_text(text)
    own = load(src).default_camera
    s, _, _ = _load(tmp_path / "cbox.xml")
    cam = sc.default_view(s)
    np.testing.assert_allclose(cam.forward, own.forward, atol=1e-6)
    assert cam.position[2] < s.bounds[0][2]


def test_default_view_prefers_the_scene_camera_and_frames_exteriors(caplog):
    s = sc.cornell_box()
    cam = sc.default_view(s, height=s.default_camera.height, width=s.default_camera.width)
    np.testing.assert_allclose(cam.world_from_cam, s.default_camera.world_from_cam)
    b = sc.SceneBuilder("block")
    b.add_box((0, 0, 0), (1, 1, 1), b.material("w"))
    block = b.build()
    with caplog.at_level(logging.INFO, logger="icbtool.scene.view"):
        cam = sc.default_view(block)
    ref = Camera.frame(block.bounds, up=block.up)
    np.testing.assert_allclose(cam.world_from_cam, ref.world_from_cam)
    assert "outside view" in caplog.text and "exterior" in caplog.text


# --------------------------------------------------------------------------- messages
def test_nan_vertex_names_file_line_and_text(tmp_path):
    p = tmp_path / "n.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    with pytest.raises(SceneError, match=r"n.obj:3: vertex 3 'v 1 nan 0' has a NaN or Inf"):
        load(p)
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv inf 2 0\nv 0 1 0\nf 1 2 3\nf 1 3 5\n")
    with pytest.warns(
        SceneRepairWarning, match=r"1 vertex position\(s\) no face uses .*line\(s\) 4"
    ):
        s = load(p)
    assert s.n_triangles == 2 and np.isfinite(s.vertices).all()


def test_nan_vertex_in_a_ply_names_the_vertex_as_read(tmp_path):
    p = tmp_path / "n.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n"
    )
    with pytest.raises(SceneError, match=r"n.ply: vertex 1 .* \[1.0, nan, 0.0\]"):
        load(p, up_axis="z")  # the coordinates as read, before the up-axis rotation


def _z_up_room(path: Path, walls: bool) -> Path:
    """A z-up OBJ: a 6 x 4 floor, and optionally tall walls that outweigh it (weak evidence)."""
    lines = ["v 0 0 0", "v 6 0 0", "v 6 4 0", "v 0 4 0", "f 1 2 3 4"]
    k = 4
    if walls:
        for x0, y0, x1, y1 in ((0, 0, 6, 0), (0, 4, 6, 4), (0, 0, 0, 4), (6, 0, 6, 4)):
            lines += [f"v {x0} {y0} 0", f"v {x1} {y1} 0", f"v {x1} {y1} 5", f"v {x0} {y0} 5"]
            lines.append(f"f {k + 1} {k + 2} {k + 3} {k + 4}")
            k += 4
    # a few small boxes so that the mesh has enough triangles
    for i in range(8):
        x = 0.5 + 0.6 * i
        base = k
        for dx, dy, dz in [(0, 0, 0), (0.5, 0, 0), (0.5, 0.5, 0), (0, 0.5, 0)]:
            lines.append(f"v {x + dx} {1 + dy} {0.8 + dz}")
        lines.append(f"f {base + 1} {base + 2} {base + 3} {base + 4}")
        k += 4
    path.write_text("\n".join(lines) + "\n")
    return path


def test_up_axis_auto_logs_its_evidence_and_warns_when_weak(tmp_path, caplog):
    with caplog.at_level(logging.INFO, logger="icbtool.scene.mesh"):
        s, _, _ = _load(_z_up_room(tmp_path / "floor.obj", walls=False))
    assert "up axis 'z' (auto): area facing x/y/z" in caplog.text and "z dominates" in caplog.text
    np.testing.assert_allclose(s.bounds[1][1], 0.8, atol=1e-6)  # z became y
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="icbtool.scene.mesh"):
        _load(_z_up_room(tmp_path / "room.obj", walls=True))
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "weak evidence" in warned[0].getMessage()
    assert "up_axis='z'" in warned[0].getMessage()


def test_approximations_never_reach_albedo_one(tmp_path):
    (tmp_path / "m.mtl").write_text(
        "newmtl glass\nKd 0.5 0.5 0.5\nKs 1 1 1\nTf 1 1 1\nillum 7\n"
        "newmtl chrome\nKd 0 0 0\nKs 1 1 1\nillum 3\n"
    )
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
        "usemtl glass\nf 1 2 3\nusemtl chrome\nf 1 3 4\n"
    )
    s, msgs, _ = _load(tmp_path / "m.obj")
    for m in s.materials:
        assert m.albedo.max() == pytest.approx(MAX_APPROXIMATED_ALBEDO)
    assert sum("scaled by" in x for x in msgs) == 2


@pytest.mark.parametrize(
    "to_world, fov_axis, size",
    [
        ('<lookat origin="0, 1, 6" target="0, 1, 0" up="0, 1, 0"/>', "x", (64, 48)),
        ('<lookat origin="1, 2, 3" target="-2, 0, 1" up="0, 0, 1"/>', "smaller", (40, 60)),
        ('<rotate y="1" angle="30"/><translate x="1" z="2"/>', "diagonal", (50, 30)),
        ('<matrix value="-1 0 0 0 0 1 0 1 0 0 -1 6.8 0 0 0 1"/>', "y", (32, 32)),
    ],
)
def test_camera_rays_equal_mitsubas_own_sensor(tmp_path, to_world, fov_axis, size):
    """The file's camera read by icbtool casts the rays Mitsuba's own sensor casts."""
    mi = _mitsuba()
    w, h = size
    xml = (
        '<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="50"/>'
        f'<string name="fov_axis" value="{fov_axis}"/><transform name="to_world">{to_world}'
        f'</transform><film type="hdrfilm"><integer name="width" value="{w}"/>'
        f'<integer name="height" value="{h}"/></film></sensor><shape type="cube"/></scene>'
    )
    (tmp_path / "c.xml").write_text(xml)
    cam = load(tmp_path / "c.xml").default_camera
    sensor = mi.load_file(str(tmp_path / "c.xml")).sensors()[0]
    for fx, fy in [(0.5, 0.5), (0.1, 0.2), (0.9, 0.7), (0.3, 0.95)]:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.ScalarPoint2f(fx, fy), mi.ScalarPoint2f(0.5, 0.5))
        _, d, _ = cam.rays(np.array([[fx * w, fy * h]]))
        np.testing.assert_allclose(d[0], np.array(ray.d), atol=1e-5)
        # Mitsuba starts the ray at the near clip plane, on the same line
        off = np.array(ray.o) - cam.position
        np.testing.assert_allclose(np.cross(off, d[0]), 0, atol=1e-6)


@pytest.mark.parametrize(
    "sensor, film",
    [
        ('<string name="focal_length" value="50mm"/>', (32, 32, None)),
        ('<string name="focal_length" value="28mm"/>', (60, 30, None)),
        ('<float name="fov" value="40"/><string name="fov_axis" value="larger"/>', (30, 50, None)),
        ('<float name="fov" value="40"/><string name="fov_axis" value="smaller"/>', (50, 30, None)),
        ('<float name="fov" value="70"/><string name="fov_axis" value="y"/>', (40, 40, None)),
        ('<float name="fov" value="60"/>', (64, 48, (10, 5, 30, 20))),
        (
            '<float name="fov" value="45"/><string name="fov_axis" value="diagonal"/>'
            '<float name="principal_point_offset_x" value="0.1"/>'
            '<float name="principal_point_offset_y" value="-0.05"/>',
            (48, 32, (8, 4, 16, 24)),
        ),
    ],
)
def test_camera_intrinsics_and_crops_equal_mitsubas(tmp_path, sensor, film):
    """focal_length (35 mm film diagonal), every fov_axis, film crops and principal point
    offsets: each pixel of the (cropped) image casts the ray Mitsuba's sensor casts."""
    mi = _mitsuba()
    w, h, crop = film
    film_xml = f'<integer name="width" value="{w}"/><integer name="height" value="{h}"/>'
    if crop is not None:
        film_xml += "".join(
            f'<integer name="crop_{k}" value="{v}"/>'
            for k, v in zip(("offset_x", "offset_y", "width", "height"), crop)
        )
    (tmp_path / "c.xml").write_text(
        f'<scene version="3.0.0"><sensor type="perspective">{sensor}<transform name="to_world">'
        '<lookat origin="1, 2, 3" target="-2, 0, 1" up="0, 0, 1"/></transform>'
        f'<film type="hdrfilm">{film_xml}</film></sensor><shape type="cube"/></scene>'
    )
    cam = load(tmp_path / "c.xml").default_camera
    cw, ch = (w, h) if crop is None else crop[2:]
    assert (cam.width, cam.height) == (cw, ch)
    sensor_mi = mi.load_file(str(tmp_path / "c.xml")).sensors()[0]
    for fx, fy in [(0.5, 0.5), (0.0, 0.0), (1.0, 1.0), (0.1, 0.9), (0.8, 0.3)]:
        ray, _ = sensor_mi.sample_ray(
            0.0, 0.5, mi.ScalarPoint2f(fx, fy), mi.ScalarPoint2f(0.5, 0.5)
        )
        _, d, _ = cam.rays(np.array([[fx * cw, fy * ch]]))
        np.testing.assert_allclose(d[0], np.array(ray.d), atol=2e-6)
    if "focal_length" in sensor and w == h:  # 50 mm, square film: 46.8 deg diagonal, 34.0 wide
        assert cam.fov_x_deg == pytest.approx(34.02204, abs=1e-4)  # Mitsuba's parse_fov test


def test_focus_distance_on_a_pinhole_is_read_silently_and_hide_emitters_is_named(tmp_path):
    """Every Mitsuba projective camera reads focus_distance (Mitsuba's own documentation scenes
    give it to perspective sensors): no warning, no effect. hide_emitters = true is not applied,
    which changes the image, so it is named with its line; false is what icbtool renders."""
    film = '<film type="hdrfilm"><integer name="width" value="8"/></film>'
    sensor = (
        '<sensor type="perspective"><float name="focus_distance" value="6"/>'
        f'<float name="fov" value="40"/>{film}</sensor>'
    )
    for hide, named in (("false", False), ("true", True)):
        (tmp_path / "c.xml").write_text(
            f'<scene version="3.0.0"><integrator type="path">'
            f'<boolean name="hide_emitters" value="{hide}"/></integrator>'
            f'{sensor}<shape type="cube"/></scene>'
        )
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cam = load(tmp_path / "c.xml").default_camera
        texts = [str(w.message) for w in caught if issubclass(w.category, SceneRepairWarning)]
        assert not any("'focus_distance'" in t for t in texts), texts
        assert cam.aperture_radius == 0 and cam.fov_x_deg == pytest.approx(40)
        hidden = [t.split("c.xml:")[1] for t in texts if "hide_emitters" in t]
        assert hidden == (
            ["1: hide_emitters is not applied: emitters and the environment the camera sees "
             "directly stay in icbtool's image"] if named else []
        )  # fmt: skip


_REFS = """<scene version="3.0.0">
  <bsdf type="diffuse" id="red"><rgb name="reflectance" value="0.8, 0.1, 0.1"/></bsdf>
  <bsdf type="diffuse" id="green"><rgb name="reflectance" value="0.1, 0.8, 0.1"/></bsdf>
  <bsdf type="diffuse" id="blue"><rgb name="reflectance" value="0.1, 0.1, 0.8"/></bsdf>
  <bsdf type="diffuse" id="grey"><rgb name="reflectance" value="0.3"/></bsdf>
  <texture type="bitmap" id="tex"><string name="filename" value="t.png"/></texture>
  <bsdf type="diffuse" id="textured"><ref name="reflectance" id="tex"/></bsdf>
  <emitter type="area" id="lamp"><rgb name="radiance" value="5, 4, 3"/></emitter>
  <emitter type="area" id="lamp2"><rgb name="radiance" value="1, 2, 3"/></emitter>
  <medium type="homogeneous" id="fog"/>
  <shape type="rectangle" id="unnamed"><ref id="red"/></shape>
  <shape type="rectangle" id="writer"><ref name="_arg_0" id="green"/><ref name="_arg_1" id="lamp"/>
  </shape>
  <shape type="rectangle" id="exporter"><ref name="bsdf" id="blue"/></shape>
  <shape type="rectangle" id="any_name"><ref name="look" id="grey"/><ref name="light" id="lamp2"/>
  </shape>
  <shape type="rectangle" id="texture"><ref id="textured"/>
    <ref name="interior" id="fog"/>
  </shape>
</scene>
"""


def test_every_ref_form_gives_mitsubas_bsdf_and_emitter(tmp_path):
    """Unnamed refs, Mitsuba's writer's ``_arg_N`` refs, exporters' ``name="bsdf"`` refs and
    any other name: each shape gets the BSDF and emitter Mitsuba gives it; a referenced texture
    is the BSDF's texture; an unsupported referenced medium is named at the <ref>'s line."""
    from PIL import Image

    mi = _mitsuba()
    Image.fromarray(np.array([[[255, 0, 0], [0, 255, 0]]], np.uint8)).save(tmp_path / "t.png")
    (tmp_path / "s.xml").write_text(_REFS)
    ours, msgs, _ = _load(tmp_path / "s.xml")
    theirs = {sh.id(): sh for sh in mi.load_file(str(tmp_path / "s.xml")).shapes()}
    order = ["unnamed", "writer", "exporter", "any_name", "texture"]
    assert len(ours.materials) == len(order)
    for name, m in zip(order, ours.materials):
        sh = theirs[name]
        bsdf = mi.traverse(sh.bsdf())
        if name == "texture":
            assert m.is_textured and Path(m.texture_path).name == "t.png"
            assert "reflectance.data" in bsdf.keys()
        else:
            np.testing.assert_allclose(m.albedo, np.array(bsdf["reflectance.value"]), err_msg=name)
        em = sh.emitter()
        rad = np.zeros(3) if em is None else np.array(mi.traverse(em)["radiance.value"])
        np.testing.assert_allclose(m.emission, rad, err_msg=name)
    assert not any("_arg_" in x or "'light'" in x or "'look'" in x for x in msgs), msgs
    line = next(i for i, t in enumerate(_REFS.splitlines(), 1) if 'name="interior"' in t)
    assert any(f"s.xml:{line} (<ref> to " in x and "'interior'" in x for x in msgs), msgs


def test_a_second_bsdf_in_a_shape_is_an_error(tmp_path):
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><bsdf type="diffuse" id="a"/>\n<shape type="cube">'
        '<ref id="a"/>\n<bsdf type="diffuse"/></shape></scene>'
    )
    with pytest.raises(SceneError, match=r"s.xml:3: <shape cube> at .*s.xml:2 has a second"):
        load(tmp_path / "s.xml")


def test_unrenderable_only_light_fails_unless_default_light_is_asked(tmp_path, capsys):
    """A scene lit only by emitters icbtool cannot render (here sunsky and sun) is an error
    naming each with its line, on load and on the command line; ``default_light=True``
    (``--default-light``) replaces them by the default sun and sky, with a warning naming them.
    Beside a light icbtool renders, they are skipped with a warning (nothing substituted)."""
    from icbtool.cli import main

    text = (
        '<scene version="3.0.0">\n<shape type="cube"/>\n<emitter type="sunsky"/>\n'
        '<emitter type="sun"/>\n</scene>'
    )
    (tmp_path / "s.xml").write_text(text)
    with pytest.raises(SceneError, match=r"<emitter sunsky> \(.*s.xml:3\), <emitter sun> "):
        load(tmp_path / "s.xml")
    rc = main(["trace", str(tmp_path / "s.xml"), "--out", str(tmp_path / "o")])
    assert rc != 0 and "--default-light" in capsys.readouterr().err
    s, msgs, _ = _load(tmp_path / "s.xml", default_light=True)
    assert [lt.name for lt in s.lights] == ["default_sun"] and s.sky is not None
    assert any("s.xml:3), <emitter sun>" in x and "replaced by" in x for x in msgs)
    (tmp_path / "lit.xml").write_text(text.replace('<emitter type="sun"/>', _POINT))
    s, msgs, _ = _load(tmp_path / "lit.xml")
    assert [lt.kind for lt in s.lights] == ["point"] and s.sky is None
    assert any("lit.xml:3: <emitter sunsky> emitter type is not supported" in x for x in msgs)


_POINT = '<emitter type="point"><point name="position" value="0, 3, 0"/></emitter>'


def test_fixture_shapes_equal_mitsubas_own_parse(tmp_path):
    """Each shape's bounding box and area as Mitsuba itself reads the fixture."""
    import re
    import shutil

    mi = _mitsuba()
    shutil.copytree(DATA, tmp_path / "m")
    xml = tmp_path / "m" / "fixture.xml"
    text = xml.read_text()
    text = re.sub(r'<shape type="bsplinecurve">.*?</shape>', "", text, flags=re.DOTALL)
    xml.write_text(re.sub(r"<medium[^>]*/>", "", text))
    ours = load(xml)
    shapes = [x for x in mi.load_file(str(xml)).shapes()]
    assert len(shapes) == 8
    by_bbox = {}
    for i, m in enumerate(ours.materials):
        faces = ours.faces[ours.face_material == i]
        v = ours.vertices[np.unique(faces)]
        by_bbox[m.name] = (v.min(0), v.max(0), _area(ours, m.name))
    for sh in shapes:
        bb = sh.bbox()
        lo, hi = np.array(bb.min), np.array(bb.max)
        name, (olo, ohi, oarea) = min(
            by_bbox.items(),
            key=lambda kv: np.abs(kv[1][0] - lo).sum() + np.abs(kv[1][1] - hi).sum(),
        )
        np.testing.assert_allclose(olo, lo, atol=2e-3, err_msg=name)
        np.testing.assert_allclose(ohi, hi, atol=2e-3, err_msg=name)
        assert oarea == pytest.approx(sh.surface_area(), rel=1e-2), name


def test_trace_default_depth_is_the_files():
    """``render(scene, cam)`` without a config traces to the file's max_depth (here 1: only
    what the camera sees directly, the constant sky), the same image as asking for it."""
    import icbtool as icb

    s, _, _ = _load(FIXTURE, params={"depth": 1})
    cam = s.default_camera.resized(12, 16)
    full = icb.trace.render(s, cam).full
    one = icb.trace.render(s, cam, icb.trace.TraceConfig(max_depth=1)).full
    np.testing.assert_array_equal(full, one)
    assert full.mean() < icb.trace.render(s, cam, icb.trace.TraceConfig(max_depth=3)).full.mean()


@pytest.mark.parametrize(
    "integrator, depth",
    [
        ('<integrator type="path"/>', -1),  # Mitsuba's default: unbounded
        ('<integrator type="direct"/>', 2),
        ('<integrator type="moment"><integrator type="path"><integer name="max_depth" '
         'value="4"/></integrator></integrator>', 4),
        ("", None),  # no integrator: the tracer's own default
    ],
)  # fmt: skip
def test_integrator_depth(tmp_path, integrator, depth):
    (tmp_path / "i.xml").write_text(
        f'<scene version="3.0.0">{integrator}<shape type="cube"/></scene>'
    )
    assert load(tmp_path / "i.xml").max_depth == depth


def test_default_view_small_cavities_are_not_a_room(caplog):
    """A closed hut taking ~3 % of an open yard: the scene is framed from outside."""
    b = sc.SceneBuilder("yard")
    w = b.material("w")
    b.add_quad((0, 0, 0), (0, 0, 10), (10, 0, 0), w)  # ground, +y
    b.add_box((9.5, 1.5, 9.5), (0.2, 3.0, 0.2), w)  # a pole: the bounds are 3 high
    for c, u, v in [  # a 2 x 2 x 2 hut, faces inward
        ((0, 0.01, 0), (0, 0, 2), (2, 0, 0)),
        ((0, 2, 0), (2, 0, 0), (0, 0, 2)),
        ((0, 0, 0), (2, 0, 0), (0, 2, 0)),
        ((0, 0, 2), (0, 2, 0), (2, 0, 0)),
        ((0, 0, 0), (0, 2, 0), (0, 0, 2)),
        ((2, 0, 0), (0, 0, 2), (0, 2, 0)),
    ]:
        b.add_quad(c, u, v, w)
    yard = b.build()
    with caplog.at_level(logging.INFO, logger="icbtool.scene.view"):
        cam = sc.default_view(yard)
    np.testing.assert_allclose(
        cam.world_from_cam, Camera.frame(yard.bounds, up=yard.up).world_from_cam
    )
    assert "small cavities, not a room" in caplog.text


def _write_serialized(path: Path, shapes: list[tuple], version: int = 4) -> None:
    """A Mitsuba .serialized file (see icbtool.scene.mitsuba.read_serialized for the format)."""
    import struct
    import zlib

    out, offsets = b"", []
    for v, f, n, uv in shapes:
        flags = 0x1000 | (0x0001 if n is not None else 0) | (0x0002 if uv is not None else 0)
        body = struct.pack("<I", flags) + (b"mesh\0" if version == 4 else b"")
        body += struct.pack("<QQ", len(v), len(f)) + np.asarray(v, np.float32).tobytes()
        for extra in (n, uv):
            if extra is not None:
                body += np.asarray(extra, np.float32).tobytes()
        body += np.asarray(f, np.uint32).tobytes()
        offsets.append(len(out))
        out += struct.pack("<HH", 0x041C, version) + zlib.compress(body)
    fmt = "<Q" if version == 4 else "<I"
    out += b"".join(struct.pack(fmt, o) for o in offsets) + struct.pack("<I", len(shapes))
    path.write_bytes(out)


@pytest.mark.parametrize("version", [3, 4])
def test_serialized_shapes(tmp_path, version):
    quad_v = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    quad_f = [[0, 1, 2], [0, 2, 3]]
    uv = [[0, 0], [1, 0], [1, 1], [0, 0.25]]
    tri_v = [[0, 0, 0], [2, 0, 0], [0, 0, 2]]
    _write_serialized(
        tmp_path / "m.serialized",
        [(quad_v, quad_f, np.tile([0, 0, 1], (4, 1)), uv), (tri_v, [[0, 2, 1]], None, None)],
        version,
    )
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0">'
        '<shape type="serialized"><string name="filename" value="m.serialized"/>'
        '<integer name="shape_index" value="1"/><bsdf type="diffuse" id="tri"/></shape>'
        '<shape type="serialized"><string name="filename" value="m.serialized"/>'
        '<transform name="to_world"><translate z="5"/></transform>'
        '<bsdf type="diffuse" id="quad"/></shape></scene>'
    )
    s, _, _ = _load(tmp_path / "s.xml")
    assert _area(s, "tri") == pytest.approx(2.0) and _area(s, "quad") == pytest.approx(1.0)
    i = [m.name for m in s.materials].index("tri")
    np.testing.assert_allclose(s.face_normals[s.face_material == i], [[0, 1, 0]], atol=1e-7)
    assert s.vertices[:, 2].max() == pytest.approx(5.0)
    (tmp_path / "bad.xml").write_text(
        '<scene version="3.0.0"><shape type="serialized"><string name="filename" '
        'value="m.serialized"/><integer name="shape_index" value="2"/></shape></scene>'
    )
    with pytest.raises(
        SceneError, match=r"bad.xml:1: .*shape_index 2 out of range: the file has 2"
    ):
        load(tmp_path / "bad.xml")
    (tmp_path / "junk.serialized").write_bytes(b"\x00" * 32)
    with pytest.raises(SceneError, match=r"not a Mitsuba serialized mesh"):
        sc.mitsuba.read_serialized(tmp_path / "junk.serialized")
    mi = _mitsuba()
    theirs = mi.load_file(str(tmp_path / "s.xml"))
    assert sum(sh.surface_area() for sh in theirs.shapes()) == pytest.approx(3.0)
    np.testing.assert_allclose(np.array(theirs.bbox().max), s.bounds[1], atol=1e-6)


def test_loud_failures_name_the_file_and_line(tmp_path, capsys):
    """A missing texture, a truncated .serialized or .ply and a scene with nothing icbtool can
    render are one-line errors naming the file (and the element's line), never a default
    material, a traceback or an exit code of 0."""
    from icbtool.cli import main

    def scene(body: str) -> Path:
        (tmp_path / "s.xml").write_text(f'<scene version="3.0.0">\n{body}\n</scene>')
        return tmp_path / "s.xml"

    tex = (
        '<shape type="cube"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
        '<string name="filename" value="gone.png"/></texture></bsdf></shape>'
    )
    with pytest.raises(FileNotFoundError, match=r"s.xml:2: texture file not found: .*gone.png"):
        load(scene(tex))
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(SceneError, match=r"s.xml:2: texture .*bad.png is not a readable image"):
        load(scene(tex.replace("gone.png", "bad.png")))
    tri = (np.eye(3), np.array([[0, 1, 2]]), None, None)
    _write_serialized(tmp_path / "m.serialized", [tri, tri])
    data = (tmp_path / "m.serialized").read_bytes()
    for cut in (len(data) // 2, len(data) - 3):
        (tmp_path / "m.serialized").write_bytes(data[:cut])
        body = '<shape type="serialized"><string name="filename" value="m.serialized"/></shape>'
        with pytest.raises(SceneError, match=r"s.xml:2: .*m.serialized: truncated or corrupt"):
            load(scene(body))
    ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    ply += "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
    (tmp_path / "t.ply").write_text(ply + "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    body = '<shape type="ply"><string name="filename" value="t.ply"/></shape>'
    with pytest.raises(SceneError, match=r"s.xml:2: <shape ply>: .*t.ply: truncated or corrupt"):
        load(scene(body))
    rc = main(["trace", str(scene('<shape type="bsplinecurve"/>')), "--out", str(tmp_path / "o")])
    assert rc != 0
    assert "s.xml: the scene has no shape icbtool can read" in capsys.readouterr().err


_INSTANCES = """<scene version="3.0.0">
  <shape type="rectangle"><transform name="to_world"><scale value="6"/>
    <rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse" id="floor"/></shape>
  <shape type="shapegroup" id="chair">
    <shape type="cube"><transform name="to_world"><scale x="0.5" y="0.1" z="0.5"/>
      <translate y="0.6"/></transform><bsdf type="diffuse" id="seat"/></shape>
    <shape type="obj"><string name="filename" value="leg.obj"/>
      <transform name="to_world"><translate x="0.7" z="0.7"/></transform>
      <bsdf type="diffuse" id="leg"><rgb name="reflectance" value="0.2, 0.1, 0.05"/></bsdf>
    </shape>
  </shape>
  <shape type="instance"><ref id="chair"/></shape>
  <shape type="instance"><ref name="shapegroup" id="chair"/>
    <transform name="to_world"><rotate y="1" angle="30"/><scale value="1.5"/>
      <translate x="3" z="-1"/></transform></shape>
  <shape type="instance"><ref id="chair"/>
    <transform name="to_world"><translate x="-3" z="1"/></transform></shape>
</scene>
"""


def test_instances_render_whole_as_in_mitsuba(tmp_path):
    """A floor and three instances of a two-shape group (each shape with its own to_world,
    each instance with another): icbtool's flattened copies are hit where Mitsuba's instances
    are (a 48 x 48 grid of rays from above at an angle, same distances), and every shape keeps
    its own material."""
    from icbtool.scene.raycast import EmbreeScene

    mi = _mitsuba()
    (tmp_path / "leg.obj").write_text(
        "v -0.15 0 -0.15\nv 0.15 0 -0.15\nv 0.15 0 0.15\nv -0.15 0 0.15\n"
        "v -0.15 0.6 -0.15\nv 0.15 0.6 -0.15\nv 0.15 0.6 0.15\nv -0.15 0.6 0.15\n"
        "f 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\n"
    )
    (tmp_path / "s.xml").write_text(_INSTANCES)
    ours = read_mitsuba(tmp_path / "s.xml")
    assert ours.shapes == 1 + 3 * 2
    assert ours.scene.n_triangles == 2 + 3 * (12 + 8)
    theirs = mi.load_file(str(tmp_path / "s.xml"))
    g = (np.arange(48) + 0.5) / 48 * 10 - 5
    x, z = np.meshgrid(g, g)
    origins = np.column_stack([x.ravel(), np.full(x.size, 8.0), z.ravel()])
    d = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    hits = EmbreeScene.from_scene(ours.scene).intersect(origins, np.tile(d, (len(origins), 1)))
    names = [m.name for m in ours.scene.materials]
    seen = set()
    for i, o in enumerate(origins):
        si = theirs.ray_intersect(mi.Ray3f(mi.ScalarPoint3f(o), mi.ScalarVector3f(d)))
        assert bool(si.is_valid()) == bool(hits.hit[i]), i
        if hits.hit[i]:
            assert float(hits.t[i]) == pytest.approx(float(si.t), abs=1e-4), i
            seen.add(names[ours.scene.face_material[hits.prim[i]]])
    assert seen == {"floor", "seat", "leg"}


def test_nested_instancing_is_refused_as_in_mitsuba(tmp_path):
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0">\n<shape type="shapegroup" id="a"><shape type="cube"/></shape>\n'
        '<shape type="shapegroup" id="b">\n<shape type="instance"><ref id="a"/></shape>'
        '</shape>\n<shape type="instance"><ref id="b"/></shape>\n</scene>'
    )
    with pytest.raises(SceneError, match=r"s.xml:4: <shape instance> inside the shapegroup at"):
        load(tmp_path / "s.xml")
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><shape type="shapegroup" id="a"><shape type="cube"/></shape>'
        "</scene>"
    )  # a group nothing instances: nothing to render
    with pytest.raises(SceneError, match=r"no shape icbtool can read"):
        load(tmp_path / "s.xml")


def test_diffuse_twin_renders_what_icbtool_renders(tmp_path):
    """The twin of the fixture keeps the BSDFs icbtool traces exactly and turns the approximated
    ones into two-sided diffuse BSDFs with icbtool's albedos: loading it gives the same
    materials without a single approximation warning."""
    ours, _, _ = _load(FIXTURE)
    (tmp_path / "out").mkdir()
    twin = sc.mitsuba.diffuse_twin(FIXTURE, tmp_path / "out")
    assert twin == tmp_path / "out" / "mitsuba" / "fixture.xml"
    s, msgs, cats = _load(twin)
    assert MaterialApproximationWarning not in cats
    assert s.n_triangles == ours.n_triangles
    assert len(s.materials) == len(ours.materials)  # in the same order (shape order)
    for theirs, m in zip(s.materials, ours.materials):
        np.testing.assert_allclose(theirs.albedo, m.albedo, atol=1e-8)
        np.testing.assert_allclose(theirs.emission, m.emission)
        assert theirs.is_textured == m.is_textured
        assert type(theirs.bsdf) is type(m.bsdf)
    assert 'type="box"' in twin.read_text()
    frag = (twin.parent / "fragments" / "bsdfs.xml").read_text()
    assert 'type="plastic"' in frag and 'type="bumpmap"' in frag  # traced exactly: kept


def test_shapes_without_a_bsdf_share_one_default_material_whatever_came_before(tmp_path):
    # Mitsuba gives each such shape its default diffuse BSDF (0.5): one material for all of
    # them, however many shapes and whatever the process loaded before (materials are keyed by
    # the BSDF object, which must be one object, not a temporary whose id may be reused)
    shapes = "".join(
        f'<shape type="rectangle"><transform name="to_world"><translate x="{3 * i}"/>'
        "</transform></shape>"
        for i in range(4)
    )
    (tmp_path / "s.xml").write_text(f'<scene version="3.0.0">{shapes}</scene>')
    for _ in range(3):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            s = load(tmp_path / "s.xml")
        assert [m.name for m in s.materials] == ["default"]
        np.testing.assert_allclose(s.materials[0].albedo, 0.5)
        assert np.all(s.face_material == 0)
