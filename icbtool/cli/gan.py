"""GAN pre-renderer commands (docs/design.md section 5):

- ``icbtool train STORE --scene S --inputs I --preset cpu --out runs/NAME [--resume]``
- ``icbtool generate RUN SCENE --camera default|path:NAME --out DIR``
- ``icbtool export RUN --onnx FILE``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from icbtool.cli._common import add_scene_argument, load_scene, run_info, select_cameras, write_json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the GAN pre-renderer on a store's baked paths")
    p.add_argument("store", help="store directory (baked with `icbtool bake`)")
    p.add_argument("--scene", default=None, help="scene name or hash in the store (default: all)")
    p.add_argument("--inputs", default="I", help="configuration A..J or comma-separated buffers")
    p.add_argument("--preset", choices=("cpu", "paper"), default="cpu")
    p.add_argument("--out", required=True, help="run directory (e.g. runs/sponza_I)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--iterations", type=int, default=None, help="override the preset's")
    p.add_argument("--vgg19-weights", default=None, help="local torchvision VGG19 .pth file")
    p.add_argument("--train-path", default=None, help="camera-path tag of the train split")
    p.add_argument("--test-path", default=None, help="camera-path tag of the test split")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--eval-every", type=int, default=None)
    p.add_argument("--crop", type=int, default=None, help="training crop side (multiple of 32)")
    p.add_argument("--base", type=int, default=None, help="first-layer width of the networks")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)

    p = sub.add_parser("generate", help="generate GI maps with a trained generator")
    p.add_argument("run", help="training run directory (or its generator.pt)")
    add_scene_argument(p)
    p.add_argument("--camera", default="default", help="'default' or 'path:NAME'")
    p.add_argument("--every", type=int, default=1, help="every K-th camera of a path")
    p.add_argument(
        "--size", type=int, nargs=2, default=None, metavar=("H", "W"), help="multiples of 32"
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--exposure", type=float, default=1.0, help="exposure of the PNG previews")
    p.set_defaults(func=_generate)

    p = sub.add_parser("export", help="export a trained generator to ONNX")
    p.add_argument("run", help="training run directory (or its generator.pt)")
    p.add_argument("--onnx", required=True, help="output .onnx file (+ .onnx.json sidecar)")
    p.add_argument("--size", type=int, nargs=2, default=(128, 128), metavar=("H", "W"))
    p.set_defaults(func=_export)


def _train(args: argparse.Namespace) -> int:
    import sys

    from icbtool import store as st
    from icbtool.gan.training import TrainConfig, TrainingDivergedError, train

    over = {
        k: v
        for k, v in {
            "inputs": args.inputs,
            "iterations": args.iterations,
            "vgg19_weights": args.vgg19_weights,
            "train_path": args.train_path,
            "test_path": args.test_path,
            "device": args.device,
            "seed": args.seed,
            "eval_every": args.eval_every,
            "crop": args.crop,
            "base": args.base,
        }.items()
        if v is not None
    }
    cfg = TrainConfig.preset(args.preset, **over)
    if not Path(args.store).is_dir():
        raise FileNotFoundError(f"store {args.store!r} does not exist")
    with st.open(args.store, st.StoreConfig(readonly=True)) as store:
        try:
            res = train(store, cfg, args.out, scene=args.scene, resume=args.resume,
                        progress=not args.no_progress)  # fmt: skip
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
    from icbtool.gan.generate import Generator
    from icbtool.imageio import to_display, write_exr, write_png

    gen = Generator.load(args.run)
    scene = load_scene(args.scene)
    h, w = (None, None) if args.size is None else args.size
    cams = select_cameras(scene, args.camera, args.every, h, w)
    names = tuple(n for n in gen.inputs if n != "mask")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
    from icbtool.gan.generate import Generator

    path = Generator.load(args.run).export_onnx(args.onnx, *args.size)
    print(f"wrote {path} and {path}.json")
    return 0
