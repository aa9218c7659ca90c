"""``icbtool render SCENE --out DIR``: rasterize float32 buffers (DL, G-buffers) to EXR + PNG."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.cli._common import add_scene_argument, load_scene, run_info, write_json


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
    p.add_argument("--every", type=int, default=1, help="with path:NAME, keep every K-th camera")
    p.add_argument("--height", type=int, default=None, help="image height (default: the camera's)")
    p.add_argument("--width", type=int, default=None, help="image width (default: the camera's)")
    p.add_argument("--fov", type=float, default=None, help="vertical field of view in degrees")
    p.add_argument(
        "--buffers",
        default="dl,albedo,normal_world,normal_view,depth,position,mask",
        help="comma-separated buffers to render",
    )
    p.add_argument("--backend", default="auto", choices=["auto", "osmesa", "egl"])
    p.add_argument("--shadow-map-size", type=int, default=None)
    p.add_argument("--area-samples", type=int, default=None)
    p.add_argument("--no-png", action="store_true", help="write EXR only")
    p.set_defaults(func=run)


def _fallback_camera(scene: Any) -> Any:
    from icbtool.camera import Camera

    b = scene.bounds
    centre = b.mean(0)
    eye = centre + np.array([0.0, 0.3, 1.2]) * scene.diagonal
    return Camera.look_at(eye, centre, (0, 1, 0), fov_y_deg=45, height=256, width=256)


def _cameras(scene: Any, args: argparse.Namespace) -> tuple[list[Any], str]:
    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    spec = args.camera
    if spec == "default":
        cams = [scene.default_camera or _fallback_camera(scene)]
    elif spec.startswith("path:"):
        name = spec[5:]
        if name not in scene.paths:
            raise ValueError(
                f"scene '{scene.name}' has no camera path {name!r}; it has {sorted(scene.paths)}"
            )
        cams = scene.paths[name].cameras()[:: args.every]
    else:
        raise ValueError(f"--camera must be 'default' or 'path:NAME', got {spec!r}")
    out = []
    for c in cams:
        if args.fov is not None:
            c = c.with_fov(args.fov)
        if args.height is not None or args.width is not None:
            h = args.height or round(c.height * (args.width / c.width))
            w = args.width or round(c.width * (args.height / c.height))
            c = c.resized(int(h), int(w))
        out.append(c)
    return out, spec


def run(args: argparse.Namespace) -> int:
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
    scene = load_scene(args.scene)
    cams, spec = _cameras(scene, args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
