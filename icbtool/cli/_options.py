"""Command-line options generated from the config dataclasses and their field docstrings.

Every setting lives in one place, its config dataclass: the field's name gives the option
(``spp`` -> ``--spp``, ``time_budget_s`` -> ``--time-budget-s``), its type the parsing (``bool``
-> ``--x/--no-x``, ``Literal`` -> choices, ``X | None``, ``tuple[int, ...]`` -> ``1,2,3``), its
default the default (shown in ``--help``) and its docstring (the string under the field, or the
entry of the class docstring's ``Attributes:`` section) the help. A field added to a config
appears on every command that uses the config, without a CLI edit. Nested config fields are
flattened under the nested field's own options (``LoopConfig.cloud.spp`` is ``--spp``).

One spelling per concept across all commands: :data:`CONCEPTS` gives the value check of the
fields that mean the same thing everywhere (sample counts, seeds, image sizes, latencies); a
command changes a field's spelling or default only through :func:`add_config`'s arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args, get_origin

from icbtool.cli._common import (
    UsageError,
    finite_float,
    float_in,
    int_at_least,
    positive_float,
    positive_int,
)
from icbtool.configdoc import field_docs


# ------------------------------------------------------------------------------ spellings
@dataclass(frozen=True)
class Spelling:
    """How a field appears on the command line where the generated form is not right.

    Attributes:
        option: the option string (default: ``--`` + the field name with dashes).
        type: the argparse ``type`` (a value check with a one-line error).
        metavar: the value's name in the help.
        help: replaces the field's docstring.
        default_text: what the help says about the default (e.g. "the path's").
    """

    option: str | None = None
    type: Callable[[str], Any] | None = None
    metavar: str | None = None
    help: str | None = None
    default_text: str | None = None


#: The value checks of fields that mean the same thing in every config (by field name).
CONCEPTS: dict[str, Spelling] = {
    "spp": Spelling(type=positive_int),
    "truth_spp": Spelling(type=positive_int),
    "seed": Spelling(type=int_at_least(0)),
    "height": Spelling(type=positive_int, metavar="H"),
    "width": Spelling(type=positive_int, metavar="W"),
    "frames": Spelling(type=positive_int),
    "threads": Spelling(type=positive_int),
    "stride": Spelling(type=positive_int),
    "limit": Spelling(type=positive_int),
    "max_depth": Spelling(type=positive_int),
    "latency_s": Spelling(type=float_in(0.0)),
    "latency_ms": Spelling(type=float_in(0.0)),
    "bandwidth_mbit": Spelling(type=float_in(0.0, lo_open=True)),
    "time_budget_s": Spelling(type=positive_float),
    "target_error": Spelling(type=positive_float),
    "timeout_s": Spelling(type=positive_float),
    "truth_every": Spelling(type=int_at_least(0)),
    "fov_multiplier": Spelling(type=float_in(1.0)),
    "pullback": Spelling(type=float_in(0.0)),
    "port": Spelling(type=int_at_least(0)),
    "max_pending": Spelling(type=positive_int),
    "iterations": Spelling(type=positive_int),
    "n_cameras": Spelling(type=positive_int),
    "generator": Spelling(metavar="RUN"),
    "models": Spelling(metavar="RUN[,RUN...]"),
}


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None


_integer.__name__ = "int"


_number = finite_float


def _json(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be JSON, got {text!r}") from None


_json.__name__ = "JSON"

#: The help of a config field that has no docstring (tests/test_cli.py fails on it).
UNDOCUMENTED = "(undocumented field)"


def _sequence(item: Callable[[str], Any], length: int | None) -> Callable[[str], tuple]:
    """An argparse type for comma-separated values (``length`` of them, or any number >= 1)."""

    def parse(text: str) -> tuple:
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts or (length is not None and len(parts) != length):
            n = f"{length}" if length is not None else "one or more"
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated values, got {text!r}")
        try:
            return tuple(item(p) for p in parts)
        except argparse.ArgumentTypeError as e:
            raise argparse.ArgumentTypeError(f"{e} (in {text!r})") from None

    parse.__name__ = "list"
    return parse


def _hints(cls: type) -> dict[str, Any]:
    """The resolved field types of ``cls``; a field whose annotation cannot be resolved (a name
    imported only under TYPE_CHECKING) is Any."""
    try:
        return typing.get_type_hints(cls)
    except NameError:
        out = {}
        module = sys.modules.get(cls.__module__)
        ns = dict(vars(module)) if module else {}
        for f in dataclasses.fields(cls):
            try:
                out[f.name] = (
                    eval(f.type, ns) if isinstance(f.type, str) else f.type  # noqa: S307
                )
            except NameError:
                out[f.name] = Any
        return out


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(args) < len(get_args(tp)):
            return args[0], True
    return tp, False


def _kind(tp: Any) -> dict[str, Any] | None:
    """argparse keywords for a field type (None: not expressible on a command line)."""
    tp, _ = _unwrap_optional(tp)
    if tp is bool:
        return {"action": Flag}
    if tp is int:
        return {"type": _integer, "metavar": "N"}
    if tp is float:
        return {"type": _number, "metavar": "X"}
    if tp is str:
        return {"type": str, "metavar": "TEXT"}
    if get_origin(tp) is Literal:
        choices = get_args(tp)
        if all(isinstance(c, str) for c in choices):
            return {"choices": choices}
        return None
    if get_origin(tp) is tuple:
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            item, length = args[0], None
        elif args and all(a == args[0] for a in args):
            item, length = args[0], len(args)
        else:
            return None
        parse = {int: _integer, float: _number, str: str}.get(item)
        if parse is None:
            return None
        meta = "X,Y" if length == 2 else "X,Y,..."
        return {"type": _sequence(parse, length), "metavar": meta}
    return None


class Flag(argparse.Action):
    """A boolean option as a pair ``--x`` / ``--no-x`` (argparse's BooleanOptionalAction, minus
    its own default text: the generator writes the defaults of every option the same way)."""

    def __init__(self, option_strings: list[str], dest: str, **kw: Any) -> None:
        both = []
        for opt in option_strings:
            both.append(opt)
            if opt.startswith("--"):
                both.append("--no-" + opt[2:])
        super().__init__(both, dest, nargs=0, **kw)

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # noqa: ANN001
        setattr(namespace, self.dest, not option_string.startswith("--no-"))

    def format_usage(self) -> str:
        return " | ".join(self.option_strings)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def _show(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, tuple):
        return ",".join(_show(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


class _Unset:
    """The default of an option whose field takes the config's (or a preset's) own value."""

    def __repr__(self) -> str:
        return "<unset>"


UNSET: Any = _Unset()


@dataclass
class _Field:
    path: tuple[str, ...]  # field names from the top config down
    dest: str
    option: str


@dataclass
class ConfigOptions:
    """The options :func:`add_config` made for a config class, and how to build it back."""

    cls: type
    fields: list[_Field]
    nested: dict[str, type]  # dotted path of a nested config field -> its class

    def values(self, args: argparse.Namespace) -> dict[str, Any]:
        """The given (not UNSET) values, nested configs as nested dicts."""
        out: dict[str, Any] = {}
        for f in self.fields:
            v = getattr(args, f.dest)
            if v is UNSET:
                continue
            d = out
            for part in f.path[:-1]:
                d = d.setdefault(part, {})
            d[f.path[-1]] = v
        return out

    def build(self, args: argparse.Namespace, **fixed: Any) -> Any:
        """The config from the parsed ``args`` (plus ``fixed`` fields); a value the config
        rejects is a :class:`UsageError` naming the option."""
        return self.call(lambda **kw: self._make(self.cls, (), kw), args, **fixed)

    def call(self, factory: Callable[..., Any], args: argparse.Namespace, **fixed: Any) -> Any:
        """``factory(**values, **fixed)`` (e.g. ``TrainConfig.preset``), the config's own
        ValueError/TypeError turned into a :class:`UsageError` that names the option."""
        try:
            return factory(**{**self.values(args), **fixed})
        except (ValueError, TypeError) as e:
            msg = str(e)
            for f in self.fields:
                owner = self.nested.get(".".join(f.path[:-1]), self.cls)
                if f"{owner.__name__}.{f.path[-1]}" in msg:
                    msg = f"{f.option}: {msg}"
                    break
            raise UsageError(msg) from None

    def _make(self, cls: type, prefix: tuple[str, ...], kw: dict[str, Any]) -> Any:
        for name, sub in list(kw.items()):
            path = ".".join((*prefix, name))
            if isinstance(sub, dict) and path in self.nested:
                kw[name] = self._make(self.nested[path], (*prefix, name), sub)
        return cls(**kw)


def add_config(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    skip: tuple[str, ...] = (),
    only: tuple[str, ...] | None = None,
    spell: Mapping[str, Spelling] | None = None,
    defaults: Mapping[str, Any] | None = None,
    unset: bool = False,
    prefix: str = "",
    title: str | None = None,
) -> ConfigOptions:
    """Add an option for every field of dataclass ``cls`` (nested config fields flattened).

    Args:
        parser: the (sub)command's parser.
        cls: the config dataclass.
        skip: field paths not offered (``"cloud.seed"``, ``"tags"``): set by the command.
        only: offer only these field paths (and the fields of nested configs under them).
        spell: per field path, a :class:`Spelling` (over :data:`CONCEPTS`).
        defaults: per field path, the command's default instead of the dataclass's.
        unset: options default to UNSET (the field keeps the config's or preset's value);
            give ``Spelling.default_text`` to say what that is.
        prefix: put before every option name of this config (``"net-"``: ``--net-latency-ms``).
        title: the help section's title (default: the class name).

    Returns:
        The :class:`ConfigOptions` that builds the config back from the parsed arguments.

    Raises:
        TypeError: a field without a default (the command must give one in ``defaults``).

    A field whose type has no plain command-line form (a dict, a list, Any) takes JSON, so that a
    new field can never be missing from the command line; one without a docstring gets
    :data:`UNDOCUMENTED` as its help (which the CLI tests reject).
    """
    spell, defaults = spell or {}, defaults or {}
    group = parser.add_argument_group(title or f"{cls.__name__} (icbtool's config)")
    out = ConfigOptions(cls, [], {})
    _add_fields(group, cls, (), out, skip, only, spell, defaults, unset, prefix)
    return out


def _add_fields(group, cls, path, out, skip, only, spell, defaults, unset, prefix) -> None:
    docs = field_docs(cls)
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        fpath = (*path, f.name)
        key = ".".join(fpath)
        if key in skip:
            continue
        if only is not None and not any(
            key == o or key.startswith(o + ".") or o.startswith(key + ".") for o in only
        ):
            continue
        tp, optional = _unwrap_optional(hints.get(f.name, Any))
        if dataclasses.is_dataclass(tp):
            out.nested[key] = tp
            _add_fields(group, tp, fpath, out, skip, only, spell, defaults, unset, prefix)
            continue
        kw = _kind(tp) or {"type": _json, "metavar": "JSON"}  # dicts, lists, anything else
        s = spell.get(key) or CONCEPTS.get(f.name) or Spelling()
        concept = CONCEPTS.get(f.name)
        vtype = s.type or (concept.type if concept else None)
        if vtype is not None and "type" in kw and "," not in kw.get("metavar", ""):
            kw["type"] = vtype
        metavar = s.metavar or (concept.metavar if concept else None)
        if metavar:
            kw["metavar"] = metavar
        if key in defaults:
            default = defaults[key]
        elif unset:
            default = UNSET
        elif f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            raise TypeError(f"{cls.__name__}.{f.name} has no default: give one in defaults=")
        # a field without a docstring still gets its option (tests/test_cli.py flags it)
        text = (s.help or docs.get(f.name) or UNDOCUMENTED).replace("%", "%%")
        if s.default_text is not None:
            text += f" (default: {s.default_text})"
        elif default is not UNSET:
            text += f" (default: {_show(default).replace('%', '%%')})"
        if optional and "type" in kw:  # "none" on the command line gives None
            inner = kw["type"]

            def maybe(text: str, inner=inner) -> Any:
                return None if text.lower() == "none" else inner(text)

            maybe.__name__ = getattr(inner, "__name__", "value")
            kw["type"] = maybe
        dest = "cfg:" + ".".join((prefix, *fpath)) if prefix else "cfg:" + key
        option = s.option or _option(prefix.replace("-", "_") + f.name)
        group.add_argument(option, dest=dest, default=default, help=text, **kw)
        out.fields.append(_Field(fpath, dest, option))


__all__ = [
    "CONCEPTS",
    "UNDOCUMENTED",
    "UNSET",
    "ConfigOptions",
    "Spelling",
    "add_config",
    "field_docs",
]
