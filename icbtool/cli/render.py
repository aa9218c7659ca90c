"""``icbtool render SCENE --out DIR``: rasterize float32 buffers (DL, G-buffers) to EXR + PNG."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

from icbtool.cli._common import (
    add_scene_argument,
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


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "render",
        help="rasterize float32 buffers (dl, albedo, normals, depth, position, mask) with OpenGL",
        description="Rasterize buffers of a scene with OpenGL (OSMesa/EGL) and write each as a "
        "float32 EXR plus a PNG preview, with a summary.json (timings, config, run info).",
    )
    add_scene_argument(p)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--camera",
        default="default",
        help="'default' (the scene's default camera) or 'path:NAME' (every camera of that path)",
    )
    p.add_argument(
        "--every", type=positive_int, default=1, help="with path:NAME, keep every K-th camera"
    )
    p.add_argument(
        "--height", type=positive_int, default=None, help="image height (default: the camera's)"
    )
    p.add_argument(
        "--width", type=positive_int, default=None, help="image width (default: the camera's)"
    )
    p.add_argument("--fov", type=fov_deg, default=None, help="vertical field of view in degrees")
    p.add_argument(
        "--buffers",
        default="dl,albedo,normal_world,normal_view,depth,position,mask",
        help="comma-separated buffers to render",
    )
    p.add_argument("--backend", default="auto", choices=["auto", "osmesa", "egl"])
    p.add_argument("--shadow-map-size", type=int_at_least(16), default=None)
    p.add_argument("--area-samples", type=positive_int, default=None)
    p.add_argument("--no-png", action="store_true", help="write EXR only")
    add_up_axis_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_out_dir(args.out)  # before any work
    from tqdm import tqdm

    from icbtool import raster
    from icbtool.imageio import preview, write_exr, write_png

    names = raster.check_buffers(args.buffers)
    kw: dict[str, Any] = {"backend": args.backend}
    if args.shadow_map_size is not None:
        kw["shadow_map_size"] = args.shadow_map_size
    if args.area_samples is not None:
        kw["area_samples"] = args.area_samples
    config = raster.RasterConfig(**kw)
    scene = load_scene(args.scene, args.up_axis, default_light=True)
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
                if not args.no_png:
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
