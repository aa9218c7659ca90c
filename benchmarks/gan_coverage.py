"""Plan and bake the views a learned GI model is missing (icbtool.gan.coverage), and measure how
far every evaluation view is from what training saw.

1. Plan: ``--views`` cameras chosen greedily from collision-free candidates in every direction to
   cover what the store's train path did not show (never looking at test cameras).
2. Bake them into the same store as path ``cover`` (same size, spp and denoising as the train
   path: ``--spp``, ``--seed``).
3. Coverage of the evaluation paths (``test``, ``walk``): per view, the median distance from its
   pixels' world positions to the nearest training pixel (fraction of the scene's diagonal), with
   train alone and with train + cover.

Writes coverage.json, coverage.png, coverage_plan.npz, coverage_bake.json and
coverage_config.json to ``--out`` (default out/bench/gan; the committed ones are in
benchmarks/results/gan). An evaluation path the store has no records of is an error naming it.

    ICBTOOL_GL_BACKEND=osmesa .venv/bin/python -m benchmarks.gan_coverage --store STORE \\
        --scene data/scenes/sponza.toml --views 40 --spp 64 --out out/bench/gan_coverage
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"


def view_coverage(store, scene, path: str, covered: np.ndarray) -> list[float]:
    """Median coverage distance of every view of ``path``."""
    from icbtool.gan.coverage import coverage_distance
    from icbtool.store.dataset import Dataset

    ds = Dataset(store, scene, "train", ("position",), paths={"train": path})
    out = []
    for s in ds:
        pos = s.inputs.transpose(1, 2, 0)[s.mask[0] > 0.5]
        out.append(float(np.median(coverage_distance(covered, pos, scene.bounds))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"), required=False)
    ap.add_argument("--scene", default=str(REPO / "data" / "scenes" / "sponza.toml"))
    ap.add_argument("--views", type=int, default=150)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--seed", type=int, default=500_000)
    ap.add_argument("--radius", type=float, default=0.01)
    ap.add_argument("--train-path", default="train")
    ap.add_argument("--cover-path", default="cover")
    ap.add_argument("--eval-paths", default="test,walk")
    ap.add_argument("--no-denoise", action="store_true")
    add_out_argument(ap, "gan")
    ap.add_argument(
        "--phase",
        choices=("all", "plan", "bake", "measure"),
        default="all",
        help="plan: choose the views (store opened read-only) and save them to "
        "OUT/coverage_plan.npz; bake: bake the first --views of a saved plan; measure: the "
        "coverage of the evaluation paths; all: the three",
    )
    args = ap.parse_args()
    if not args.store:
        ap.error("--store (or ICBTOOL_GAN_STORE) is required")

    import icbtool as icb
    from icbtool.bake import BakeConfig, bake
    from icbtool.gan.coverage import plan_coverage, store_points
    from icbtool.provenance import run_info, write_json

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = icb.scene.load(args.scene)
    load0 = os.getloadavg()[0]
    plan_file = out / "coverage_plan.npz"
    ro = icb.store.StoreConfig(readonly=True, create=False)
    with icb.store.open(args.store, ro) as store:
        train_pts = store_points(store, [args.train_path], scene, stride=2)
        first = next(iter(icb.store.Dataset(
            store, scene, "train", ("position",), paths={"train": args.train_path}
        )))  # fmt: skip
        h, w = first.mask.shape[1:]
    intr = scene.paths[args.train_path].intrinsics.resized(h, w)
    if args.phase in ("all", "plan"):
        t0 = time.perf_counter()
        plan = plan_coverage(
            scene, args.views, intr, covered=train_pts, radius=args.radius, name=args.cover_path
        )
        t_plan = time.perf_counter() - t0
        np.savez(
            plan_file,
            world_from_cam=plan.path.world_from_cam,
            gain=plan.gain,
            before=plan.uncovered_before,
            after=plan.uncovered_after,
            candidates=plan.candidates,
            seconds=t_plan,
        )
        print(
            f"plan: {plan.candidates} candidates, uncovered {100 * plan.uncovered_before:.1f} % -> "
            f"{100 * plan.uncovered_after:.1f} % in {t_plan:.0f} s -> {plan_file}"
        )
        if args.phase == "plan":
            return
    saved = np.load(plan_file)
    # the plan is greedy: its first n views are the best n-view plan
    poses = saved["world_from_cam"][: args.views]
    bake_file = out / "coverage_bake.json"
    if args.phase in ("all", "bake"):
        path = icb.camera.CameraPath(
            np.arange(len(poses)) / 30.0, poses, intr, name=args.cover_path
        )
        cfg = BakeConfig(
            spp=args.spp, seed=args.seed, denoise=not args.no_denoise, resolution=(h, w)
        )
        with icb.store.open(args.store) as store:
            t0 = time.perf_counter()
            rep = bake(scene, path, store, cfg)
            write_json(
                bake_file,
                {
                    "views": len(poses),
                    "rendered": len(rep.rendered),
                    "seconds": time.perf_counter() - t0,
                    "spp": args.spp,
                    "denoise": not args.no_denoise,
                    "load_1min": [load0, os.getloadavg()[0]],
                },
            )
        if args.phase == "bake":
            return
    baked = json.loads(bake_file.read_text())
    with icb.store.open(args.store, ro) as store:
        cover_pts = store_points(store, [args.cover_path], scene, stride=2)
        both = np.concatenate([train_pts, cover_pts])
        cov = {}
        for p in [s for s in args.eval_paths.split(",") if s]:
            if not len(icb.store.Dataset(store, scene, "train", ("position",), paths={"train": p})):
                raise SystemExit(
                    f"gan_coverage: evaluation path {p!r} has no records in {args.store}: bake it "
                    f"(icbtool bake SCENE --path {p} --store {args.store} ...) or leave it out of "
                    "--eval-paths"
                )
            cov[p] = {
                "train": view_coverage(store, scene, p, train_pts),
                "train+cover": view_coverage(store, scene, p, both),
            }
    summary = {p: {k: float(np.median(v)) for k, v in d.items()} for p, d in cov.items()}
    result = {
        "candidates": int(saved["candidates"]),
        "views": len(poses),
        "radius": args.radius,
        "uncovered_before": float(saved["before"]),
        "uncovered_after": float(saved["after"]),
        "gain": saved["gain"].tolist(),
        "plan_seconds": float(saved["seconds"]),
        "bake": baked,
        "coverage_per_view": cov,
        "median_coverage": summary,
        "load_1min": [load0, os.getloadavg()[0]],
    }
    write_json(out / "coverage.json", result)
    write_json(out / "coverage_config.json", {"args": vars(args), "run": run_info()})
    print(json.dumps(summary, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(100 * saved["gain"])
    ax[0].set(xlabel="chosen view", ylabel="% of its pixels newly covered", title="greedy plan")
    for p, d in cov.items():
        for k, v in d.items():
            ax[1].plot(100 * np.asarray(v), label=f"{p} vs {k}")
    ax[1].set(xlabel="view", ylabel="median distance to nearest training pixel (% diag)",
              yscale="log", title="coverage of evaluation views")  # fmt: skip
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=110)


if __name__ == "__main__":
    main()
