"""``icbtool bake SCENE --path NAME --store DIR``: bake a camera path into a store."""

from __future__ import annotations

import argparse
import contextlib

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_scene_argument,
    add_size_arguments,
    check_out_dir,
    int_at_least,
    load_scene,
    select_cameras,
    store_holds_no_record,
)
from icbtool.cli._options import add_config
from icbtool.optional import require


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "bake",
        help="render the CRT-buffers of a camera path into a store",
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.bake import BakeConfig

    add_scene_argument(p)
    p.add_argument("--path", required=True, help="camera path name in the scene (e.g. train)")
    p.add_argument(
        "--store", required=True, metavar="DIR", help="store directory (created if missing)"
    )
    add_size_arguments(p, what="render")
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
        help="render on an existing Dask cluster (tls://HOST:8786 with the --dask-tls-* or "
        "--dask-config credentials; tcp:// only with --dask-insecure; docs/network.md) instead",
    )
    bake = add_config(p, BakeConfig, skip=("resolution", "prefetch_config", "progress", "tags"))
    from icbtool.system.dask_cluster import JoinSecurity

    join = add_config(p, JoinSecurity, prefix="dask-", title="joining a Dask cluster")
    p.set_defaults(func=_run, bake_options=bake, join_options=join)


def _run(args: argparse.Namespace) -> int:
    size = None if args.height is None or args.width is None else (args.height, args.width)
    cfg = args.bake_options.build(args, resolution=size)  # a bad setting: exit 2, no work
    check_out_dir(args.store, "--store", holds_nothing=store_holds_no_record)
    if cfg.denoise:
        require("pyoidn", "--denoise (Open Image Denoise)")
    from icbtool import bake as B
    from icbtool import store as st

    if args.workers or args.scheduler:
        require("distributed", "render workers on Dask (--workers N / --scheduler)")
    join = None
    if args.scheduler:
        from icbtool.system.dask_cluster import check_join

        try:
            join = args.join_options.build(args)
            check_join(args.scheduler, join)
        except ValueError as e:
            raise UsageError(str(e)) from None

    scene = load_scene(args.scene)
    if (args.height is None) != (args.width is None):  # one side: the other keeps the aspect
        from dataclasses import replace

        (_, cam), *_ = select_cameras(scene, f"path:{args.path}", 1, args.height, args.width)
        cfg = replace(cfg, resolution=(cam.height, cam.width))
    with contextlib.ExitStack() as stack:
        pool = None
        if args.workers or args.scheduler:
            from icbtool.system.workers import open_pool

            pool = stack.enter_context(
                open_pool(scene, args.workers, args.scheduler, security=join)
            )
            print(f"render workers: {pool.capacity} at {pool.address}", flush=True)
        store = stack.enter_context(st.open(args.store))
        rep = B.bake(scene, args.path, store, cfg, pool=pool)
        n = len(store)
    print(
        f"baked {len(rep.rendered)} views ({len(rep.skipped)} already stored) in "
        f"{rep.seconds:.1f} s ({rep.seconds_per_view:.2f} s/view); store holds {n} records"
    )
    return 0
