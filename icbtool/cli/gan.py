"""GAN pre-renderer commands (docs/gan.md):

- ``icbtool train --store DIR --scene S --inputs I --preset cpu --out runs/NAME [--resume]``
- ``icbtool generate RUN SCENE --camera default|path:NAME --out DIR [--height H --width W]``
- ``icbtool export RUN --onnx FILE [--height H --width W]``

``generate`` and ``export`` also take a world-space run (``icbtool world``, docs/radiance.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_out_argument,
    add_scene_argument,
    add_size_arguments,
    add_store_argument,
    check_out_dir,
    check_training_args,
    float_in,
    load_scene,
    positive_int,
    run_info,
    select_cameras,
    write_json,
)
from icbtool.cli._options import Spelling, add_config

#: A GAN generator's image sides are multiples of this (icbtool.gan.models.MULTIPLE, which
#: imports torch; a test checks they agree): checked before any work.
GAN_SIZE_MULTIPLE = 32


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "train",
        _train_options,
        help="train the GAN pre-renderer on a store's baked paths",
        description="Train the GAN pre-renderer (icbtool.gan.train) on a store's baked train "
        "path, evaluating on its test path. Every TrainConfig field is an option; unset ones "
        "take the preset's value.",
    )
    add_command(
        sub,
        "generate",
        _generate_options,
        help="generate GI maps with a trained generator or world model",
    )
    add_command(
        sub, "export", _export_options, help="export a trained generator or world model to ONNX"
    )


def _train_options(p: argparse.ArgumentParser) -> None:
    import typing

    from icbtool.gan.training import TrainConfig

    presets = typing.get_args(typing.get_type_hints(TrainConfig.preset)["name"])
    add_store_argument(p, "store directory (baked with `icbtool bake`)")
    p.add_argument("--scene", default=None, help="scene name or hash in the store (default: all)")
    p.add_argument("--preset", choices=presets, default=presets[0], help="the field defaults")
    add_out_argument(p, what=": the run (e.g. runs/sponza_I)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="show a progress bar with the losses",
    )
    by_preset = {name: TrainConfig.preset(name) for name in presets}
    spell = {}
    for f in dataclasses.fields(TrainConfig):
        values = {name: getattr(cfg, f.name) for name, cfg in by_preset.items()}
        shown = {
            k: ",".join(map(str, v)) if isinstance(v, tuple) else str(v) for k, v in values.items()
        }
        if len(set(shown.values())) == 1:
            text = next(iter(shown.values()))
        else:
            text = "the preset's: " + ", ".join(f"{k} {v}" for k, v in shown.items())
        spell[f.name] = Spelling(default_text=text)
    train = add_config(p, TrainConfig, unset=True, spell=spell)
    p.set_defaults(func=_train, train_options=train)


def _generate_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a run of `icbtool train` or `icbtool world` (or its .pt file)")
    add_scene_argument(p)
    p.add_argument(
        "--camera", default="default", help="'default' (the scene's camera) or 'path:NAME'"
    )
    p.add_argument(
        "--every", type=positive_int, default=1, help="with path:NAME, every K-th camera"
    )
    add_size_arguments(p)
    add_out_argument(p)
    p.add_argument(
        "--exposure",
        type=float_in(0.0, lo_open=True),
        default=1.0,
        help="exposure of the PNG previews",
    )
    p.set_defaults(func=_generate)


def _export_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a run of `icbtool train` or `icbtool world` (or its .pt file)")
    p.add_argument(
        "--onnx", required=True, metavar="FILE", help="output .onnx file (+ .onnx.json sidecar)"
    )
    add_size_arguments(p, default=(128, 128), what="input (a GAN; a world model is per point)")
    p.set_defaults(func=_export)


def _train(args: argparse.Namespace) -> int:
    import sys

    from icbtool import store as st
    from icbtool.gan.training import TrainConfig, TrainingDivergedError, train

    factory = lambda **kw: TrainConfig.preset(args.preset, **kw)  # noqa: E731
    cfg = args.train_options.call(factory, args)  # a bad setting: one line, exit 2
    out = check_training_args(args)  # before any work
    with st.open(args.store, st.StoreConfig(readonly=True)) as store:
        try:
            res = train(store, cfg, out, scene=args.scene, resume=args.resume,
                        progress=args.progress)  # fmt: skip
        except TrainingDivergedError as e:
            print(f"icbtool train: error: {e}", file=sys.stderr)
            return 1
    last = res.evals[-1] if res.evals else {}
    print(
        f"trained to iteration {res.step} in {res.seconds:.1f} s; last test SSIM "
        f"{last.get('ssim', float('nan')):.4f} MSE {last.get('mse', float('nan')):.2f}; "
        f"perceptual {res.perceptual}; run in {res.run_dir}"
    )
    return 0


def _generate(args: argparse.Namespace) -> int:
    import numpy as np

    from icbtool import raster
    from icbtool.imageio import to_display, write_exr, write_png
    from icbtool.pipeline import load_client_model

    run = Path(args.run)
    if not run.exists():
        raise UsageError(f"RUN {args.run!r}: no such run directory")
    if not (run / "radiance.pt").is_file():  # a GAN run: the U-Net wants multiples of 32
        for side in ("height", "width"):
            v = getattr(args, side)
            if v is not None and v % GAN_SIZE_MULTIPLE:
                m = GAN_SIZE_MULTIPLE
                raise UsageError(
                    f"--{side} {v}: a GAN generator's sides are multiples of {m} "
                    f"(e.g. {max(m, round(v / m) * m)})"
                )
    out = check_out_dir(args.out)  # before any work
    gen = load_client_model(args.run)  # a GAN run or a world-space one (icbtool world)
    scene = load_scene(args.scene)
    cams = select_cameras(scene, args.camera, args.every, args.height, args.width)
    names = tuple(n for n in gen.inputs if n != "mask")
    frames = []
    with raster.Rasterizer(scene, raster.RasterConfig()) as r:
        for name, cam in cams:
            buf = r.render(cam, names)
            t0 = time.perf_counter()
            gi = gen.generate(buf)
            ms = 1000 * (time.perf_counter() - t0)
            write_exr(out / f"{name}_gi.exr", gi)
            write_png(out / f"{name}_gi.png", to_display(gi, args.exposure))
            frames.append({"name": name, "camera": cam.to_dict(), "generate_ms": ms})
    write_json(
        out / "summary.json",
        {
            "run": str(args.run),
            "scene": args.scene,
            "camera": args.camera,
            "inputs": list(gen.inputs),
            "median_generate_ms": float(np.median([f["generate_ms"] for f in frames])),
            "frames": frames,
            "run_info": run_info(),
        },
    )
    print(f"generated {len(frames)} GI maps into {out}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from icbtool.pipeline import load_client_model

    model = load_client_model(args.run)
    if hasattr(model, "irradiance"):  # world space: per point, no image size
        path = model.export_onnx(args.onnx)
    else:
        path = model.export_onnx(args.onnx, args.height, args.width)
    print(f"wrote {path} and {path}.json")
    return 0
