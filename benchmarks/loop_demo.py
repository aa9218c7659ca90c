"""The ICB loop's numbers as `make demo` makes them, kept as a results file.

Runs ``icbtool demo --fresh`` (Cornell box, 24 client frames at 128x128 along the test path,
T_IL = 100 ms, cloud GI at 16 spp denoised: the CLI defaults) into a temporary folder with an empty
cloud cache, and copies its small outputs (``summary.json``, ``config.json``, ``frames.csv``) to
benchmarks/results/loop/, with the wall time of the whole command and the machine in
``loop_demo.json``. docs/benchmarks.md's loop numbers are generated from these files
(benchmarks/page.py).

    .venv/bin/python -m benchmarks.loop_demo
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.cli import main as icbtool_main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cornell_box")
    add_out_argument(ap, "loop")
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="icb_loop_demo_") as tmp:
        load_before = os.getloadavg()
        t0 = time.perf_counter()
        rc = icbtool_main(["demo", args.scene, "--fresh", "--out", tmp])
        wall_s = time.perf_counter() - t0
        if rc != 0:
            raise SystemExit(f"loop_demo.py: `icbtool demo` failed with exit code {rc}")
        for name in ("summary.json", "config.json", "frames.csv"):
            shutil.copyfile(Path(tmp) / name, out / name)
    write_json(
        out / "loop_demo.json",
        {
            "command": f"icbtool demo {args.scene} --fresh --out TMP (CLI defaults otherwise)",
            "wall_s": wall_s,
            "what": "wall time of the whole demo command after the install, empty cloud cache, "
            "numba kernels already compiled (cached on disk)",
            "load_average_1_5_15min_before": load_before,
            "load_average_1_5_15min_after": os.getloadavg(),
            "run_info": run_info(),
        },
    )
    print(f"demo took {wall_s:.1f} s; wrote {out}/{{summary,config,loop_demo}}.json, frames.csv")


if __name__ == "__main__":
    main()
