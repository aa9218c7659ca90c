"""``icbtool lpm SCENE --out DIR``: build the lightweight progressive mesh of a scene, measure
every level (triangles, bytes, geometric and client-side error, time to first frame) and write
stats (JSON, CSV), a plot, a row of DL previews and optionally the wire chunks."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from icbtool.cli._common import (
    UsageError,
    add_scene_argument,
    add_up_axis_argument,
    check_out_dir,
    int_at_least,
    load_scene,
    positive_int,
)


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "lpm",
        help="build the lightweight progressive mesh (levels of detail) and measure each level",
        description="Build the LPM of a scene (quadric decimation, coarse to fine) and write "
        "per-level stats (triangles, bytes, geometric error, client depth/DL error, warping, "
        "time to first frame) as JSON and CSV, a plot, DL previews and optionally the chunks.",
    )
    add_scene_argument(p)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--ratios", type=_floats, default=None, help="triangle ratios per level, e.g. 0.05,0.25,1"
    )
    p.add_argument(
        "--texture-max",
        type=_ints,
        default=None,
        help="largest texture side per level (0: keep), e.g. 128,512,0",
    )
    p.add_argument("--texture-format", choices=("png", "jpeg"), default="png")
    p.add_argument("--budget", choices=("global", "per_group"), default="global")
    p.add_argument("--size", type=int_at_least(16), default=128, help="preview/eval image side")
    p.add_argument("--cameras", type=positive_int, default=3, help="client cameras to measure")
    p.add_argument(
        "--gi-spp",
        type=int_at_least(0),
        default=0,
        help="spp of the reference GI maps for the warp measurement (0: skip, the default)",
    )
    p.add_argument("--chunks", action="store_true", help="also write every chunk to OUT/chunks")
    add_up_axis_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_out_dir(args.out)
    from icbtool import lpm
    from icbtool.lpm.evaluate import EvalConfig, evaluate
    from icbtool.lpm.report import write_chunks, write_report

    kw: dict[str, Any] = {"texture_format": args.texture_format, "budget": args.budget}
    if args.ratios is not None:
        kw["ratios"] = args.ratios
        kw["texture_max"] = args.texture_max or tuple(0 for _ in args.ratios)
    elif args.texture_max is not None:
        raise UsageError("--texture-max needs --ratios (one size per level)")
    cfg = lpm.LPMConfig(**kw)
    scene = load_scene(args.scene, args.up_axis, default_light=True)
    t0 = time.perf_counter()
    built = lpm.build(scene, cfg, progress=sys.stderr.isatty())
    build_s = time.perf_counter() - t0
    ecfg = EvalConfig(n_cameras=args.cameras, height=args.size, width=args.size, gi_spp=args.gi_spp)
    ev = evaluate(built, ecfg, progress=sys.stderr.isatty())
    files = write_report(out, "lpm", built, ev, ecfg, {"build_total_s": build_s})
    if args.chunks:
        n = write_chunks(out / "chunks", built)
        print(f"wrote {n} chunk files to {out / 'chunks'}")
    for r in ev.rows:
        print(
            f"L{r['level']}: {r['triangles']:>7} tri  {r['bytes'] / 1e6:7.2f} MB  "
            f"rms {r['geometric']['rms']:.2e}  hausdorff {r['geometric']['hausdorff']:.2e}  "
            f"depth>1% {r['client']['depth_bad_fraction']:.3f}  "
            f"DL SSIM {r['client']['dl_ssim']:.3f}"
        )
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0
