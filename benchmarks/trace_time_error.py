"""Error against time of our path tracer (raw, adaptive, denoised) next to Mitsuba 3.

For the Cornell box and Sponza: RMSE of the linear "full" radiance and FLIP (LDR, on
icbtool.imageio.to_display images) against a high-sample reference, for renders of increasing spp.
Each renderer is measured against its own high-spp reference (ours against ours, Mitsuba against
Mitsuba: they differ slightly in conventions, e.g. shading normals); the RMSE between the two
references is reported as `reference_gap`. Mitsuba cannot split DL/GI, so "full" is compared.

    .venv/bin/python benchmarks/trace_time_error.py [--size 128] [--ref-spp 256]

Writes benchmarks/results/trace/time_error.{json,png}. Mitsuba is a benchmark peer only.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

import icbtool as icb
from icbtool.cli._common import run_info, write_json
from icbtool.imageio import to_display
from icbtool.trace import TraceConfig

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"
MAX_DEPTH = 8


def to_mitsuba(scene, cam, spp: int):
    """A Mitsuba scene dict for our Scene (two-sided diffuse, area emitters, sun, sky)."""
    import mitsuba as mi

    d = {"type": "scene", "integrator": {"type": "path", "max_depth": MAX_DEPTH, "rr_depth": 4}}
    up = cam.up
    d["sensor"] = {
        "type": "perspective",
        "fov": cam.fov_y_deg,
        "fov_axis": "y",
        "to_world": mi.ScalarTransform4f().look_at(
            origin=cam.position.tolist(),
            target=(cam.position + cam.forward).tolist(),
            up=up.tolist(),
        ),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {
            "type": "hdrfilm",
            "width": cam.width,
            "height": cam.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
    }
    for mi_idx, m in enumerate(scene.materials):
        faces = np.flatnonzero(scene.face_material == mi_idx)
        if len(faces) == 0:
            continue
        if m.is_textured:
            refl = {
                "type": "bitmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(m.texture * m.albedo.astype(np.float32))),
                "raw": True,
                "filter_type": "bilinear",
            }
        else:
            refl = {"type": "rgb", "value": m.albedo.tolist()}
        bsdf = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": refl}}
        d[f"mesh{mi_idx}"] = {
            "type": "ply",
            "filename": _write_ply(scene, faces, mi_idx),
            "bsdf": bsdf,
            "face_normals": False,
        }
        if m.is_emissive:
            d[f"mesh{mi_idx}"]["emitter"] = {
                "type": "area",
                "radiance": {"type": "rgb", "value": m.emission.tolist()},
            }
    for i, lt in enumerate(scene.lights_of("directional")):
        d[f"sun{i}"] = {
            "type": "directional",
            "direction": lt.direction.tolist(),
            "irradiance": {"type": "rgb", "value": lt.irradiance.tolist()},
        }
    if scene.sky is not None:
        if scene.sky.kind == "uniform":
            d["sky"] = {
                "type": "constant",
                "radiance": {"type": "rgb", "value": scene.sky.zenith.tolist()},
            }
        else:  # lat-long envmap of the gradient sky; Mitsuba's envmap: +y up, u along phi
            h, w = 128, 256
            th = (np.arange(h) + 0.5) / h * np.pi
            ph = (np.arange(w) + 0.5) / w * 2 * np.pi
            T, P = np.meshgrid(th, ph, indexing="ij")
            dirs = np.stack([np.sin(P) * np.sin(T), np.cos(T), -np.cos(P) * np.sin(T)], -1)
            img = scene.sky.radiance(dirs).astype(np.float32)
            d["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(img)}
    return d


_PLY_DIR = Path("/tmp/icb_trace_bench_ply")


def _write_ply(scene, faces, idx) -> str:
    import trimesh

    _PLY_DIR.mkdir(exist_ok=True)
    f = scene.faces[faces]
    used, inv = np.unique(f, return_inverse=True)
    path = _PLY_DIR / f"{scene.name}_{idx}.ply"
    tm = trimesh.Trimesh(
        scene.vertices[used], inv.reshape(-1, 3), process=False, vertex_normals=scene.normals[used]
    )
    if scene.uvs is not None:
        tm.visual = trimesh.visual.TextureVisuals(uv=scene.uvs[used])
    tm.export(path)
    return str(path)


def mitsuba_render(scene, cam, spp: int, seed: int = 0) -> tuple[np.ndarray, float]:
    import mitsuba as mi

    sc = mi.load_dict(to_mitsuba(scene, cam, spp))
    t0 = time.perf_counter()
    img = np.asarray(mi.render(sc, spp=spp, seed=seed), np.float32)[..., :3]
    return img, time.perf_counter() - t0


def errors(ref: np.ndarray, img: np.ndarray) -> dict:
    import flip_evaluator

    rmse = float(np.sqrt(np.mean((img - ref) ** 2)))
    a = to_display(ref).astype(np.float32) / 255
    b = to_display(img).astype(np.float32) / 255
    _, flip, _ = flip_evaluator.evaluate(a, b, "LDR")
    return {"rmse": rmse, "flip": float(flip)}


def sponza():
    os.environ.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    return icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")


def main() -> None:
    import mitsuba as mi

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--spps", default="1,2,4,8,16,32")
    ap.add_argument("--scenes", default="cornell_box,sponza")
    args = ap.parse_args()
    try:
        mi.set_variant("llvm_ad_rgb")
    except (ImportError, AttributeError, RuntimeError):
        mi.set_variant("scalar_rgb")
    spps = [int(s) for s in args.spps.split(",")]
    results = {"mitsuba_variant": mi.variant(), "scenes": {}}
    for name in args.scenes.split(","):
        scene = icb.scene.cornell_box() if name == "cornell_box" else sponza()
        cam = scene.default_camera.resized(args.size, args.size)
        base = dict(max_depth=MAX_DEPTH, rr_depth=4, spp_per_pass=4)
        ref_ours = icb.trace.render(scene, cam, TraceConfig(spp=args.ref_spp, seed=1000, **base))
        ref_mi, _ = mitsuba_render(scene, cam, args.ref_spp, seed=1000)
        gap = float(np.sqrt(np.mean((ref_ours.full - ref_mi) ** 2)))
        curves = {"ours_raw": [], "ours_denoised": [], "ours_adaptive": [], "mitsuba": []}
        for spp in tqdm(spps, desc=name):
            r = icb.trace.render(scene, cam, TraceConfig(spp=spp, seed=spp, **base))
            curves["ours_raw"].append(
                {"spp": spp, "time_s": r.stats.time_s["total"], **errors(ref_ours.full, r.full)}
            )
            r = icb.trace.render(scene, cam, TraceConfig(spp=spp, seed=spp, denoise=True, **base))
            curves["ours_denoised"].append(
                {
                    "spp": spp,
                    "time_s": r.stats.time_s["total"],
                    **errors(ref_ours.full, r.direct + r.gi),
                }
            )
            r = icb.trace.render(
                scene,
                cam,
                TraceConfig(
                    spp=4 * spp, seed=spp, adaptive=True, target_error=0.5 / np.sqrt(spp), **base
                ),
            )
            curves["ours_adaptive"].append(
                {
                    "spp": float(r.spp.mean()),
                    "time_s": r.stats.time_s["total"],
                    **errors(ref_ours.full, r.full),
                }
            )
            img, dt = mitsuba_render(scene, cam, spp, seed=spp)
            curves["mitsuba"].append({"spp": spp, "time_s": dt, **errors(ref_mi, img)})
        results["scenes"][name] = {
            "size": args.size,
            "ref_spp": args.ref_spp,
            "reference_gap_rmse": gap,
            "reference_mean_ours": float(ref_ours.full.mean()),
            "reference_mean_mitsuba": float(ref_mi.mean()),
            "curves": curves,
        }
        print(name, "reference gap RMSE", gap, ref_ours.full.mean(), ref_mi.mean())
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(
        OUT / "time_error.json",
        {"args": vars(args), "max_depth": MAX_DEPTH, "results": results, "run_info": run_info()},
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["scenes"])
    fig, axes = plt.subplots(2, len(names), figsize=(5 * len(names), 7), squeeze=False)
    for j, name in enumerate(names):
        for key, c in results["scenes"][name]["curves"].items():
            t = [p["time_s"] for p in c]
            for i, metric in enumerate(("rmse", "flip")):
                axes[i, j].loglog(t, [p[metric] for p in c], "o-", label=key)
                axes[i, j].set_xlabel("time (s)")
                axes[i, j].set_ylabel(f"{metric} of full")
                axes[i, j].set_title(f"{name} {args.size}x{args.size}")
        axes[0, j].legend()
    fig.tight_layout()
    fig.savefig(OUT / "time_error.png", dpi=100)
    print(f"wrote {OUT / 'time_error.json'}")


if __name__ == "__main__":
    main()
