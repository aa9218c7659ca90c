"""ICB's Figure 7 on Sponza: test SSIM / MSE of the GAN pre-renderer against iterations, one curve
per input configuration A-J (docs/design.md section 5), with the test truth's own noise ceiling.

Data: a store baked with ``icbtool bake`` holding the scene's "train" path and its "test" path
(records tagged by path), and a second store holding some of the same test cameras traced with
other seeds (the noise ceiling: SSIM of two truths). The 128x128 stores used for the committed
results are the Sponza store of docs/benchmarks.md ("What held learned GI back": train, test
every 5th camera, walk, cover views); the noise ceiling's second store, when measured, holds
some of the test cameras traced with another seed::

    icbtool bake data/scenes/sponza.toml --path test --store CEILING --spp 256 --stride 15 \\
        --seed 200000 --height 128 --width 128 --denoise

Training is round-robin in chunks (every configuration to 250 iterations, then every one to 500,
...), each run resumable, so an interrupted experiment always has comparable curves and a rerun
continues where it stopped. After every chunk it writes --out/figure7.json
(curves, best configuration, world vs view normals, the first iteration reaching the target
SSIM), figure7.png (the curves) and figure7_config.json (settings, versions, machine).

    ICBTOOL_GAN_STORE=STORE ICBTOOL_GAN_CEILING=CEILING .venv/bin/python -m benchmarks.gan_figure7
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"
#: (view-normal, world-normal) configuration pairs compared in docs/design.md section 5.
NORMAL_PAIRS = (("E", "H"), ("F", "I"), ("G", "J"))


#: The settings Figure 7 used with the ``paper-cpu`` preset before the ``cpu`` preset existed
#: (kept so that ``--preset paper-cpu`` reproduces those results). Sponza's GI (train set: median
#: 0.11, 99th percentile 0.36, max 0.93) spread over the tanh range: 0.11 -> -0.47, 0.36 ->
#: -0.04, 0.93 -> 0.35 (the defaults 0.25 / 64 would squeeze it into [-1, -0.75]).
PAPER_CPU_FIGURE7 = dict(crop=64, base=32, hdr_scale=0.05, hdr_max=4.0, train_path="train")


def add_training_arguments(ap: argparse.ArgumentParser) -> None:
    """The training settings Figure 7 and the experiments built on it share."""
    ap.add_argument(
        "--preset", default="cpu", choices=("cpu", "paper-cpu"),
        help="cpu: the measured recipe (configurations without positions get no position "
        "features); paper-cpu: the paper's design as the first Figure 7 was run",
    )  # fmt: skip
    ap.add_argument("--chunk", type=int, default=250, help="round-robin step (iterations)")
    ap.add_argument("--crop", type=int, default=None, help="training crop (default: preset's)")
    ap.add_argument("--base", type=int, default=None, help="default: the preset's")
    ap.add_argument("--eval-frames", type=int, default=0, help="0: every test view")
    ap.add_argument("--hdr-scale", type=float, default=None, help="default: the preset's")
    ap.add_argument("--hdr-max", type=float, default=None, help="default: the preset's")
    ap.add_argument(
        "--train-path", default=None,
        help="store path(s) to train on (default: train,cover for cpu, train for paper-cpu)",
    )  # fmt: skip


def train_config(args: argparse.Namespace, inputs: str, **overrides):
    """The preset ``args.preset`` with the settings of :func:`add_training_arguments` (one
    chunk): ``cpu`` with its own crop, width and HDR curve and the coverage views unless given;
    ``paper-cpu`` with :data:`PAPER_CPU_FIGURE7` unless given."""
    from icbtool import gan
    from icbtool.gan.data import resolve_inputs

    preset = getattr(args, "preset", "paper-cpu")
    given = {
        k: getattr(args, k, None) for k in ("crop", "base", "hdr_scale", "hdr_max", "train_path")
    }
    if preset == "cpu":
        fields = {"train_path": "train,cover"}
        if "position" not in resolve_inputs(inputs):
            fields["position_octaves"] = 0
    else:
        fields = dict(PAPER_CPU_FIGURE7)
    fields.update({k: v for k, v in given.items() if v is not None})
    return gan.TrainConfig.preset(
        preset,
        inputs=inputs,
        iterations=args.chunk,
        eval_every=args.chunk,
        checkpoint_every=args.chunk,
        eval_frames=args.eval_frames,
        **{**fields, **overrides},
    )


def last_iteration(run: Path) -> int:
    """The last evaluated iteration of a run directory (0 without evaluations)."""
    p = run / "evals.json"
    if not p.exists():
        return 0
    ev = json.loads(p.read_text())
    ev = ev["evals"] if isinstance(ev, dict) else ev
    return max((int(e["iteration"]) for e in ev), default=0)


def train_round_robin(
    jobs: dict[str, tuple[str | Path, Any, Path]],
    iterations: int,
    chunk: int,
    scene: str,
    after_chunk: Callable[[int], None] | None = None,
) -> None:
    """Train every job to ``chunk`` iterations, then every one to ``2 chunk``, ... up to
    ``iterations`` (resuming; a job already there is skipped), so an interrupted experiment
    always has comparable runs.

    Args:
        jobs: name -> (store directory, TrainConfig, run directory).
        after_chunk: called with the iteration count every job has reached.
    """
    import icbtool.store as S
    from icbtool import gan

    ro = S.StoreConfig(readonly=True, record_hits=False)
    for target in range(chunk, iterations + 1, chunk):
        for store_dir, cfg, run in jobs.values():
            if last_iteration(run) >= target:
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # the once-per-run VGG notice
                with S.open(store_dir, ro) as store:
                    gan.train(store, dataclasses.replace(cfg, iterations=target), run,
                              scene=scene, resume=True)  # fmt: skip
        if after_chunk is not None:
            after_chunk(target)


def noise_ceiling(store_dir: str, ceiling_dir: str, scene: str, exposure: float) -> dict:
    """SSIM / MSE between two independently traced truths of the same test cameras."""
    import icbtool.store as S
    from icbtool import metrics

    ro = S.StoreConfig(readonly=True, record_hits=False)
    with S.open(store_dir, ro) as a, S.open(ceiling_dir, ro) as b:

        def by_index(st: S.Store) -> dict[int, int]:
            return {
                int(i.meta.tags["index"]): i.record_id
                for i in st
                if i.meta.tags.get("path") == "test"
                and scene in (i.meta.scene_name, i.meta.scene_hash)
            }

        ia, ib = by_index(a), by_index(b)
        shared = sorted(set(ia) & set(ib))
        if not shared:
            raise SystemExit(f"{ceiling_dir}: no test camera in common with {store_dir}")
        ssim, mse = [], []
        for k in shared:
            ga, gb = a.get(ia[k]).gi, b.get(ib[k]).gi
            ssim.append(metrics.ssim(ga, gb, exposure))
            mse.append(metrics.mse(ga, gb, exposure))
    return {
        "views": shared,
        "ssim_mean": float(np.mean(ssim)),
        "ssim_min": float(np.min(ssim)),
        "mse_mean": float(np.mean(mse)),
        "ssim_per_view": ssim,
    }


def chosen_run(run: str | None, out: Path, runs: str) -> tuple[Path, float]:
    """The run directory Figures 8 and the time/error study use (``run``, else the best of
    ``out/figure7.json`` in ``runs``) and its display exposure."""
    if run is None:
        f7 = json.loads((out / "figure7.json").read_text())
        path = Path(runs) / f7["summary"]["best"]
    else:
        path = Path(run)
    cfg = json.loads((path / "config.json").read_text())
    return path, float(cfg["train_config"]["display_exposure"])


def curves(runs: Path, configs: str) -> dict[str, dict[str, list[float]]]:
    out = {}
    for c in configs:
        p = runs / c / "evals.json"
        if p.exists():
            ev = json.loads(p.read_text())
            ev = ev["evals"] if isinstance(ev, dict) else ev
            out[c] = {
                "iteration": [int(e["iteration"]) for e in ev],
                "ssim": [float(e["ssim"]) for e in ev],
                "mse": [float(e["mse"]) for e in ev],
            }
    return out


def summarise(cv: dict, target: float) -> dict:
    common = min((max(v["iteration"]) for v in cv.values()), default=0)

    def at(c: str, key: str) -> float | None:
        v = cv[c]
        its = [i for i in v["iteration"] if i <= common]
        return v[key][v["iteration"].index(max(its))] if its else None

    final = {c: {"ssim": at(c, "ssim"), "mse": at(c, "mse")} for c in cv}
    ranked = sorted(
        (c for c in final if final[c]["ssim"] is not None), key=lambda c: -final[c]["ssim"]
    )
    reach = {
        c: next((i for i, s in zip(v["iteration"], v["ssim"]) if s >= target), None)
        for c, v in cv.items()
    }
    pairs = []
    for view, world in NORMAL_PAIRS:
        if view in final and world in final and final[view]["ssim"] is not None:
            d = final[world]["ssim"] - final[view]["ssim"]
            pairs.append({"view": view, "world": world, "ssim_world_minus_view": d})
    return {
        "common_iteration": common,
        "at_common_iteration": final,
        "ranking_by_ssim": ranked,
        "best": ranked[0] if ranked else None,
        "world_vs_view_normals": pairs,
        "target_ssim": target,
        "first_iteration_reaching_target": reach,
    }


def plot(cv: dict, ceiling: dict | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for c, v in sorted(cv.items()):
        ax[0].plot(v["iteration"], v["ssim"], marker=".", label=c)
        ax[1].plot(v["iteration"], v["mse"], marker=".", label=c)
    if ceiling is not None:
        ax[0].axhline(ceiling["ssim_mean"], color="k", ls="--", lw=1, label="truth vs truth")
        ax[1].axhline(ceiling["mse_mean"], color="k", ls="--", lw=1, label="truth vs truth")
    ax[0].axhline(0.88, color="grey", ls=":", lw=1)
    ax[0].set(xlabel="iteration", ylabel="test SSIM (display, 0-255)", title="SSIM")
    ax[1].set(xlabel="iteration", ylabel="test MSE (display, 0-255)", title="MSE", yscale="log")
    ax[0].legend(ncol=2, fontsize=8)
    fig.suptitle("GAN pre-renderer on Sponza, input configurations A-J (ICB Figure 7)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"), required=False)
    ap.add_argument("--ceiling-store", default=os.environ.get("ICBTOOL_GAN_CEILING"))
    ap.add_argument("--scene", default="sponza", help="scene name (or hash) in the store")
    ap.add_argument("--configs", default="ABCDEFGHIJ")
    ap.add_argument("--iterations", type=int, default=2000)
    add_training_arguments(ap)
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: write figure7.json/png from the runs as they are (after a stop)",
    )
    ap.add_argument(
        "--demodulate",
        action="store_true",
        help="learn GI / albedo (TrainConfig.demodulate, our addition); use another --runs/--out",
    )
    ap.add_argument("--target-ssim", type=float, default=0.88)
    ap.add_argument(
        "--score-paths", default="test,walk",
        help="after the last chunk (and with --report-only), every run's generator is scored on "
        "every view of these store paths (held-out views: walk)",
    )  # fmt: skip
    ap.add_argument("--runs", default=str(REPO / "out" / "gan_figure7"), help="run directories")
    add_out_argument(ap, "gan")
    args = ap.parse_args()
    if not args.store:
        raise SystemExit("give --store (or set ICBTOOL_GAN_STORE): a baked Sponza store")

    from icbtool.provenance import run_info, write_json

    out, runs = Path(args.out), Path(args.runs)
    out.mkdir(parents=True, exist_ok=True)
    cfgs = {c: train_config(args, c, demodulate=args.demodulate) for c in args.configs}
    exposure = next(iter(cfgs.values())).display_exposure
    write_json(
        out / "figure7_config.json",
        {"args": vars(args), "train_configs": cfgs, "run": run_info()},
    )
    ceiling = None
    if args.ceiling_store:
        ceiling = noise_ceiling(args.store, args.ceiling_store, args.scene, exposure)
        print(
            f"noise ceiling (truth vs truth, {len(ceiling['views'])} views): "
            f"SSIM {ceiling['ssim_mean']:.4f} (min {ceiling['ssim_min']:.4f})"
        )
    t0 = time.perf_counter()
    if not args.report_only:
        jobs = {c: (args.store, cfg, runs / c) for c, cfg in cfgs.items()}
        train_round_robin(
            jobs,
            args.iterations,
            args.chunk,
            args.scene,
            lambda target: report(runs, args, out, ceiling, t0, target),
        )
    if args.report_only:
        report(runs, args, out, ceiling, t0, None)


def final_scores(runs: Path, args: argparse.Namespace) -> dict:
    """Each run's generator on every view of ``args.score_paths``: {config: {path: {views, ssim,
    mse}, iteration}}."""
    import icbtool.store as S
    from benchmarks.gan_ablation import score

    paths = [p for p in args.score_paths.split(",") if p]
    cfg = train_config(args, args.configs[0])
    out = {}
    with S.open(args.store, S.StoreConfig(readonly=True, record_hits=False)) as store:
        for c in args.configs:
            run = runs / c
            if not (run / "generator.pt").exists():
                continue
            out[c] = {
                "iteration": last_iteration(run),
                **score(store, args.scene, run, paths, cfg.display_exposure),
            }
    return out


def report(runs: Path, args: argparse.Namespace, out: Path, ceiling, t0: float, target) -> None:
    """Write figure7.json / figure7.png from the runs' evaluations and print the ranking."""
    from icbtool.provenance import write_json

    cv = curves(runs, args.configs)
    summary = summarise(cv, args.target_ssim)
    res = {
        "curves": cv,
        "summary": summary,
        "noise_ceiling": ceiling,
        "wall_s_this_invocation": time.perf_counter() - t0,
    }
    if target is None or target >= args.iterations:
        res["final_scores"] = final_scores(runs, args)
        res["load_1min"] = os.getloadavg()[0]
    write_json(out / "figure7.json", res)
    plot(cv, ceiling, out / "figure7.png")
    best = summary["best"]
    print(
        f"[{target or 'as stopped'} iterations] best {best}: SSIM "
        f"{summary['at_common_iteration'][best]['ssim']:.4f}; "
        f"ranking {summary['ranking_by_ssim']}"
    )


if __name__ == "__main__":
    main()
