"""Dependencies run one way, from geometry up to the applications (STYLE.md).

Every ``import icbtool.X`` in the library (module level or inside a function) is read from the
source with ``ast`` and checked against the layer table below: a package may import only
packages of lower layers (and itself).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "icbtool"

#: Layer of each top-level part of the library; lower layers never import higher ones.
LAYERS: dict[str, int] = {
    "buffers": 0,
    "provenance": 0,
    "imageio": 0,
    "camera": 1,
    "metrics": 1,
    "scene": 2,
    "prefetch": 2,
    "warp": 2,
    "raster": 3,
    "trace": 3,
    "store": 3,
    "bake": 4,
    "gan": 4,
    "radiance": 4,
    "lpm": 4,
    "system": 5,
    "pipeline": 6,
    "net": 7,
    "cli": 8,
    "__main__": 9,
    "__init__": 9,
    "_optional": 0,
}


def _part(path: Path) -> str:
    rel = path.relative_to(PKG)
    return rel.parts[0].removesuffix(".py")


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
            if node.module == "icbtool":
                names = [f"icbtool.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for n in names:
            if n.startswith("icbtool."):
                out.add(n.split(".")[1])
    return out


def test_every_library_part_has_a_layer():
    parts = {_part(p) for p in PKG.rglob("*.py")}
    assert parts <= set(LAYERS), f"add to LAYERS: {sorted(parts - set(LAYERS))}"


@pytest.mark.parametrize("path", sorted(PKG.rglob("*.py")), ids=lambda p: str(p.relative_to(PKG)))
def test_imports_point_down(path):
    me = _part(path)
    bad = sorted(d for d in _imports(path) if d != me and d in LAYERS and LAYERS[d] >= LAYERS[me])
    assert not bad, f"{path.relative_to(PKG)} (layer {LAYERS[me]}) imports {bad}: upward"


def test_camera_imports_nothing_else_of_icbtool():
    for p in (PKG / "camera").rglob("*.py"):
        assert _imports(p) <= {"camera"}, p
