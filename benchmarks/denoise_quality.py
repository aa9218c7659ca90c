"""Open Image Denoise quality settings: time against error of the denoised GI.

Renders each scene once (256x256, default config, 4 spp), denoises the GI with OIDN's 'high',
'balanced' and 'fast' quality (first-hit albedo + normal), and scores direct + denoised GI against
the tracer's own 1024-spp reference (cached by benchmarks/trace_time_error.py, or rendered here).

Where OIDN's time goes: besides ``icbtool.trace.denoise`` (pyoidn's one-call API, which keeps its
device and filter between calls but binds the images and commits the filter on every call), each
quality is timed as a filter committed once on fixed buffers with only ``execute`` timed, on
OIDN's default threads and on one thread (:func:`execute_ms`; its output is checked equal to
``denoise``'s).

    .venv/bin/python -m benchmarks.denoise_quality [--spp 4] [--repeats 5]

Writes --out/denoise_quality.{json,png}.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from benchmarks.trace_time_error import MAX_DEPTH, bench_scene, errors, reference_cache  # noqa: E402
from icbtool.trace import TraceConfig
from icbtool.trace.tracer import denoise_inputs

OUT = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "trace"
QUALITIES = ("high", "balanced", "fast")


def reference(name: str, scene, cam, ref_spp: int = 1024) -> np.ndarray:
    cache = reference_cache(name, cam.width, ref_spp)
    if cache.is_file():
        return np.load(cache)["ours_full"]
    cfg = TraceConfig(spp=ref_spp, seed=1000, sampler="independent", max_depth=MAX_DEPTH,
                      rr_depth=4, spp_per_pass=4)  # fmt: skip
    return icb.trace.render(scene, cam, cfg, progress=True).full


def execute_ms(
    gi, albedo, normal, quality: str, threads: int, repeats: int
) -> tuple[float, np.ndarray]:
    """OIDN's filter alone: a device (``numThreads`` = ``threads``; 0: OIDN's default), one RT
    filter committed once on fixed buffers (the inputs as icbtool.trace.denoise prepares them,
    :func:`~icbtool.trace.tracer.denoise_inputs`), the fastest of ``repeats`` ``execute`` calls
    after one untimed call; and its output."""
    import pyoidn

    qualities = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                 "fast": pyoidn.OIDN_QUALITY_FAST}  # fmt: skip
    color, albedo, normal = denoise_inputs(gi, albedo, normal)
    images = {"color": color, "albedo": albedo, "normal": normal, "output": np.empty_like(color)}
    dev = pyoidn.Device()
    flt = None
    try:
        if threads:
            dev.set_int("numThreads", threads)
        dev.commit()
        flt = pyoidn.Filter(dev, "RT")
        for name, image in images.items():
            flt.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
        flt.set_bool("hdr", True)
        flt.set_quality(qualities[quality])
        flt.commit()
        flt.execute()
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            flt.execute()
            best = min(best, time.perf_counter() - t0)
        err = dev.get_error()
        if err is not None:
            raise RuntimeError(f"OIDN failed: {err}")
    finally:
        if flt is not None:
            flt.release()
        dev.release()
    return 1e3 * best, np.maximum(images["output"], 0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=5)
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    load_start = os.getloadavg()
    rows = []
    for name in ("cornell_box", "sponza"):
        try:
            scene = bench_scene(name)
        except (FileNotFoundError, ValueError) as e:
            print(f"{name} unavailable: {e}")
            continue
        cam = scene.default_camera.resized(args.size, args.size)
        ref = reference(name, scene, cam)
        cfg = TraceConfig(spp=args.spp, seed=args.spp, max_depth=MAX_DEPTH, rr_depth=4)
        r = icb.trace.render(scene, cam, cfg)
        raw = {"scene": name, "quality": "none (raw)", "denoise_ms": 0.0}
        rows.append({**raw, **errors(ref, r.full)})
        for q in QUALITIES:
            icb.trace.denoise(r.gi_raw, r.albedo, r.normal, quality=q)  # loads the weights
            best, out = np.inf, None
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = icb.trace.denoise(r.gi_raw, r.albedo, r.normal, quality=q)
                best = min(best, time.perf_counter() - t0)
            row = {"scene": name, "quality": q, "denoise_ms": 1e3 * best}
            for threads, key in ((0, "execute_ms"), (1, "execute_ms_1_thread")):
                row[key], own = execute_ms(r.gi_raw, r.albedo, r.normal, q, threads, args.repeats)
                if not np.allclose(own, out, rtol=1e-3, atol=1e-5):
                    raise RuntimeError(f"the committed filter's {q} output differs from denoise's")
            rows.append({**row, **errors(ref, r.direct + out)})
        for row in rows[-4:]:
            print(f"{name} {row['quality']:>10}: {row['denoise_ms']:6.1f} ms (execute alone "
                  f"{row.get('execute_ms', 0.0):.1f}, one thread "
                  f"{row.get('execute_ms_1_thread', 0.0):.1f}), RMSE {row['rmse']:.4f}, "
                  f"FLIP {row['flip']:.4f}")  # fmt: skip
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "denoise_quality.json", {"args": vars(args), "rows": rows,
                                               "load_average_start": load_start,
                                               "load_average_end": os.getloadavg(),
                                               "run_info": run_info()})  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for ax, key in zip(axes, ("denoise_ms", "rmse", "flip")):
        for i, sc in enumerate(scenes):
            sel = [r for r in rows if r["scene"] == sc]
            ax.bar(np.arange(len(sel)) + 0.4 * i, [r[key] for r in sel], 0.4, label=sc)
            ax.set_xticks(np.arange(len(sel)) + 0.2, [r["quality"] for r in sel], fontsize=8)
        ax.set_title(key)
    axes[0].legend()
    fig.suptitle(f"OIDN quality, {args.size}x{args.size}, {args.spp} spp GI")
    fig.tight_layout()
    fig.savefig(OUT / "denoise_quality.png", dpi=100)
    print(f"wrote {OUT / 'denoise_quality.json'}")


if __name__ == "__main__":
    main()
