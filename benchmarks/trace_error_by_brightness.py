"""Where our error per sample differs from Mitsuba's: RMSE and FLIP by display brightness.

On the Cornell box our RMSE per sample is about half of Mitsuba's from 8 spp, but our FLIP per
sample only a little lower. This splits both images' errors (each renderer against its own
reference, as trace_time_error.py measures them) by the display brightness of the reference pixel:
pixel count, mean FLIP, RMS error and each bin's share of the summed squared error.

    .venv/bin/python -m benchmarks.trace_error_by_brightness [--spp 8] [--scenes cornell_box,sponza]

It reads the references trace_time_error.py cached (run that first, same size and reference spp).
Writes --out/error_by_brightness.json.
"""

from __future__ import annotations

import argparse

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument
from benchmarks.trace_time_error import (
    MAX_DEPTH,
    MITSUBA_VARIANT,
    bench_scene,
    cached_references,
    load_mitsuba,
    mitsuba_render,
    write_results,
)
from icbtool.imageio import to_display
from icbtool.trace import TraceConfig

#: bins of the reference's display brightness (mean of the 8-bit RGB / 255)
BINS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99, 1.01)


def by_bin(ref: np.ndarray, img: np.ndarray, disp: np.ndarray) -> list[dict]:
    import flip_evaluator

    a = to_display(ref).astype(np.float32) / 255
    b = to_display(img).astype(np.float32) / 255
    fmap = np.asarray(flip_evaluator.evaluate(a, b, "LDR")[0])
    se = ((img - ref) ** 2).mean(-1)
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = (disp >= lo) & (disp < hi)
        if not sel.any():
            continue
        rows.append(
            {
                "display_brightness": [lo, hi],
                "pixels": int(sel.sum()),
                "flip_mean": float(fmap[sel].mean()),
                "rms_error": float(np.sqrt(se[sel].mean())),
                "share_of_squared_error": float(se[sel].sum() / se.sum()),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument("--ref-spp", default="cornell_box:1024,sponza:512")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    load_mitsuba(MITSUBA_VARIANT)
    ref_spp = dict(kv.split(":") for kv in args.ref_spp.split(","))
    out = {"args": vars(args), "scenes": {}}
    for name in args.scenes.split(","):
        z = cached_references(name, args.size, ref_spp[name])
        scene = bench_scene(name)
        cam = scene.default_camera.resized(args.size, args.size)
        cfg = TraceConfig(spp=args.spp, seed=args.spp, max_depth=MAX_DEPTH, rr_depth=4)
        ours = icb.trace.render(scene, cam, cfg).full
        theirs, _ = mitsuba_render(scene, cam, args.spp, seed=args.spp)
        disp = to_display(z["ours_full"]).astype(np.float32).mean(-1) / 255
        rows_o = by_bin(z["ours_full"], ours, disp)
        rows_m = by_bin(z["mitsuba"], theirs, disp)
        out["scenes"][name] = {"ours": rows_o, "mitsuba": rows_m}
        print(name, f"{args.spp} spp")
        for ro, rm in zip(rows_o, rows_m, strict=True):
            lo, hi = ro["display_brightness"]
            print(
                f"  [{lo:.2f}, {hi:.2f}) {ro['pixels']:6d} px: FLIP {ro['flip_mean']:.4f} / "
                f"{rm['flip_mean']:.4f}, RMS {ro['rms_error']:.4f} / {rm['rms_error']:.4f}, "
                f"share of squared error {ro['share_of_squared_error']:.2f} / "
                f"{rm['share_of_squared_error']:.2f} (ours / Mitsuba)"
            )
    write_results(out, "error_by_brightness.json", args.out)


if __name__ == "__main__":
    main()
