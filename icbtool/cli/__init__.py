"""The ``icbtool`` command line. Each subcommand is a module in this package that defines
``register(subparsers)``; it is discovered automatically, so adding a command touches one file.

The options of the settings come from the config dataclasses (:mod:`icbtool.cli._options`):
one spelling per concept across every command, every option with its help and its default.
Ctrl-C ends any command with exit code 130 and one line (stores are closed, their committed
records kept); warnings print as one line each.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import pkgutil
import sys
import warnings
from collections.abc import Iterator
from typing import Any

#: Options of earlier versions that have another spelling now (one spelling per concept).
RENAMED = {
    "--size": "--height H --width W",
    "--latency-ms": "--net-latency-ms",
    "--bandwidth-mbit": "--net-bandwidth-mbit",
    "--fast-embree": "--no-robust",
    "--no-generator": "--no-use-generator",
    "--generator": "--models RUN[,RUN...] (serve: the client model offered, as ONNX)",
}


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions as written; every option's help ends with its default (unless it says it
    already, or the default is nothing: None, False, or the config's own)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        d = action.default
        if (
            action.option_strings
            and "default" not in text
            and d is not None
            and d is not False
            and d != ()
            and d is not argparse.SUPPRESS
            and not action.required
        ):
            shown = ",".join(map(str, d)) if isinstance(d, (tuple, list)) else str(d)
            text += f" (default: {shown.replace('%', '%%')})"
        return text


class Parser(argparse.ArgumentParser):
    """argparse's parser with :class:`HelpFormatter` as the default formatter (subcommands
    inherit it)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


class _Commands(argparse._SubParsersAction):
    """The subcommands: a command's options are added when it is chosen (its config classes,
    e.g. the trainer's with torch, are imported only then), see :func:`add_command`."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # noqa: ANN001
        from icbtool.cli._common import populate

        chosen = self._name_parser_map.get(values[0]) if values else None
        if chosen is not None:
            populate(chosen)
        super().__call__(parser, namespace, values, option_string)


def build_parser() -> argparse.ArgumentParser:
    import icbtool

    parser = Parser(
        prog="icbtool",
        description="Intelligent CloudBaking: hybrid cloud/client rendering research tool.",
    )
    parser.add_argument("--version", action="version", version=f"icbtool {icbtool.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", action=_Commands)
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


@contextlib.contextmanager
def one_line_warnings(command: str) -> Iterator[None]:
    """Print each Python warning as ``icbtool COMMAND: warning: MESSAGE``: one line, without
    the source line that Python's default format adds."""
    old = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
        text = " ".join(str(message).split())
        print(f"icbtool {command}: warning: {text}", file=file or sys.stderr)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = old


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``icbtool`` console script. Returns the exit code."""
    command = "icbtool"
    try:
        parser = build_parser()
        args, extras = parser.parse_known_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        if extras:  # reported by the command's parser, with the new spelling of an old option
            chosen = next(a for a in parser._actions if isinstance(a, _Commands))
            renamed = [f"{o} is now {RENAMED[o]}" for o in extras if o in RENAMED]
            hint = f" ({'; '.join(renamed)})" if renamed else ""
            chosen.choices[args.command].error(f"unrecognized arguments: {' '.join(extras)}{hint}")
        command = f"icbtool {args.command}"
        from icbtool.cli._common import UsageError, resolve_store
        from icbtool.optional import MissingOptionalDependency

        with one_line_warnings(args.command):
            rc = 1
            try:
                resolve_store(args, args.command)
                rc = int(args.func(args) or 0)
                return rc
            except UsageError as e:  # a bad argument, found before any work: exit 2
                print(f"{command}: error: {e}", file=sys.stderr)
                rc = 2
                return rc
            except (ValueError, FileNotFoundError, OSError, MissingOptionalDependency) as e:
                print(f"{command}: error: {e}", file=sys.stderr)  # user errors: one line
                return rc
            finally:  # a failure or Ctrl-C leaves no empty output folder or store behind
                if rc != 0:
                    _discard_empty_outputs()
    except KeyboardInterrupt:  # Ctrl-C: stores were closed on the way out (with blocks)
        lead = "\n" if sys.stderr.isatty() else ""  # off the terminal's ^C / progress bar line
        print(f"{lead}{command}: interrupted", file=sys.stderr)
        return 130


def _discard_empty_outputs() -> None:
    """:func:`icbtool.cli._common.discard_empty_outputs`, once more if Ctrl-C cuts it short."""
    from icbtool.cli._common import discard_empty_outputs

    for _ in range(2):
        try:
            discard_empty_outputs()
            return
        except KeyboardInterrupt:
            continue
