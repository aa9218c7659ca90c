"""What the benchmark scripts share: the repository's folders, the scenes, where results go and
how they are written (with the machine, the library versions and the load).

Every script is a module with a ``main()``, run from the repository root as
``python -m benchmarks.NAME``. It writes into ``--out`` (default ``out/bench/<topic>``, never the
committed ``benchmarks/results/`` unless that is what ``--out`` says), and it uses icbtool's
public API only (tests/test_layers.py checks both).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from icbtool.provenance import run_info, to_jsonable, write_json

__all__ = [
    "REPO",
    "RESULTS",
    "add_out_argument",
    "bench_scene",
    "default_out",
    "load_average",
    "run_info",
    "sponza",
    "to_jsonable",
    "write_json",
    "write_results",
]

REPO = Path(__file__).resolve().parents[1]
#: the committed results the docs are generated from (docs/benchmarks.md)
RESULTS = REPO / "benchmarks" / "results"


def default_out(topic: str) -> Path:
    """Where a benchmark of ``topic`` writes unless told otherwise: ``out/bench/<topic>``."""
    return Path("out") / "bench" / topic


def add_out_argument(ap: argparse.ArgumentParser, topic: str) -> None:
    """The one ``--out`` option of every benchmark script (default ``out/bench/<topic>``)."""
    ap.add_argument(
        "--out",
        type=Path,
        default=default_out(topic),
        help=f"folder for the results (default: %(default)s; the committed ones, which "
        f"docs/benchmarks.md is made from: benchmarks/results/{topic})",
    )


def load_average() -> tuple[float, float, float]:
    """The 1, 5 and 15-minute load averages now (recorded with every timing)."""
    return os.getloadavg()


def write_results(
    path: str | os.PathLike, data: dict[str, Any], load_start: tuple | None = None
) -> Path:
    """``data`` as JSON at ``path``, with the machine and versions (``run_info``) and the load
    averages at the start (when given) and now.

    Returns:
        The file written.
    """
    out = dict(data)
    if load_start is not None:
        out["load_average_start"] = list(load_start)
    out["load_average_end"] = list(load_average())
    out["run_info"] = run_info()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_json(path, out)


def sponza():
    """The Sponza atrium (data/scenes/sponza.toml; the mesh from ``$ICBTOOL_SPONZA``, default
    the repository's sibling ``shared/scenes/sponza``)."""
    import icbtool as icb

    os.environ.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    return icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")


def bench_scene(name: str):
    """A benchmark scene by name: the built-in Cornell box, or Sponza."""
    import icbtool as icb

    if name == "cornell_box":
        return icb.scene.cornell_box()
    if name == "sponza":
        return sponza()
    raise ValueError(f"benchmark scene {name!r}: expected 'cornell_box' or 'sponza'")
