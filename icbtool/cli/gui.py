"""``icbtool gui [SCENE] [--store DIR] [--run DIR] [--screenshot FILE]``: the desktop app.

Opens the Qt + PyVista window (package ``icbtool_gui``, extra ``gui``): the scene with the store's
octree leaves and reference frusta (click one to see its GI), the client moving along the path with
its prefetch frustum, the frame's images with SSIM / FLIP heatmaps against the truth, and a GAN
trainer running in a background process. Without --store it opens the demo's store (out/demo/cache,
after `make demo`) with the demo's settings, else bakes a small one in out/gui/store. --screenshot
saves the window as a PNG and exits (under a private Xvfb when there is no display).
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from icbtool.cli._common import UsageError, add_scene_argument
from icbtool.optional import require


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gui",
        help="the desktop app: 3D view, image panels, trainer (extra gui)",
        description=__doc__,
    )
    add_scene_argument(p, optional=True)
    p.add_argument("--store", default=None, help="the cloud's store (default: out/demo/cache)")
    p.add_argument("--run", default=None, help="a GAN run directory (icbtool train --out)")
    p.add_argument("--screenshot", default=None, metavar="FILE", help="save the window and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.store is not None and not Path(args.store).is_dir():
        raise UsageError(f"--store {args.store!r} is not a directory")
    if args.run is not None and not Path(args.run).is_dir():
        raise UsageError(f"--run {args.run!r} is not a directory")
    if args.screenshot is not None and Path(args.screenshot).is_dir():
        raise UsageError(f"--screenshot {args.screenshot!r} is a directory, not a file")
    for module in ("PySide6", "pyvista", "pyvistaqt"):
        require(module, "the desktop app (icbtool gui)")
    # the app is the top-level package icbtool_gui/ of this distribution
    app = importlib.import_module("icbtool_gui.app")
    return app.main(args.scene, args.store, args.run, args.screenshot)
