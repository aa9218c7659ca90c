"""Mitsuba 3 scene files rendered by Mitsuba itself and by icbtool's tracer (full radiance).

For each public Mitsuba scene file given (fetched into a temporary folder, never committed), the
file is loaded by ``icb.scene.load`` (the default camera is the file's sensor, the depth its
integrator's ``max_depth``) and traced; Mitsuba renders the same file through its own parser, so
transforms, shapes, camera and lights are checked end to end. The only changes Mitsuba's copy
gets (``icbtool.scene.mitsuba.diffuse_twin``, in a temporary copy of the scene folder): every
BSDF becomes the two-sided diffuse BSDF icbtool renders for it (same albedo: the approximated
ones switched to diffuse in both), and every pixel filter becomes ``box``.

Numbers per scene: the mean bias per channel (``mean(ours) / mean(mitsuba) - 1``) and the blurred
relative RMSE (Gaussian, sigma ``--blur`` px, of both images; RMSE over pixels and channels over
the mean of Mitsuba's image) of icbtool against Mitsuba seed A, next to the same numbers of
Mitsuba seed B against Mitsuba seed A (Mitsuba's seed-to-seed noise, the floor), all at the same
spp. Images side by side (icbtool | Mitsuba | |difference| x 4) in PNG.

    nice -n 10 .venv/bin/python -m benchmarks.mitsuba_xml_compare \\
        --scene /tmp/mitsuba_scenes/scenes/cbox/cbox-rgb.xml res=128 \\
        --scene /tmp/mitsuba_scenes/bitterli_cbox.xml resx=128 resy=128

Writes --out/compare.json and <folder>_<stem>.png per scene. Mitsuba is
a benchmark peer only (``make bench-deps``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.imageio import to_display
from icbtool.optional import require
from icbtool.scene.mitsuba import diffuse_twin
from icbtool.scene.obj import MaterialApproximationWarning
from icbtool.trace import TraceConfig

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "mitsuba_xml"


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, sigma=(sigma, sigma, 0), mode="nearest")


def compare(img: np.ndarray, ref: np.ndarray, sigma: float) -> dict:
    m_ref = ref.mean((0, 1))
    bias = img.mean((0, 1)) / np.maximum(m_ref, 1e-12) - 1
    d = blur(img, sigma) - blur(ref, sigma)
    rel = float(np.sqrt(np.mean(d**2)) / max(float(ref.mean()), 1e-12))
    return {"bias_per_channel": bias.tolist(), "blurred_rel_rmse": rel}


def side_by_side(ours: np.ndarray, theirs: np.ndarray, path: Path) -> None:
    from PIL import Image

    scale = 1.0 / max(float(np.percentile(theirs.mean(-1), 99)), 1e-6)
    diff = np.abs(ours - theirs) * 4
    strip = np.concatenate([ours, theirs, diff], axis=1) * scale
    Image.fromarray(to_display(strip.astype(np.float32))).save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--scene",
        nargs="+",
        action="append",
        required=True,
        metavar=("XML", "PARAM=VALUE"),
        help="a Mitsuba scene file and its $-parameters (e.g. the film size)",
    )
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--blur", type=float, default=1.5, help="Gaussian sigma in pixels")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--seed", type=int, default=0)
    add_out_argument(ap, "mitsuba_xml")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    mi = require("mitsuba", "the Mitsuba 3 benchmark peer (make bench-deps)")
    if args.variant not in mi.variants():
        raise SystemExit(f"FAIL: Mitsuba variant {args.variant!r} unavailable: {mi.variants()}")
    mi.set_variant(args.variant)
    OUT.mkdir(parents=True, exist_ok=True)
    results: dict = {
        "run_info": run_info(),
        "mitsuba_version": mi.__version__,
        "mitsuba_variant": mi.variant(),
        "config": {**vars(args), "scene": [list(x) for x in args.scene]},
        "load_average_start": list(os.getloadavg()),
        "scenes": {},
    }
    for spec in args.scene:
        xml = Path(spec[0]).resolve()
        params = dict(p.split("=", 1) for p in spec[1:])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scene = icb.scene.load(xml, params=params)
        approx = [str(w.message) for w in caught if w.category is MaterialApproximationWarning]
        cam = scene.default_camera
        depth = scene.max_depth or 8
        cfg = TraceConfig(spp=args.spp, seed=args.seed, max_depth=depth)
        icb.trace.render(scene, cam.resized(8, 8), TraceConfig(spp=1))  # JIT warm-up
        t0 = time.perf_counter()
        ours = icb.trace.render(scene, cam, cfg).full
        t_ours = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            copy = diffuse_twin(xml, tmp, params=params)
            mparams = {k: (int(v) if v.lstrip("-").isdigit() else v) for k, v in params.items()}
            mscene = mi.load_file(str(copy), **mparams)
            t0 = time.perf_counter()
            mi_a = np.asarray(mi.render(mscene, spp=args.spp, seed=args.seed + 1))[..., :3]
            t_mi = time.perf_counter() - t0
            mi_b = np.asarray(mi.render(mscene, spp=args.spp, seed=args.seed + 2))[..., :3]
        if mi_a.shape != ours.shape:
            raise SystemExit(f"FAIL: image sizes differ: ours {ours.shape}, Mitsuba {mi_a.shape}")
        r = {
            "file": str(xml),
            "params": params,
            "triangles": scene.n_triangles,
            "materials": len(scene.materials),
            "lights": len(scene.lights),
            "max_depth": depth,
            "approximated_bsdfs_switched_to_diffuse": len(approx),
            "camera": repr(cam),
            "icbtool_vs_mitsuba": compare(ours, mi_a, args.blur),
            "mitsuba_seed_to_seed": compare(mi_b, mi_a, args.blur),
            "mean_rgb": {
                "icbtool": ours.mean((0, 1)).tolist(),
                "mitsuba": mi_a.mean((0, 1)).tolist(),
            },
            "time_s": {"icbtool": t_ours, "mitsuba_one_render": t_mi},
        }
        key = f"{xml.parent.name}_{xml.stem}"
        results["scenes"][key] = r
        side_by_side(ours, mi_a, OUT / f"{key}.png")
        ours_vs, floor = r["icbtool_vs_mitsuba"], r["mitsuba_seed_to_seed"]
        print(
            f"{key}: bias {np.round(np.array(ours_vs['bias_per_channel']) * 100, 2)} %, "
            f"blurred rel RMSE {100 * ours_vs['blurred_rel_rmse']:.2f} % (Mitsuba seed-to-seed: "
            f"bias {np.round(np.array(floor['bias_per_channel']) * 100, 2)} %, "
            f"RMSE {100 * floor['blurred_rel_rmse']:.2f} %)"
        )
    results["load_average_end"] = list(os.getloadavg())
    write_json(OUT / "compare.json", results)
    print(f"-> {OUT / 'compare.json'}")


if __name__ == "__main__":
    main()
