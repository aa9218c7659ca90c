"""Time vs error: the generator against the path tracer at equal SSIM (docs/design.md section 5).

On test frames of a baked store (truth: the store's GI, traced with many samples and denoised), it
times and scores

* the generator of a training run (``--run``, default Figure 7's best): torch and onnxruntime,
  1 and 2 threads (median of ``--repeats`` after a warm-up call), at the store's resolution;
* the path tracer (icbtool.trace, GI only) at increasing spp, raw and OIDN-denoised;

and reports, for the generator's SSIM, the tracer's time to reach it and the speed-up
(:func:`icbtool.gan.baselines.equal_quality`: linear in log time between measured spp on the
curve's monotone envelope; when the tracer's cheapest point is already better, or it never gets
there, the result says so and no ratio is given). It also times the generator alone at
128, 256 and 512 pixels. Writes --out/time_error.{json,png}.

    ICBTOOL_GAN_STORE=STORE .venv/bin/python -m benchmarks.gan_time_error
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument
from benchmarks.gan_figure7 import chosen_run

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"


def _median_ms(repeats: int, fn, *args) -> tuple[float, float]:
    """(first call ms, median ms of ``repeats`` later calls) of ``fn(*args)``."""
    t0 = time.perf_counter()
    fn(*args)
    first = 1e3 * (time.perf_counter() - t0)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        ts.append(1e3 * (time.perf_counter() - t0))
    return first, float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"))
    ap.add_argument("--scene-file", default=str(REPO / "data" / "scenes" / "sponza.toml"))
    ap.add_argument("--scene", default="sponza", help="scene name (or hash) in the store")
    ap.add_argument("--run", default=None, help="training run (default: Figure 7's best)")
    ap.add_argument("--runs", default=str(REPO / "out" / "gan_figure7"))
    ap.add_argument("--frames", type=int, default=8, help="test views, spread along the path")
    ap.add_argument("--spps", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64])
    ap.add_argument("--repeats", type=int, default=5)
    add_out_argument(ap, "gan")
    args = ap.parse_args()
    if not args.store:
        raise SystemExit("give --store (or set ICBTOOL_GAN_STORE): a baked Sponza store")

    import torch

    import icbtool.store as S
    from icbtool import metrics, trace
    from icbtool.gan import Generator
    from icbtool.gan.baselines import equal_quality
    from icbtool.optional import require
    from icbtool.provenance import run_info, write_json
    from icbtool.scene import load

    load0 = os.getloadavg()[0]
    ort = require("onnxruntime", "timing the generator under onnxruntime")
    out = Path(args.out)
    run, exposure = chosen_run(args.run, out, args.runs)
    exposure = float(
        json.loads((run / "config.json").read_text())["train_config"]["display_exposure"]
    )
    gen = Generator.load(run)
    scene = load(args.scene_file)
    tmp = Path(tempfile.mkdtemp(prefix="icb-onnx-"))
    onnx_path = gen.export_onnx(tmp / "g.onnx")

    def ort_session(threads: int):
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        return ort.InferenceSession(str(onnx_path), so, providers=["CPUExecutionProvider"])

    ro = S.StoreConfig(readonly=True, record_hits=False)
    train_path = json.loads((run / "config.json").read_text())["train_config"]["train_path"]
    res: dict = {"run": str(run), "train_path": train_path, "inputs": list(gen.inputs),
                 "frames": []}  # fmt: skip
    gen_pts: dict[str, list[tuple[float, float]]] = {}
    tracer_pts: dict[str, list[tuple[float, float]]] = {"raw": [], "denoised": []}
    with S.open(args.store, ro) as store:
        ds = S.Dataset(store, args.scene, split="test", inputs=gen.inputs)
        ids = ds.record_ids
        pick = [ids[int(k)] for k in np.linspace(0, len(ids) - 1, min(args.frames, len(ids)))]
        trace.render(scene, store.get(pick[0]).camera, trace.TraceConfig(spp=1))  # compile
        for n, rid in enumerate(pick):
            rec = store.get(rid)
            truth = rec.gi
            row: dict = {"record_id": rid, "generator": {}, "tracer": []}
            x = gen.encode(rec)[None]
            pred = gen.generate(rec)
            ssim_g = metrics.ssim(pred, truth, exposure)
            for threads in (1, 2):
                torch.set_num_threads(threads)
                _, ms_t = _median_ms(args.repeats, gen.generate, rec)
                sess = ort_session(threads)
                name = sess.get_inputs()[0].name
                _, ms_o = _median_ms(args.repeats, sess.run, None, {name: x})
                for key, ms in ((f"torch_{threads}t", ms_t), (f"onnxruntime_{threads}t", ms_o)):
                    row["generator"][key] = {"ms": ms, "ssim": ssim_g}
                    gen_pts.setdefault(key, []).append((ms, ssim_g))
            torch.set_num_threads(2)
            for spp in args.spps:
                for denoise in (False, True):
                    cfg = trace.TraceConfig(spp=spp, seed=7919 * (n + 1) + spp, denoise=denoise)
                    t0 = time.perf_counter()
                    r = trace.render(scene, rec.camera, cfg)
                    ms = 1e3 * (time.perf_counter() - t0)
                    s = metrics.ssim(r.gi, truth, exposure)
                    kind = "denoised" if denoise else "raw"
                    row["tracer"].append({"spp": spp, "kind": kind, "ms": ms, "ssim": s})
            res["frames"].append(row)
            print(f"frame {n + 1}/{len(pick)}: generator SSIM {ssim_g:.4f}")
    # means over frames, per setting
    summary: dict = {"generator": {}, "tracer": {}}
    for key, pts in gen_pts.items():
        summary["generator"][key] = {
            "ms": float(np.mean([p[0] for p in pts])),
            "ssim": float(np.mean([p[1] for p in pts])),
        }
    for kind in ("raw", "denoised"):
        for spp in args.spps:
            rows = [
                t
                for f in res["frames"]
                for t in f["tracer"]
                if t["kind"] == kind and t["spp"] == spp
            ]
            ms, s = (
                float(np.mean([t["ms"] for t in rows])),
                float(np.mean([t["ssim"] for t in rows])),
            )
            summary["tracer"].setdefault(kind, []).append({"spp": spp, "ms": ms, "ssim": s})
            tracer_pts[kind].append((ms, s))
    best_key = min(summary["generator"], key=lambda k: summary["generator"][k]["ms"])
    g = summary["generator"][best_key]
    equal = {}
    for kind in ("raw", "denoised"):
        pts = tracer_pts[kind]
        e = equal_quality([p[0] for p in pts], [p[1] for p in pts], g["ssim"])
        equal[kind] = {
            "tracer_ms": e.cost,
            "status": e.status,  # interpolated / measured / above (no equal point) / below
            "cheapest": {"ms": e.cheapest[0], "ssim": e.cheapest[1]},
            "speedup": None if e.cost is None else e.cost / g["ms"],
        }
    summary["equal_ssim"] = {
        "generator": best_key,
        **g,
        "tracer": equal,
        "target_speedup": {"denoised": 5, "raw": 50},
    }
    # the generator alone at three sizes
    sizes = {}
    c = gen.encoding.n_channels
    for side in (128, 256, 512):
        x = np.zeros((1, c, side, side), np.float32)
        for threads in (1, 2):
            torch.set_num_threads(threads)
            xt = torch.from_numpy(x)
            with torch.no_grad():
                _, ms_t = _median_ms(args.repeats, gen.module, xt)
            sess = ort_session(threads)
            name = sess.get_inputs()[0].name
            _, ms_o = _median_ms(args.repeats, sess.run, None, {name: x})
            sizes[f"{side}"] = {
                **sizes.get(f"{side}", {}),
                f"torch_{threads}t": ms_t,
                f"onnxruntime_{threads}t": ms_o,
            }
    summary["generator_ms_by_size"] = sizes
    res["summary"] = summary
    res["run_info"] = run_info()
    res["load_1min"] = [load0, os.getloadavg()[0]]
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "time_error.json", res)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for kind, pts in tracer_pts.items():
        ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=f"path tracer, {kind}")
    for key, v in summary["generator"].items():
        ax.scatter([v["ms"]], [v["ssim"]], marker="*", s=120, label=f"generator, {key}")
    ax.set(
        xscale="log",
        xlabel="ms per frame",
        ylabel="SSIM vs truth (display, 0-255)",
        title=f"GI at {truth.shape[1]}x{truth.shape[0]}: time against error",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "time_error.png", dpi=100)
    e = summary["equal_ssim"]
    print(json.dumps(e, indent=2))


if __name__ == "__main__":
    main()
