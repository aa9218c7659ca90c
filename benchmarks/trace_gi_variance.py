"""Where the GI's noise comes from, and what the tracer's path knobs buy at equal CPU time.

``trace_error_split.py`` shows that FLIP (and most of the RMSE) is the GI's noise. This script
goes one level down, with the default sampler at 1 spp (a pixel's one sample is uniformly
distributed under every sampler, so the variance per pixel is the estimator's own):

- **The variance per pixel across seeds** of the GI (linear RGB) and of the full image after the
  display transform (what FLIP sees: dark pixels weigh more), mean over pixels, for the default
  config and for one knob changed at a time: Russian roulette from other depths
  (``rr_depth``; ``rr_depth`` = ``max_depth`` turns it off within the path limit) and branching
  after the first vertex (``gi_splits``).
- **Its process CPU time** per render (median over seeds; renders of all configs interleaved, so a
  busy spell of the machine hits them alike).
- **Efficiency** at equal CPU time, relative to the default: (V_default T_default) / (V T) (> 1:
  the knob gives less noise for the same time).
- **Where the GI's variance lies**: with ``gi_splits`` = k, a sample's k branches share its camera
  ray, first hit and the light sampled there, and each has its own bounce and all that follows.
  The variance they share is at most V(k) for every k, so V(4) / V(1) bounds the share of the
  camera ray and first hit from above (the default sampler stratifies a sample's branches
  against each other, so V(k) can fall faster than 1 / k).

    .venv/bin/python -m benchmarks.trace_gi_variance [--size 256] [--seeds 32] \
        [--scenes cornell_box,sponza]

Writes --out/gi_variance.{json,png} (the 1-minute load at start and end).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

import numpy as np
from tqdm import tqdm

import icbtool as icb
from benchmarks.common import add_out_argument
from benchmarks.trace_time_error import MAX_DEPTH, bench_scene, write_results
from icbtool.imageio import to_display
from icbtool.trace import TraceConfig

DEFAULT = "default (rr_depth 4, gi_splits 1)"
NO_ROULETTE = f"no roulette (rr_depth {MAX_DEPTH})"
#: (label, TraceConfig changes from the default); the first is the baseline
CONFIGS: list[tuple[str, dict]] = [
    (DEFAULT, {}),
    ("rr_depth 2", dict(rr_depth=2)),
    ("rr_depth 3", dict(rr_depth=3)),
    ("rr_depth 6", dict(rr_depth=6)),
    (NO_ROULETTE, dict(rr_depth=MAX_DEPTH)),
    ("gi_splits 2", dict(gi_splits=2)),
    ("gi_splits 4", dict(gi_splits=4)),
]
SPLIT_LABELS = {1: DEFAULT, 2: "gi_splits 2", 4: "gi_splits 4"}


class _Moments:
    """Per-pixel sums for the variance across seeds (float64: 32 seeds of values <= ~10)."""

    def __init__(self) -> None:
        self.n = 0
        self.s: np.ndarray | None = None
        self.s2: np.ndarray | None = None

    def add(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64)
        if self.s is None:
            self.s, self.s2 = np.zeros_like(x), np.zeros_like(x)
        self.s += x
        self.s2 += x * x
        self.n += 1

    def mean_variance(self) -> float:
        """Mean over pixels and channels of the unbiased variance across the added images."""
        m = self.s / self.n
        return float(np.mean((self.s2 - self.n * m * m) / (self.n - 1)))


def measure(name: str, size: int, seeds: int, spp: int) -> dict:
    scene = bench_scene(name)
    cam = scene.default_camera.resized(size, size)
    base = dict(spp=spp, max_depth=MAX_DEPTH, rr_depth=4)
    cfgs = [(label, TraceConfig(**{**base, **change})) for label, change in CONFIGS]
    for _, cfg in cfgs:  # warm-up (kernel compile or cache load), not counted
        icb.trace.render(scene, cam, cfg)
    gi = {label: _Moments() for label, _ in cfgs}
    disp = {label: _Moments() for label, _ in cfgs}
    cpu: dict[str, list[float]] = {label: [] for label, _ in cfgs}
    bar = tqdm(total=seeds * len(cfgs), desc=f"{name} 1 spp x {seeds} seeds", leave=False)
    for seed in range(seeds):
        for label, cfg in cfgs:  # interleaved: the machine's slow spells hit every config
            c0 = time.process_time()
            r = icb.trace.render(scene, cam, replace(cfg, seed=7000 + seed))
            cpu[label].append(time.process_time() - c0)
            gi[label].add(r.gi)
            disp[label].add(to_display(r.full).astype(np.float64) / 255.0)
            bar.update()
    bar.close()
    rows = []
    for label, _ in cfgs:
        v_gi, v_d, t = gi[label].mean_variance(), disp[label].mean_variance(), cpu[label]
        rows.append({"config": label, "gi_variance": v_gi, "display_variance": v_d,
                     "cpu_s_median": float(np.median(t)), "cpu_s_all": t})  # fmt: skip
    b = rows[0]
    for row in rows:
        t_rel = row["cpu_s_median"] / b["cpu_s_median"]
        row["cpu_rel"] = t_rel
        row["gi_variance_rel"] = row["gi_variance"] / b["gi_variance"]
        row["display_variance_rel"] = row["display_variance"] / b["display_variance"]
        row["gi_efficiency_rel"] = 1.0 / (row["gi_variance_rel"] * t_rel)
        row["display_efficiency_rel"] = 1.0 / (row["display_variance_rel"] * t_rel)
    by = {r["config"]: r for r in rows}
    off = by[NO_ROULETTE]
    return {
        "size": size,
        "spp": spp,
        "rows": rows,
        "baseline": DEFAULT,
        # V(k) >= the variance shared by a sample's k branches, for every k: so V(4) / V(1)
        # bounds the share of the camera ray, first hit and its light sample from above
        "gi_variance_divided_by_splits": {
            str(k): b["gi_variance"] / by[lab]["gi_variance"] for k, lab in SPLIT_LABELS.items()
        },
        "shared_share_at_most": by[SPLIT_LABELS[4]]["gi_variance"] / b["gi_variance"],
        "roulette_added_gi_variance": b["gi_variance"] / off["gi_variance"] - 1.0,
    }


def plot(results: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["scenes"])
    fig, axes = plt.subplots(1, len(names), figsize=(6.5 * len(names), 4.2), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        rows = results["scenes"][name]["rows"]
        x = np.arange(len(rows))
        w = 0.21
        for i, (key, lab) in enumerate(
            [
                ("gi_variance_rel", "GI variance"),
                ("cpu_rel", "CPU time"),
                ("gi_efficiency_rel", "efficiency, GI (1 / variance x time)"),
                ("display_efficiency_rel", "efficiency, full image after the display transform"),
            ]
        ):
            ax.bar(x + (i - 1.5) * w, [r[key] for r in rows], w, label=lab)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xticks(x, [r["config"].split(" (")[0] for r in rows], rotation=30, ha="right")
        ax.set_ylabel("relative to the default config")
        ax.set_title(f"{name}: 1 spp, {results['args']['seeds']} seeds")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seeds", type=int, default=32)
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the JSON only")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    if args.replot:
        plot(json.loads((args.out / "gi_variance.json").read_text()), args.out / "gi_variance.png")
        return
    if args.seeds < 2:
        ap.error("--seeds must be >= 2 (a variance across seeds)")
    out = {"args": vars(args), "load_average_start": list(os.getloadavg()), "scenes": {}}
    for name in args.scenes.split(","):
        res = measure(name, args.size, args.seeds, 1)
        out["scenes"][name] = res
        print(
            f"{name}: at most {100 * res['shared_share_at_most']:.0f} % of the GI's variance is "
            f"shared by a sample's branches (camera ray, first hit); roulette from depth 4 adds "
            f"{100 * res['roulette_added_gi_variance']:.0f} %",
            flush=True,
        )
        for r in res["rows"]:
            print(
                f"  {r['config']:<36} GI var x{r['gi_variance_rel']:.3f}  display var "
                f"x{r['display_variance_rel']:.3f}  CPU x{r['cpu_rel']:.3f}  efficiency GI "
                f"x{r['gi_efficiency_rel']:.3f}, display x{r['display_efficiency_rel']:.3f}",
                flush=True,
            )
    out["load_average_end"] = list(os.getloadavg())
    write_results(out, "gi_variance.json", args.out)
    plot(out, args.out / "gi_variance.png")
    print(f"wrote {args.out / 'gi_variance.png'}")


if __name__ == "__main__":
    main()
