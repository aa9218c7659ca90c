"""Helpers shared by the CLI subcommands."""

from __future__ import annotations

import argparse
import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from icbtool.provenance import run_info, to_jsonable, write_json


def populate(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add a command's options now if :func:`add_command` deferred them (idempotent)."""
    options = parser.__dict__.pop("icb_options", None)
    if options is not None:
        options(parser)
    return parser


def add_command(
    sub: argparse._SubParsersAction,
    name: str,
    options: Callable[[argparse.ArgumentParser], None],
    **kwargs: Any,
) -> argparse.ArgumentParser:
    """A subcommand whose options ``options(parser)`` adds when the command is chosen."""
    p = sub.add_parser(name, **kwargs)
    p.icb_options = options  # type: ignore[attr-defined]
    return p


def commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser by its name (``"store check"``), options added."""
    out: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for p in action.choices.values():
                out[p.prog.removeprefix("icbtool").strip()] = populate(p)
                out.update(commands(p))
    return out


class UsageError(ValueError):
    """A bad command-line value found before any work: ``icbtool CMD: error: ...``, exit code 2."""


def int_at_least(lo: int) -> Callable[[str], int]:
    """An argparse ``type`` for an integer >= ``lo`` (a bad value is an argparse error, exit 2)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {v}")
        return v

    parse.__name__ = f"int>={lo}"
    return parse


def float_in(lo: float, hi: float = math.inf, lo_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type`` for a finite float in ``[lo, hi)`` (``(lo, hi)`` with ``lo_open``)."""
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g})"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be a number in {interval}, got {text!r}"
            ) from None
        if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v < hi):
            raise argparse.ArgumentTypeError(f"must be a number in {interval}, got {text}")
        return v

    parse.__name__ = f"float in {interval}"
    return parse


#: Image sizes, counts, samples: integers >= 1.
positive_int = int_at_least(1)
#: Durations, errors: finite floats > 0.
positive_float = float_in(0.0, lo_open=True)
#: Vertical field of view in degrees: (0, 180).
fov_deg = float_in(0.0, 180.0, lo_open=True)


#: Output directories that this process's command created (:func:`check_out_dir`): the
#: directory, the topmost folder created with it, and whether its content is worth nothing.
_CREATED: list[tuple[Path, Path, Callable[[Path], bool]]] = []


def holds_no_file(path: Path) -> bool:
    """True when the folder ``path`` holds no file (at most empty folders)."""
    return not any(p.is_file() for p in path.rglob("*"))


def store_holds_no_record(path: Path) -> bool:
    """True when the store folder ``path`` holds no record (or no store yet)."""
    if holds_no_file(path):
        return True
    from icbtool import store as st

    try:
        with st.open(path, st.StoreConfig(readonly=True)) as s:
            return len(s) == 0
    except Exception:  # unreadable: not for this clean-up to judge, keep it
        return False


def discard_empty_outputs() -> list[Path]:
    """Remove the output directories that :func:`check_out_dir` created for this command and
    that hold nothing worth keeping, with the empty parents it created: called by ``icbtool``
    after a failure or a Ctrl-C, so that a failed command leaves no empty ``--out`` folder or
    empty store behind. Returns the removed directories."""
    import shutil

    removed = []
    while _CREATED:
        out, top, holds_nothing = _CREATED.pop()
        try:
            if not out.is_dir() or not holds_nothing(out):
                continue
            shutil.rmtree(out)
            removed.append(out)
            parent = out.parent
            while parent != top.parent and parent.is_dir() and not any(parent.iterdir()):
                parent.rmdir()
                parent = parent.parent
        except OSError:  # best effort: the command's own error is what the user needs
            continue
    return removed


def check_out_dir(
    path: str | Path, option: str = "--out", holds_nothing: Callable[[Path], bool] = holds_no_file
) -> Path:
    """Make sure ``path`` is (or can be made) a writable directory, before any work is done.

    Creates the directory (and its parents) if missing, then creates and deletes a temporary file
    in it: permission bits alone say nothing when running as root, a read-only file system or a
    full disk. A directory created here is removed again when the command fails or is
    interrupted while ``holds_nothing(path)`` (:func:`discard_empty_outputs`).

    Args:
        path: the output directory.
        option: the option's name, for the message.
        holds_nothing: whether the output is worth nothing after a failure (default: it holds
            no file; :func:`store_holds_no_record` for a store).

    Returns:
        The directory as a Path.

    Raises:
        UsageError: ``path`` exists and is not a directory, lies under a file, cannot be created,
            or is not writable; the message names the option, the path and the OS's reason.
    """
    p = Path(path)
    try:
        if p.exists() and not p.is_dir():
            raise UsageError(f"{option} {str(path)!r}: exists and is not a directory")
        for parent in p.absolute().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise UsageError(
                        f"{option} {str(path)!r}: {str(parent)!r} is a file, not a directory"
                    )
                break
    except OSError as e:  # e.g. a parent folder that cannot be searched
        raise UsageError(f"{option} {str(path)!r}: cannot access ({e.strerror or e})") from None
    top = p.absolute()  # the topmost folder that mkdir creates
    while not top.parent.exists():
        top = top.parent
    created = not top.exists()
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(
            f"{option} {str(path)!r}: cannot create the directory ({e.strerror or e})"
        ) from None
    if created:
        _CREATED.append((p.absolute(), top, holds_nothing))
    try:
        with tempfile.TemporaryFile(dir=p, prefix=".icbtool-write-check-"):
            pass
    except OSError as e:
        raise UsageError(f"{option} {str(path)!r}: not writable ({e.strerror or e})") from None
    return p


def scene_spec(text: str) -> str:
    """An argparse ``type`` for a scene: a built-in (procedural) scene name or an existing file;
    anything else is an argparse error that suggests the closest built-in name and lists them."""
    import difflib

    from icbtool.scene import PROCEDURAL

    if text in PROCEDURAL or Path(text).exists():
        return text
    names = sorted(PROCEDURAL)
    close = difflib.get_close_matches(text, names, n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    raise argparse.ArgumentTypeError(
        f"{text!r} is neither a file nor a built-in scene; {hint}built-in scenes: "
        + ", ".join(names)
    )


scene_spec.__name__ = "scene"


def scene_help() -> str:
    """The help of SCENE, naming every built-in scene (from the one table of them)."""
    from icbtool.scene.procedural import PROCEDURAL

    return (
        f"a built-in scene ({', '.join(sorted(PROCEDURAL))}), a scene description (.toml), a "
        "Mitsuba 3 scene file (.xml) or a mesh file (.obj, .ply, .glb, .gltf)"
    )


def add_scene_argument(p: argparse.ArgumentParser, optional: bool = False) -> None:
    """The positional SCENE (``optional``: may be left out, default cornell_box)."""
    if optional:
        p.add_argument(
            "scene",
            nargs="?",
            default="cornell_box",
            type=scene_spec,
            help=scene_help() + " (default: cornell_box)",
        )
    else:
        p.add_argument("scene", type=scene_spec, help=scene_help())


def add_size_arguments(
    p: argparse.ArgumentParser, default: tuple[int, int] | None = None, what: str = "image"
) -> None:
    """``--height H --width W``: the one spelling of an image size on every command."""
    for side, i in (("height", 0), ("width", 1)):
        if default is None:
            text = f"{what} {side} (default: the camera's; alone, the other side keeps the aspect)"
        else:
            text = f"{what} {side} (default: {default[i]})"
        p.add_argument(
            f"--{side}",
            type=positive_int,
            default=None if default is None else default[i],
            metavar=side[0].upper(),
            help=text,
        )


def add_store_argument(p: argparse.ArgumentParser, help: str) -> None:
    """``--store DIR`` (required): the one spelling of a store on every command. The positional
    STORE of earlier versions still works, with a deprecation line (:func:`resolve_store`)."""
    p.add_argument("--store", default=None, metavar="DIR", help=help + " (required)")
    p.add_argument("store_positional", nargs="?", default=None, help=argparse.SUPPRESS)
    p.set_defaults(store_required=True)


def resolve_store(args: argparse.Namespace, command: str) -> None:
    """Put a positional STORE (deprecated) into ``args.store``, saying so on one line.

    Raises:
        UsageError: no store given, or both spellings.
    """
    old = getattr(args, "store_positional", None)
    if old is not None:
        if args.store is not None:
            raise UsageError(f"give the store once: --store {args.store!r} and {old!r}")
        import sys

        print(
            f"icbtool {command}: warning: a positional STORE is deprecated, use --store {old}",
            file=sys.stderr,
        )
        args.store = old
    if getattr(args, "store_required", False) and args.store is None:
        raise UsageError("--store DIR is required")


def check_training_args(args: argparse.Namespace) -> Path:
    """Before any training work: ``args.store`` is a directory, ``--resume`` names an existing
    run, and ``--out`` is writable (:func:`check_out_dir`). Returns the run directory."""
    if not Path(args.store).is_dir():
        raise FileNotFoundError(f"store {args.store!r} does not exist (or is not a directory)")
    out = Path(args.out)
    if args.resume and not out.is_dir():
        raise UsageError(f"--resume: --out {args.out!r} is not a run directory")
    return check_out_dir(out)


def add_out_argument(
    p: argparse.ArgumentParser, default: str | None = None, what: str = ""
) -> None:
    """``--out DIR``: checked (created, writable) before any work by :func:`check_out_dir`."""
    text = f"output directory{what} (created if missing; checked before any work)"
    if default is None:
        p.add_argument("--out", required=True, metavar="DIR", help=text)
    else:
        p.add_argument("--out", default=default, metavar="DIR", help=text)


def finite_float(text: str) -> float:
    """argparse type: a finite number (NaN and infinities are refused)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


finite_float.__name__ = "float"


def add_time_argument(p: argparse.ArgumentParser) -> None:
    """``--time T``: the scene time of an animated scene (keyframed lights and meshes)."""
    p.add_argument(
        "--time",
        type=finite_float,
        default=0.0,
        metavar="T",
        help="scene time in seconds for an animated scene (keyframes; see "
        "icbtool.scene.animation); a static scene is the same at every time (default: 0)",
    )


def add_up_axis_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--up-axis",
        choices=("auto", "y", "z", "x"),
        default=None,
        help="the mesh file's up axis (rotated to +y) (default: the file's or description's; "
        "'auto': y for glTF, guessed for OBJ/PLY, see icbtool.scene.load.guess_up_axis)",
    )


def add_default_light_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--default-light",
        action="store_true",
        help="light a scene that has no light icbtool can render with icbtool's default sun "
        "and gradient sky (icbtool.scene.with_default_light); without it such a scene is an "
        "error naming what is missing",
    )


def load_scene(
    spec: str,
    up_axis: str | None = None,
    default_light: bool = False,
    require_light: bool = False,
) -> Any:
    """:func:`icbtool.scene.load_scene`, imported when called: ``icbtool --help`` imports every
    command's module, and ``icbtool.scene`` takes about a second to import."""
    from icbtool.scene.select import load_scene

    return load_scene(spec, up_axis, default_light, require_light)


def select_cameras(scene: Any, spec: str, *args: Any, **kwargs: Any) -> list[tuple[str, Any]]:
    """:func:`icbtool.scene.select_cameras`, imported when called (see :func:`load_scene`)."""
    from icbtool.scene.select import select_cameras

    return select_cameras(scene, spec, *args, **kwargs)


__all__ = [
    "add_command",
    "commands",
    "populate",
    "scene_help",
    "UsageError",
    "add_out_argument",
    "add_scene_argument",
    "add_size_arguments",
    "add_store_argument",
    "resolve_store",
    "check_out_dir",
    "discard_empty_outputs",
    "holds_no_file",
    "store_holds_no_record",
    "float_in",
    "fov_deg",
    "int_at_least",
    "positive_float",
    "positive_int",
    "add_up_axis_argument",
    "add_default_light_argument",
    "load_scene",
    "run_info",
    "scene_spec",
    "select_cameras",
    "to_jsonable",
    "write_json",
]
