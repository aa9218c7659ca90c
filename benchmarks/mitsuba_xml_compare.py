"""Mitsuba 3 scene files rendered by Mitsuba itself and by icbtool's tracer (full radiance).

For each public Mitsuba scene file given (fetched into a temporary folder, never committed), the
file is loaded by ``icb.scene.load`` (the default camera is the file's sensor, the depth its
integrator's ``max_depth``) and traced; Mitsuba renders the same file through its own parser, so
transforms, shapes, BSDFs, camera and lights are checked end to end. The only changes Mitsuba's
copy gets (``icbtool.scene.mitsuba.diffuse_twin``, in a temporary copy of the scene folder): a
BSDF icbtool approximates becomes the two-sided diffuse BSDF icbtool renders for it (the BSDFs it
traces exactly stay Mitsuba's own), every pixel filter becomes ``box``, and with ``--size`` every
film is resized (``--width``; the height keeps the film's aspect; both renderers read the
resized file).

Numbers per scene: the mean bias per channel (``mean(ours) / mean(mitsuba) - 1``) and the blurred
relative RMSE (Gaussian, sigma ``--blur`` px, of both images; RMSE over pixels and channels over
the mean of Mitsuba's image) of icbtool against Mitsuba seed A, next to the same numbers of
Mitsuba seed B against Mitsuba seed A (Mitsuba's seed-to-seed noise, the floor), all at the same
spp; what icbtool said it skipped or approximated (its warnings). Images side by side
(icbtool | Mitsuba | |difference| x 4) in PNG, and every pair in ``sheet.png``.

Mitsuba's own documentation scenes (mitsuba-data's ``docs/scenes``, with ``common/meshes`` and
``common/textures`` copied beside them and the ``<path value="../../common"/>`` lines removed):

    nice -n 10 .venv/bin/python -m benchmarks.mitsuba_xml_compare --spp 256 --width 128 \
        --scene /tmp/mdocs/bsdf_roughplastic_ggx.xml --scene /tmp/mdocs/bsdf_conductor_gold.xml

Writes --out/compare.json and <folder>_<stem>.png per scene. Mitsuba is
a benchmark peer only (``make bench-deps``).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.imageio import to_display
from icbtool.optional import require
from icbtool.scene import SceneRepairWarning
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


def contact_sheet(out: Path, keys: list[str], columns: int = 4) -> Path:
    """One PNG of every scene's pair (icbtool | Mitsuba, the first two thirds of its strip),
    labelled, in a grid: ``out / "sheet.png"``."""
    from PIL import Image, ImageDraw

    strips = [Image.open(out / f"{k}.png").convert("RGB") for k in keys]
    strips = [s.crop((0, 0, s.width * 2 // 3, s.height)) for s in strips]  # icbtool | Mitsuba
    cw = max(s.width for s in strips)
    ch = max(s.height for s in strips) + 14
    rows = -(-len(strips) // columns)
    sheet = Image.new("RGB", (columns * cw, rows * ch), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, (k, s) in enumerate(zip(keys, strips)):
        x, y = (i % columns) * cw, (i // columns) * ch
        draw.text((x + 2, y + 1), k.split("_", 1)[-1], fill=(0, 0, 0))
        sheet.paste(s, (x, y + 14))
    sheet = sheet.quantize(256)  # a palette image: a tenth of the size, for the repository
    sheet.save(out / "sheet.png", optimize=True)
    return out / "sheet.png"


_FILM = re.compile(r"<film\b.*?</film>", re.S)


def resize_films(folder: Path, width: int, height: int) -> None:
    """Set every film's width and height in the XML files of ``folder`` (a scene's temporary
    copy): Mitsuba then renders at the size icbtool's resized camera has."""
    for f in folder.rglob("*.xml"):
        text = f.read_text()

        def one(m: re.Match) -> str:
            film = re.sub(r'(name="width"\s+value=")[^"]*"', rf'\g<1>{width}"', m.group(0))
            return re.sub(r'(name="height"\s+value=")[^"]*"', rf'\g<1>{height}"', film)

        new = _FILM.sub(one, text)
        if new != text:
            f.write_text(new)


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
    ap.add_argument(
        "--width",
        type=int,
        default=None,
        help="render every scene at this film width (height: the film's aspect), both sides",
    )
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
        "mitsuba_refused": {},
    }
    for spec in args.scene:
        xml = Path(spec[0]).resolve()
        params = dict(p.split("=", 1) for p in spec[1:])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scene = icb.scene.load(xml, params=params)
        approx = [str(w.message) for w in caught if w.category is MaterialApproximationWarning]
        said = sorted(
            {
                str(w.message).replace(str(xml.parent) + "/", "")
                for w in caught
                if issubclass(w.category, (SceneRepairWarning, MaterialApproximationWarning))
            }
        )
        with tempfile.TemporaryDirectory() as tmp:
            if args.width:  # both renderers read the same resized films
                plain = Path(tmp) / "plain"
                shutil.copytree(xml.parent, plain / xml.parent.name)
                cam0 = scene.default_camera
                height = max(1, round(args.width * cam0.height / cam0.width))
                resize_films(plain / xml.parent.name, args.width, height)
                src = plain / xml.parent.name / xml.name
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # said above
                    scene = icb.scene.load(src, params=params)
            else:
                src = xml
            cam = scene.default_camera
            depth = scene.max_depth or 8
            cfg = TraceConfig(spp=args.spp, seed=args.seed, max_depth=depth)
            icb.trace.render(scene, cam.resized(8, 8), TraceConfig(spp=1))  # JIT warm-up
            t0 = time.perf_counter()
            ours = icb.trace.render(scene, cam, cfg).full
            t_ours = time.perf_counter() - t0
            copy = diffuse_twin(src, Path(tmp), params=params)
            mparams = {k: (int(v) if v.lstrip("-").isdigit() else v) for k, v in params.items()}
            try:
                mscene = mi.load_file(str(copy), **mparams)
            except RuntimeError as e:  # a file Mitsuba refuses: said, and the next scene
                results["mitsuba_refused"][str(xml)] = str(e).splitlines()[0]
                print(f"{xml.name}: Mitsuba refuses it: {str(e).splitlines()[0]}")
                continue
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
            "icbtool_said": said,
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
        write_json(OUT / "compare.json", results)  # so far, in case a later scene fails
        side_by_side(ours, mi_a, OUT / f"{key}.png")
        ours_vs, floor = r["icbtool_vs_mitsuba"], r["mitsuba_seed_to_seed"]
        print(
            f"{key}: bias {np.round(np.array(ours_vs['bias_per_channel']) * 100, 2)} %, "
            f"blurred rel RMSE {100 * ours_vs['blurred_rel_rmse']:.2f} % (Mitsuba seed-to-seed: "
            f"bias {np.round(np.array(floor['bias_per_channel']) * 100, 2)} %, "
            f"RMSE {100 * floor['blurred_rel_rmse']:.2f} %)"
        )
    results["load_average_end"] = list(os.getloadavg())
    contact_sheet(OUT, list(results["scenes"]))
    write_json(OUT / "compare.json", results)
    print(f"-> {OUT / 'compare.json'}")


if __name__ == "__main__":
    main()
