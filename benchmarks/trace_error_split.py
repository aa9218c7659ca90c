"""Which half of our image carries its error: the GI's noise or the direct light's.

Our tracer splits every render into ``direct`` (emission seen and shadow-tested light at the first
hit) and ``gi`` (the rest), and so does the cached high-spp reference. Swapping one half of a
render for the reference's leaves only the other half's noise: RMSE and FLIP of the full image
with the GI's noise alone and with the direct light's noise alone, next to the whole render's,
mean over seeds. A sampling change aimed at one half can only move the metric that half carries.

    .venv/bin/python -m benchmarks.trace_error_split [--scenes cornell_box,sponza] [--spps 4,16]

It reads the references trace_time_error.py cached (run that first, same size and reference spp).
Writes --out/error_split.json.
"""

from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

import icbtool as icb
from benchmarks.common import add_out_argument
from benchmarks.trace_time_error import (
    MAX_DEPTH,
    bench_scene,
    cached_references,
    errors,
    write_results,
)
from icbtool.trace import TraceConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spps", default="4,16")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument("--ref-spp", default="cornell_box:1024,sponza:512")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    ref_spp = dict(kv.split(":") for kv in args.ref_spp.split(","))
    out = {"args": vars(args), "scenes": {}}
    for name in args.scenes.split(","):
        z = cached_references(name, args.size, ref_spp[name])
        ref_full, ref_direct = z["ours_full"], z["ours_direct"]
        ref_gi = ref_full - ref_direct
        scene = bench_scene(name)
        cam = scene.default_camera.resized(args.size, args.size)
        rows = []
        for spp in [int(s) for s in args.spps.split(",")]:
            got = {"whole render": [], "GI noise only": [], "direct noise only": []}
            for seed in tqdm(range(args.seeds), desc=f"{name} {spp} spp", leave=False):
                cfg = TraceConfig(spp=spp, seed=500 + seed, max_depth=MAX_DEPTH, rr_depth=4)
                r = icb.trace.render(scene, cam, cfg)
                got["whole render"].append(errors(ref_full, r.full))
                got["GI noise only"].append(errors(ref_full, ref_direct + r.gi))
                got["direct noise only"].append(errors(ref_full, r.direct + ref_gi))
            row = {"spp": spp}
            for part, errs in got.items():
                row[part] = {m: float(np.mean([e[m] for e in errs])) for m in ("rmse", "flip")}
            rows.append(row)
            print(
                f"{name} {spp} spp: "
                + "; ".join(
                    f"{part} RMSE {row[part]['rmse']:.4f} FLIP {row[part]['flip']:.4f}"
                    for part in got
                ),
                flush=True,
            )
        out["scenes"][name] = rows
    write_results(out, "error_split.json", args.out)


if __name__ == "__main__":
    main()
