"""Make the stored Cornell box GI reference used by tests/test_trace.py (statistical z-test).

Writes tests/data/trace_cornell_ref.npz: per-pixel mean and variance-of-the-mean of the traced GI
(and direct), plus the config used (as JSON), at 32x32 with many samples.

    .venv/bin/python -m benchmarks.trace_make_reference [--spp 4096]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import run_info
from icbtool.trace import TraceConfig

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "tests" / "data" / "trace_cornell_ref.npz"
SIZE = 32
#: the test renders with the same config but another seed and fewer spp
REF_CONFIG = dict(max_depth=6, rr_depth=4, seed=12345, spp_per_pass=64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=4096)
    args = ap.parse_args()
    scene = icb.scene.cornell_box()
    cam = scene.default_camera.resized(SIZE, SIZE)
    cfg = TraceConfig(spp=args.spp, **REF_CONFIG)
    res = icb.trace.render(scene, cam, cfg, progress=True)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        OUT,
        gi_mean=res.gi,
        gi_var=res.variance,
        direct_mean=res.direct,
        spp=res.spp,
        config=json.dumps(asdict(cfg)),
        height=SIZE,
        width=SIZE,
        run_info=json.dumps(run_info()),
    )
    print(f"wrote {OUT} ({res.stats.time_s['total']:.1f} s, {res.stats.samples} samples)")


if __name__ == "__main__":
    main()
