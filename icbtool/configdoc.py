"""The documentation of a config dataclass's fields, read from its source (docs/conventions.md):
the one reader behind the command line's help (``icbtool.cli._options``) and the desktop app's
tool tips (``icbtool_gui.forms``)."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap


def field_docs(cls: type) -> dict[str, str]:
    """The documentation of every field of dataclass ``cls`` (and its dataclass bases): the
    string literal right under the field, else its entry in the class docstring's ``Attributes:``
    section (Google style; ``a, b: text`` documents both). Whitespace is collapsed."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        docs.update(_attributes_section(klass.__doc__ or ""))
        docs.update(_attribute_docstrings(klass))
    return docs


def _attribute_docstrings(cls: type) -> dict[str, str]:
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # no source (frozen app, REPL): the Attributes section only
        return {}
    body = ast.parse(source).body[0]
    out: dict[str, str] = {}
    if not isinstance(body, ast.ClassDef):
        return out
    stmts = body.body
    for a, b in zip(stmts, stmts[1:]):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            out[a.target.id] = " ".join(b.value.value.split())
    return out


_ENTRY = re.compile(r"^([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)*)\s*(?:\([^)]*\))?\s*:\s*(.*)$")


def _attributes_section(doc: str) -> dict[str, str]:
    lines = inspect.cleandoc(doc).splitlines()
    try:
        start = next(i for i, ln in enumerate(lines) if ln.strip() == "Attributes:")
    except StopIteration:
        return {}
    base = len(lines[start]) - len(lines[start].lstrip())
    out: dict[str, str] = {}
    names: list[str] = []
    entry_indent = None
    for ln in lines[start + 1 :]:
        if not ln.strip():
            continue
        indent = len(ln) - len(ln.lstrip())
        if indent <= base:
            break  # the next section
        m = _ENTRY.match(ln.strip())
        if m and (entry_indent is None or indent == entry_indent):
            entry_indent = indent
            names = [n.strip() for n in m.group(1).split(",")]
            for n in names:
                out[n] = m.group(2).strip()
        elif names:
            for n in names:
                out[n] = f"{out[n]} {ln.strip()}"
    return out


__all__ = ["field_docs"]
