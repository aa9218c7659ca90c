"""ICB's Figure 8: generated GI, real (traced) GI and their difference on test frames, with SSIM,
MSE (display scale, RGB 0-255, as the paper) and FLIP.

The generator is a training run (``--run DIR``), by default the best configuration of
benchmarks/results/gan/figure7.json in ``--runs``. Frames are spread evenly over the store's test
path. Writes --out/figure8.png (one row per frame: generated | real |
|difference| x4) and figure8.json (per-frame and mean metrics, the run, its iteration).

    ICBTOOL_GAN_STORE=STORE .venv/bin/python -m benchmarks.gan_figure8
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument
from benchmarks.gan_figure7 import chosen_run

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"))
    ap.add_argument("--scene", default="sponza", help="scene name (or hash) in the store")
    ap.add_argument("--run", default=None, help="training run directory (default: Figure 7's best)")
    ap.add_argument("--runs", default=str(REPO / "out" / "gan_figure7"))
    ap.add_argument("--frames", type=int, default=6)
    add_out_argument(ap, "gan")
    args = ap.parse_args()
    if not args.store:
        raise SystemExit("give --store (or set ICBTOOL_GAN_STORE): a baked Sponza store")

    import icbtool.store as S
    from icbtool import metrics
    from icbtool.gan import Generator
    from icbtool.imageio import to_display, write_png
    from icbtool.optional import require
    from icbtool.provenance import run_info, write_json

    flip_evaluator = require("flip_evaluator", "the FLIP metric of Figure 8")
    out = Path(args.out)
    run, exposure = chosen_run(args.run, out, args.runs)
    evals = json.loads((run / "evals.json").read_text())
    gen = Generator.load(run)
    ro = S.StoreConfig(readonly=True, record_hits=False)
    rows, per_frame = [], []
    with S.open(args.store, ro) as store:
        ds = S.Dataset(store, args.scene, split="test", inputs=gen.inputs)
        ids = ds.record_ids
        if not ids:
            raise SystemExit(f"{args.store}: no test records for scene {args.scene!r}")
        pick = [ids[int(k)] for k in np.linspace(0, len(ids) - 1, min(args.frames, len(ids)))]
        for rid in pick:
            rec = store.get(rid)
            pred = gen.generate(rec)
            truth = rec.gi
            a, b = to_display(pred, exposure), to_display(truth, exposure)
            _, flip, _ = flip_evaluator.evaluate(
                b.astype(np.float32) / 255, a.astype(np.float32) / 255, "LDR"
            )
            diff = np.clip(4 * np.abs(a.astype(np.int16) - b.astype(np.int16)), 0, 255)
            rows.append(np.concatenate([a, b, diff.astype(np.uint8)], axis=1))
            per_frame.append(
                {
                    "record_id": rid,
                    "path_index": rec.meta.tags.get("index"),
                    "ssim": metrics.ssim(pred, truth, exposure),
                    "mse": metrics.mse(pred, truth, exposure),
                    "flip": float(flip),
                }
            )
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "figure8.png", np.concatenate(rows, axis=0))
    mean = {k: float(np.mean([f[k] for f in per_frame])) for k in ("ssim", "mse", "flip")}
    write_json(
        out / "figure8.json",
        {
            "run": str(run),
            "inputs": list(gen.inputs),
            "iteration": evals[-1]["iteration"] if evals else None,
            "display_exposure": exposure,
            "frames": per_frame,
            "mean": mean,
            "columns": "generated | real | |difference| x4 (display scale)",
            "run_info": run_info(),
        },
    )
    print(
        f"{run.name} ({', '.join(gen.inputs)}), {len(per_frame)} test frames: SSIM "
        f"{mean['ssim']:.4f}, MSE {mean['mse']:.1f}, FLIP {mean['flip']:.4f} -> {out}/figure8.*"
    )


if __name__ == "__main__":
    main()
