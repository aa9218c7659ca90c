"""``icbtool render SCENE --out DIR``: rasterize float32 buffers (DL, G-buffers) to EXR + PNG."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from icbtool.cli._common import (
    add_command,
    add_default_light_argument,
    add_out_argument,
    add_scene_argument,
    add_size_arguments,
    add_time_argument,
    add_up_axis_argument,
    check_out_dir,
    fov_deg,
    int_at_least,
    load_scene,
    positive_int,
    run_info,
    select_cameras,
    write_json,
)
from icbtool.cli._options import Spelling, add_config


def register(subparsers: argparse._SubParsersAction) -> None:
    add_command(
        subparsers,
        "render",
        help="rasterize float32 buffers (dl, albedo, normals, depth, position, mask) with OpenGL",
        description="Rasterize buffers of a scene with OpenGL (OSMesa/EGL) and write each as a "
        "float32 EXR plus a PNG preview, with a summary.json (timings, config, run info).",
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.raster import RasterConfig

    add_scene_argument(p)
    add_out_argument(p)
    p.add_argument(
        "--camera",
        default="default",
        help="'default' (the scene's default camera) or 'path:NAME' (every camera of that path)",
    )
    p.add_argument(
        "--every", type=positive_int, default=1, help="with path:NAME, keep every K-th camera"
    )
    add_size_arguments(p)
    p.add_argument(
        "--fov",
        type=fov_deg,
        default=None,
        help="vertical field of view in degrees (default: the camera's)",
    )
    p.add_argument(
        "--buffers",
        default="dl,albedo,normal_world,normal_view,depth,position,mask",
        help="comma-separated buffers to render",
    )
    p.add_argument(
        "--png", action=argparse.BooleanOptionalAction, default=True,
        help="also write a PNG preview of every buffer (--no-png: EXR only)",
    )  # fmt: skip
    add_up_axis_argument(p)
    add_time_argument(p)
    add_default_light_argument(p)
    raster = add_config(
        p,
        RasterConfig,
        spell={
            "shadow_map_size": Spelling(type=int_at_least(16)),
            "area_shadow_map_size": Spelling(type=int_at_least(16)),
            "area_samples": Spelling(type=positive_int),
            "texture_size": Spelling(type=int_at_least(1)),
        },
    )
    p.set_defaults(func=run, raster_options=raster)


def run(args: argparse.Namespace) -> int:
    config = args.raster_options.build(args)  # a bad setting: one line, exit 2, before any work
    out = check_out_dir(args.out)
    from tqdm import tqdm

    from icbtool import raster
    from icbtool.imageio import preview, write_exr, write_png

    names = raster.check_buffers(args.buffers)
    scene = load_scene(
        args.scene, args.up_axis, default_light=args.default_light, require_light=True
    ).at(args.time)
    spec = args.camera
    cams = [
        c for _, c in select_cameras(scene, spec, args.every, args.height, args.width, args.fov)
    ]
    frames = []
    t0 = time.perf_counter()
    try:
        r = raster.Rasterizer(scene, config)
    except raster.GLBackendError as e:
        print(f"icbtool render: error: {e}", file=sys.stderr)
        return 1
    with r:
        for i, cam in enumerate(tqdm(cams, desc="render", unit="cam", disable=len(cams) < 2)):
            buf = r.render(cam, names)
            stem = f"{i:04d}_" if len(cams) > 1 else ""
            for n, img in buf.as_dict().items():
                write_exr(out / f"{stem}{n}.exr", img)
                if args.png:
                    png = preview(img, raster.PREVIEW_KIND[n], mask=buf.mask)
                    write_png(out / f"{stem}{n}.png", png)
            frames.append({"index": i, "camera": cam.to_dict(), "timings_ms": buf.timings})
        backend = r.backend
        setup_ms = r.setup_ms
    totals = [f["timings_ms"]["total"] for f in frames]
    write_json(
        out / "summary.json",
        {
            "scene": args.scene,
            "scene_repr": repr(scene),
            "scene_time": scene.time,
            "camera": spec,
            "buffers": [n for n in raster.BUFFER_NAMES if n in names or n == "mask"],
            "backend": backend,
            "config": config,
            "setup_ms": setup_ms,
            "median_frame_ms": float(np.median(totals)),
            "wall_s": time.perf_counter() - t0,
            "frames": frames,
            "run_info": run_info(),
        },
    )
    print(
        f"wrote {len(frames)} frame(s) x {len(names)} buffer(s) to {out} "
        f"({backend}, median {np.median(totals):.1f} ms/frame)"
    )
    return 0
