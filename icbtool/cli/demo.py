"""``icbtool demo``: the main job on the built-in default scene (the Cornell box).

1. the client's buffers (DL, albedo, normals, depth, position, mask) at the default camera;
2. the ICB loop along the scene's test path (:mod:`icbtool.pipeline`): raster, cache lookup or
   cloud render at the prefetch camera, warp, combine, inpaint, DL + GI, scored against the truth.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from icbtool._optional import require
from icbtool.cli._common import (
    UsageError,
    add_denoise_quality_argument,
    check_out_dir,
    float_in,
    int_at_least,
    load_scene,
    positive_int,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job on the default scene (Cornell box)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "scene",
        nargs="?",
        default="cornell_box",
        help="procedural scene name, scene description (.toml) or mesh file (default: cornell_box)",
    )
    p.set_defaults(func=run)
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--path", default="test", help="camera path the client follows")
    p.add_argument("--frames", type=positive_int, default=24, help="client frames along the path")
    p.add_argument("--size", type=positive_int, default=128, help="client image size (square)")
    p.add_argument("--spp", type=positive_int, default=16, help="samples per pixel of the cloud GI")
    p.add_argument(
        "--latency", type=float_in(0.0), default=0.1, help="interaction latency T_IL (s)"
    )
    p.add_argument(
        "--truth-every", type=int_at_least(0), default=6, help="score every N-th frame (0: never)"
    )
    p.add_argument(
        "--truth-spp", type=positive_int, default=128, help="samples per pixel of the truth"
    )
    p.add_argument("--no-prefetch", action="store_true", help="reference at the old camera")
    p.add_argument("--no-denoise", action="store_true", help="serve raw (noisy) GI maps")
    add_denoise_quality_argument(p)
    p.add_argument("--fresh", action="store_true", help="empty the cloud cache first")
    p.add_argument(
        "--generator",
        default=None,
        metavar="RUN",
        help="a trained GAN run (icbtool train): the client generates its GI with it and asks "
        "the cloud only when it cannot (the paper's rule)",
    )


def run(args: argparse.Namespace) -> int:
    import shutil

    from icbtool import imageio, pipeline, raster

    out = check_out_dir(args.out)  # before any work
    if args.generator is not None and not (Path(args.generator) / "generator.pt").is_file():
        raise UsageError(f"--generator {args.generator!r}: no generator.pt in that run directory")
    if not args.no_denoise:
        require("pyoidn", "denoising the demo's GI maps (--no-denoise skips it)")
    if args.fresh and (out / "cache").exists():
        shutil.rmtree(out / "cache")
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    print(f"scene: {scene}")
    cam = scene.default_camera
    if cam is None:
        raise ValueError(f"scene {args.scene!r} has no default camera")
    cam = cam.resized(2 * args.size, 2 * args.size)
    buf = raster.render(scene, cam)
    for name in buf.names:
        arr = getattr(buf, name)
        imageio.write_png(
            out / "buffers" / f"{name}.png",
            imageio.preview(arr, raster.PREVIEW_KIND[name], mask=buf.valid),
        )
    print(f"client buffers at the default camera -> {out / 'buffers'}")
    cfg = pipeline.LoopConfig(
        path=args.path,
        frames=args.frames,
        height=args.size,
        width=args.size,
        spp=args.spp,
        latency_s=args.latency,
        truth_every=args.truth_every,
        truth_spp=args.truth_spp,
        prefetch=not args.no_prefetch,
        denoise=not args.no_denoise,
        denoise_quality=args.denoise_quality,
        generator=args.generator,
    )
    report = pipeline.run_loop(scene, cfg, out_dir=out)
    s = report.summary()
    print(json.dumps(s, indent=2))
    print(
        f"done in {time.perf_counter() - t0:.1f} s; outputs in {out}/ "
        "(frames/*.png, loop.png, summary.json, frames.csv, buffers/*.png)"
    )
    return 0
