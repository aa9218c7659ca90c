"""``icbtool trace SCENE --out DIR``: path trace GI maps (EXR + PNG previews + summary JSON)."""

from __future__ import annotations

import argparse
import logging
from dataclasses import asdict
from pathlib import Path

from icbtool._optional import require
from icbtool.cli._common import (
    add_denoise_quality_argument,
    add_scene_argument,
    add_up_axis_argument,
    check_out_dir,
    int_at_least,
    load_scene,
    positive_float,
    positive_int,
    run_info,
    select_cameras,
    write_json,
)


def _max_depth(text: str) -> int:
    """argparse type of --max-depth: an integer >= 1, or -1 (unbounded)."""
    v = int_at_least(-1)(text)
    if v == 0:
        raise argparse.ArgumentTypeError("must be an integer >= 1 or -1 (unbounded), got 0")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "trace",
        help="path trace GI / direct / full maps of a scene",
        description="Path trace a scene (Embree) and write gi, direct, full, variance and spp "
        "as EXR with PNG previews, plus summary.json (stats, config, run info).",
    )
    add_scene_argument(p)
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument(
        "--camera",
        default="default",
        help="'default' (the scene's default camera) or path:NAME (a camera path)",
    )
    p.add_argument(
        "--every", type=positive_int, default=1, help="with path:NAME, trace every K-th camera"
    )
    p.add_argument("--spp", type=positive_int, default=64, help="samples per pixel (budget)")
    p.add_argument("--time-budget", type=positive_float, default=None, help="seconds per view")
    p.add_argument(
        "--target-error",
        type=positive_float,
        default=None,
        help="stop at this mean relative standard error of the GI",
    )
    p.add_argument(
        "--adaptive", action="store_true", help="adaptive sampling (needs --target-error)"
    )
    p.add_argument("--denoise", action="store_true", help="denoise gi with Open Image Denoise")
    add_denoise_quality_argument(p)
    p.add_argument(
        "--max-depth",
        type=_max_depth,
        default=None,
        help="max path depth (-1 = unbounded); default: the scene file's (a Mitsuba "
        "integrator's max_depth), else 8",
    )
    p.add_argument(
        "--sky-sampling",
        choices=("auto", "mis", "bsdf"),
        default="auto",
        help="sky light samples with MIS ('auto': only for a peaked sky)",
    )
    p.add_argument("--sampler", choices=("sobol", "independent"), default="sobol")
    p.add_argument(
        "--fast-embree",
        action="store_true",
        help="Embree without robust mode (~15 %% faster; a ray may slip through a shared edge)",
    )
    p.add_argument("--seed", type=int_at_least(0), default=0)
    p.add_argument("--threads", type=positive_int, default=2)
    p.add_argument(
        "--height", type=positive_int, default=None, help="image height (default: the camera's)"
    )
    p.add_argument(
        "--width", type=positive_int, default=None, help="image width (default: the camera's)"
    )
    add_up_axis_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_out_dir(args.out)  # before any work
    if args.denoise:
        require("pyoidn", "--denoise (Open Image Denoise)")
    import numpy as np
    from tqdm import tqdm

    from icbtool.imageio import preview, write_exr, write_png
    from icbtool.trace import TraceConfig, render

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    scene = load_scene(args.scene, args.up_axis, default_light=True)
    max_depth = args.max_depth
    if max_depth is None:
        max_depth = scene.max_depth if scene.max_depth is not None else 8
    cfg = TraceConfig(
        spp=args.spp,
        seed=args.seed,
        max_depth=max_depth,
        time_budget_s=args.time_budget,
        target_error=args.target_error,
        adaptive=args.adaptive,
        denoise=args.denoise,
        denoise_quality=args.denoise_quality,
        threads=args.threads,
        sky_sampling=args.sky_sampling,
        sampler=args.sampler,
        robust=not args.fast_embree,
    )
    cams = select_cameras(scene, args.camera, args.every, args.height, args.width)
    views = []
    for name, cam in tqdm(cams, desc="trace", disable=len(cams) < 2):
        res = render(scene, cam, cfg, progress=len(cams) == 1)
        d = out / name if len(cams) > 1 else out
        d.mkdir(parents=True, exist_ok=True)
        for key in ("gi", "direct", "full", "variance"):
            write_exr(d / f"{key}.exr", getattr(res, key))
        write_exr(d / "spp.exr", res.spp[..., None].astype(np.float32))
        exposure = None
        from icbtool.imageio import auto_exposure

        exposure = auto_exposure(res.full)
        for key in ("gi", "direct", "full"):
            write_png(d / f"{key}.png", preview(getattr(res, key), exposure=exposure))
        write_png(d / "variance.png", preview(np.sqrt(res.variance)))
        spp_img = (res.spp / max(res.spp.max(), 1))[..., None].astype(np.float32)
        write_png(d / "spp.png", preview(np.repeat(spp_img, 3, -1), kind="position"))
        views.append(
            {"name": name, "camera": cam.to_dict(), "stats": asdict(res.stats), "dir": str(d)}
        )
    write_json(
        out / "summary.json",
        {
            "scene": scene.name,
            "source": scene.source,
            "config": asdict(cfg),
            "views": views,
            "run_info": run_info(),
        },
    )
    print(f"wrote {len(views)} view(s) to {out}")
    return 0
