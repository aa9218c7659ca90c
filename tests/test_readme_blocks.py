"""Every shell and Python block of README.md and of the pages in docs/ runs as written, on the
built-in scenes.

Conventions (README.md repeats them in a comment at its top; every page follows them):

- A fenced block tagged ``bash``, ``sh``, ``shell`` or ``python`` is a block to check; a usage
  synopsis (``icbtool demo [SCENE] ...``) is fenced as ``text`` and is not.
- An HTML comment on the line right above the fence marks the block:
  ``<!-- readme-test: slow -->`` it takes minutes: run only with the slow tests;
  ``<!-- readme-test: sponza -->`` it needs the Sponza scene: run (with the slow tests) only
  where Sponza is (``ICBTOOL_SPONZA`` or the repository's sibling ``shared/scenes/sponza``);
  ``<!-- readme-test: skip REASON -->`` never run (it installs packages, opens a window, runs
  the test suite itself ...). Markers combine: ``<!-- readme-test: slow sponza -->``.
- A line that ends in ``# [sponza]`` needs Sponza: where it is missing the line is left out (a
  Python statement becomes ``pass``), the rest of the block runs.
- A Python block is a script of its own (its own imports); shell blocks run with ``bash -e``.
  Both run in a fresh temporary folder that holds links to the repository's ``data/``,
  ``tests/`` and ``benchmarks/`` (what they write stays there), with ``icbtool`` on the PATH.
- An unmarked block runs in the default (quick) test run: keep it to seconds.

The default run checks every block, marked or not, without running the slow ones: Python
compiles, every name it reads is bound in the block, and every ``icb.X.Y`` it names exists;
shell parses (``bash -n``), every ``make T`` is a Makefile target, every ``icbtool ...`` line is
accepted by the command line's parser and every script it names exists.
"""

from __future__ import annotations

import ast
import builtins
import contextlib
import importlib
import io
import os
import re
import shlex
import subprocess
import sys
import types
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
#: the documents whose blocks are checked: the README and every page under docs/
DOCS = [README, *sorted((REPO / "docs").rglob("*.md"))]
LANGS = {"bash": "shell", "sh": "shell", "shell": "shell", "python": "python"}
MARKERS = {"slow", "sponza", "skip"}
SPONZA_LINE = "# [sponza]"


@dataclass
class Block:
    """One fenced block of a document."""

    doc: str  # the document, relative to the repository ("README.md", "docs/guide/cli.md")
    line: int  # 1-based line of the opening fence
    kind: str  # "shell" or "python"
    code: str
    marks: set[str] = field(default_factory=set)
    reason: str = ""

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}:{self.kind}"


def readme_blocks(text: str | None = None, doc: str = "README.md") -> list[Block]:
    """The shell and Python blocks of a document (default: the README) with their markers.

    Args:
        text: the document's text; None: README.md's.
        doc: the document's name in block ids and errors.

    Raises:
        ValueError: an unknown marker or an unclosed fence (naming the document and line).
    """
    lines = (README.read_text() if text is None else text).splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = re.match(r"^```(\w+)?\s*$", lines[i])
        if not m:
            i += 1
            continue
        lang, start = (m.group(1) or "").lower(), i
        end = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("```")), None)
        if end is None:
            raise ValueError(f"{doc}:{start + 1}: the ``` fence is never closed")
        marks, reason = set(), ""
        prev = lines[start - 1].strip() if start > 0 else ""
        mm = re.match(r"^<!--\s*readme-test:\s*(.*?)\s*-->$", prev)
        if mm:
            words = mm.group(1).split()
            while words and words[0] in MARKERS:
                marks.add(words.pop(0))
            reason = " ".join(words)
            if not marks:
                raise ValueError(
                    f"{doc}:{start}: readme-test marker {prev!r} names none of {MARKERS}"
                )
        if lang in LANGS:
            code = "\n".join(lines[start + 1 : end]) + "\n"
            blocks.append(Block(doc, start + 1, LANGS[lang], code, marks, reason))
        i = end + 1
    return blocks


def sponza_present() -> bool:
    d = Path(os.environ.get("ICBTOOL_SPONZA", REPO.parent / "shared" / "scenes" / "sponza"))
    return (d / "sponza_textured.obj").is_file()


def without_sponza_lines(block: Block) -> str:
    """The block's code with its ``# [sponza]`` lines left out (Python: ``pass``)."""
    out = []
    for line in block.code.splitlines():
        if line.rstrip().endswith(SPONZA_LINE):
            if block.kind == "python":
                out.append(line[: len(line) - len(line.lstrip())] + "pass")
            continue
        out.append(line)
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------------------ static checks
def python_problems(code: str) -> list[str]:
    """What is wrong with a Python block without running it: names read but bound nowhere in
    it (it must be a script of its own) and ``icbtool`` attributes that do not exist."""
    tree = ast.parse(code)
    bound, loaded = set(dir(builtins)), []
    modules: dict[str, str] = {}  # local name -> icbtool module path
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            if isinstance(node.ctx, ast.Load):
                loaded.append(node)
            else:
                bound.add(node.id)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            bound.add(node.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                bound.add((a.asname or a.name).split(".")[0])
                if a.name.split(".")[0] == "icbtool":
                    modules[a.asname or "icbtool"] = a.name if a.asname else "icbtool"
        elif isinstance(node, ast.ImportFrom):
            for a in node.names:
                bound.add(a.asname or a.name)
                if (node.module or "").split(".")[0] == "icbtool":
                    modules[a.asname or a.name] = f"{node.module}.{a.name}"
    problems = [
        f"line {n.lineno}: {n.id!r} is read but never defined in the block"
        for n in loaded
        if n.id not in bound
    ]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("icbtool"):
            mod = importlib.import_module(node.module)
            problems += [
                f"line {node.lineno}: {node.module} has no {a.name!r}"
                for a in node.names
                if not hasattr(mod, a.name) and not _submodule(f"{node.module}.{a.name}")
            ]
        if not isinstance(node, ast.Attribute) or not isinstance(node.ctx, ast.Load):
            continue
        chain, root = [], node
        while isinstance(root, ast.Attribute):
            chain.insert(0, root.attr)
            root = root.value
        if not isinstance(root, ast.Name) or root.id not in modules:
            continue
        obj, path = _resolve(modules[root.id]), modules[root.id]
        for attr in chain:
            if not isinstance(obj, (types.ModuleType, type)):
                break  # a value (a result, an instance): its attributes are checked by running
            if not hasattr(obj, attr):
                problems.append(f"line {node.lineno}: {path} has no attribute {attr!r}")
                break
            obj, path = getattr(obj, attr), f"{path}.{attr}"
    return sorted(set(problems))


def _submodule(name: str) -> bool:
    try:
        importlib.import_module(name)
        return True
    except ImportError:
        return False


def _resolve(dotted: str) -> object:
    """``icbtool.store`` -> the module; ``icbtool.system.Cloud`` -> the class."""
    try:
        return importlib.import_module(dotted)
    except ImportError:
        mod, _, attr = dotted.rpartition(".")
        return getattr(importlib.import_module(mod), attr)


def _make_targets() -> set[str]:
    text = (REPO / "Makefile").read_text()
    return {m.group(1) for m in re.finditer(r"^([A-Za-z0-9_./-]+)\s*:(?!=)", text, re.M)}


def _commands(code: str) -> list[list[str]]:
    """Simple commands of a shell block (continuations joined, comments dropped, split at
    ``&&``, ``||``, ``;`` and ``|``), leading ``VAR=value`` words removed."""
    text = code.replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        lex = shlex.shlex(line, posix=True, punctuation_chars=";&|")
        lex.whitespace_split = True
        lex.commenters = "#"
        words, cmd = list(lex), []
        for w in [*words, ";"]:
            if w in (";", "&&", "||", "|", "&"):
                while cmd and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", cmd[0]):
                    cmd.pop(0)
                if cmd:
                    out.append(cmd)
                cmd = []
            else:
                cmd.append(w)
    return out


def shell_problems(code: str) -> list[str]:
    """What is wrong with a shell block without running it: syntax (``bash -n``), make targets
    that the Makefile lacks, icbtool command lines its parser refuses, scripts that are not
    there."""
    from icbtool.cli import build_parser

    r = subprocess.run(["bash", "-n"], input=code, capture_output=True, text=True)
    if r.returncode:
        return [f"bash -n: {r.stderr.strip()}"]
    problems, targets = [], _make_targets()
    for cmd in _commands(code):
        while cmd and cmd[0] in ("xvfb-run", "nice", "time", "env"):
            cmd = cmd[1:]
            while cmd and (cmd[0].startswith("-") or cmd[0].lstrip("-").isdigit()):
                cmd = cmd[1:]
        if not cmd:
            continue
        prog, args = cmd[0], cmd[1:]
        if prog.endswith("python") or prog.endswith("python3") or prog == "$PY":
            if args[:2] == ["-m", "icbtool"]:
                prog, args = "icbtool", args[2:]
            elif args and args[0].endswith(".py") and not (REPO / args[0]).is_file():
                problems.append(f"{' '.join(cmd)}: no script {args[0]}")
                continue
        if prog == "make":
            problems += [
                f"make {t}: no such target in the Makefile"
                for t in args
                if not t.startswith("-") and "=" not in t and t not in targets
            ]
        elif prog == "icbtool":
            err = io.StringIO()
            try:
                with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                    build_parser().parse_args(args)
            except SystemExit as e:
                if e.code:
                    problems.append(f"{' '.join(cmd)}: {err.getvalue().strip()}")
        elif "/" in prog and not prog.startswith(("/", "$", "~")) and not (REPO / prog).exists():
            problems.append(f"{' '.join(cmd)}: no {prog} in the repository")
    return problems


# ------------------------------------------------------------------------------ running
def run_block(block: Block, workdir: Path, timeout_s: float) -> subprocess.CompletedProcess:
    """Run a block as written (Sponza lines left out where Sponza is missing) in ``workdir``."""
    code = block.code if sponza_present() else without_sponza_lines(block)
    for name in ("data", "tests", "benchmarks"):
        if not (workdir / name).exists():
            (workdir / name).symlink_to(REPO / name)
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""),
        "MPLBACKEND": "Agg",
    }
    env.setdefault("ICBTOOL_GL_BACKEND", "osmesa")
    if block.kind == "python":
        script = workdir / f"block_{block.line}.py"
        script.write_text(code)
        cmd = [sys.executable, str(script)]
    else:
        cmd = ["bash", "-e", "-o", "pipefail", "-c", code]
    return subprocess.run(cmd, cwd=workdir, env=env, capture_output=True, text=True,
                          timeout=timeout_s)  # fmt: skip


def doc_blocks() -> list[Block]:
    """The blocks of every document in DOCS."""
    return [
        b for path in DOCS for b in readme_blocks(path.read_text(), str(path.relative_to(REPO)))
    ]


BLOCKS = doc_blocks()


def test_the_readme_has_blocks_and_states_the_convention():
    """The extractor sees the README's and the guide's blocks (one that found none would pass
    every test) and the README says how to mark a block."""
    readme = [b for b in BLOCKS if b.doc == "README.md"]
    assert {b.kind for b in readme} == {"shell", "python"}, [b.id for b in readme]
    guide = {b.doc for b in BLOCKS if b.doc.startswith("docs/guide/")}
    assert len(guide) >= 5 and len(BLOCKS) >= 15, sorted(guide)
    assert "readme-test:" in README.read_text().split("\n## ", 1)[0]
    for b in BLOCKS:
        if "skip" in b.marks:
            assert b.reason, f"{b.id}: say why it is skipped (<!-- readme-test: skip REASON -->)"


def test_the_marker_rules():
    text = (
        "<!-- readme-test: slow sponza -->\n```python\nx = 1\ny = 2  # [sponza]\n```\n"
        "```text\nicbtool demo [SCENE]\n```\n<!-- readme-test: skip installs packages -->\n"
        "```bash\npip install .\n```\n"
    )
    a, b = readme_blocks(text)
    assert (a.line, a.kind, a.marks) == (2, "python", {"slow", "sponza"})
    assert without_sponza_lines(a) == "x = 1\npass\n"
    assert (b.kind, b.marks, b.reason) == ("shell", {"skip"}, "installs packages")
    with pytest.raises(ValueError, match="names none of"):
        readme_blocks("<!-- readme-test: later -->\n```bash\nls\n```\n")
    with pytest.raises(ValueError, match="never closed"):
        readme_blocks("```bash\nls\n")
    assert python_problems("import icbtool as icb\nicb.scene.cornell_box(points)\n") == [
        "line 2: 'points' is read but never defined in the block"
    ]
    assert python_problems("import icbtool as icb\nicb.store.no_such_thing()\n") == [
        "line 2: icbtool.store has no attribute 'no_such_thing'"
    ]
    assert shell_problems("make no-such-target\n") == [
        "make no-such-target: no such target in the Makefile"
    ]
    assert shell_problems("icbtool render cornell_box --out o --no-such-option\n")
    assert shell_problems("icbtool store evict DIR  # a comment\nmake test && make demo\n") == []


@pytest.mark.parametrize("block", BLOCKS, ids=[b.id for b in BLOCKS])
def test_block_parses_and_its_names_resolve(block):
    problems = python_problems(block.code) if block.kind == "python" else shell_problems(block.code)
    assert not problems, f"{block.id}:\n" + "\n".join(problems)


def _run_or_skip(block: Block, tmp_path: Path) -> None:
    if "skip" in block.marks:
        pytest.skip(f"{block.id}: {block.reason}")
    if "sponza" in block.marks and not sponza_present():
        pytest.skip(f"{block.id} needs Sponza (ICBTOOL_SPONZA)")
    r = run_block(block, tmp_path, timeout_s=1800)
    assert r.returncode == 0, f"{block.id} failed:\n{r.stdout[-3000:]}\n{r.stderr[-5000:]}"


QUICK = [b for b in BLOCKS if not b.marks & {"slow", "sponza"}]
SLOW = [b for b in BLOCKS if b.marks & {"slow", "sponza"}]


@pytest.mark.parametrize("block", QUICK, ids=[b.id for b in QUICK])
def test_quick_block_runs(block, tmp_path):
    _run_or_skip(block, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("block", SLOW, ids=[b.id for b in SLOW])
def test_slow_block_runs(block, tmp_path):
    _run_or_skip(block, tmp_path)


def test_code_and_docs_cite_only_documents_in_the_repository():
    """Docstrings cite docs/design.md and docs/conventions.md (in the repository), never the
    design notes they were written from (ICB.md, STYLE.md), which a clone does not have."""
    cited = []
    for path in [*REPO.glob("*.md"), *REPO.glob("docs/**/*.md")] + [
        p
        for d in ("icbtool", "icbtool_gui", "tests", "benchmarks")
        for p in (REPO / d).rglob("*.py")
    ]:
        if path == Path(__file__):
            continue
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if "ICB.md" in line or "STYLE.md" in line:
                cited.append(f"{path.relative_to(REPO)}:{n}")
    assert not cited, f"cite docs/design.md or docs/conventions.md instead: {cited}"
    design = (REPO / "docs" / "design.md").read_text()
    for n in range(1, 8):  # the sections the code cites by number
        assert f"\n## {n}. " in design, n
