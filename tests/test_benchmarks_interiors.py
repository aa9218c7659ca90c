"""benchmarks.interiors' scene preparation: what both renderers read of an incomplete scene."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from benchmarks.interiors import MISSING_TEXTURE_RGB, prepare

_SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/></sensor>
  <shape type="obj" id="books">
    <string name="filename" value="books.obj"/>
    <bsdf type="roughplastic">
      <texture name="diffuse_reflectance" type="bitmap">
        <string name="filename" value="missing/books.jpg"/>
      </texture>
    </bsdf>
  </shape>
  <shape type="obj" id="wall">
    <string name="filename" value="books.obj"/>
    <bsdf type="bumpmap">
      <texture type="bitmap"><string name="filename" value="missing/height.png"/></texture>
      <bsdf type="diffuse" id="plaster"/>
    </bsdf>
  </shape>
  <shape type="obj" id="gone"><string name="filename" value="gone.obj"/></shape>
</scene>
"""


def test_prepare_names_missing_meshes_and_makes_missing_textures_constant(tmp_path: Path):
    (tmp_path / "books.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    src = tmp_path / "room.xml"
    src.write_text(_SCENE)
    out = prepare(src, tmp_path / "prepared", 32, 18, 4)
    assert out["dropped"] == ["gone.obj"]
    assert out["replaced_textures"] == ["missing/books.jpg", "missing/height.png"]
    root = ET.parse(out["file"]).getroot()
    shapes = {s.get("id"): s for s in root.iter("shape")}
    assert set(shapes) == {"books", "wall"}
    rgb = shapes["books"].find("bsdf/rgb")
    assert rgb is not None and rgb.attrib == {
        "name": "diffuse_reflectance",
        "value": MISSING_TEXTURE_RGB,
    }
    assert shapes["books"].find("bsdf/texture") is None
    # the bump map without its height field is the BSDF it wrapped
    bsdf = shapes["wall"].find("bsdf")
    assert bsdf is not None and bsdf.get("type") == "diffuse" and bsdf.get("id") == "plaster"
    # the mesh that is there keeps an absolute file name
    assert shapes["books"].find("string").get("value") == str(tmp_path / "books.obj")
