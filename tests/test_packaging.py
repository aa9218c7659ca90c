"""Packaging: every third-party module the library imports is declared in setup.cfg
``install_requires`` (optional ones go through :func:`icbtool.optional.require` and are extras),
pyrender is not needed, and the shaders are package data. The wheel itself is checked by
``.ci/wheel_smoke.sh`` (run by ``make test``)."""

from __future__ import annotations

import ast
import configparser
import re
import sys
from importlib import metadata
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "icbtool"


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements(text: str) -> set[str]:
    out = set()
    for line in re.split(r"[\n;]", text):
        line = line.split("#", 1)[0].strip()
        if line:
            out.add(_norm(re.split(r"[<>=!~\[ ]", line, maxsplit=1)[0]))
    return out


def _cfg() -> configparser.ConfigParser:
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    return cfg


def _third_party_imports(root: Path = PKG) -> dict[str, set[str]]:
    """Top-level module -> files under ``root`` importing it (module level or inside functions)."""
    found: dict[str, set[str]] = {}
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                top = n.split(".")[0]
                first_party = top in ("icbtool", "icbtool_gui", "__future__")
                if not first_party and top not in sys.stdlib_module_names:
                    found.setdefault(top, set()).add(str(path.relative_to(REPO)))
    return found


def _module_owners() -> dict[str, set[str]]:
    """Top-level module -> installed distributions providing it (read from their file lists, so
    that a bare extension module such as OpenEXR's .so is found too)."""
    owners: dict[str, set[str]] = {}
    for dist in metadata.distributions():
        record = dist.read_text("RECORD") or dist.read_text("top_level.txt") or ""
        tops = {line.split(",", 1)[0].split("/", 1)[0] for line in record.splitlines()}
        for top in tops:
            if top.endswith((".dist-info", ".egg-info", ".pth")) or top in (
                "",
                "..",
                "__pycache__",
            ):
                continue
            top = top.split(".", 1)[0]  # pkg, mod.py, mod.cpython-311-x86_64-linux-gnu.so
            owners.setdefault(top, set()).add(_norm(dist.metadata["Name"]))
    return owners


def test_every_runtime_import_is_declared():
    declared = _requirements(_cfg()["options"]["install_requires"])
    dists = _module_owners()
    undeclared = {}
    for module, files in sorted(_third_party_imports().items()):
        owners = dists.get(module, set())
        assert owners, f"{module} (imported by {sorted(files)}) is not installed here"
        if not owners & declared:
            undeclared[module] = (sorted(owners), sorted(files))
    assert not undeclared, f"imported but not in install_requires: {undeclared}"


def test_the_desktop_app_imports_only_what_install_requires_and_its_extra_declare():
    """icbtool_gui/ (installed with icbtool, imported by `icbtool gui`) may use the ``gui``
    extra."""
    cfg = _cfg()
    declared = _requirements(cfg["options"]["install_requires"])
    declared |= _requirements(cfg["options.extras_require"]["gui"])
    dists = _module_owners()
    imports = _third_party_imports(REPO / "icbtool_gui")
    assert {"PySide6", "pyvista", "pyvistaqt", "matplotlib"} <= set(imports)
    undeclared = {
        m: (sorted(dists.get(m, set())), sorted(f))
        for m, f in imports.items()
        if not dists.get(m, set()) & declared
    }
    assert not undeclared, f"icbtool_gui/ imports these, declared nowhere: {undeclared}"


def test_the_known_imports_are_found():
    """The scanner sees imports inside functions (a scanner that finds nothing would pass)."""
    imports = _third_party_imports()
    for module in ("numpy", "OpenGL", "cv2", "OpenEXR", "matplotlib", "embreex", "torch"):
        assert module in imports, module
    assert "icbtool/pipeline.py" in imports["matplotlib"]  # a function-level import


def test_optional_modules_are_not_imported_directly():
    """Optional packages go through require() so that a missing one names its extra."""
    from icbtool.optional import EXTRAS

    direct = {m: f for m, f in _third_party_imports().items() if m in EXTRAS}
    assert not direct, f"import these with icbtool.optional.require: {direct}"


def test_no_pyrender_and_a_working_pyopengl():
    """pyrender pins PyOpenGL==3.1.0 (broken OSMesa); icbtool neither declares nor imports it."""
    opts = _cfg()["options"]
    assert "pyrender" not in _requirements(opts["install_requires"])
    assert "pyrender" not in _third_party_imports()
    pyopengl = [ln for ln in opts["install_requires"].splitlines() if "PyOpenGL" in ln]
    assert pyopengl == ["PyOpenGL>=3.1.10"]


def test_shaders_are_package_data():
    pattern = _cfg()["options.package_data"]["icbtool"]
    globs = [g.strip() for g in pattern.split(",")]
    shaders = sorted(p for p in (PKG / "raster" / "shaders").iterdir() if p.is_file())
    assert len(shaders) >= 6
    for s in shaders:
        rel = s.relative_to(PKG)
        assert any(rel.match(g) for g in globs), f"{rel} is not matched by package_data {globs}"


def test_the_distribution_installs_no_generic_top_level_name():
    """setup.cfg's packages are icbtool and icbtool_gui only: the desktop app is not a top-level
    ``gui`` (a name other distributions install too), and `icbtool gui` imports it by that name."""
    from setuptools import find_packages

    include = [p.strip() for p in _cfg()["options.packages.find"]["include"].split(",")]
    tops = {p.split(".")[0] for p in find_packages(str(REPO), include=include)}
    assert tops == {"icbtool", "icbtool_gui"}, tops
    assert not (REPO / "gui" / "__init__.py").exists()
    cli = (PKG / "cli" / "gui.py").read_text()
    assert 'import_module("icbtool_gui.app")' in cli


def test_every_subpackage_is_a_lazy_attribute():
    """``icb.NAME`` works for every public subpackage and module (icb.net once raised
    AttributeError: it was missing from the lazy list)."""
    import icbtool

    public = {
        p.stem if p.suffix == ".py" else p.name
        for p in PKG.iterdir()
        if not p.name.startswith("_")
        and (p.suffix == ".py" or (p.is_dir() and (p / "__init__.py").exists()))
    }
    assert public <= set(icbtool._SUBMODULES), public - set(icbtool._SUBMODULES)
    assert set(icbtool._SUBMODULES) <= set(dir(icbtool))
