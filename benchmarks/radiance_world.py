"""World-space GI: the hash-grid irradiance model and the probe volume next to
the trivial baselines, on every view of the test path and of held-out views, with coverage.

Methods (rows), all fitted on the train path's pixels only (``--train-paths``):

- ``constant``: one colour on surfaces, the train pixels' mean GI;
- ``albedo x k``: GI = k * albedo, k per channel by least squares on the train pixels;
- ``probes``: the irradiance probe volume (:class:`icbtool.radiance.ProbeConfig`);
- ``hash grid``: the multi-resolution grid + MLP (:class:`icbtool.radiance.RadianceConfig`),
  trained for ``--iterations`` (resumable: the run directory is reused).

For every evaluation path (``--eval-paths``; those missing from the store are skipped and
named): mean SSIM / MSE (display scale 0-255, :mod:`icbtool.metrics`) and FLIP (LDR, when
flip-evaluator is installed: extra ``metrics``) over ALL its views, and
per view its coverage: the median distance from its surface pixels to the nearest train pixel
(a 200k subsample, scipy cKDTree) as a fraction of the scene's bounding-box diagonal. A binned
plot shows how per-pixel SSIM and GI error depend on that distance; the JSON says which share
of each path's pixels have no train pixel within 1 % / 5 % of the diagonal. Speed: the exported
ONNX model in onnxruntime with 1 thread on 128^2 and 256^2 points (every pixel a surface pixel:
the upper bound), and the bytes a client downloads (the .onnx file).

    nice -n 10 env ICBTOOL_GL_BACKEND=osmesa .venv/bin/python -m benchmarks.radiance_world \\
        --store out/stores/sponza128 --tag sponza128 --levels 8 --iterations 1000

Writes to ``--out`` (default out/bench/radiance; the committed ones: benchmarks/results/radiance)
world_TAG.json, world_TAG_views.csv, world_TAG_strip.png
(per method: prediction | truth | |difference| on the best- and worst-covered test view and a
held-out view) and world_TAG_coverage.png. The 1-minute load average is recorded before and
after (the machine is shared: times are upper bounds).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "radiance"
BINS = np.array([0.0, 0.0025, 0.005, 0.01, 0.02, 0.05, 0.1, 1.0])


def _onnx_ms(path: Path, pos: np.ndarray, nrm: np.ndarray, n: int, repeat: int) -> float:
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    idx = np.arange(n) % len(pos)
    feed = {"position": pos[idx], "normal": nrm[idx]}
    sess.run(None, feed)
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        sess.run(None, feed)
        ts.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--store",
        default=os.environ.get("ICB_STORE"),
        required="ICB_STORE" not in os.environ,
        help='the Sponza store (docs/benchmarks.md, "What held learned GI back")',
    )
    ap.add_argument("--tag", default="sponza128")
    ap.add_argument("--train-paths", default="train")
    ap.add_argument("--eval-paths", default="test,walk")
    ap.add_argument("--work", default="/tmp/icb_radiance_runs", help="run directories")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--batch-size", type=int, default=4096)
    ap.add_argument("--levels", type=int, default=8)
    ap.add_argument("--log2-table", type=int, default=15)
    ap.add_argument("--probe-resolution", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=20, help="timed onnxruntime runs")
    add_out_argument(ap, "radiance")
    args = ap.parse_args()
    global OUT
    OUT = args.out

    import torch

    import icbtool.store as S
    from icbtool import metrics
    from icbtool.imageio import to_display, write_png
    from icbtool.provenance import run_info, write_json
    from icbtool.radiance.coverage import TrainCoverage
    from icbtool.radiance.data import pixels_from_records, records_of_path
    from icbtool.radiance.model import RadianceModel
    from icbtool.radiance.training import (
        ProbeConfig,
        RadianceConfig,
        load_views,
        predict_view,
        train,
    )

    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    train_paths = tuple(p for p in args.train_paths.split(",") if p)
    work = Path(args.work) / args.tag
    OUT.mkdir(parents=True, exist_ok=True)
    results: dict = {"config": vars(args), "load_1min_before": load_before, "run": run_info()}
    with S.open(args.store, S.StoreConfig(readonly=True)) as st:
        eval_paths, skipped = [], []
        for p in args.eval_paths.split(","):
            (eval_paths if records_of_path(st, p) else skipped).append(p)
        results["eval_paths"], results["eval_paths_missing"] = eval_paths, skipped
        train_ids = [r for p in train_paths for r in records_of_path(st, p)]
        samples = pixels_from_records(st, train_ids)
        views = {p: load_views(st, records_of_path(st, p)) for p in eval_paths}
        meta_bounds = st.info(train_ids[0]).meta.scene_bounds
        if meta_bounds is not None:
            diag = float(np.linalg.norm(np.subtract(meta_bounds[1], meta_bounds[0])))
        else:  # the surfaces seen by any view
            allp = np.concatenate([samples.position] + [v.position for vs in views.values()
                                                          for v in vs])  # fmt: skip
            diag = float(np.linalg.norm(allp.max(0) - allp.min(0)))
        results["scene_diagonal"] = diag
        results["train_records"], results["train_pixels"] = len(train_ids), len(samples)

        # -- baselines (closed form on the train pixels)
        a, g = samples.albedo.astype(np.float64), samples.gi.astype(np.float64)
        const = g.mean(0).astype(np.float32)
        k = ((a * g).sum(0) / (a * a).sum(0)).astype(np.float32)
        results["constant_colour"], results["albedo_k"] = const.tolist(), k.tolist()

        # -- the two world-space models
        t0 = time.perf_counter()
        probe_dir = work / f"probes_r{args.probe_resolution}"
        if not (probe_dir / "radiance.pt").exists():
            train(st, ProbeConfig(resolution=args.probe_resolution, train_paths=train_paths,
                                  eval_paths=()), probe_dir, progress=False)  # fmt: skip
        # reading the train records + the least-squares fit
        results["probe_fit_s"] = json.loads((probe_dir / "config.json").read_text())["fit_seconds"]
        grid_cfg = RadianceConfig(
            iterations=args.iterations,
            batch_size=args.batch_size,
            levels=args.levels,
            log2_table=args.log2_table,
            train_paths=train_paths,
            eval_paths=(),
            checkpoint_every=250,
            eval_every=10**9,
        )
        grid_dir = work / f"grid_i{args.iterations}_b{args.batch_size}_l{args.levels}"
        t0 = time.perf_counter()
        res = train(st, grid_cfg, grid_dir, resume=True, progress=True)
        results["grid_train_s_this_call"] = time.perf_counter() - t0
        results["grid_train_s_total"] = res.seconds
        models = {
            "hash grid": RadianceModel.load(grid_dir),
            "probes": RadianceModel.load(probe_dir),
        }

        def make(name: str, v) -> np.ndarray:
            s = v.surface[..., None]
            if name == "constant":
                return np.where(s, const, 0.0).astype(np.float32)
            if name == "albedo x k":
                return np.where(s, v.albedo * k, 0.0).astype(np.float32)
            return predict_view(models[name], v)

        names = ["hash grid", "probes", "albedo x k", "constant"]

        # -- coverage and scores
        cov = TrainCoverage(samples.position, diag)
        try:
            import flip_evaluator  # noqa: F401

            has_flip = True
        except ImportError:  # extra "metrics": the FLIP column is left out, and said so
            has_flip = False
        results["flip"] = "on (LDR, display transform)" if has_flip else "off: no flip-evaluator"
        rows, per_pixel = [], {n: {p: [] for p in eval_paths} for n in names}
        dist_px = {p: [] for p in eval_paths}
        for p in eval_paths:
            for i, v in enumerate(views[p]):
                d_map = np.full(v.surface.shape, np.nan)
                d_map[v.surface] = cov.distances(v.position)
                dist_px[p].append(d_map[v.surface])
                row = {"path": p, "view": i, "record": v.record_id,
                       "coverage": float(np.nanmedian(d_map))}  # fmt: skip
                for n in names:
                    pred = make(n, v)
                    row[f"{n}_ssim"] = metrics.ssim(pred, v.gi)
                    row[f"{n}_mse"] = metrics.mse(pred, v.gi)
                    if has_flip:
                        row[f"{n}_flip"] = metrics.flip(v.gi, pred)
                    smap = metrics.ssim_map(pred, v.gi, padding="same")
                    err = np.abs(to_display(pred).astype(float) - to_display(v.gi)).mean(-1)
                    per_pixel[n][p].append((d_map[v.surface], smap[v.surface], err[v.surface]))
                rows.append(row)
        table = {}
        for n in names:
            table[n] = {}
            for p in eval_paths:
                sel = [r for r in rows if r["path"] == p]
                table[n][p] = {
                    "views": len(sel),
                    "ssim": float(np.mean([r[f"{n}_ssim"] for r in sel])),
                    "mse": float(np.mean([r[f"{n}_mse"] for r in sel])),
                }
                if has_flip:
                    table[n][p]["flip"] = float(np.mean([r[f"{n}_flip"] for r in sel]))
        results["table"] = table
        results["coverage"] = {
            p: {
                "median_view_coverage": float(
                    np.median([r["coverage"] for r in rows if r["path"] == p])
                ),  # fmt: skip
                "share_pixels_beyond_1pct": float(np.mean(np.concatenate(dist_px[p]) > 0.01)),
                "share_pixels_beyond_5pct": float(np.mean(np.concatenate(dist_px[p]) > 0.05)),
            }
            for p in eval_paths
        }
        binned = {}
        for n in names:
            binned[n] = {}
            for p in eval_paths:
                d = np.concatenate([t[0] for t in per_pixel[n][p]])
                s_ = np.concatenate([t[1] for t in per_pixel[n][p]])
                e_ = np.concatenate([t[2] for t in per_pixel[n][p]])
                b = np.digitize(d, BINS) - 1
                binned[n][p] = [
                    {"lo": float(BINS[j]), "hi": float(BINS[j + 1]), "pixels": int((b == j).sum()),
                     "ssim": float(s_[b == j].mean()) if (b == j).any() else None,
                     "abs_err_255": float(e_[b == j].mean()) if (b == j).any() else None}
                    for j in range(len(BINS) - 1)
                ]  # fmt: skip
        results["binned_by_coverage"] = binned

        # -- speed and bytes (onnxruntime, 1 thread)
        test_v = views[eval_paths[0]] if eval_paths else []
        pos = np.concatenate([v.position for v in test_v]).astype(np.float32)
        nrm = np.concatenate([v.normal for v in test_v]).astype(np.float32)
        speed = {}
        for n, m in models.items():
            onnx_path = work / f"{n.replace(' ', '_')}.onnx"
            m.export_onnx(onnx_path)
            speed[n] = {
                "onnx_bytes": onnx_path.stat().st_size,
                "parameter_bytes": m.nbytes,
                "ms_128": _onnx_ms(onnx_path, pos, nrm, 128 * 128, args.repeat),
                "ms_256": _onnx_ms(onnx_path, pos, nrm, 256 * 256, args.repeat),
            }
        speed["albedo x k"] = {"onnx_bytes": 12, "parameter_bytes": 12}
        speed["constant"] = {"onnx_bytes": 12, "parameter_bytes": 12}
        results["speed"] = speed

        # -- strip: best- and worst-covered test view, first held-out view
        picks = []
        if eval_paths:
            sel = [r for r in rows if r["path"] == eval_paths[0]]
            picks += [min(sel, key=lambda r: r["coverage"]), max(sel, key=lambda r: r["coverage"])]
            for p in eval_paths[1:2]:
                picks.append([r for r in rows if r["path"] == p][0])
        strips = []
        for r in picks:
            v = views[r["path"]][r["view"]]
            truth = to_display(v.gi)
            d_map = np.zeros(v.surface.shape)
            d_map[v.surface] = cov.distances(v.position)
            heat = (np.clip(d_map / 0.05, 0, 1)[..., None] * [255, 64, 0]).astype(np.uint8)
            line = []
            for n in names:
                pred = to_display(make(n, v))
                diff = np.abs(pred.astype(np.int16) - truth.astype(np.int16)).astype(np.uint8)
                line.append(np.concatenate([pred, truth, diff], 1))
            line.append(np.concatenate([heat, truth, np.zeros_like(truth)], 1))
            strips.append(np.concatenate(line, 1))
            sep = np.full((2, strips[-1].shape[1], 3), 255, np.uint8)
            strips.append(sep)
        if strips:
            write_png(OUT / f"world_{args.tag}_strip.png", np.concatenate(strips[:-1], 0))
        results["strip"] = {
            "rows": [f"{r['path']} view {r['view']} (coverage {r['coverage']:.4f})" for r in picks],
            "columns": [f"{n}: prediction | truth | |difference|" for n in names]
            + ["coverage distance (red = 5 % of the diagonal or more) | truth"],
        }
    results["load_1min_after"] = os.getloadavg()[0]
    write_json(OUT / f"world_{args.tag}.json", results)
    with open(OUT / f"world_{args.tag}_views.csv", "w", newline="") as f:
        if rows:
            w = csv.DictWriter(f, list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    _plot(OUT / f"world_{args.tag}_coverage.png", binned, rows, names, eval_paths)
    for n in names:
        line = "  ".join(
            f"{p}: SSIM {table[n][p]['ssim']:.3f} MSE {table[n][p]['mse']:.0f} "
            f"FLIP {table[n][p].get('flip', float('nan')):.3f}"
            for p in eval_paths
        )
        print(f"{n:>11}: {line}  {speed.get(n, {})}")
    print("coverage:", results["coverage"])


def _plot(path: Path, binned: dict, rows: list, names: list, paths: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for n in names:
        for p, ls in zip(paths, ["-", "--", ":"]):
            b = [r for r in binned[n][p] if r["pixels"] > 200]
            x = [100 * (r["lo"] + r["hi"]) / 2 if r["hi"] < 1 else 100 * r["lo"] * 2 for r in b]
            ax[0].plot(x, [r["ssim"] for r in b], ls, marker="o", label=f"{n} ({p})")
            ax[1].plot(x, [r["abs_err_255"] for r in b], ls, marker="o", label=f"{n} ({p})")
    for p, mk in zip(paths, ["o", "s", "^"]):
        sel = [r for r in rows if r["path"] == p]
        for n in names[:2]:
            ax[2].scatter([100 * r["coverage"] for r in sel], [r[f"{n}_ssim"] for r in sel],
                          marker=mk, label=f"{n} ({p})", s=14)  # fmt: skip
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    for a in ax[:2]:
        a.set_xscale("log")
        a.xaxis.set_major_formatter(ScalarFormatter())
        a.xaxis.set_minor_formatter(NullFormatter())
    ax[0].set_xlabel("distance to nearest train pixel (% of scene diagonal, bin centre)")
    ax[1].set_xlabel(ax[0].get_xlabel())
    ax[0].set_ylabel("mean per-pixel SSIM")
    ax[1].set_ylabel("mean |error| (0-255)")
    ax[2].set_xlabel("view coverage: median distance (% of diagonal)")
    ax[2].set_ylabel("view SSIM")
    for a in ax:
        a.legend(fontsize=6)
        a.grid(alpha=0.3)
    fig.suptitle("World-space GI: quality vs distance to the train pixels")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
