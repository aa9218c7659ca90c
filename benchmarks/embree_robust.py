"""What Embree's robust (watertight) mode buys the path tracer: leaks counted, images compared.

``TraceConfig.robust`` decides whether the tracer's Embree scene is built with
``RTC_SCENE_FLAG_ROBUST``. Robust traversal costs 20-45 % of Embree's time per ray
(``trace_profile.py``'s ns-per-ray table); Mitsuba 3 builds its scenes without it. This measures
what that time buys:

1. Leaks through closed meshes (icospheres, inward rays from random inside points), for random
   directions (what path tracing shoots) and for rays aimed exactly at shared edges and vertices
   (the worst case). A ray from inside a closed mesh that finds no hit leaked.
2. Pixel-centre rays along a quad's diagonal (a raster-like camera lined up with an edge).
3. Whole renders of the Cornell box and Sponza, robust and not, same seed and config: the
   difference of the mean images against the noise (per-pixel z-scores of the difference).

    .venv/bin/python -m benchmarks.embree_robust [--spp 64] [--size 128] [--rays 4000000]

Writes --out/embree_robust.json.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import trimesh

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.trace import TraceConfig, render
from icbtool.trace import kernels as K
from icbtool.trace.rtc import RtcScene

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"


def misses(v: np.ndarray, f: np.ndarray, o: np.ndarray, d: np.ndarray, robust: bool) -> int:
    """Rays (o, d) that find no hit in the mesh (v, f) through the tracer's own Embree calls."""
    rs = RtcScene(v, f, robust=robust)
    n = len(o)
    t, u, w = (np.zeros(n, np.float32) for _ in range(3))
    prim = np.zeros(n, np.int32)
    o = np.ascontiguousarray(o, np.float32)
    d = np.ascontiguousarray(d, np.float32)
    K.rtc_intersect_batch(rs.ptr, rs.fn_intersect, o, d, t, prim, u, w, 0, n)
    return int((prim < 0).sum())


def unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def leaks(n_rays: int, rng: np.random.Generator) -> list[dict]:
    rows = []
    for sub in (5, 7):
        m = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
        v = np.asarray(m.vertices, np.float32)
        f = np.asarray(m.faces)
        # origins well inside (|o| <= 0.5), so every ray from them must hit the sphere
        o = unit(rng.normal(size=(n_rays, 3))) * (0.5 * rng.random((n_rays, 1)) ** (1 / 3))
        e = m.edges_unique
        targets = np.concatenate([(v[e[:, 0]] + v[e[:, 1]]) / 2, v])
        aimed = unit(targets[rng.integers(0, len(targets), n_rays)] - o)
        for rays, d in (
            ("random directions", unit(rng.normal(size=(n_rays, 3)))),
            ("aimed at edges and vertices", aimed),
        ):
            row = {"mesh": f"icosphere, {len(f)} triangles", "rays": rays, "n": n_rays}
            for robust in (True, False):
                row[f"leaks_robust_{robust}"] = misses(v, f, o, d, robust)
            rows.append(row)
            print(row, flush=True)
    return rows


def diagonal(n: int = 512) -> dict:
    """Pinhole rays through the pixel centres of a quad whose diagonal crosses pixel centres."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    x = (np.arange(n) + 0.5) / n
    xx, yy = np.meshgrid(x, x)
    tgt = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1)
    eye = np.array([0.37, 0.61, 2.0])
    d = unit(tgt - eye)
    o = np.broadcast_to(eye, d.shape)
    row = {"rays": n * n, "on_diagonal": n}
    for robust in (True, False):
        row[f"misses_robust_{robust}"] = misses(v, f, o, d, robust)
    print("diagonal:", row, flush=True)
    return row


def images(spp: int, size: int) -> list[dict]:
    os.environ.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    scenes = {"cornell_box": icb.scene.cornell_box}
    if Path(os.environ["ICBTOOL_SPONZA"]).is_dir():
        scenes["sponza"] = lambda: icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")
    rows = []
    for name, make in scenes.items():
        scene = make()
        cam = scene.default_camera.resized(size, size)
        res = {}
        for robust in (True, False):
            cfg = TraceConfig(spp=spp, seed=7, max_depth=8, robust=robust)
            res[robust] = render(scene, cam, cfg)
        a, b = res[True], res[False]
        diff = (b.full - a.full).mean(-1)
        # both images' variance of the mean (independent renders: the seeds' paths differ as soon
        # as one ray goes another way)
        var = (a.variance + b.variance).mean(-1) / 3 + 1e-12
        z = diff / np.sqrt(var)
        covered = a.mask[..., 0] > 0
        row = {
            "scene": name,
            "spp": spp,
            "size": size,
            "mean_full_robust": float(a.full.mean()),
            "mean_full_not_robust": float(b.full.mean()),
            "relative_difference_of_means": float(b.full.mean() / a.full.mean() - 1),
            "pixels_identical": float((a.full == b.full).all(-1).mean()),
            "z_mean_over_covered": float(z[covered].mean()),
            "z_std_over_covered": float(z[covered].std()),
            "pixels_abs_z_over_5": int((np.abs(z[covered]) > 5).sum()),
            "rays_robust": a.stats.total_rays,
            "rays_not_robust": b.stats.total_rays,
        }
        print(row, flush=True)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--size", type=int, default=128)
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    rng = np.random.default_rng(0)
    out = {
        "args": vars(args),
        "leaks": leaks(args.rays, rng),
        "diagonal": diagonal(),
        "images": images(args.spp, args.size),
        "run_info": run_info(),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "embree_robust.json", out)
    print(f"wrote {OUT / 'embree_robust.json'}")


if __name__ == "__main__":
    main()
