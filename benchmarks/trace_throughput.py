"""Rays per second of the path tracer (primary, bounce, shadow) next to raw Embree on the same rays.

The tracer runs once with a recording EmbreeScene; the recorded ray batches are then replayed
through EmbreeScene alone, so the difference is the cost of our shading code (numpy).

    .venv/bin/python benchmarks/trace_throughput.py [--size 256] [--spp 8]

Writes benchmarks/results/trace/throughput.{json,png}.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import icbtool as icb
from icbtool.cli._common import run_info, write_json
from icbtool.trace import TraceConfig
from icbtool.trace.embree import EmbreeScene

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"


def sponza():
    os.environ.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    return icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")


class Recorder:
    """Wraps an EmbreeScene, keeping every batch (kind, origins, directions, tfar)."""

    def __init__(self, es: EmbreeScene) -> None:
        self.es, self.log = es, []
        self.first = True

    def intersect(self, o, d, tnear=0.0, tfar=None, threads=None):
        self.log.append(("intersect", np.array(o, np.float32), np.array(d, np.float32), None))
        return self.es.intersect(o, d, tnear, tfar, threads)

    def intersect_raw(self, o, d, threads=None, out=None):
        self.log.append(("intersect", np.array(o, np.float32), np.array(d, np.float32), None))
        return self.es.intersect_raw(o, d, threads, out=out)

    def occluded_raw(self, o, d, tfar, threads=None):
        self.log.append(
            ("occluded", np.array(o, np.float32), np.array(d, np.float32), np.array(tfar))
        )
        return self.es.occluded_raw(o, d, tfar, threads)

    def occluded(self, o, d, tfar, threads=None):
        self.log.append(
            (
                "occluded",
                np.array(o, np.float32),
                np.array(d, np.float32),
                np.array(tfar, np.float32),
            )
        )
        return self.es.occluded(o, d, tfar, threads)


def bench(scene, cam, cfg) -> dict:
    from icbtool.trace import tracer as tr

    es = EmbreeScene.from_scene(scene, robust=cfg.robust, threads=cfg.threads)
    rec = Recorder(es)
    key = f"embree_robust={cfg.robust}"
    t0 = time.perf_counter()
    res = icb.trace.render(scene, cam, replace(cfg, spp=1))  # warm-up (JIT cache, scene data)
    warmup_s = time.perf_counter() - t0
    scene._cache[key] = rec
    try:
        res = tr.render(scene, cam, cfg)
    finally:
        scene._cache[key] = es
    st = res.stats
    t0 = time.perf_counter()
    kinds = {"primary": 0.0, "bounce": 0.0, "shadow": 0.0}
    counts = {"primary": 0, "bounce": 0, "shadow": 0}
    first_per_pass = True
    for kind, o, d, tf in rec.log:
        t1 = time.perf_counter()
        if kind == "intersect":
            es.intersect_raw(o, d)
        else:
            es.occluded_raw(o, d, tf.copy())
        dt = time.perf_counter() - t1
        if kind == "occluded":
            name = "shadow"
        else:
            # the first intersect batch of each pass is the primary rays: their count is H*W*k
            name = "primary" if first_per_pass else "bounce"
        if kind == "intersect":
            first_per_pass = False
        kinds[name] += dt
        counts[name] += len(o)
        if kind == "intersect" and len(o) == 0:
            first_per_pass = True
    replay = time.perf_counter() - t0
    # primary/bounce split is not marked in the log across passes: use the tracer's own counts
    total_rays = st.total_rays
    return {
        "scene": scene.name,
        "size": [cam.height, cam.width],
        "triangles": scene.n_triangles,
        "spp": cfg.spp,
        "warmup_render_s": warmup_s,
        "load_average_1min": os.getloadavg()[0],
        "tracer_total_s": st.time_s["total"],
        "tracer_time_s": st.time_s,
        "rays": st.rays,
        "tracer_Mrays_per_s": total_rays / st.time_s["total"] / 1e6,
        "embree_replay_s": replay,
        "embree_replay_Mrays_per_s": total_rays / replay / 1e6,
        "embree_share_of_tracer_time": replay / st.time_s["total"],
        "replay_by_kind_Mrays_per_s": {
            "intersect": (st.rays["primary"] + st.rays["bounce"])
            / max(kinds["primary"] + kinds["bounce"], 1e-9)
            / 1e6,
            "shadow": st.rays["shadow"] / max(kinds["shadow"], 1e-9) / 1e6,
        },
        "tracer_by_kind_Mrays_per_s_embree_only": {
            "intersect": (st.rays["primary"] + st.rays["bounce"])
            / max(st.time_s.get("intersect", 0), 1e-9)
            / 1e6,
            "shadow": st.rays["shadow"] / max(st.time_s.get("shadow", 0), 1e-9) / 1e6,
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--sampler", default="sobol", choices=["sobol", "independent"])
    args = ap.parse_args()
    cfg = TraceConfig(spp=args.spp, spp_per_pass=4, max_depth=8, seed=0, sampler=args.sampler)
    rows = []
    scenes = [("cornell_box", icb.scene.cornell_box)]
    try:
        sp = sponza()
        scenes.append(("sponza", lambda: sp))
    except (FileNotFoundError, ValueError) as e:
        print(f"Sponza unavailable: {e}")
    for name, make in scenes:
        scene = make()
        cam = scene.default_camera.resized(args.size, args.size)
        row = bench(scene, cam, cfg)
        print(
            name,
            {
                k: row[k]
                for k in (
                    "tracer_Mrays_per_s",
                    "embree_replay_Mrays_per_s",
                    "embree_share_of_tracer_time",
                )
            },
        )
        rows.append(row)
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(
        OUT / "throughput.json",
        {"config": cfg, "args": vars(args), "results": rows, "run_info": run_info()},
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    x = np.arange(len(rows))
    ax.bar(
        x - 0.2,
        [r["tracer_Mrays_per_s"] for r in rows],
        0.4,
        label="tracer (all rays, incl. shading)",
    )
    ax.bar(x + 0.2, [r["embree_replay_Mrays_per_s"] for r in rows], 0.4, label="EmbreeScene replay")
    ax.set_xticks(x, [f"{r['scene']}\n{r['triangles']} tris" for r in rows])
    ax.set_ylabel("Mrays/s (2 threads)")
    ax.set_title(f"{args.size}x{args.size}, {args.spp} spp, max_depth 8")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "throughput.png", dpi=100)
    print(f"wrote {OUT / 'throughput.json'}")


if __name__ == "__main__":
    main()
