"""How long the path tracer's first use takes: numba compiling its kernels, then loading them.

The tracer's kernels are compiled by numba on first use and cached on disk (``cache=True``); a
new machine, a fresh checkout or a change to ``icbtool/trace/kernels.py`` pays the compilation
once, and later processes load the cached machine code. This script measures both from clean
processes, so that docs/benchmarks.md can say what a new user waits for:

- ``compile_s``: the first render (Cornell box, 16 x 16, 1 spp) in a new process whose numba cache
  (``NUMBA_CACHE_DIR``) is an empty folder: compiling every kernel a render needs.
- ``cache_load_s``: the same render in a second new process on the cache the first one wrote.
- ``warm_render_s``: the same render again in that process (the render itself).
- ``import_s``: ``import icbtool`` in each process (numba and the kernels are imported lazily).

    .venv/bin/python -m benchmarks.trace_compile [--trials 1]

Writes --out/compile.json (with the 1-minute load at start and end). A trial
takes about a minute and a half on the 2-core VM of this project.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"

#: run in a clean process: times the import, the first render and a second one (JSON on stdout)
_PROBE = """
import json, time
t0 = time.perf_counter()
import icbtool as icb
from icbtool.trace import TraceConfig
t1 = time.perf_counter()
scene = icb.scene.cornell_box()
cam = scene.default_camera.resized(16, 16)
t2 = time.perf_counter()
icb.trace.render(scene, cam, TraceConfig(spp=1))
t3 = time.perf_counter()
icb.trace.render(scene, cam, TraceConfig(spp=1))
t4 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_render_s": t3 - t2, "second_render_s": t4 - t3}))
"""


def probe(cache_dir: Path) -> dict:
    """One clean process with numba's cache in ``cache_dir``: its :data:`_PROBE` times."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "PYTHONPATH": str(REPO)}
    r = subprocess.run(
        [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=900
    )
    if r.returncode != 0:
        raise RuntimeError(f"the probe process failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    from icbtool.provenance import run_info, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1, help="fresh caches to compile into")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    load_start = os.getloadavg()
    trials = []
    t_run = time.perf_counter()
    for k in range(args.trials):
        with tempfile.TemporaryDirectory(prefix="icbtool-numba-cache-") as d:
            first = probe(Path(d))
            second = probe(Path(d))
        trials.append(
            {
                "compile_s": first["first_render_s"],
                "cache_load_s": second["first_render_s"],
                "warm_render_s": second["second_render_s"],
                "import_s": [first["import_s"], second["import_s"]],
            }
        )
        print(
            f"trial {k + 1}/{args.trials}: first use (compile) {first['first_render_s']:.1f} s, "
            f"cache load {second['first_render_s']:.2f} s, render "
            f"{second['second_render_s'] * 1000:.1f} ms",
            flush=True,
        )
    out = {
        "args": vars(args),
        "what": "a 16x16 1-spp Cornell box render in a new process: with an empty numba cache "
        "(compile_s), then in a second process on the cache the first wrote (cache_load_s)",
        "load_average_start": list(load_start),
        "load_average_end": list(os.getloadavg()),
        "wall_s": time.perf_counter() - t_run,
        "trials": trials,
        "run_info": run_info(),
    }
    path = write_json(OUT / "compile.json", out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
