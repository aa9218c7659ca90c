"""Soft shadows of the client's DL against the tracer's direct light: penumbra and lit bias.

For each scene view, the tracer's ``direct`` (box-filtered pixels, max_depth 2, ``--spp``) is the
reference; pixels are classified by :func:`icbtool.raster.accuracy.shadow_bias` (the reference
over the unshadowed raster light: a penumbra in (0.05, 0.95), lit from 0.98; interior pixels only,
from a 4x finer raster, without the emitter seen). Raster configurations:

* ``default``: ``RasterConfig()`` of this checkout;
* ``supersample2``: ``RasterConfig(dl_supersample=2)`` of this checkout;
* ``before_default`` / ``before_supersample2``: the same two configurations rendered by another
  checkout's Python (``--before-python``, e.g. main's venv before this change; its ``dl`` images
  come back through a temporary .npz, so only the public ``Rasterizer`` API is used there).

Each is judged twice: on ``dl`` itself, and on its shading (``dl / albedo``, each renderer's own
albedo: the raster's at the points it shaded, the tracer's box-filtered ``albedo``), which sets the
light apart from how the two filter textures (Sponza).

Timing: median ``dl``-only raster time at 512^2 of each configuration (warm Rasterizer, shadow maps
cached, ``--frames`` frames), over ``--rounds`` rounds that run the baseline's process and this
checkout's back to back, so that both see the same load; the 1-minute load average at the start
and end of each process is recorded (the machine is shared).

Views: the built-in Cornell box (its camera; and a view inside it of the tall block's shadow on
the red wall and the floor, at grazing incidence), the classic Cornell data as a glTF in
millimetres scaled to metres (benchmarks/cornell_gltf.py: McGuire-style geometry, one emissive quad
promoted to an area light), and Sponza (sun + sky; hard shadows) when ``$ICBTOOL_SPONZA`` or the
shared copy exists.

    python -m benchmarks.raster_shadow_accuracy [--size 128] [--spp 1024]
        [--before-python OTHER_CHECKOUT/.venv/bin/python] [--out benchmarks/results/raster]

Writes OUT/shadow_accuracy.json and OUT/shadow_accuracy.png (per view: traced | each config |
|difference| / mean, white = 20 %).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, add_out_argument, load_average, sponza, write_results

CONFIGS = {"default": {}, "supersample2": {"dl_supersample": 2}}


def views(size: int) -> dict:
    """name -> (scene loader key, camera) of every view measured."""
    import icbtool as icb
    from icbtool.camera import Camera

    cb = icb.scene.cornell_box()
    out = {
        "cornell_box": ("cornell_box", cb.default_camera.resized(size, size)),
        "cornell_box_inside": (
            "cornell_box",
            Camera.look_at((0.4, 0.9, 0.6), (-1.0, 0.5, -0.4), (0, 1, 0), 60, size, size),
        ),
    }
    from benchmarks.cornell_gltf import cornell_camera_m

    out["cornell_gltf"] = ("cornell_gltf", cornell_camera_m(size, size))
    if sponza_path() is not None:
        sp = load_scene("sponza")
        out["sponza"] = ("sponza", sp.default_camera.resized(size, size))
    return out


def sponza_path() -> Path | None:
    """The Sponza mesh folder (``$ICBTOOL_SPONZA``, default the repository's sibling
    ``shared/scenes/sponza``), or None where it is missing."""
    root = Path(os.environ.get("ICBTOOL_SPONZA", REPO.parent / "shared" / "scenes" / "sponza"))
    return root if (root / "sponza_textured.obj").exists() else None


_SCENES: dict = {}


def load_scene(key: str):
    """The scene of a view (cached; the glTF is written into a temporary folder)."""
    if key in _SCENES:
        return _SCENES[key]
    import icbtool as icb

    if key == "cornell_box":
        s = icb.scene.cornell_box()
    elif key == "cornell_gltf":
        from benchmarks.cornell_gltf import write_cornell_gltf

        tmp = Path(tempfile.mkdtemp(prefix="icb_shadow_acc_"))
        s = icb.scene.load(write_cornell_gltf(tmp / "cornell_mm.gltf"))
    elif key == "sponza":
        s = sponza()
    else:
        raise ValueError(f"unknown scene {key!r}")
    _SCENES[key] = s
    return s


def render_dl(size: int, timing_frames: int, out: Path) -> None:
    """Render every view's dl under each config with this process's icbtool (maybe a baseline
    checkout), and the dl-only times at 512^2; save them to ``out`` (.npz)."""
    from icbtool.raster import RasterConfig, Rasterizer

    arrays: dict[str, np.ndarray] = {}
    for name, (key, cam) in views(size).items():
        scene = load_scene(key)
        for cfg_name, kw in CONFIGS.items():
            with Rasterizer(scene, RasterConfig(**kw)) as r:
                arrays[f"{name}/{cfg_name}/dl"] = r.render(cam, "dl").dl
                big = cam.resized(512, 512)
                r.render(big, "dl")  # shadow maps, shaders
                ts = []
                for _ in range(timing_frames):
                    t0 = time.perf_counter()
                    r.render(big, "dl")
                    ts.append(1e3 * (time.perf_counter() - t0))
                arrays[f"{name}/{cfg_name}/ms"] = np.array(ts)
    np.savez(out, **arrays)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=5, help="timed 512^2 frames per config")
    ap.add_argument("--rounds", type=int, default=2, help="back-to-back timing rounds")
    ap.add_argument("--before-python", default=None, help="baseline checkout's python")
    add_out_argument(ap, "raster")
    ap.add_argument("--render-only", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.render_only is not None:  # the baseline's subprocess
        render_dl(args.size, args.frames, args.render_only)
        return

    from scipy.ndimage import binary_dilation

    from icbtool.imageio import to_display, write_png
    from icbtool.raster import RasterConfig, Rasterizer
    from icbtool.raster.accuracy import interior_pixels, shadow_bias
    from icbtool.trace import TraceConfig, render

    load_start = load_average()
    runs: dict[str, tuple[dict, list]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.rounds):
            for label, py in (("before", args.before_python), ("", sys.executable)):
                if py is None:
                    continue
                f = Path(tmp) / f"{label or 'after'}.npz"
                load0 = load_average()[0]
                cmd = [py, "-m", "benchmarks.raster_shadow_accuracy", "--render-only", str(f)]
                cmd += ["--size", str(args.size), "--frames", str(args.frames)]
                subprocess.run(cmd, check=True, cwd=REPO)
                got = dict(np.load(f))
                if label in runs:  # images are deterministic: keep the first; pool the times
                    old, loads = runs[label]
                    for k in old:
                        if k.endswith("/ms"):
                            old[k] = np.concatenate([old[k], got[k]])
                    loads.append([load0, load_average()[0]])
                else:
                    runs[label] = (got, [[load0, load_average()[0]]])
    results: dict = {}
    strips = []
    for name, (key, cam) in views(args.size).items():
        scene = load_scene(key)
        t0 = time.perf_counter()
        traced = render(scene, cam, TraceConfig(spp=args.spp, max_depth=2, seed=1))
        ref = traced.direct
        t_ref = time.perf_counter() - t0
        h, w = cam.height, cam.width
        with Rasterizer(scene, RasterConfig(shadows=False)) as r:
            fine = r.render(cam.resized(4 * h, 4 * w), ("normal_world", "albedo", "position", "dl"))
            # the albedo each config's dl was shaded with: pixel centres, or a 2x2 box
            alb = {
                "default": r.render(cam, "albedo").albedo,
                "supersample2": r.render(cam.resized(2 * h, 2 * w), "albedo")
                .albedo.reshape(h, 2, w, 2, 3)
                .mean((1, 3)),
            }
        free = fine.dl.reshape(h, 4, w, 4, 3).mean((1, 3))
        free_alb = fine.albedo.reshape(h, 4, w, 4, 3).mean((1, 3))
        # the emitters seen, and 2 pixels around them (a ceiling pixel beside a light's edge
        # lies in the light's plane, and its footprint may hold some of the light)
        seen_light = binary_dilation(free.mean(-1) > 0.5 * free.mean(-1).max(), iterations=2)
        select = interior_pixels(fine, 4) & ~seen_light
        rows = {}
        imgs = [ref]
        for label, (arrays, loads) in runs.items():
            for cfg_name in CONFIGS:
                dl = arrays[f"{name}/{cfg_name}/dl"]
                b = shadow_bias(dl, ref, free, select)
                # shading (dl / albedo): the light alone, apart from how each renderer filters
                # textures (the raster: a mipmapped sRGB8 array; the tracer: bilinear texels)
                a = alb[cfg_name]
                ok = select & (np.minimum(a, traced.albedo).min(-1) > 1e-3)
                ok &= free_alb.min(-1) > 1e-3
                sh = shadow_bias(
                    dl / np.maximum(a, 1e-3),
                    ref / np.maximum(traced.albedo, 1e-3),
                    free / np.maximum(free_alb, 1e-3),
                    ok,
                )
                full = f"{label}_{cfg_name}" if label else cfg_name
                ms = arrays[f"{name}/{cfg_name}/ms"]
                rows[full] = {
                    **b.as_dict(),
                    "shading": sh.as_dict(),
                    "dl_ms_512_median": float(np.median(ms)),
                    "dl_ms_512_all": ms.tolist(),
                    "load_average_1min_start_end": loads,
                }
                imgs.append(dl)
                print(
                    f"{name:20s} {full:22s} penumbra % {np.round(100 * b.penumbra, 2)} "
                    f"({b.penumbra_pixels} px)  lit % {np.round(100 * b.lit, 2)} "
                    f"({b.lit_pixels} px)  shading: penumbra % {np.round(100 * sh.penumbra, 2)} "
                    f"lit % {np.round(100 * sh.lit, 2)}  dl {np.median(ms):.0f} ms @512^2"
                )
        results[name] = {
            "size": [h, w],
            "reference": {"spp": args.spp, "max_depth": 2, "time_s": t_ref},
            "configs": rows,
        }
        lum = ref.mean(-1)
        e = 1.0 / max(float(np.percentile(lum[~seen_light], 99)), 1e-6)
        strip = [to_display(x, e) for x in imgs]
        mean = max(float(ref[~seen_light].mean()), 1e-6)
        for x in imgs[1:]:
            d = np.clip(np.abs(x - ref).mean(-1, keepdims=True) / mean / 0.2, 0, 1)
            strip.append(to_display(np.repeat(d, 3, -1)))
        strips.append(np.concatenate(strip, axis=1))
    args.out.mkdir(parents=True, exist_ok=True)
    write_results(
        args.out / "shadow_accuracy.json",
        {
            "args": {k: str(v) for k, v in vars(args).items() if k != "render_only"},
            "configs": CONFIGS,
            "views": results,
        },
        load_start,
    )
    write_png(args.out / "shadow_accuracy.png", np.concatenate(strips, axis=0))
    print(f"wrote {args.out / 'shadow_accuracy.json'} and shadow_accuracy.png")


if __name__ == "__main__":
    main()
