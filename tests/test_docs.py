"""The documentation's shape: a short README, an index that reaches every page, links that
resolve, a package docstring that is an overview, and no issue numbers or dates of runs in
docs, docstrings and test names (those belong to commit messages and to docs/benchmarks.md)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
BENCH_PAGE = DOCS / "benchmarks.md"

#: "issue 17", "issues 20 and 17.4", "issue-22", "issue #3": a tracker the repository does not have
ISSUE = re.compile(r"\bissues?[ -]?#?\d+", re.IGNORECASE)
#: a calendar date (2026-11-27): when a run happened is a results file's business
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def markdown_files() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]


def source_files() -> list[Path]:
    """The Python (and browser JavaScript) sources of the library, app, tests and benchmarks."""
    files = [
        p
        for d in ("icbtool", "icbtool_gui", "tests", "benchmarks")
        for p in (REPO / d).rglob("*.py")
    ]
    files += sorted((REPO / "icbtool" / "web" / "src").glob("*.js"))
    return sorted(files)


def docstrings_and_comments(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every docstring and comment of a Python file; a JS file: its comments."""
    text = path.read_text()
    out = []
    if path.suffix == ".js":
        for m in re.finditer(r"//[^\n]*|/\*.*?\*/", text, re.S):
            out.append((text.count("\n", 0, m.start()) + 1, m.group(0)))
        return out
    tree = ast.parse(text)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                first = node.body[0]
                out.append((first.lineno, doc))
    for n, line in enumerate(text.splitlines(), 1):
        if "#" in line:
            out.append((n, line[line.index("#") :]))
    return out


def test_the_scans_see_what_they_must_refuse():
    assert ISSUE.search("as issue 17 asks") and ISSUE.search("the issue-22 speed changes")
    assert ISSUE.search("(issues 20 and 17.4)") and not ISSUE.search("an issue with 2 cores")
    assert DATE.search("the quiet run of 2026-11-27 03:30") and not DATE.search("0.2026-11")
    found = docstrings_and_comments(Path(__file__))
    assert any("docstring and comment" in text for _, text in found)


def test_readme_is_a_front_door():
    text = (REPO / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; move detail to docs/"
    head = text[: text.index("\n## Install")]
    assert "make demo" in head and "make test" in head, "the two commands come first"
    assert "docs/index.md" in text and "docs/benchmarks.md" in text
    assert "<!-- bench:" not in text, "benchmark tables live on docs/benchmarks.md"


def test_every_page_is_reachable_from_the_index():
    index = (DOCS / "index.md").read_text()
    linked = {(DOCS / m.group(1).split("#")[0]).resolve() for m in LINK.finditer(index)}
    missing = [
        str(p.relative_to(REPO))
        for p in DOCS.rglob("*.md")
        if p.name != "index.md" and p.resolve() not in linked
    ]
    assert not missing, f"link these from docs/index.md: {missing}"


def test_relative_links_resolve():
    broken = []
    for page in markdown_files():
        for n, line in enumerate(page.read_text().splitlines(), 1):
            for m in LINK.finditer(line):
                target = m.group(1)
                if re.match(r"^[a-z]+:", target) or target.startswith("#"):
                    continue
                if not (page.parent / target.split("#")[0]).exists():
                    broken.append(f"{page.relative_to(REPO)}:{n}: {target}")
    assert not broken, broken


def test_no_issue_numbers_anywhere():
    hits = []
    for path in markdown_files() + source_files():
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if ISSUE.search(line) and path != Path(__file__):
                hits.append(f"{path.relative_to(REPO)}:{n}: {line.strip()[:80]}")
    assert not hits, "say what the change is for, not which ticket asked for it:\n" + "\n".join(
        hits
    )


def test_no_dates_of_runs_outside_the_benchmarks_page():
    """Docs prose (the benchmarks page aside), docstrings and comments carry no dates; a run's
    date is in its results file and in the commit that added it."""
    hits = []
    for page in markdown_files():
        if page == BENCH_PAGE:
            continue
        for n, line in enumerate(page.read_text().splitlines(), 1):
            if DATE.search(line):
                hits.append(f"{page.relative_to(REPO)}:{n}")
    for path in source_files():
        if path == Path(__file__) or path.name == "page.py":  # page.py writes the page
            continue
        for n, text in docstrings_and_comments(path):
            if DATE.search(text):
                hits.append(f"{path.relative_to(REPO)}:{n}")
    assert not hits, hits


def test_test_names_say_what_they_check():
    bad = []
    for path in sorted((REPO / "tests").glob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name.startswith(
                ("test", "Test")
            ):
                if re.search(r"issue_?\d+|20\d\d_?[01]\d", node.name, re.IGNORECASE):
                    bad.append(f"{path.name}::{node.name}")
    assert not bad, bad


def test_help_icbtool_is_an_overview():
    import icbtool

    doc = icbtool.__doc__
    assert len(doc.splitlines()) >= 15
    for part in icbtool._SUBMODULES:
        assert f"``{part}``" in doc, f"icbtool's docstring does not name {part}"
    for where in ("README.md", "docs/index.md", "docs/guide/", "docs/benchmarks.md"):
        assert where in doc
    for entry in ("icb.scene.load", "icb.raster.render", "icb.trace.render", "run_loop"):
        assert entry in doc


def test_import_icbtool_and_its_overview_stay_light():
    """The overview is the package docstring: reading it imports no numerical library."""
    heavy = ("numpy", "torch", "OpenGL", "numba", "scipy", "matplotlib")
    code = (
        f"import sys, icbtool; icbtool.__doc__; print([m for m in {heavy!r} if m in sys.modules])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]", f"import icbtool imported {r.stdout.strip()}"
