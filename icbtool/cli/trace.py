"""``icbtool trace SCENE --out DIR``: path trace GI maps (EXR + PNG previews + summary JSON)."""

from __future__ import annotations

import argparse
import logging
from dataclasses import asdict, replace

from icbtool.cli._common import (
    add_command,
    add_default_light_argument,
    add_out_argument,
    add_scene_argument,
    add_size_arguments,
    add_time_argument,
    add_up_axis_argument,
    check_out_dir,
    int_at_least,
    load_scene,
    positive_int,
    run_info,
    select_cameras,
    write_json,
)
from icbtool.cli._options import Spelling, add_config
from icbtool.optional import require


def _max_depth(text: str) -> int:
    """argparse type of --max-depth: an integer >= 1, or -1 (unbounded)."""
    v = int_at_least(-1)(text)
    if v == 0:
        raise argparse.ArgumentTypeError("must be an integer >= 1 or -1 (unbounded), got 0")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "trace",
        help="path trace GI / direct / full maps of a scene",
        description="Path trace a scene (Embree) and write gi, direct, full, variance and spp "
        "as EXR with PNG previews, plus summary.json (stats, config, run info).",
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.trace import TraceConfig

    add_scene_argument(p)
    add_out_argument(p)
    p.add_argument(
        "--camera",
        default="default",
        help="'default' (the scene's default camera) or path:NAME (a camera path)",
    )
    p.add_argument(
        "--every", type=positive_int, default=1, help="with path:NAME, trace every K-th camera"
    )
    add_size_arguments(p)
    add_up_axis_argument(p)
    add_time_argument(p)
    add_default_light_argument(p)
    trace = add_config(
        p,
        TraceConfig,
        defaults={"max_depth": None},
        spell={
            "max_depth": Spelling(
                type=_max_depth,
                metavar="N",
                default_text="the scene file's (a Mitsuba integrator's max_depth), else 8",
            ),
            "spp_per_pass": Spelling(type=positive_int),
            "rr_depth": Spelling(type=int_at_least(0)),
            "adaptive_min_passes": Spelling(type=positive_int),
        },
    )
    p.set_defaults(func=run, trace_options=trace)


def run(args: argparse.Namespace) -> int:
    depth = getattr(args, "cfg:max_depth")  # None: the scene file's, known once it is loaded
    # a bad setting: one line, exit 2, before any work
    cfg = args.trace_options.build(args, max_depth=8 if depth is None else depth)
    out = check_out_dir(args.out)
    if cfg.denoise:
        require("pyoidn", "--denoise (Open Image Denoise)")
    import numpy as np
    from tqdm import tqdm

    from icbtool.imageio import preview, write_exr, write_png
    from icbtool.trace import render

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    scene = load_scene(
        args.scene, args.up_axis, default_light=args.default_light, require_light=True
    ).at(args.time)
    if depth is None and scene.max_depth is not None:
        cfg = replace(cfg, max_depth=scene.max_depth)
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
            "scene_time": scene.time,
            "config": asdict(cfg),
            "views": views,
            "run_info": run_info(),
        },
    )
    print(f"wrote {len(views)} view(s) to {out}")
    return 0
