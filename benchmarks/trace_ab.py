"""Paired A/B timing of the path tracer in two checkouts (a refactor's "speed unchanged" check).

On a shared, loaded machine two benchmark runs minutes apart differ by 2x; this runs one long-lived
process per checkout (each imports its own ``icbtool`` and warms its numba cache) and alternates
renders between them, so both see the same load: each round is one render in A and one in B; the
result is the median of the per-round ratios B / A of the tracer's Mrays/s (whole render, wall) and
of its rays per second of process CPU time (less sensitive to other processes' load; single-
threaded by default), with the 1-minute load recorded every render.

    .venv/bin/python -m benchmarks.trace_ab --a /tmp/before --b . [--rounds 9] [--size 128]

Writes --out/ab_<scene or --name>.json (with the machine, the versions and each
checkout's commit; the oldest files have the load alone).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.common import add_out_argument, run_info

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"

CHILD = r"""
import json, os, sys, time
import icbtool as icb
from icbtool.trace import TraceConfig, render
name, size, spp, root = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
threads = int(sys.argv[5])
robust = {} if sys.argv[6] == "default" else {"robust": sys.argv[6] == "1"}
if name == "sponza":
    sc = icb.scene.load(os.path.join(root, "data", "scenes", "sponza.toml"))
else:
    sc = getattr(icb.scene, name)()
cam = sc.default_camera.resized(size, size)
cfg = TraceConfig(spp=spp, spp_per_pass=4, max_depth=8, seed=0, threads=threads, **robust)
render(sc, cam, TraceConfig(spp=1))
print("ready", flush=True)
for _ in sys.stdin:
    c0 = time.process_time()
    st = render(sc, cam, cfg).stats
    cpu = time.process_time() - c0
    print(json.dumps({"mrays": st.total_rays / st.time_s["total"] / 1e6,
                      "mrays_per_cpu_s": st.total_rays / cpu / 1e6,
                      "rays": st.total_rays, "load": os.getloadavg()[0]}), flush=True)
"""


def _start(
    root: Path, scene: str, size: int, spp: int, threads: int, robust: str
) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(root))
    env.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    p = subprocess.Popen(
        [sys.executable, "-c", CHILD, scene, str(size), str(spp), str(root), str(threads), robust],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=root,
        env=env,
    )
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"{root}: the tracer did not start ({line!r})")
    return p


def _one(p: subprocess.Popen) -> dict:
    p.stdin.write("go\n")
    p.stdin.flush()
    return json.loads(p.stdout.readline())


def add_checkout_args(ap: argparse.ArgumentParser) -> None:
    """--a, --b (the two checkouts), --scene and --size (what both render): the arguments of
    every two-checkout comparison (this script, trace_rmse_ab.py)."""
    ap.add_argument("--a", type=Path, required=True, help="checkout A (before)")
    ap.add_argument("--b", type=Path, default=REPO, help="checkout B (after)")
    ap.add_argument("--scene", default="cornell_box", help="a built-in scene name or 'sponza'")
    ap.add_argument("--size", type=int, default=128)


def _commit(path: Path) -> str | None:
    """The git commit a checkout is at (a dirty tree is marked), or None outside git."""

    def git(*argv: str) -> str:
        done = subprocess.run(["git", "-C", str(path), *argv], capture_output=True, text=True)
        done.check_returncode()
        return done.stdout.strip()

    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--", "icbtool")
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + (" (icbtool/ modified)" if dirty else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_checkout_args(ap)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--name", default=None, help="results file ab_<name>.json (default: scene)")
    ap.add_argument(
        "--robust",
        choices=("default", "0", "1"),
        default="default",
        help="Embree's robust mode in both (default: each checkout's TraceConfig default)",
    )
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    a = _start(args.a.resolve(), args.scene, args.size, args.spp, args.threads, args.robust)
    b = _start(args.b.resolve(), args.scene, args.size, args.spp, args.threads, args.robust)
    rows = []
    try:
        for r in range(args.rounds):
            pair = (_one(a), _one(b)) if r % 2 == 0 else tuple(reversed((_one(b), _one(a))))
            rows.append({"a": pair[0], "b": pair[1]})
            print(
                r,
                f"A {pair[0]['mrays']:.3f}  B {pair[1]['mrays']:.3f} Mrays/s wall;",
                f"A {pair[0]['mrays_per_cpu_s']:.3f}  B {pair[1]['mrays_per_cpu_s']:.3f} per CPU s",
                flush=True,
            )
    finally:
        for p in (a, b):
            p.stdin.close()
            p.wait(timeout=60)
    if any(x["a"]["rays"] != x["b"]["rays"] for x in rows):
        print("note: A and B traced different numbers of rays")
    ratio = [x["b"]["mrays"] / x["a"]["mrays"] for x in rows]
    cpu_ratio = [x["b"]["mrays_per_cpu_s"] / x["a"]["mrays_per_cpu_s"] for x in rows]
    res = {
        "a": str(args.a),
        "b": str(args.b),
        "args": {k: str(v) for k, v in vars(args).items()},
        "median_mrays_a": statistics.median(x["a"]["mrays"] for x in rows),
        "median_mrays_b": statistics.median(x["b"]["mrays"] for x in rows),
        "median_ratio_b_over_a": statistics.median(ratio),
        "ratio_quartiles": statistics.quantiles(ratio, n=4) if len(ratio) > 1 else ratio,
        "median_cpu_ratio_b_over_a": statistics.median(cpu_ratio),
        "cpu_ratio_quartiles": (
            statistics.quantiles(cpu_ratio, n=4) if len(cpu_ratio) > 1 else cpu_ratio
        ),
        "load_1min": [x["a"]["load"] for x in rows],
        "rounds": rows,
        "commits": {"a": _commit(args.a), "b": _commit(args.b)},
        "run_info": run_info(),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"ab_{args.name or args.scene}.json"
    path.write_text(json.dumps(res, indent=1))
    med, cmed = res["median_ratio_b_over_a"], res["median_cpu_ratio_b_over_a"]
    print(
        f"{args.scene} {args.size}^2 {args.spp} spp: median B/A = {med:.3f} wall, {cmed:.3f} CPU"
        f" (A {res['median_mrays_a']:.3f}, B {res['median_mrays_b']:.3f} Mrays/s); wrote {path}"
    )


if __name__ == "__main__":
    main()
