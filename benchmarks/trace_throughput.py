"""Rays per second of the path tracer (primary, bounce, shadow) next to raw Embree on the same rays.

The tracer runs once normally (timed, 2 threads) and once more, single-threaded, recording every
ray it traces (``render(..., ray_log=...)``: same seed, so the same rays). The recorded rays are
then replayed through Embree alone, two ways: embreex's batched ``scene.run`` (EmbreeScene, 2
threads) and the tracer's own direct Embree calls without shading (icbtool.trace.rtc, 2 threads).
The difference between the tracer's time and the replay is the cost of our shading code.

    .venv/bin/python -m benchmarks.trace_throughput [--size 256] [--spp 8]

Writes --out/throughput.{json,png}.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, sponza, write_json
from icbtool.scene.raycast import EmbreeScene
from icbtool.trace import TraceConfig
from icbtool.trace import kernels as K
from icbtool.trace.rtc import RtcScene

REPO = Path(__file__).resolve().parents[1]
#: ray kinds of the tracer's ray log
KINDS = (("primary", 0), ("bounce", 2), ("shadow", 1))
OUT = REPO / "benchmarks" / "results" / "trace"


def write_profile_results(
    out_name: str, cfg: TraceConfig, args: argparse.Namespace, load_start, rows: list, method: str
) -> tuple[Path, tuple[float, float, float]]:
    """A per-scene study's results as ``<args.out>/<out_name>.json``: its config,
    arguments, method (the script's docstring), rows, the load averages at start and now, and
    this machine's run info. Returns the file and the load averages now."""
    out_dir = Path(getattr(args, "out", OUT))
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{out_name}.json"
    load_end = os.getloadavg()
    write_json(
        path,
        {
            "config": cfg,
            "args": vars(args),
            "load_average_start": load_start,
            "load_average_end": load_end,
            "method": method,
            "results": rows,
            "run_info": run_info(),
        },
    )
    return path, load_end


def ray_log(scene, cam, cfg, capacity: int) -> tuple[dict[str, np.ndarray], int]:
    """Every ray of one render in tracing order (the tracer's ``ray_log``: o, d, tfar, kind)
    and how many there are."""
    log = icb.trace.ray_log_buffers(capacity)
    icb.trace.render(scene, cam, cfg, ray_log=log)
    n = int(log["n"][0])
    if n >= capacity:
        raise RuntimeError(f"ray log full ({capacity} rays): raise the capacity")
    return log, n


def record(scene, cam, cfg, capacity: int) -> dict[str, dict[str, np.ndarray]]:
    """The rays of one render by kind (primary, bounce, shadow): contiguous o, d (N, 3) and
    tfar (N,) float32, in tracing order within each kind."""
    log, n = ray_log(scene, cam, cfg, capacity)
    sel = {name: log["kind"][:n] == kind for name, kind in KINDS}
    return {
        name: {k: np.ascontiguousarray(log[k][:n][m]) for k in ("o", "d", "tfar")}
        for name, m in sel.items()
    }


def n_rays(rays: dict[str, dict[str, np.ndarray]]) -> int:
    return sum(len(r["tfar"]) for r in rays.values())


def replay_embreex(es: EmbreeScene, rays: dict, threads: int = 2) -> dict[str, float]:
    """Seconds embreex needs for each kind of :func:`record`'s rays."""
    out = {}
    for name, r in rays.items():
        t0 = time.perf_counter()
        if name == "shadow":
            es.occluded_raw(r["o"], r["d"], r["tfar"].copy(), threads)
        else:
            es.intersect_raw(r["o"], r["d"], threads)
        out[name] = time.perf_counter() - t0
    return out


def replay_direct(rs: RtcScene, rays: dict, threads: int = 2) -> dict[str, float]:
    """Seconds the tracer's direct Embree calls need for each kind of rays (no shading)."""
    pool = ThreadPoolExecutor(threads)
    out = {}
    for name, r in rays.items():
        o, d, tf = r["o"], r["d"], r["tfar"]
        n = len(o)
        edges = np.linspace(0, n, threads + 1).astype(np.int64)
        parts = [(int(edges[i]), int(edges[i + 1])) for i in range(threads)]
        t0 = time.perf_counter()
        if name == "shadow":
            blocked = np.empty(n, np.bool_)
            args = (K.rtc_occluded_batch, rs.ptr, rs.fn_occluded, o, d, tf, blocked)
        else:
            t, prim = np.empty(n, np.float32), np.empty(n, np.int32)
            u, v = np.empty(n, np.float32), np.empty(n, np.float32)
            args = (K.rtc_intersect_batch, rs.ptr, rs.fn_intersect, o, d, t, prim, u, v)
        for f in [pool.submit(*args, lo, hi) for lo, hi in parts]:
            f.result()
        out[name] = time.perf_counter() - t0
    pool.shutdown()
    return out


def bench(scene, cam, cfg, repeats: int = 3) -> dict:
    t0 = time.perf_counter()
    icb.trace.render(scene, cam, replace(cfg, spp=1))  # warm-up (JIT cache, scene data, BVH)
    warmup_s = time.perf_counter() - t0
    runs = [icb.trace.render(scene, cam, cfg) for _ in range(repeats)]
    res = min(runs, key=lambda r: r.stats.time_s["total"])
    st = res.stats
    rays = record(scene, cam, cfg, capacity=int(st.total_rays * 1.05) + 1024)
    n_logged = n_rays(rays)
    es = EmbreeScene.from_scene(scene, robust=cfg.robust, threads=2)
    rs = RtcScene.of(scene, robust=cfg.robust)
    emb = min((replay_embreex(es, rays) for _ in range(repeats)), key=lambda x: sum(x.values()))
    dirc = min((replay_direct(rs, rays) for _ in range(repeats)), key=lambda x: sum(x.values()))
    total_rays = st.total_rays
    t_trace = st.time_s["total"]
    return {
        "scene": scene.name,
        "size": [cam.height, cam.width],
        "triangles": scene.n_triangles,
        "spp": cfg.spp,
        "warmup_render_s": warmup_s,
        "load_average_1min": os.getloadavg()[0],
        "tracer_total_s": t_trace,
        "tracer_time_s": st.time_s,
        "rays": st.rays,
        "rays_logged_for_replay": n_logged,
        "tracer_Mrays_per_s": total_rays / t_trace / 1e6,
        "embreex_replay_s": emb,
        "embreex_replay_Mrays_per_s": n_logged / sum(emb.values()) / 1e6,
        # the kinds the ray log replays (the edge probes run before the first sample, unlogged)
        "embreex_replay_by_kind_Mrays_per_s": {k: st.rays[k] / emb[k] / 1e6 for k in emb},
        "direct_embree_replay_by_kind_Mrays_per_s": {k: st.rays[k] / dirc[k] / 1e6 for k in dirc},
        "direct_embree_replay_s": dirc,
        "direct_embree_replay_Mrays_per_s": n_logged / sum(dirc.values()) / 1e6,
        "embree_share_of_tracer_time": sum(dirc.values()) / t_trace,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--sampler", default="sobol", choices=["sobol", "independent"])
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    load_start = os.getloadavg()
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
                    "embreex_replay_Mrays_per_s",
                    "direct_embree_replay_Mrays_per_s",
                    "embree_share_of_tracer_time",
                )
            },
        )
        rows.append(row)
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(
        OUT / "throughput.json",
        {
            "config": cfg,
            "args": vars(args),
            "load_average_start": list(load_start),
            "quiet": load_start[0] < 1.0,
            "results": rows,
            "run_info": run_info(),
        },
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    x = np.arange(len(rows))
    ax.bar(
        x - 0.27,
        [r["tracer_Mrays_per_s"] for r in rows],
        0.27,
        label="tracer (all rays, incl. shading)",
    )
    ax.bar(
        x,
        [r["direct_embree_replay_Mrays_per_s"] for r in rows],
        0.27,
        label="Embree alone (direct calls)",
    )
    ax.bar(
        x + 0.27, [r["embreex_replay_Mrays_per_s"] for r in rows], 0.27, label="embreex scene.run"
    )
    ax.set_xticks(x, [f"{r['scene']}\n{r['triangles']} tris" for r in rows])
    ax.set_ylabel("Mrays/s (2 threads)")
    ax.set_title(f"{args.size}x{args.size}, {args.spp} spp, max_depth 8")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "throughput.png", dpi=100)
    print(f"wrote {OUT / 'throughput.json'}")


if __name__ == "__main__":
    main()
