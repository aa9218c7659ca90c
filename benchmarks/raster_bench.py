"""Raster benchmark: ms per frame for the full buffer set vs the same buffers by ray casting.

For each available GL backend (osmesa, egl; each in its own subprocess, since a process can bind
PyOpenGL to one platform only), on the Cornell box and on Sponza (sun + sky,
data/scenes/sponza.toml) at 256x256 and 512x512:

* ``raster``: :class:`icbtool.raster.Rasterizer` (context and uploads reused), every buffer
  (dl with shadows, albedo, world/view normals, depth, position, mask), median over ``--frames``
  frames after 2 warm-up frames. Two modes: ``cached`` (default config: the shadow maps of the
  static lights are rendered once per Rasterizer) and ``shadows_every_frame``
  (``cache_shadow_maps=False``: the shadow pass is paid in every frame).
* ``open3d``: what a user could do instead with Open3D's RaycastingScene (Embree, all cores) for
  the same camera: primary rays + one shadow ray per hit towards the sun (Cornell box: towards the
  light's centre). Ray directions are precomputed once (not timed); building the shadow rays and
  casting them is timed. Raster and Open3D frames are interleaved so that both see the same
  machine load.

Writes --out/: results.json (numbers, configs, run info), raster_bench.png (bar
plot), and PNG previews of the Sponza and Cornell box buffers (look at them).

Usage: .venv/bin/python -m benchmarks.raster_bench [--frames 10] [--backends osmesa,egl]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument
from icbtool.optional import require

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "raster"
SIZES = (256, 512)


def load_sponza():
    from icbtool.scene.load import load

    return load(REPO / "data" / "scenes" / "sponza.toml")


def open3d_frame(rs, o3c, rays: np.ndarray, light: dict) -> None:
    """Primary rays + one shadow ray per hit (the ray-casting cost of the same buffers)."""
    r = rs.cast_rays(o3c.Tensor(rays))
    t = r["t_hit"].numpy()
    hit = np.isfinite(t)
    o = rays[hit, :3]
    d = rays[hit, 3:]
    n = r["primitive_normals"].numpy()[hit]
    n = n * -np.sign((n * d).sum(1, keepdims=True))  # towards the camera (two-sided)
    p = o + d * t[hit, None] + 1e-4 * n
    if light["kind"] == "directional":
        sd = np.broadcast_to(light["to_light"], p.shape)
        shadow = np.concatenate([p, sd], 1).astype(np.float32)
        rs.test_occlusions(o3c.Tensor(shadow))
    else:
        sd = light["position"] - p
        dist = np.linalg.norm(sd, axis=1, keepdims=True)
        shadow = np.concatenate([p, sd / dist], 1).astype(np.float32)
        rs.test_occlusions(o3c.Tensor(shadow), tfar=float(np.median(dist)))
    r["primitive_ids"].numpy()  # the G-buffer ids a user would need


def worker(backend: str, frames: int) -> dict:
    """Run in a subprocess bound to ``backend``; returns the numbers."""
    o3d = require("open3d", "the Open3D raycasting comparison")

    import icbtool as icb
    from icbtool.imageio import preview, write_png

    o3c = o3d.core
    scenes = {"cornell_box": icb.scene.cornell_box(), "sponza": load_sponza()}
    results: list[dict] = []
    configs = {
        "cached": icb.raster.RasterConfig(backend=backend),
        "shadows_every_frame": icb.raster.RasterConfig(backend=backend, cache_shadow_maps=False),
    }
    for sname, scene in scenes.items():
        rs = o3d.t.geometry.RaycastingScene()
        rs.add_triangles(o3c.Tensor(scene.vertices), o3c.Tensor(scene.faces.astype(np.uint32)))
        sun = scene.lights_of("directional")
        if sun:
            light = {"kind": "directional", "to_light": -sun[0].direction.astype(np.float32)}
        else:
            a = scene.lights_of("area")[0]
            light = {"kind": "point", "position": a.corner + 0.5 * (a.edge_u + a.edge_v)}
        for mode, cfg in configs.items():
            with icb.raster.Rasterizer(scene, cfg) as r:
                for size in SIZES:
                    cam = scene.default_camera.resized(size, size)
                    o, d, _ = cam.rays()
                    rays = np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32)
                    rt, ot, stages = [], [], []
                    for i in range(frames + 2):
                        t0 = time.perf_counter()
                        buf = r.render(cam)
                        t1 = time.perf_counter()
                        open3d_frame(rs, o3c, rays, light)
                        t2 = time.perf_counter()
                        if i >= 2:
                            rt.append(1e3 * (t1 - t0))
                            ot.append(1e3 * (t2 - t1))
                            stages.append(buf.timings)
                    stage_med = {
                        k: float(np.median([s.get(k, 0.0) for s in stages])) for k in stages[0]
                    }
                    results.append(
                        {
                            "backend": backend,
                            "scene": sname,
                            "triangles": scene.n_triangles,
                            "size": size,
                            "mode": mode,
                            "raster_ms_median": float(np.median(rt)),
                            "raster_ms_all": rt,
                            "raster_stages_ms_median": stage_med,
                            "open3d_ms_median": float(np.median(ot)),
                            "open3d_ms_all": ot,
                            "setup_ms": r.setup_ms,
                        }
                    )
                    print(
                        f"[{backend}] {sname} {size} {mode}: raster {np.median(rt):.1f} ms, "
                        f"open3d {np.median(ot):.1f} ms",
                        file=sys.stderr,
                    )
                    if backend == "osmesa" and mode == "cached" and size == 512:
                        for n in ("dl", "albedo", "normal_world", "depth", "normal_view"):
                            img = preview(
                                getattr(buf, n), icb.raster.PREVIEW_KIND[n], mask=buf.mask
                            )
                            write_png(OUT / f"{sname}_{n}.png", img)
    return {"results": results, "configs": {k: v for k, v in configs.items()}}


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = sorted({(r["scene"], r["size"]) for r in results})
    series = sorted({(r["backend"], r["mode"]) for r in results})
    fig, ax = plt.subplots(figsize=(10, 4.5))
    width = 0.8 / (len(series) + 1)
    x = np.arange(len(groups))
    for k, (backend, mode) in enumerate(series):
        vals = [
            next(
                (
                    r["raster_ms_median"]
                    for r in results
                    if (r["scene"], r["size"]) == g
                    and r["backend"] == backend
                    and r["mode"] == mode
                ),
                np.nan,
            )
            for g in groups
        ]
        ax.bar(x + k * width, vals, width, label=f"raster {backend} ({mode})")
    o3 = [
        np.median([r["open3d_ms_median"] for r in results if (r["scene"], r["size"]) == g])
        for g in groups
    ]
    ax.bar(
        x + len(series) * width,
        o3,
        width,
        label="Open3D rays (primary + shadow)",
        color="k",
        alpha=0.6,
    )
    ax.set_xticks(x + 0.4 - width / 2)
    ax.set_xticklabels([f"{s} {n}x{n}" for s, n in groups])
    ax.set_ylabel("ms per frame (median)")
    ax.set_title("Full buffer set (DL with shadows, albedo, normals, depth, position, mask)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--backends", default="osmesa,egl")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    add_out_argument(ap, "raster")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    if args.frames < 10:
        raise SystemExit("--frames must be >= 10")
    OUT.mkdir(parents=True, exist_ok=True)
    if args.worker:
        from benchmarks.common import to_jsonable

        print(json.dumps(to_jsonable(worker(args.worker, args.frames))))
        return 0
    from tqdm import tqdm

    from benchmarks.common import run_info, write_json

    load_start = os.getloadavg()
    all_results, configs, skipped = [], {}, {}
    for backend in tqdm(args.backends.split(","), desc="backends"):
        env = {k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM",)}
        env["ICBTOOL_GL_BACKEND"] = backend
        res = subprocess.run(
            [sys.executable, __file__, "--worker", backend, "--frames", str(args.frames)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        if res.returncode != 0:
            skipped[backend] = f"worker failed (exit {res.returncode}); see stderr above"
            continue
        out = json.loads(res.stdout.strip().splitlines()[-1])
        all_results += out["results"]
        configs[backend] = out["configs"]
    target = [
        {
            "backend": r["backend"],
            "mode": r["mode"],
            "raster_ms": r["raster_ms_median"],
            "open3d_ms": r["open3d_ms_median"],
            "met": r["raster_ms_median"] <= r["open3d_ms_median"],
        }
        for r in all_results
        if r["scene"] == "sponza" and r["size"] == 512
    ]
    write_json(
        OUT / "results.json",
        {
            "description": __doc__,
            "frames": args.frames,
            "target_sponza_512_raster_le_open3d": target,
            "results": all_results,
            "skipped_backends": skipped,
            "configs": configs,
            "load_average_at_start": load_start,
            "load_average_at_end": os.getloadavg(),
            "run_info": run_info(),
        },
    )
    plot(all_results, OUT / "raster_bench.png")
    for t in target:
        print(f"Sponza 512: {t}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
