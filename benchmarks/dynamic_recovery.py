"""Recovery after scene changes: the invalidation rule against a stale cache, full invalidation
and DL only, on the moving-light Cornell box along its test path.

A client follows the Cornell box's test camera path at ``--speed`` times its pace (slowly, so
that the cache serves and old records are met again) for the 6 s of the scene's timeline while
the ceiling light of ``cornell_box_moving_light`` moves. Two timelines:

* ``steps``: the scene time jumps between the animation's key times (light home, +0.45 m, -0.45
  m, home again) and holds in between, so each change is one step and the frames until
  recovery after it can be counted;
* ``continuous``: the scene time is the path time (the light slides from 0 s to 4 s and rests
  after): every frame during the motion is a change.

Every frame is scored against the truth at the current state (a path-traced image of the scene
at that time, ``--truth-spp``): SSIM and FLIP of the final frame. Methods (one cloud and one
client each, same requests, T_IL = ``--latency``):

* ``rule``: ``CloudConfig(invalidation="rule")``: a stale record serves marked while a cheap
  (``--cheap-spp``, denoised) render replaces it, refined to ``--spp`` when met again;
* ``full``: ``invalidation="all"``: any change makes a record a miss, re-rendered at ``--spp``
  when requested (lazy: a stronger baseline than re-rendering the whole cache at each change);
* ``stale``: ``invalidation="none"``: records serve whatever their state;
* ``dl_only``: the client's direct light alone;
* ``oracle`` (the steady state): ``full``, asked at the frame's own scene time (no T_IL between
  the change and the request): what ICB shows when its cache holds the current state.

Recovery after a change at frame c: the first frame from which the method's SSIM stays within
``--tolerance`` of the oracle's until the next change (None: never). Cloud cost: renders,
render seconds and samples per pixel x pixels rendered; bytes: each reply's reference encoded
with the network's default codecs.

    .venv/bin/python -m benchmarks.dynamic_recovery --out benchmarks/results/dynamic
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import add_out_argument, load_average, write_results

METHODS = ("rule", "full", "stale", "oracle")
INVALIDATION = {"rule": "rule", "full": "all", "stale": "none", "oracle": "all"}
#: Length of the run in scene time (s): the light moves until 4 s, then rests.
SCENE_S = 6.0
#: steps timeline: (from time, scene time held)
STEPS = ((0.0, 0.0), (1.5, 1.0), (3.0, 3.0), (4.5, 4.0))


def scene_time(t: float, timeline: str) -> float:
    """The scene time shown at time ``t`` of the run on ``timeline``."""
    if timeline == "continuous":
        return float(t)
    return float([tau for start, tau in STEPS if t >= start][-1])


def recovery(ssim: np.ndarray, oracle: np.ndarray, start: int, stop: int, tol: float) -> int | None:
    """Frames after ``start`` until ``ssim`` stays within ``tol`` of ``oracle`` up to ``stop``."""
    ok = ssim[start:stop] >= oracle[start:stop] - tol
    for j in range(len(ok)):
        if ok[j:].all():
            return j
    return None


def reply_bytes(ref: Any) -> int:
    """Bytes of a reply's reference on the wire (default codecs: GI, depth, mask)."""
    from icbtool.net import codec

    parts, payload = codec.pack_parts(
        [
            ("gi", ref.gi, codec.DEFAULT_GI_CODEC),
            ("depth", ref.depth, codec.DEFAULT_DEPTH_CODEC),
            ("mask", ref.mask, codec.DEFAULT_DEPTH_CODEC),
        ]
    )
    return len(payload)


def run(args: argparse.Namespace, timeline: str) -> dict[str, Any]:
    import icbtool as icb
    from icbtool import metrics, system, trace
    from icbtool.store import invalidation

    size = args.size
    scene = icb.scene.PROCEDURAL["cornell_box_moving_light"](height=size, width=size)
    path = scene.paths["test"]
    path = path.with_intrinsics(path.intrinsics.resized(size, size))
    times = np.linspace(0.0, SCENE_S, args.frames)

    def path_time(t: float) -> float:  # the camera walks the path at args.speed
        return float(path.times[0]) + args.speed * t

    base = system.CloudConfig(
        spp=args.spp, cheap_spp=args.cheap_spp, latency_s=args.latency, max_depth=args.max_depth
    )
    rows: dict[str, list[dict[str, Any]]] = {m: [] for m in (*METHODS, "dl_only")}
    with tempfile.TemporaryDirectory(prefix="icb-dynamic-") as tmp:
        clouds = {
            m: system.Cloud(
                scene,
                Path(tmp) / m,
                dataclasses.replace(base, invalidation=INVALIDATION[m]),
            )
            for m in METHODS
        }
        clients = {m: system.Client(scene, clouds[m]) for m in METHODS}
        try:
            for k, t in enumerate(times):
                tau = scene_time(float(t), timeline)
                t_req = max(float(t) - args.latency, 0.0)
                tau_req = scene_time(t_req, timeline)
                cam = path.camera_at(path_time(float(t)))
                v_t, v_r = (args.speed * v for v in path.velocity_cam(path_time(t_req)))
                tr = trace.render(
                    scene.at(tau),
                    cam,
                    trace.TraceConfig(
                        spp=args.truth_spp, seed=10_000 + k, max_depth=args.max_depth
                    ),
                )
                truth = tr.full
                for m in METHODS:
                    req = system.GIRequest(
                        path.camera_at(path_time(t_req)),
                        v_t,
                        v_r,
                        time_s=tau if m == "oracle" else tau_req,
                        seq=k,
                    )
                    renders0 = clouds[m].renders
                    fr = clients[m].frame(cam, req, time_s=tau)
                    ref = fr.reply.reference
                    rows[m].append(
                        {
                            "t": float(t),
                            "scene_time": tau,
                            "ssim": metrics.ssim(fr.final, truth),
                            "flip": metrics.flip(truth, fr.final),
                            "ssim_gi": metrics.ssim(fr.gi, tr.gi),
                            "stale": fr.stale,
                            "cache_hit": fr.reply.cache_hit,
                            "renders": clouds[m].renders - renders0,
                            "render_ms": fr.reply.timings_ms.get("render", 0.0),
                            "spp": ref.meta.spp,
                            "state_current": invalidation.record_state(ref.meta)[0]
                            == invalidation.state_id(scene.at(tau)),
                            "bytes": reply_bytes(ref),
                        }
                    )
                    if m == "rule":
                        rows["dl_only"].append(
                            {
                                "t": float(t),
                                "scene_time": tau,
                                "ssim": metrics.ssim(fr.wrt.dl, truth),
                                "flip": metrics.flip(truth, fr.wrt.dl),
                                "ssim_gi": metrics.ssim(np.zeros_like(tr.gi), tr.gi),
                            }
                        )
                print(
                    f"{timeline} frame {k + 1}/{len(times)} t={t:.2f} scene={tau:.2f} "
                    + " ".join(f"{m}={rows[m][-1]['ssim']:.3f}" for m in rows),
                    flush=True,
                )
            samples = {m: clouds[m].samples_traced for m in METHODS}
        finally:
            for m in METHODS:
                clients[m].close()
                clouds[m].close()
    return _summarise(rows, times, timeline, args, samples)


def _summarise(
    rows: dict[str, list[dict[str, Any]]],
    times: np.ndarray,
    timeline: str,
    args: argparse.Namespace,
    samples: dict[str, int],
) -> dict[str, Any]:
    taus = np.array([r["scene_time"] for r in rows["oracle"]])
    changes = [k for k in range(1, len(taus)) if taus[k] != taus[k - 1]]
    bounds = [*changes, len(taus)]
    oracle = np.array([r["ssim"] for r in rows["oracle"]])
    oracle_gi = np.array([r["ssim_gi"] for r in rows["oracle"]])
    dt = float(times[1] - times[0]) if len(times) > 1 else 0.0
    out: dict[str, Any] = {}
    for m, rs in rows.items():
        ssim = np.array([r["ssim"] for r in rs])
        ssim_gi = np.array([r["ssim_gi"] for r in rs])
        s: dict[str, Any] = {
            "mean_ssim": float(ssim.mean()),
            "mean_flip": float(np.mean([r["flip"] for r in rs])),
            "mean_ssim_gi": float(ssim_gi.mean()),
            "final_ssim": float(ssim[-1]),
        }
        tol = args.tolerance
        if timeline == "steps":
            segs = list(zip(changes, bounds[1:]))
            rec = [recovery(ssim, oracle, c, e, tol) for c, e in segs]
            s["recovery_frames"] = rec
            s["recovery_s"] = [None if r is None else r * dt for r in rec]
            s["recovery_frames_gi"] = [recovery(ssim_gi, oracle_gi, c, e, tol) for c, e in segs]
        else:  # continuous: the light rests after its last key (4 s); recovery after that
            rest = int(np.searchsorted(times, 4.0))
            n = len(ssim)
            s["frames_until_recovery_after_rest"] = recovery(ssim, oracle, rest, n, tol)
            s["frames_until_recovery_after_rest_gi"] = recovery(ssim_gi, oracle_gi, rest, n, tol)
            s["mean_ssim_gap_to_oracle_while_moving"] = float(np.mean(oracle[:rest] - ssim[:rest]))
            s["mean_ssim_gi_gap_to_oracle_while_moving"] = float(
                np.mean(oracle_gi[:rest] - ssim_gi[:rest])
            )
        if m != "dl_only":
            s["stale_frames"] = int(sum(r["stale"] for r in rs))
            s["frames_not_current_state"] = int(sum(not r["state_current"] for r in rs))
            s["cloud_renders"] = int(sum(r["renders"] for r in rs))
            s["cloud_render_s"] = float(sum(r["render_ms"] for r in rs) / 1e3)
            s["samples_traced"] = int(samples[m])
            s["reply_bytes"] = int(sum(r["bytes"] for r in rs))
        out[m] = s
    return {
        "timeline": timeline,
        "changes_at_frames": changes,
        "frame_dt_s": dt,
        "summary": out,
        "frames": rows,
    }


def plot(results: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(2, n, figsize=(6 * n, 6.4), squeeze=False)
    for (row, key, what), (col, (timeline, r)) in (
        (rc, cr)
        for rc in ((0, "ssim", "final frame"), (1, "ssim_gi", "GI alone"))
        for cr in enumerate(results.items())
    ):
        ax = axes[row][col]
        for m, style in (
            ("oracle", "k:"),
            ("rule", "C0-"),
            ("full", "C1--"),
            ("stale", "C3-."),
            ("dl_only", "C7-"),
        ):
            ts = [f["t"] for f in r["frames"][m]]
            ax.plot(ts, [f[key] for f in r["frames"][m]], style, label=m, lw=1.4)
        for c in r["changes_at_frames"] if timeline == "steps" else []:
            ax.axvline(r["frames"]["oracle"][c]["t"], color="0.8", lw=0.8, zorder=0)
        if timeline == "continuous":
            ax.axvspan(0.0, 4.0, color="0.93", zorder=0, label="light moving" if row else None)
        ax.set_title(f"{timeline} timeline")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"SSIM of the {what} vs truth")
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="client frames along the path")
    ap.add_argument("--size", type=int, default=64, help="client image side (pixels)")
    ap.add_argument("--spp", type=int, default=16, help="the cloud's samples per pixel")
    ap.add_argument("--cheap-spp", type=int, default=4, help="first render after a change")
    ap.add_argument("--truth-spp", type=int, default=64, help="samples of the truth images")
    ap.add_argument("--max-depth", type=int, default=6, help="longest traced path")
    ap.add_argument("--latency", type=float, default=0.1, help="T_IL (s)")
    ap.add_argument("--speed", type=float, default=0.1, help="the camera's pace on its path")
    ap.add_argument("--tolerance", type=float, default=0.02, help="SSIM within the oracle's")
    ap.add_argument(
        "--timelines", default="steps,continuous", help="comma-separated: steps, continuous"
    )
    add_out_argument(ap, "dynamic")
    args = ap.parse_args(argv)
    load0 = load_average()
    t0 = time.perf_counter()
    results = {tl: run(args, tl) for tl in args.timelines.split(",")}
    args.out.mkdir(parents=True, exist_ok=True)
    plot(results, args.out / "dynamic_recovery.png")
    data = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "scene": "cornell_box_moving_light",
        "path": "test",
        "wall_s": time.perf_counter() - t0,
        "results": results,
    }
    write_results(args.out / "dynamic_recovery.json", data, load0)
    for tl, r in results.items():
        print(tl, {m: s for m, s in r["summary"].items()})


if __name__ == "__main__":
    main()
