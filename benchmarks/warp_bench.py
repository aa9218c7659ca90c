"""Warp timing: icbtool.warp (with hole masks) next to kornia's warp_frame_depth (no mask).

Same input in the same run: a 512x512 RGB image, smooth depth, a small camera motion, 2 torch
threads and 2 numba threads, median of N runs after warm-up, the methods' calls interleaved
round-robin. ``--repeats R`` repeats the whole interleaved measurement R times (the machine is
shared: the spread over repeats is reported with the machine load before each). Writes
benchmarks/results/warp/{warp_bench.json, warp_bench.png}.

    .venv/bin/python benchmarks/warp_bench.py [--size 512] [--runs 30] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from icbtool.camera import Camera
from icbtool.cli._common import run_info, write_json

OUT = Path(__file__).resolve().parent / "results" / "warp"


def timeit_interleaved(fns: dict, runs: int, warmup: int = 3) -> dict:
    """Median and min ms of each function, calls interleaved round-robin so that a changing
    machine load hits every method alike."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(runs):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            ts[k].append(time.perf_counter() - t0)
    return {
        k: {"median_ms": 1e3 * statistics.median(v), "min_ms": 1e3 * min(v), "runs": runs}
        for k, v in ts.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    import kornia

    from icbtool import warp

    n = args.size
    rng = np.random.default_rng(0)
    src_cam = Camera.from_fov(50.0, n, n)
    pose = np.eye(4)
    pose[:3, :3] = np.array(
        [[np.cos(0.02), 0, np.sin(0.02)], [0, 1, 0], [-np.sin(0.02), 0, np.cos(0.02)]]
    )
    pose[:3, 3] = (0.05, -0.02, 0.03)
    dst_cam = src_cam.with_pose(pose)
    yy, xx = np.mgrid[0:n, 0:n] / n
    depth = (3.0 + np.sin(6 * xx) * np.cos(4 * yy)).astype(np.float32)[..., None]
    image = rng.random((n, n, 3)).astype(np.float32)

    img_t = torch.from_numpy(image).permute(2, 0, 1)[None].contiguous()
    d_t = torch.from_numpy(depth).permute(2, 0, 1)[None].contiguous()
    K = torch.from_numpy(src_cam.K).float()[None]
    K_k = torch.from_numpy(src_cam.K_kornia()).float()[None]
    src_from_dst = torch.from_numpy(src_cam.cam_from_world @ dst_cam.world_from_cam).float()[None]
    dst_from_src = torch.linalg.inv(src_from_dst)

    from icbtool.warp.functional import inverse_depth_slopes

    slopes = inverse_depth_slopes(d_t)  # once per reference (it is warped to many frames)

    def inference(fn):
        def run():
            with torch.inference_mode():
                return fn()

        return run

    cfg_numba = warp.WarpConfig(backend="numba", threads=args.threads)
    cfg_numba_1 = warp.WarpConfig(backend="numba", threads=1)
    cfg_torch = warp.WarpConfig(backend="torch")
    t0 = time.perf_counter()
    warp.backward(image, depth, src_cam, depth, dst_cam, config=cfg_numba)
    first_numba_call_s = time.perf_counter() - t0  # JIT compile, or loading numba's disk cache

    fns = {
        "kornia_warp_frame_depth": inference(
            lambda: kornia.geometry.depth.warp_frame_depth(img_t, d_t, src_from_dst, K_k)
        ),
        "icbtool_warp_backward_torch": inference(
            lambda: warp.warp_backward(img_t, d_t, d_t, K, K, src_from_dst)
        ),
        "icbtool_warp_backward_torch_precomputed_slopes": inference(
            lambda: warp.warp_backward(img_t, d_t, d_t, K, K, src_from_dst, src_slopes=slopes)
        ),
        "icbtool_warp_backward_torch_no_slope_test": inference(
            lambda: warp.warp_backward(img_t, d_t, d_t, K, K, src_from_dst, slope_limit=0.0)
        ),
        "icbtool_warp_forward_torch": inference(
            lambda: warp.warp_forward(img_t, d_t, K, K, dst_from_src, (n, n))
        ),
        "icbtool_warp_backward_numpy_numba": lambda: warp.backward(
            image, depth, src_cam, depth, dst_cam, config=cfg_numba
        ),
        "icbtool_warp_backward_numpy_numba_1thread": lambda: warp.backward(
            image, depth, src_cam, depth, dst_cam, config=cfg_numba_1
        ),
        "icbtool_warp_backward_numpy_torch": lambda: warp.backward(
            image, depth, src_cam, depth, dst_cam, config=cfg_torch
        ),
        "icbtool_warp_forward_numpy_numba": lambda: warp.forward(
            image, depth, src_cam, dst_cam, config=cfg_numba
        ),
        "icbtool_warp_forward_numpy_torch": lambda: warp.forward(
            image, depth, src_cam, dst_cam, config=cfg_torch
        ),
    }
    repeats = []
    for _ in tqdm(range(args.repeats), desc="repeats"):
        load_before = os.getloadavg()
        repeats.append(
            {"load_average_1_5_15min_before": load_before, **timeit_interleaved(fns, args.runs)}
        )
    # per method: the median over repeats of each repeat's median (and the spread)
    results = {}
    for k in fns:
        meds = [r[k]["median_ms"] for r in repeats]
        results[k] = {
            "median_ms": statistics.median(meds),
            "min_ms": min(r[k]["min_ms"] for r in repeats),
            "median_ms_per_repeat": meds,
            "runs": args.runs,
        }
    with torch.inference_mode():
        # agreement check of the two backward warps (same conventions) on interior pixels whose
        # four taps all passed (kornia zero-pads and blends across depth edges; we replicate the
        # border half pixel and drop failing taps)
        ours = warp.warp_backward(img_t, d_t, d_t, K, K, src_from_dst)
        theirs = kornia.geometry.depth.warp_frame_depth(img_t, d_t, src_from_dst, K_k)
        uv = ours.src_uv
        inner = (uv[:, :1] > 1) & (uv[:, :1] < n - 1) & (uv[:, 1:] > 1) & (uv[:, 1:] < n - 1)
        ok = (inner & (ours.weight > 0.999)).expand_as(ours.image)
        diff = float((ours.image - theirs)[ok].abs().max())
        # the numba kernel against the torch reference (float32 both)
        nb_res = warp.backward(image, depth, src_cam, depth, dst_cam, config=cfg_numba)
        ours_img = ours.image[0].permute(1, 2, 0).numpy()
        numba_vs_torch = {
            "max_abs_image_diff": float(np.abs(nb_res.image - ours_img).max()),
            "holes_differing_pixels": int((nb_res.holes != ours.holes[0, 0].numpy()).sum()),
        }
    load = os.getloadavg()
    kornia_ms = results["kornia_warp_frame_depth"]["median_ms"]
    ratio = results["icbtool_warp_backward_numpy_numba"]["median_ms"] / kornia_ms
    ratios = {k: v["median_ms"] / kornia_ms for k, v in results.items()}
    out = {
        "config": vars(args),
        "results": results,
        "numba_backward_over_kornia": ratio,
        "median_over_kornia": ratios,
        "ratio_spread_over_repeats": {
            k: [r[k]["median_ms"] / r["kornia_warp_frame_depth"]["median_ms"] for r in repeats]
            for k in fns
        },
        "repeats": repeats,
        "first_numba_call_s": first_numba_call_s,
        "numba_vs_torch": numba_vs_torch,
        "max_abs_diff_vs_kornia_on_agreeing_interior_pixels": diff,
        "hole_ratio": float(ours.holes.float().mean()),
        "load_average_1_5_15min_after": load,
        "run_info": run_info(),
    }
    write_json(OUT / "warp_bench.json", out)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    vals = [results[k]["median_ms"] for k in names]
    lo = [v - min(results[k]["median_ms_per_repeat"]) for k, v in zip(names, vals, strict=True)]
    hi = [max(results[k]["median_ms_per_repeat"]) - v for k, v in zip(names, vals, strict=True)]
    fig, ax = plt.subplots(figsize=(10, 5))
    colors = ["gray" if k.startswith("kornia") else "tab:blue" for k in names]
    colors = ["tab:green" if "numba" in k else c for k, c in zip(names, colors, strict=True)]
    ax.barh(names, vals, xerr=[lo, hi], color=colors, capsize=3)
    ax.axvline(kornia_ms, color="gray", ls="--", lw=1)
    for i, v in enumerate(vals):
        ax.text(v, i, f" {v:.1f} ms", va="bottom")
    ax.invert_yaxis()
    ax.set_xlabel(
        f"ms at {n}x{n}, {args.threads} threads: median of {args.repeats} repeat medians "
        f"({args.runs} interleaved runs each);\nwhiskers: min/max repeat median; "
        f"load avg {load[0]:.1f} after"
    )
    ax.set_title("warp: icbtool (with hole masks) vs kornia warp_frame_depth (no mask)")
    fig.tight_layout()
    fig.savefig(OUT / "warp_bench.png", dpi=100)
    for k in names:
        per = ", ".join(f"{v:.1f}" for v in results[k]["median_ms_per_repeat"])
        print(f"{k:48s} {results[k]['median_ms']:7.2f} ms  (repeats: {per})")
    print(f"numba backward (with masks) / kornia = {ratio:.2f}, max |diff| on valid = {diff:.2e}")
    print(f"numba vs torch: {numba_vs_torch}, first numba call {first_numba_call_s:.2f} s")


if __name__ == "__main__":
    main()
