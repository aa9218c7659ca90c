"""What limits learned GI: the recipe, and one change at a time (the learned-GI ablation).

The recipe (``RECIPE``, the ``cpu`` preset's training): configuration J (albedo, DL, world
normals, world positions) with Fourier features of the position computed inside the network,
demodulated targets, the full-resolution skip, width 16, L1 + SSIM
loss without the critic, cosine learning rate, weight averaging, 64-pixel crops in batches of 8,
trained on the train path plus the coverage views (``train,cover``: benchmarks/gan_coverage.py).
Each variant changes exactly one thing. The best of them, "constant lr", is what the ``cpu``
preset became (the recipe with a constant learning rate); the speed study (target: <= 15 ms
per 256 x 256 frame, benchmarks/gan_speed.py) then changed one thing at a time from that preset,
with seed replicates for the run-to-run spread, and the ``cpu`` preset is now its last row
("half-res features + 1x1 head + base 8, 20000 iterations"). Runs train round-robin in chunks
(resumable: a rerun continues), then every run is scored on ALL views of the test path and of
the held-out walk.

    ICBTOOL_GL_BACKEND=osmesa ICBTOOL_GAN_STORE=STORE .venv/bin/python -m benchmarks.gan_ablation \\
        --runs out/runs/ablation --iterations 3000

Writes --out/ablation.json, ablation.csv, ablation.png (test SSIM against
iterations, one curve per variant) and ablation_config.json.
"""

from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"

#: The generator's architecture when the ablation began (width 16, full-resolution position
#: features, 3 x 3 head): the recipe pins it, so the rows measured before the speed study keep their
#: configs whatever the ``cpu`` preset becomes.
FIRST_NET = dict(
    base=16,
    position_resolution="full",
    head_kernel=3,
    skip_features=True,
    input_reduce=0,
    top_width=0,
)

#: The recipe: the ``cpu`` preset as it was first planned (a cosine learning rate; the ablation
#: found the preset's constant one better), trained on the train path plus the coverage views.
RECIPE = dict(lr_schedule="cosine", train_path="train,cover", **FIRST_NET)

#: The ``cpu`` preset before the speed study (the recipe with a constant learning rate): the
#: speed variants (target: <= 15 ms at 256 x 256) each change one thing of it.
CPU_BEFORE = {"lr_schedule": "constant"}

#: name -> (what changes, the fields that change)
VARIANTS: dict[str, tuple[str, dict]] = {
    "recipe": ("the recipe (cosine learning rate)", {}),
    "no cover": ("train path only (no coverage views)", {"train_path": "train"}),
    "no demodulation": ("targets are GI, not GI / albedo", {"demodulate": False}),
    "no full-res skip": ("the paper's U-Net (no full-resolution skip)", {"full_res_skip": False}),
    "no SSIM term": ("L1 alone", {"weight_ssim": 0.0}),
    "paper loss": (
        "L_a + L_c (WGAN-GP critic, weights 1 / 1)",
        {"weight_adv": 1.0, "weight_l1": 1.0, "weight_ssim": 0.0},
    ),  # fmt: skip
    "constant lr": (
        "no cosine schedule: the cpu preset before the speed study",
        {"lr_schedule": "constant"},
    ),
    "no averaging": ("no weight averaging", {"ema": 0.0}),
    "crop 128": (
        "whole 128 x 128 images (no crop augmentation), batch 2",
        {"crop": 128, "batch_size": 2},
    ),  # fmt: skip
    "base 32": ("twice the width (the cpu preset before)", {"base": 32}),
    "input I": (
        "configuration I (depth instead of position: no position features either)",
        {"inputs": "I", "position_octaves": 0},
    ),  # fmt: skip
    "no position features": ("no Fourier features of the position", {"position_octaves": 0}),
    # the speed study: one change from the cpu preset before it (benchmarks/gan_speed.py)
    "seed 1": (
        "the cpu preset before, another seed (run-to-run spread)",
        {**CPU_BEFORE, "seed": 1},
    ),  # fmt: skip
    "4 octaves": (
        "cpu preset before, 4 octaves of position features",
        {**CPU_BEFORE, "position_octaves": 4},
    ),  # fmt: skip
    "1x1 reduction": (
        "cpu preset before, a 1x1 reduction of input + features to 16 channels",
        {**CPU_BEFORE, "input_reduce": 16},
    ),  # fmt: skip
    "half-res features": (
        "cpu preset before, position features at half resolution",
        {**CPU_BEFORE, "position_resolution": "half"},
    ),  # fmt: skip
    "skip without features": (
        "cpu preset before, the full-res skip without the features",
        {**CPU_BEFORE, "skip_features": False},
    ),  # fmt: skip
    "1x1 head": (
        "cpu preset before, a 1x1 full-resolution head",
        {**CPU_BEFORE, "head_kernel": 1},
    ),  # fmt: skip
    "top width 8": ("cpu preset before, the last level 8 wide", {**CPU_BEFORE, "top_width": 8}),
    "half-res features + 1x1 head": (
        "cpu preset before, both",
        {**CPU_BEFORE, "position_resolution": "half", "head_kernel": 1},
    ),  # fmt: skip
    "half-res features + 1x1 head, seed 1": (
        "the same, another seed (run-to-run spread)",
        {**CPU_BEFORE, "position_resolution": "half", "head_kernel": 1, "seed": 1},
    ),  # fmt: skip
    "half-res features + 1x1 head + base 8": (
        "the same, half the width (the generator's cost falls about 4x)",
        {**CPU_BEFORE, "position_resolution": "half", "head_kernel": 1, "base": 8},
    ),  # fmt: skip
    "half-res features + 1x1 head + base 8, seed 1": (
        "the same, another seed (run-to-run spread)",
        {**CPU_BEFORE, "position_resolution": "half", "head_kernel": 1, "base": 8, "seed": 1},
    ),  # fmt: skip
    "half-res features + 1x1 head + base 8, 6000 iterations": (
        "the same, trained twice as long (an iteration costs about half)",
        {
            **CPU_BEFORE,
            "position_resolution": "half",
            "head_kernel": 1,
            "base": 8,
            "iterations": 6000,
        },
    ),  # fmt: skip
    "half-res features + 1x1 head + base 8, 12000 iterations": (
        "the same, trained four times as long",
        {
            **CPU_BEFORE,
            "position_resolution": "half",
            "head_kernel": 1,
            "base": 8,
            "iterations": 12000,
        },
    ),  # fmt: skip
    "half-res features + 1x1 head + base 8, 20000 iterations": (
        "the same, trained about seven times as long: the cpu preset",
        {
            **CPU_BEFORE,
            "position_resolution": "half",
            "head_kernel": 1,
            "base": 8,
            "iterations": 20000,
        },
    ),  # fmt: skip
}


def config(name: str, iterations: int, chunk: int):
    """A variant's TrainConfig: ``iterations`` unless the variant sets its own."""
    from icbtool import gan

    fields = {"iterations": iterations, "eval_every": chunk, "checkpoint_every": chunk,
              **RECIPE, **VARIANTS[name][1]}  # fmt: skip
    return gan.TrainConfig.preset("cpu", **fields)


def score(store, scene, run: Path, paths: list[str], exposure: float) -> dict:
    """Mean SSIM / MSE of a run's generator over every view of each path."""
    from icbtool import gan, metrics
    from icbtool.store.dataset import Dataset

    g = gan.Generator.load(run)
    out = {}
    for p in paths:
        ids = Dataset(store, scene, "test", g.inputs, paths={"test": p}).record_ids
        s, m = [], []
        for rid in ids:
            rec = store.get(rid)
            pred = g.generate(rec)
            s.append(metrics.ssim(pred, rec.gi, exposure))
            m.append(metrics.mse(pred, rec.gi, exposure))
        out[p] = {"views": len(ids), "ssim": float(np.mean(s)), "mse": float(np.mean(m))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"))
    ap.add_argument("--scene", default="sponza")
    ap.add_argument("--runs", default="out/runs/ablation")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--chunk", type=int, default=500)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (default: all)")
    ap.add_argument("--eval-paths", default="test,walk")
    ap.add_argument("--score-only", action="store_true", help="no training, score what exists")
    add_out_argument(ap, "gan")
    args = ap.parse_args()
    if not args.store:
        ap.error("--store (or ICBTOOL_GAN_STORE) is required")

    import icbtool.store as S
    from benchmarks.gan_figure7 import curves, train_round_robin
    from icbtool.provenance import run_info, write_json

    names = args.only or list(VARIANTS)
    bad = sorted(set(names) - set(VARIANTS))
    if bad:
        ap.error(f"unknown variants {bad}; choose from {list(VARIANTS)}")
    runs = Path(args.runs)
    load0 = os.getloadavg()[0]
    jobs = {
        n: (args.store, config(n, args.iterations, args.chunk), runs / n.replace(" ", "_"))
        for n in names
    }
    if not args.score_only:
        for its in sorted({cfg.iterations for _, cfg, _ in jobs.values()}):
            group = {n: j for n, j in jobs.items() if j[1].iterations == its}
            train_round_robin(group, its, args.chunk, args.scene)
    ro = S.StoreConfig(readonly=True, record_hits=False)
    res: dict = {"recipe": config("recipe", args.iterations, args.chunk).to_dict(), "variants": {}}
    paths = [p for p in args.eval_paths.split(",") if p]
    with S.open(args.store, ro) as store:
        for n, (_, cfg, run) in jobs.items():
            if not (run / "generator.pt").exists():
                continue
            cv = curves(run.parent, [run.name]).get(run.name, {})
            res["variants"][n] = {
                "change": VARIANTS[n][0],
                "iteration": cv["iteration"][-1] if cv else None,
                "seconds": _seconds(run),
                "curve": cv,
                **score(store, args.scene, run, paths, cfg.display_exposure),
            }
            v = res["variants"][n]
            print(f"{n:18s} " + "  ".join(f"{p} {v[p]['ssim']:.3f}" for p in paths))
    res["load_1min"] = [load0, os.getloadavg()[0]]
    out = Path(args.out)
    write_json(out / "ablation.json", res)
    write_json(out / "ablation_config.json", {"args": vars(args), "run": run_info()})
    with open(out / "ablation.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["variant", "change", "iteration", *[f"{p}_{k}" for p in paths
                                                         for k in ("ssim", "mse")]])  # fmt: skip
        for n, v in res["variants"].items():
            w.writerow([n, v["change"], v["iteration"],
                        *[f"{v[p][k]:.4f}" for p in paths for k in ("ssim", "mse")]])  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for n, v in res["variants"].items():
        if v["curve"]:
            ax.plot(v["curve"]["iteration"], v["curve"]["ssim"], label=n, marker=".")
    ax.set(xlabel="iteration", ylabel="test SSIM (every test view)", title="ablation")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "ablation.png", dpi=110)


def _seconds(run: Path) -> float | None:
    import json

    p = run / "evals.json"
    if not p.exists():
        return None
    ev = json.loads(p.read_text())
    return float(ev[-1]["seconds"]) if ev else None


if __name__ == "__main__":
    main()
