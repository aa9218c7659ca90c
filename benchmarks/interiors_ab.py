"""Paired A/B of icbtool's whole ``trace`` on an interior in two checkouts (before/after a change).

Each round runs ``python -m icbtool trace SCENE`` once in checkout A (its folder first on
``sys.path``: A's ``icbtool``) and once in B, back to back in child processes (the same load
for both), and records per run the wall time, the peak RSS (the child's own VmHWM, as
:mod:`benchmarks.interiors`), the tracer's own phase times and the load average around it. The
images of A and B are compared: ``identical`` says whether every pixel is bit-for-bit equal (the
expected answer of a layout-only change). Both checkouts need their numba kernels compiled first
(``python -m icbtool.trace.warm`` in each), or the first round times the compilation.

    .venv/bin/python -m benchmarks.interiors_ab --a /tmp/before --b . --scene prepared.xml \\
        --spp 16 --rounds 3 --out benchmarks/results/interiors

Writes ``<out>/ab_<scene>.json`` with the medians of the per-round ratios B / A.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument, load_average, write_results
from benchmarks.interiors import icbtool_trace


def _commit(root: Path) -> str:
    """The checkout's HEAD, or "unknown" (an exported tree: give ``--a-commit``)."""
    cmd = ["git", "-C", str(root), "rev-parse", "HEAD"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else "unknown"


def main() -> None:
    from icbtool.imageio import read_exr

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--a", type=Path, required=True, help="checkout A (before)")
    ap.add_argument("--a-commit", default=None, help="A's commit when A is not a git checkout")
    ap.add_argument("--b", type=Path, default=Path("."), help="checkout B (after)")
    ap.add_argument("--scene", type=Path, required=True, help="a Mitsuba scene file")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    add_out_argument(ap, "interiors")
    args = ap.parse_args()
    for name in ("a", "b"):
        root = getattr(args, name).resolve()
        if not (root / "icbtool" / "__init__.py").is_file():
            raise SystemExit(f"FAIL: --{name} {root} is not an icbtool checkout")
        setattr(args, name, root)
    if not args.scene.is_file():
        raise SystemExit(f"FAIL: --scene {args.scene}: no such file")
    load_start = load_average()
    rounds = []
    with tempfile.TemporaryDirectory(prefix="interiors_ab_") as tmp:
        for r in range(args.rounds):
            pair = {}
            for name in ("a", "b"):
                pair[name] = icbtool_trace(
                    args.scene,
                    args.spp,
                    args.seed,
                    Path(tmp) / f"{name}{r}",
                    args.max_depth,
                    checkout=getattr(args, name),
                )
            img = [read_exr(Path(tmp) / f"{n}{r}" / "full.exr") for n in ("a", "b")]
            pair["identical"] = bool(np.array_equal(img[0], img[1]))
            rounds.append(pair)
            print(
                f"round {r}: A {pair['a']['wall_s']:.1f} s {pair['a']['peak_rss_mb']:.0f} MB | "
                f"B {pair['b']['wall_s']:.1f} s {pair['b']['peak_rss_mb']:.0f} MB | "
                f"identical {pair['identical']}",
                flush=True,
            )

    def med(key: str) -> float:
        return float(statistics.median(p["b"][key] / p["a"][key] for p in rounds))

    results = {
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "commits": {"a": args.a_commit or _commit(args.a), "b": _commit(args.b)},
        "rounds": rounds,
        "ratios_b_over_a": {"wall": med("wall_s"), "peak_rss": med("peak_rss_mb")},
        "all_identical": all(p["identical"] for p in rounds),
    }
    path = args.out / f"ab_{args.scene.stem.split('.')[0]}.json"
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(path, results, load_start)
    print(f"B / A: wall {results['ratios_b_over_a']['wall']:.2f}x, peak RSS "
          f"{results['ratios_b_over_a']['peak_rss']:.2f}x -> {path}")  # fmt: skip


if __name__ == "__main__":
    main()
