"""Warp timing: icbtool.warp (with hole masks) next to kornia's warp_frame_depth (no mask).

Same input in the same run: a 512x512 RGB image, smooth depth, a small camera motion, 2 torch
threads and 2 numba threads, median of N runs after warm-up, the methods' calls interleaved
round-robin; the per-run times are saved, and the summary gives medians and minima (no means),
the first call apart, and speed ratios over kornia as ratio of medians and of mins.
``--repeats R`` repeats the whole interleaved measurement R times (the machine is shared: the
spread over repeats is reported with the machine load before each). Writes
benchmarks/results/warp/{warp_bench.json, warp_bench.png}.

    .venv/bin/python -m benchmarks.warp_bench [--size 512] [--runs 30] [--repeats 3]
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

from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.camera import Camera

OUT = Path(__file__).resolve().parent / "results" / "warp"


def timeit_interleaved(fns: dict, runs: int, warmup: int = 3) -> dict:
    """Per-run ms of each function, calls interleaved round-robin so that a changing machine
    load hits every method alike. The warm-up calls are timed too (the first one pays torch's or
    numba's first-call costs) but kept apart from the runs."""
    warm: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(warmup):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            warm[k].append(1e3 * (time.perf_counter() - t0))
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(runs):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            ts[k].append(1e3 * (time.perf_counter() - t0))
    return {
        k: {
            "median_ms": statistics.median(v),
            "min_ms": min(v),
            "runs": runs,
            "run_ms": v,
            "warmup_ms": warm[k],
        }
        for k, v in ts.items()
    }


def summarize(repeats: list[dict], names: list[str], reference: str) -> dict:
    """Per method: medians and minima over all runs, and speed ratios against ``reference``.

    Args:
        repeats: one dict per repeat, ``{name: {"run_ms": [...], "warmup_ms": [...]}}``.
        names: the methods.
        reference: the method the ratios divide by (kornia).

    Returns:
        ``{name: {...}}`` with ``median_ms`` (median of all timed runs), ``min_ms`` (min of all
        runs), ``median_ms_per_repeat``, ``first_call_ms`` (the first warm-up call of the first
        repeat, apart), and the ratios over the reference: ``ratio_of_medians``,
        ``ratio_of_mins`` (min-of-runs), and per repeat ``ratio_of_medians_per_repeat``,
        ``ratio_of_mins_per_repeat``. No mean anywhere: a few slow runs (load spikes, first
        calls) would dominate it.
    """

    def pooled(k: str) -> list[float]:
        return [t for r in repeats for t in r[k]["run_ms"]]

    ref_all = pooled(reference)
    out = {}
    for k in names:
        v = pooled(k)
        out[k] = {
            "median_ms": statistics.median(v),
            "min_ms": min(v),
            "median_ms_per_repeat": [statistics.median(r[k]["run_ms"]) for r in repeats],
            "min_ms_per_repeat": [min(r[k]["run_ms"]) for r in repeats],
            "first_call_ms": repeats[0][k]["warmup_ms"][0],
            "runs": len(v),
            "ratio_of_medians": statistics.median(v) / statistics.median(ref_all),
            "ratio_of_mins": min(v) / min(ref_all),
            "ratio_of_medians_per_repeat": [
                statistics.median(r[k]["run_ms"]) / statistics.median(r[reference]["run_ms"])
                for r in repeats
            ],
            "ratio_of_mins_per_repeat": [
                min(r[k]["run_ms"]) / min(r[reference]["run_ms"]) for r in repeats
            ],
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    add_out_argument(ap, "warp")
    args = ap.parse_args()
    global OUT
    OUT = args.out
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
    results = summarize(repeats, list(fns), "kornia_warp_frame_depth")
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
    nb = results["icbtool_warp_backward_numpy_numba"]
    out = {
        "config": vars(args),
        "summary": "per method over all runs of all repeats: median and min ms (no means), the "
        "first call apart; speed ratios over kornia as ratio of medians and ratio of mins "
        "(min-of-runs), overall and per repeat; raw per-run ms in repeats[*][method].run_ms",
        "results": results,
        "numba_backward_over_kornia": {
            "ratio_of_medians": nb["ratio_of_medians"],
            "ratio_of_mins": nb["ratio_of_mins"],
            "ratio_of_medians_per_repeat": nb["ratio_of_medians_per_repeat"],
            "ratio_of_mins_per_repeat": nb["ratio_of_mins_per_repeat"],
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
        f"ms at {n}x{n}, {args.threads} threads: median of all {args.repeats}x{args.runs} "
        f"interleaved runs;\nwhiskers: min/max repeat median; "
        f"load avg {load[0]:.1f} after"
    )
    ax.set_title("warp: icbtool (with hole masks) vs kornia warp_frame_depth (no mask)")
    fig.tight_layout()
    fig.savefig(OUT / "warp_bench.png", dpi=100)
    for k in names:
        per = ", ".join(f"{v:.1f}" for v in results[k]["median_ms_per_repeat"])
        print(
            f"{k:48s} median {results[k]['median_ms']:7.2f} ms, min {results[k]['min_ms']:7.2f}"
            f", first call {results[k]['first_call_ms']:7.1f}  (repeat medians: {per})"
        )
    print(
        f"numba backward (with masks) / kornia: ratio of medians {nb['ratio_of_medians']:.2f}, "
        f"of mins {nb['ratio_of_mins']:.2f}; max |diff| on valid = {diff:.2e}"
    )
    print(f"numba vs torch: {numba_vs_torch}, first numba call {first_numba_call_s:.2f} s")


if __name__ == "__main__":
    main()
