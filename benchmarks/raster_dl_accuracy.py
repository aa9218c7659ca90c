"""The client's direct light (raster DL) against the tracer's direct light, at shadow edges too.

The tracer's ``direct`` (same DL/GI split, docs/guide/python-api.md, "Radiometry") is the
reference: traced with box-filtered (jittered) pixels at many spp, since that is what the cloud's GI
is combined with.
The raster shades one point per pixel unless ``RasterConfig.dl_supersample = k`` (k x k points,
box-filtered). For each k: the mean bias per channel and the relative RMSE of the images blurred
by a 5x5 box, over the covered pixels, (a) on the whole image and (b) without the pixels that see
the emitter itself (dilated by 2 px: at 128^2 the ceiling light is a sliver a few pixels tall,
whose filtered radiance dominates (a)), and (c) on the penumbra and edge pixels (where the
traced direct light differs from its 3x3 median by > 5 %); and the cost: median raster time of
``dl`` at 512^2 (the machine is shared: the 1-minute load is recorded).

    .venv/bin/python -m benchmarks.raster_dl_accuracy [--obj CornellBox-Original.obj]
        [--size 128] [--spp 2048]

Default scene: the built-in ``cornell_box``; ``--obj`` adds an OBJ scene (McGuire's
CornellBox-Original, fetched into a temporary folder; not shipped) seen from (0, 1, 3.4).
Writes --out/dl_accuracy.{json,png}.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation, median_filter, uniform_filter

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.camera import Camera
from icbtool.imageio import to_display, write_png
from icbtool.raster import RasterConfig, Rasterizer
from icbtool.trace import TraceConfig, render

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "raster"
KS = (1, 2, 3, 4)


def metrics(dl: np.ndarray, ref: np.ndarray, sel: np.ndarray) -> dict:
    """Bias per channel and blurred relative RMSE of dl against ref over the pixels ``sel``."""
    w = uniform_filter(sel.astype(float), 5, mode="nearest")[..., None]

    def blur(x):
        return uniform_filter(x * sel[..., None], size=(5, 5, 1), mode="nearest") / np.maximum(
            w, 1e-9
        )

    bias = dl[sel].mean(0) / ref[sel].mean(0) - 1
    rr = np.sqrt(np.mean((blur(dl) - blur(ref))[sel] ** 2)) / ref[sel].mean()
    raw = np.sqrt(np.mean((dl - ref)[sel] ** 2)) / ref[sel].mean()
    return {
        "pixels": int(sel.sum()),
        "bias_per_channel": bias.tolist(),
        "blurred_rel_rmse": float(rr),
        "rel_rmse": float(raw),
    }


def cost_ms(scene, cam, k: int, repeats: int) -> float:
    with Rasterizer(scene, RasterConfig(dl_supersample=k)) as r:
        r.render(cam, "dl")  # shadow maps, shaders
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r.render(cam, "dl")
            ts.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(ts))


def one(name: str, scene, cam, spp: int, repeats: int) -> tuple[dict, np.ndarray]:
    t0 = time.perf_counter()
    tr = render(scene, cam, TraceConfig(spp=spp, max_depth=2, seed=1, pixel_jitter=True))
    ref, cov = tr.direct, tr.mask[..., 0] > 0.5
    t_ref = time.perf_counter() - t0
    lum = ref.mean(-1)
    # the light itself: far brighter than anything it lights; and its 2-pixel neighbourhood
    core = lum > 0.5 * lum.max()
    emitter = binary_dilation(core, iterations=2)
    edge = cov & ~emitter & (np.abs(lum - median_filter(lum, 3)) > 0.05 * np.maximum(lum, 1e-3))
    rows, imgs = [], [ref]
    for k in KS:
        with Rasterizer(scene, RasterConfig(dl_supersample=k)) as r:
            dl = r.render(cam, "dl").dl
        imgs.append(dl)
        rows.append(
            {
                "dl_supersample": k,
                "whole_image": metrics(dl, ref, cov),
                "without_emitter_pixels": metrics(dl, ref, cov & ~emitter),
                "penumbra_and_edge_pixels": metrics(dl, ref, edge),
                "cost_ms_512": cost_ms(scene, cam.resized(512, 512), k, repeats),
                "load_average_1min": os.getloadavg()[0],
            }
        )
        m = rows[-1]
        print(
            name,
            f"k={k}",
            "bias(whole) %",
            np.round(np.array(m["whole_image"]["bias_per_channel"]) * 100, 2),
            "blurred rel RMSE (whole / no emitter / edges) %",
            round(100 * m["whole_image"]["blurred_rel_rmse"], 2),
            round(100 * m["without_emitter_pixels"]["blurred_rel_rmse"], 2),
            round(100 * m["penumbra_and_edge_pixels"]["blurred_rel_rmse"], 2),
            f"cost {m['cost_ms_512']:.0f} ms @512^2",
        )
    e = 1.0 / max(float(np.percentile(lum[cov & ~emitter], 99)), 1e-6)
    strip = [to_display(x, e) for x in imgs]
    for x in imgs[1:]:  # |raster - traced| / mean, white = 20 %
        d = np.abs(x - ref).mean(-1, keepdims=True) / max(float(ref[cov].mean()), 1e-6) / 0.2
        strip.append(to_display(np.repeat(np.clip(d, 0, 1), 3, -1)))
    res = {
        "size": [cam.height, cam.width],
        "reference": {"spp": spp, "pixel_jitter": True, "max_depth": 2, "time_s": t_ref},
        "emitter_pixels": int(emitter.sum()),
        "penumbra_and_edge_pixels": int(edge.sum()),
        "covered_pixels": int(cov.sum()),
        "by_supersample": rows,
    }
    return res, np.concatenate(strip, axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--obj", type=Path, default=None, help="also this OBJ (McGuire's box)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=5)
    add_out_argument(ap, "raster")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    scenes = {}
    cb = icb.scene.cornell_box()
    scenes["cornell_box"] = (cb, cb.default_camera.resized(args.size, args.size))
    if args.obj is not None:
        s = icb.scene.load(args.obj)
        cam = Camera.look_at((0, 1, 3.4), (0, 1, 0), (0, 1, 0), 40, args.size, args.size)
        scenes[args.obj.stem] = (s, cam)
    results, strips = {}, []
    for name, (scene, cam) in scenes.items():
        results[name], strip = one(name, scene, cam, args.spp, args.repeats)
        strips.append(strip)
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(
        OUT / "dl_accuracy.json",
        {"args": {k: str(v) for k, v in vars(args).items()}, "scenes": results,
         "run_info": run_info()},
    )  # fmt: skip
    write_png(OUT / "dl_accuracy.png", np.concatenate(strips, axis=0))
    print(
        f"wrote {OUT / 'dl_accuracy.json'} and dl_accuracy.png (rows: scenes; traced | raster "
        f"k={', '.join(map(str, KS))} | |difference| / mean per k, white = 20 %)"
    )


if __name__ == "__main__":
    main()
