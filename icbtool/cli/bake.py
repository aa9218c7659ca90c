"""``icbtool bake SCENE --path NAME --store DIR``: bake a camera path into a store."""

from __future__ import annotations

import argparse
import contextlib

from icbtool._optional import require
from icbtool.cli._common import (
    add_denoise_quality_argument,
    add_scene_argument,
    check_out_dir,
    float_in,
    int_at_least,
    load_scene,
    positive_int,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bake", help="render the CRT-buffers of a camera path into a store")
    add_scene_argument(p)
    p.add_argument("--path", required=True, help="camera path name in the scene (e.g. train)")
    p.add_argument("--store", required=True, help="store directory (created if missing)")
    p.add_argument("--spp", type=positive_int, default=16, help="GI samples per pixel")
    p.add_argument(
        "--seed", type=int_at_least(0), default=0, help="base seed (view k uses seed + k)"
    )
    p.add_argument(
        "--gbuffer",
        choices=("raster", "trace"),
        default="raster",
        help="DL and G-buffers from the rasterizer or a primary ray cast",
    )
    p.add_argument("--cloud-camera", choices=("same", "wider", "prefetch"), default="same")
    p.add_argument(
        "--fov-multiplier", type=float_in(1.0), default=1.5, help="--cloud-camera wider: FOV factor"
    )
    p.add_argument(
        "--pullback", type=float_in(0.0), default=0.0, help="--cloud-camera wider: pull-back"
    )
    p.add_argument(
        "--size",
        type=positive_int,
        nargs=2,
        default=None,
        metavar=("H", "W"),
        help="render size (default: the path's)",
    )
    p.add_argument("--stride", type=positive_int, default=1, help="bake every n-th camera")
    p.add_argument("--limit", type=positive_int, default=None, help="at most this many cameras")
    p.add_argument("--denoise", action="store_true", help="denoise GI with OIDN")
    add_denoise_quality_argument(p)
    p.add_argument(
        "--workers",
        type=int_at_least(0),
        default=0,
        help="render workers: 0 renders in this process; N starts a local Dask cluster of N "
        "worker processes on 127.0.0.1 (same records; needs the 'cloud' extra)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="render on an existing Dask cluster (e.g. tcp://127.0.0.1:8786) instead",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    check_out_dir(args.store, "--store")  # before any work
    if args.denoise:
        require("pyoidn", "--denoise (Open Image Denoise)")
    from icbtool import bake as B
    from icbtool import store as st

    if args.workers or args.scheduler:
        require("distributed", "render workers on Dask (--workers N / --scheduler)")

    scene = load_scene(args.scene)
    cfg = B.BakeConfig(
        spp=args.spp,
        seed=args.seed,
        gbuffer=args.gbuffer,
        cloud_camera=args.cloud_camera,
        fov_multiplier=args.fov_multiplier,
        pullback=args.pullback,
        resolution=None if args.size is None else tuple(args.size),
        stride=args.stride,
        limit=args.limit,
        denoise=args.denoise,
        denoise_quality=args.denoise_quality,
    )
    with contextlib.ExitStack() as stack:
        pool = None
        if args.workers or args.scheduler:
            from icbtool.system.workers import open_pool

            pool = stack.enter_context(open_pool(scene, args.workers, args.scheduler))
            print(f"render workers: {pool.capacity} at {pool.address}", flush=True)
        store = stack.enter_context(st.open(args.store))
        rep = B.bake(scene, args.path, store, cfg, pool=pool)
        n = len(store)
    print(
        f"baked {len(rep.rendered)} views ({len(rep.skipped)} already stored) in "
        f"{rep.seconds:.1f} s ({rep.seconds_per_view:.2f} s/view); store holds {n} records"
    )
    return 0
