"""World-space GI commands (docs/radiance.md):

- ``icbtool world grid --store DIR --out runs/NAME [--resume] [RadianceConfig fields]``: train the
  hash-grid + MLP irradiance model.
- ``icbtool world probes --store DIR --out runs/NAME [ProbeConfig fields]``: fit the probe volume.

``icbtool generate`` and ``icbtool export`` take the run these write, as they take a GAN run.
"""

from __future__ import annotations

import argparse

from icbtool.cli._common import (
    add_command,
    add_out_argument,
    add_store_argument,
    check_training_args,
)
from icbtool.cli._options import add_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "world",
        help="fit GI in world space (hash grid or probe volume) on a store's baked paths",
        description="Fit a world-space irradiance model E(position, normal) on a store's train "
        "paths and score it on its evaluation paths (icbtool.radiance.train). The client "
        "multiplies E by its albedo; `icbtool generate` and `icbtool export` take the run.",
    )
    models = p.add_subparsers(dest="world_model", metavar="MODEL", required=True,
                              action=type(sub), help="grid or probes")  # fmt: skip
    add_command(models, "grid", _grid_options,
                help="train the multi-resolution hash grid + MLP (torch)")  # fmt: skip
    add_command(models, "probes", _probe_options,
                help="fit the irradiance probe volume (one least-squares solve)")  # fmt: skip


def _common(p: argparse.ArgumentParser, what: str) -> None:
    add_store_argument(p, "store directory (baked with `icbtool bake`)")
    p.add_argument("--scene", default=None, help="scene name or hash in the store (default: all)")
    add_out_argument(p, what=f": the run (e.g. runs/{what})")
    p.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="show a progress bar and the evaluations",
    )


def _grid_options(p: argparse.ArgumentParser) -> None:
    from icbtool.radiance import RadianceConfig

    _common(p, "sponza_grid")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.set_defaults(func=_fit, world_options=add_config(p, RadianceConfig))


def _probe_options(p: argparse.ArgumentParser) -> None:
    from icbtool.radiance import ProbeConfig

    _common(p, "sponza_probes")
    p.set_defaults(func=_fit, resume=False, world_options=add_config(p, ProbeConfig))


def _fit(args: argparse.Namespace) -> int:
    from icbtool import store as st
    from icbtool.radiance import train

    cfg = args.world_options.build(args)  # a bad setting: one line, exit 2
    out = check_training_args(args)  # before any work
    with st.open(args.store, st.StoreConfig(readonly=True, create=False)) as store:
        res = train(store, cfg, out, scene=args.scene, resume=args.resume,
                    progress=args.progress)  # fmt: skip
    scores = "; ".join(
        f"{path} SSIM {row['ssim']:.4f} MSE {row['mse']:.2f} ({row.get('views', '?')} views)"
        for path in cfg.eval_paths
        if (row := res.last(path)) is not None
    )
    how = f"{res.steps} steps" if res.steps else "one least-squares fit"
    print(f"fitted in {res.seconds:.1f} s ({how}); {scores}; run in {res.run_dir}")
    return 0
