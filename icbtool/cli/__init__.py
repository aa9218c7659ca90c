"""The ``icbtool`` command line. Each subcommand is a module in this package that defines
``register(subparsers)``; it is discovered automatically, so adding a command touches one file.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys


def build_parser() -> argparse.ArgumentParser:
    import icbtool

    parser = argparse.ArgumentParser(
        prog="icbtool",
        description="Intelligent CloudBaking: hybrid cloud/client rendering research tool.",
    )
    parser.add_argument("--version", action="version", version=f"icbtool {icbtool.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``icbtool`` console script. Returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from icbtool._optional import MissingOptionalDependency
    from icbtool.cli._common import UsageError

    try:
        return int(args.func(args) or 0)
    except UsageError as e:  # a bad argument, found before any work: like argparse, exit 2
        print(f"icbtool {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, OSError, MissingOptionalDependency) as e:
        print(f"icbtool {args.command}: error: {e}", file=sys.stderr)  # user errors: one line
        return 1
