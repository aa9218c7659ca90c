"""The GAN trainer on another device (a GPU): the paper preset end to end, its speed and losses.

``TrainConfig.device`` is a setting ("cpu" or "cuda"); this checks the whole training path on it
(store -> dataset -> crops -> generator, WGAN-GP critic, VGG19 perceptual loss -> checkpoint ->
evaluation) where no renderer, data set or weights file may be at hand: the store is synthetic
(256 x 256 views of a plane whose GI is a known smooth function of the world position, scaled by
the albedo; albedo, DL, normals and depth as a renderer would give them), and with
``--random-vgg`` a VGG19 state dict of torchvision's random initialisation stands in for the
ImageNet weights (the perceptual loss's cost and code path, not its meaning). The same config runs
on the CPU for a few iterations for the speed ratio.

    python -m benchmarks.gan_device_check --device cuda --iterations 300 --out /tmp/gan_check

Writes OUT/gan_device_check.json (iterations per second on each device, first and last losses,
the evaluation SSIM, peak GPU memory) and the run folders.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from icbtool import store as S
from icbtool.camera import Camera
from icbtool.gan.training import TrainConfig, train
from icbtool.provenance import run_info, write_json


def record(i: int, size: int, path: str) -> S.CRTBuffer:
    """View i of the plane z = 2 (camera at x = 0.15 i): GI = albedo * a smooth function of x."""
    m = np.eye(4)
    m[0, 3] = 0.15 * i
    cam = Camera.from_fov(60.0, size, size, m)
    u = np.arange(size) + 0.5
    v = np.arange(size) + 0.5
    wx = 0.15 * i + (u - cam.cx) / cam.fx * 2.0
    wy = (v - cam.cy) / cam.fy * 2.0
    checker = ((np.floor(4 * wx)[None, :] + np.floor(4 * wy)[:, None]) % 2)[..., None]
    albedo = (0.3 + 0.5 * checker * np.array([1.0, 0.7, 0.4])).astype(np.float32)
    light = 0.2 + 0.1 * np.sin(3.0 * wx)[None, :, None] + 0.05 * np.cos(2.0 * wy)[:, None, None]
    gi = (albedo * light).astype(np.float32)
    pos = np.stack(np.broadcast_arrays(wx[None, :], wy[:, None], np.full((1, 1), 2.0)), -1)
    ones = np.ones((size, size, 1), np.float32)
    return S.CRTBuffer(
        camera=cam,
        meta=S.RecordMeta("plane", "ph", "lh", spp=64, tags={"path": path, "index": i}),
        gi=gi,
        dl=(0.5 * albedo).astype(np.float32),
        albedo=albedo,
        normal_world=np.broadcast_to(np.float32([0, 0, -1]), (size, size, 3)).copy(),
        depth=2.0 * ones,
        position=pos.astype(np.float32),
        mask=ones,
    )


def timed_run(st, cfg: TrainConfig, out: Path) -> dict:
    losses: list[dict] = []
    stamps: list[float] = []

    def on_step(it: int, ls: dict) -> None:
        if cfg.device == "cuda":
            torch.cuda.synchronize()
        stamps.append(time.perf_counter())
        losses.append({k: float(v) for k, v in ls.items()})

    t0 = time.perf_counter()
    res = train(st, cfg, out, progress=False, on_step=on_step)
    # iterations per second after the first 10 (warm-up: cuDNN autotuning, allocator)
    k = min(10, len(stamps) - 2)
    rate = (len(stamps) - 1 - k) / (stamps[-1] - stamps[k]) if len(stamps) > k + 1 else None
    return {
        "device": cfg.device,
        "iterations": len(stamps),
        "wall_s": time.perf_counter() - t0,
        "iterations_per_s": rate,
        "first_losses": losses[0] if losses else None,
        "last_losses": losses[-1] if losses else None,
        "final_eval": res.evals[-1] if res.evals else None,
        "perceptual": res.perceptual,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--cpu-iterations", type=int, default=12, help="0: no CPU comparison")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--preset", default="paper", choices=("paper", "paper-cpu", "cpu"))
    ap.add_argument("--random-vgg", action="store_true", help="a random-initialised VGG19 file")
    ap.add_argument("--out", type=Path, default=Path("/tmp/gan_device_check"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    vgg = None
    if args.random_vgg:
        import torchvision

        vgg = args.out / "vgg19_random_init.pth"
        torch.save(torchvision.models.vgg19(weights=None).state_dict(), vgg)
    result: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "runs": []}
    shutil.rmtree(args.out / "store", ignore_errors=True)
    with S.open(args.out / "store", S.StoreConfig(fsync=False)) as st:
        for i in range(12):
            st.put(record(i, args.size, "train"))
        for i in range(12, 16):
            st.put(record(i, args.size, "test"))
        runs = [(args.device, args.iterations)]
        if args.cpu_iterations and args.device != "cpu":
            runs.append(("cpu", args.cpu_iterations))
        for device, n in runs:
            cfg = TrainConfig.preset(
                args.preset,
                device=device,
                iterations=n,
                eval_every=n,
                vgg19_weights=None if vgg is None else str(vgg),
            )
            shutil.rmtree(args.out / f"run_{device}", ignore_errors=True)
            r = timed_run(st, cfg, args.out / f"run_{device}")
            if device == "cuda":
                r["peak_gpu_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
                r["gpu"] = torch.cuda.get_device_name()
            print(json.dumps(r), flush=True)
            result["runs"].append(r)
    rates = {r["device"]: r["iterations_per_s"] for r in result["runs"]}
    if rates.get("cuda") and rates.get("cpu"):
        result["cuda_over_cpu_speed"] = rates["cuda"] / rates["cpu"]
    result["torch"] = torch.__version__
    result["run_info"] = run_info()
    write_json(args.out / "gan_device_check.json", result)
    print(f"wrote {args.out / 'gan_device_check.json'}")


if __name__ == "__main__":
    main()
