"""``icbtool lpm SCENE --out DIR``: build the lightweight progressive mesh of a scene, measure
every level (triangles, bytes, geometric and client-side error, time to first frame) and write
stats (JSON, CSV), a plot, a row of DL previews and optionally the wire chunks."""

from __future__ import annotations

import argparse
import sys
import time

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_default_light_argument,
    add_out_argument,
    add_scene_argument,
    add_up_axis_argument,
    check_out_dir,
    int_at_least,
    load_scene,
)
from icbtool.cli._options import Spelling, add_config


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "lpm",
        _options,
        help="build the lightweight progressive mesh (levels of detail) and measure each level",
        description="Build the LPM of a scene (quadric decimation, coarse to fine) and write "
        "per-level stats (triangles, bytes, geometric error, client depth/DL error, warping, "
        "time to first frame) as JSON and CSV, a plot, DL previews and optionally the chunks.",
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.lpm import LPMConfig
    from icbtool.lpm.evaluate import EvalConfig

    add_scene_argument(p)
    add_out_argument(p)
    p.add_argument("--chunks", action="store_true", help="also write every chunk to OUT/chunks")
    add_up_axis_argument(p)
    add_default_light_argument(p)
    lpm = add_config(p, LPMConfig)
    ev = add_config(
        p,
        EvalConfig,
        skip=("raster",),
        defaults={"gi_spp": 0},
        spell={
            "n_cameras": Spelling(option="--cameras"),
            "height": Spelling(type=int_at_least(16), metavar="H"),
            "width": Spelling(type=int_at_least(16), metavar="W"),
            "gi_spp": Spelling(
                type=int_at_least(0),
                help="spp of the reference GI maps for the warp measurement (0: skip it)",
            ),
        },
        title="the measurement of every level (EvalConfig)",
    )
    p.set_defaults(func=run, lpm_options=lpm, eval_options=ev)


def run(args: argparse.Namespace) -> int:
    from icbtool import lpm
    from icbtool.lpm.evaluate import evaluate
    from icbtool.lpm.report import write_chunks, write_report

    given = args.lpm_options.values(args)
    default = lpm.LPMConfig()
    ratios_given = given["ratios"] != default.ratios
    sizes_given = given["texture_max"] != default.texture_max
    if ratios_given and not sizes_given:  # new levels: full-size textures unless told
        given["texture_max"] = tuple(0 for _ in given["ratios"])
    elif sizes_given and not ratios_given:
        raise UsageError("--texture-max needs --ratios (one size per level)")
    cfg = args.lpm_options.call(lambda **kw: lpm.LPMConfig(**kw), args, **given)
    ecfg = args.eval_options.build(args)
    out = check_out_dir(args.out)  # before any work
    scene = load_scene(
        args.scene, args.up_axis, default_light=args.default_light, require_light=True
    )
    t0 = time.perf_counter()
    built = lpm.build(scene, cfg, progress=sys.stderr.isatty())
    build_s = time.perf_counter() - t0
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
