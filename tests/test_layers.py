"""Dependencies run one way, from geometry up to the applications (docs/conventions.md section 1).

Every import of the library by the library (module level, inside a function or under
``TYPE_CHECKING``) is read from the source with ``ast`` and checked against the layer table
below: a package may import only packages of lower layers (and itself). Read are
``import icbtool.X``, ``from icbtool.X import ...``, ``from icbtool import X``, relative imports,
and ``import icbtool`` (or ``import icbtool as icb``) followed by ``icbtool.X`` in the code.
Inside a package, the modules must not import each other in a circle either.
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
    "configdoc": 0,
    "imageio": 0,
    "camera": 1,
    "runs": 1,
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
    "optional": 0,
}


def _part(path: Path) -> str:
    rel = path.relative_to(PKG)
    return rel.parts[0].removesuffix(".py")


def _module_name(path: Path) -> str:
    """``icbtool/net/codec.py`` -> ``icbtool.net.codec``; a package's ``__init__``: the package."""
    parts = ["icbtool", *path.relative_to(PKG).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_modules(path: Path) -> set[str]:
    """The dotted names of everything of icbtool that ``path`` imports, however spelled.

    ``from icbtool.a import b`` gives ``icbtool.a.b`` when that is a module, else ``icbtool.a``;
    ``import icbtool`` (as any name) gives ``icbtool.X`` for every attribute ``X`` read on it."""
    tree = ast.parse(path.read_text(), str(path))
    here = _module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    out: set[str] = set()
    whole: set[str] = set()  # local names bound to the icbtool package itself
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module != "icbtool" and not module.startswith("icbtool."):
                continue
            for a in node.names:
                sub = f"{module}.{a.name}"
                out.add(sub if _is_module(sub) else module)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "icbtool":
                    whole.add(a.asname or "icbtool")
                elif a.name.startswith("icbtool."):
                    out.add(a.name)
    if whole:  # `import icbtool` then `icbtool.scene.load(...)`: the attributes used
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in whole
            ):
                out.add(f"icbtool.{node.attr}")
    return out


def _is_module(name: str) -> bool:
    rel = Path(*name.split(".")[1:])
    return (PKG / rel).with_suffix(".py").is_file() or (PKG / rel / "__init__.py").is_file()


def _imports(path: Path) -> set[str]:
    """The top-level parts of icbtool (``scene``, ``net``...) that ``path`` imports."""
    return {n.split(".")[1] for n in _imported_modules(path) if n.count(".") >= 1}


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


#: Import circles inside a package that are known and being untied (none now: net
#: codec/crypto/protocol, scene description/load and trace kernels/rtc were); a circle not listed
#: here fails the test.
KNOWN_CYCLES: list[set[str]] = []


def _cycles() -> list[set[str]]:
    """The strongly connected components (more than one module) of the import graph of every
    package's modules, each a set of dotted module names."""
    graph: dict[str, set[str]] = {}
    for path in PKG.rglob("*.py"):
        me = _module_name(path)
        top = me.split(".")[:2]
        graph[me] = {n for n in _imported_modules(path) if n.split(".")[:2] == top and n != me}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[set[str]] = []

    def visit(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circles_inside_a_package():
    new = [c for c in _cycles() if c not in KNOWN_CYCLES]
    assert not new, "modules that import each other in a circle: " + "; ".join(
        " <-> ".join(sorted(c)) for c in new
    )


def test_known_cycles_are_still_cycles():
    """An entry of KNOWN_CYCLES that is gone must leave the list (so it cannot come back)."""
    gone = [c for c in KNOWN_CYCLES if c not in _cycles()]
    assert not gone, f"untied, remove from KNOWN_CYCLES: {gone}"


def _write(tmp: Path, rel: str, text: str) -> Path:
    p = tmp / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "source,expect",
    [
        ("import icbtool\nicbtool.net.serve()\n", {"net"}),
        ("import icbtool as icb\nx = icb.gan.train\n", {"gan"}),
        ("from icbtool import pipeline\n", {"pipeline"}),
        ("from icbtool.system.cloud import Cloud\n", {"system"}),
        ("def f():\n    import icbtool.cli\n", {"cli"}),
        ("from ..net import codec\n", {"net"}),
        ("import numpy\n", set()),
    ],
)
def test_the_import_reader_sees_every_spelling(source, expect, tmp_path):
    """The reader itself, on sources that do each spelling (a module of a fake ``store``)."""
    globals()["PKG"], old = tmp_path, PKG
    try:
        for part in ("net", "gan", "pipeline", "system", "cli", "store"):
            _write(tmp_path, f"{part}/__init__.py", "")
        _write(tmp_path, "net/codec.py", "")
        path = _write(tmp_path, "store/mod.py", source)
        assert _imports(path) == expect
    finally:
        globals()["PKG"] = old


#: Packages outside the library that use only its public API: no module or name whose dotted
#: path has a part starting with ``_`` (``icbtool.cli._common``, ``icbtool.warp._numba``).
CLIENTS: list[str] = ["icbtool_gui", "benchmarks"]


def _private_uses(path: Path) -> list[str]:
    """The private modules and names of icbtool that ``path`` imports, however spelled (module
    level or inside functions; ``from icbtool.a import _b`` and ``icbtool.a._b`` attributes)."""
    tree = ast.parse(path.read_text(), str(path))
    used: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level:
            module = node.module or ""
            if module == "icbtool" or module.startswith("icbtool."):
                used.update(f"{module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            used.update(a.name for a in node.names if a.name.startswith("icbtool."))
        elif isinstance(node, ast.Attribute):  # icb.cli._common.load_scene
            chain = [node.attr]
            value = node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in ("icb", "icbtool"):
                used.add(".".join(["icbtool", *reversed(chain)]))
    return sorted(u for u in used if any(p.startswith("_") for p in u.split(".")[1:]))


@pytest.mark.parametrize(
    "path",
    sorted(p for c in CLIENTS for p in (PKG.parent / c).rglob("*.py")),
    ids=lambda p: str(p.relative_to(PKG.parent)),
)
def test_clients_use_only_the_public_api(path):
    bad = _private_uses(path)
    assert not bad, f"{path.relative_to(PKG.parent)} imports private parts of icbtool: {bad}"


@pytest.mark.parametrize(
    "source,expect",
    [
        ("from icbtool.cli._common import load_scene\n", ["icbtool.cli._common.load_scene"]),
        ("def f():\n    import icbtool.warp._numba\n", ["icbtool.warp._numba"]),
        ("from icbtool.scene import _private\n", ["icbtool.scene._private"]),
        (
            "import icbtool as icb\nicb.cli._common.x()\n",
            ["icbtool.cli._common", "icbtool.cli._common.x"],
        ),
        ("from icbtool.scene import load_scene\nimport icbtool as icb\nicb.store.open()\n", []),
    ],
)
def test_the_private_use_reader_sees_every_spelling(source, expect, tmp_path):
    path = _write(tmp_path, "client/mod.py", source)
    assert _private_uses(path) == expect


BENCH = PKG.parent / "benchmarks"
#: benchmarks/ modules that are shared pieces, not scripts
BENCH_SHARED = {"__init__", "common", "cornell_gltf"}


@pytest.mark.parametrize("path", sorted(BENCH.glob("*.py")), ids=lambda p: p.name)
def test_benchmarks_are_modules_of_one_package(path):
    """Each benchmark is ``python -m benchmarks.NAME``: a ``main()``, run under ``__main__``;
    it reaches other benchmarks and the shared pieces through the package (no ``sys.path``
    edits) and never imports the tests."""
    tree = ast.parse(path.read_text(), str(path))
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr == "path":
            if isinstance(node.value, ast.Name) and node.value.id == "sys":
                problems.append(f"line {node.lineno}: sys.path")
        if isinstance(node, ast.ImportFrom) and not node.level:
            top = (node.module or "").split(".")[0]
            if top in ("tests", "conftest") or (BENCH / f"{top}.py").is_file():
                problems.append(f"line {node.lineno}: from {node.module} (use benchmarks.X)")
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                if top in ("tests", "conftest") or (BENCH / f"{top}.py").is_file():
                    problems.append(f"line {node.lineno}: import {a.name}")
    if path.stem not in BENCH_SHARED:
        names = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        if "main" not in names:
            problems.append("no main()")
        if "__main__" not in path.read_text():
            problems.append("main() is not run under __main__")
    assert not problems, f"benchmarks/{path.name}: {problems}"
