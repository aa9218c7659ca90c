"""Environment-map lighting against Mitsuba 3: the same scene, lit by the same lat-long EXR with
the same ``to_world`` rotation, rendered by Mitsuba's ``path`` integrator and by icbtool's tracer
(full radiance = direct + gi).

The map is written by this script (a sky-like HDR: a small, very bright sun, a blue dome, a dark
ground; 256 x 128 texels) and loaded by both renderers from the file; icbtool gets it through
``Sky.from_envmap`` with the rotation of a TOML ``[sky] rotation`` (``envmap_rotation``), which
Mitsuba gets as ``to_world``. Reported: the mean bias per channel (ours / Mitsuba - 1), the
relative RMSE of the images blurred by a 5x5 box, and Mitsuba's own seed-to-seed value of that
RMSE (its noise floor at the reference spp).

    .venv/bin/python -m benchmarks.envmap_mitsuba [--size 128] [--spp 1024] [--ours-spp 512]

Writes --out/mitsuba.{json,png} (images side by side).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from benchmarks.trace_time_error import load_mitsuba, to_mitsuba
from icbtool.imageio import to_display, write_exr, write_png
from icbtool.trace import TraceConfig

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "envmap"
ROTATION = (0.0, 1.0, 0.0, 40.0)  # [sky] rotation: axis, degrees (Mitsuba: <rotate y=1 angle=40>)


def sky_exr(path: Path, h: int = 128, w: int = 256) -> Path:
    """A sky-like lat-long HDR map in Mitsuba's convention (see icbtool.scene.Sky)."""
    v = np.arange(h)[:, None] / (h - 1)
    u = (np.arange(w)[None, :] + 0.5) / w
    th, ph = v * np.pi, u * 2 * np.pi
    d = np.stack(
        np.broadcast_arrays(np.sin(ph) * np.sin(th), np.cos(th), -np.cos(ph) * np.sin(th)), -1
    )
    sun = np.array([0.55, 0.6, 0.58]) / np.linalg.norm([0.55, 0.6, 0.58])
    blob = 2000.0 * np.exp((d @ sun - 1) / 0.0008)
    up = np.clip(d[..., 1:2], 0, 1)
    dome = np.where(
        d[..., 1:2] >= 0,
        (1 - up) * np.array([0.9, 0.85, 0.8]) + up * np.array([0.25, 0.4, 0.9]),
        np.array([0.12, 0.1, 0.08]),
    )
    img = (dome + blob[..., None] * np.array([1.0, 0.92, 0.8])).astype(np.float32)
    return write_exr(path, img)


def scene_with_map(exr: Path):
    """boxes_on_floor (no sun) lit by the map through a TOML description's [sky]."""
    from icbtool.scene.description import envmap_rotation

    base = icb.scene.boxes_on_floor(n_boxes=8, seed=3, sun_irradiance=0.0)
    sky = icb.scene.Sky.from_envmap(exr, scale=1.0, world_from_map=envmap_rotation(ROTATION))
    return replace(base, lights=(), sky=sky)


def blur(img: np.ndarray, k: int = 5) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(img, size=(k, k, 1), mode="nearest")


def rel_rmse(a: np.ndarray, ref: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - ref) ** 2)) / max(float(ref.mean()), 1e-12))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=1024, help="Mitsuba spp per reference render")
    ap.add_argument("--ours-spp", type=int, default=512)
    ap.add_argument("--mitsuba-variant", default="llvm_ad_rgb")
    add_out_argument(ap, "envmap")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    mi = load_mitsuba(args.mitsuba_variant)
    tmp = Path(tempfile.mkdtemp(prefix="icb_envmap_"))
    exr = sky_exr(tmp / "sky.exr")
    scene = scene_with_map(exr)
    cam = scene.default_camera.resized(args.size, args.size)
    # Mitsuba: the same geometry/materials (two-sided diffuse), the map from the file
    d = to_mitsuba(replace(scene, sky=None), cam, args.spp, max_depth=8)
    ax, ay, az, ang = ROTATION
    d["sky"] = {
        "type": "envmap",
        "filename": str(exr),
        "to_world": mi.ScalarTransform4f().rotate([ax, ay, az], ang),
    }
    msc = mi.load_dict(d)
    times = {}
    refs = []
    for seed in (1, 2):
        t0 = time.perf_counter()
        refs.append(np.asarray(mi.render(msc, spp=args.spp, seed=seed), np.float32)[..., :3])
        times[f"mitsuba_seed{seed}_s"] = time.perf_counter() - t0
    ref = 0.5 * (refs[0] + refs[1])
    t0 = time.perf_counter()
    res = icb.trace.render(
        scene, cam, TraceConfig(spp=args.ours_spp, max_depth=8, seed=7, sky_sampling="mis")
    )
    times["ours_s"] = time.perf_counter() - t0
    ours = res.full
    bias = (ours.reshape(-1, 3).mean(0) / ref.reshape(-1, 3).mean(0) - 1).tolist()
    out = {
        "scene": "boxes_on_floor(n_boxes=8, seed=3), no sun, lit by a generated sky EXR",
        "map": "256 x 128 sky: sun blob (peak 2000) + dome; rotation " + str(ROTATION),
        "size": args.size,
        "mitsuba_spp": [args.spp, args.spp],
        "ours_spp": args.ours_spp,
        "mean_bias_per_channel": bias,
        "blurred_rel_rmse_ours_vs_mitsuba": rel_rmse(blur(ours), blur(ref)),
        "blurred_rel_rmse_mitsuba_seed_to_seed": rel_rmse(blur(refs[0]), blur(refs[1])),
        "rel_rmse_ours_vs_mitsuba": rel_rmse(ours, ref),
        "rel_rmse_mitsuba_seed_to_seed": rel_rmse(refs[0], refs[1]),
        "time_s": times,
        "load_average_1min": os.getloadavg()[0],
        "mitsuba_variant": mi.variant(),
        "run_info": run_info(),
    }
    print({k: out[k] for k in list(out)[4:10]})
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "mitsuba.json", out)
    e = 1.0 / max(float(np.percentile(ref.mean(-1), 99)), 1e-6)
    diff = np.abs(ours - ref).mean(-1, keepdims=True) / max(float(ref.mean()), 1e-6)
    heat = to_display(np.repeat(np.clip(diff, 0, 1), 3, -1))
    strip = np.concatenate(
        [to_display(ours, e), to_display(ref, e), heat], axis=1
    )  # ours | Mitsuba | |diff| / mean (white = 100 %)
    write_png(OUT / "mitsuba.png", strip)
    print(f"wrote {OUT / 'mitsuba.json'} and mitsuba.png (ours | Mitsuba | |diff| / mean)")


if __name__ == "__main__":
    main()
