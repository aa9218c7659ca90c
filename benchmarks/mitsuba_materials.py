"""Mitsuba 3's BSDFs: icbtool's tracer against Mitsuba 3 on material-preview scenes.

Each scene is a sphere of one BSDF on a diffuse floor under a constant environment and a small
area light (the scenes of tests/test_trace_bsdf.py's peer suite, larger here). Mitsuba 3
(``scalar_rgb``, the same file) renders a reference at ``--ref-spp``; both renderers then render
at each of ``--spp`` with a new seed. Per scene and spp: mean bias per channel of icbtool
(``mean(ours) / mean(ref) - 1``), blurred relative RMSE (Gaussian sigma 1.5 px) of each renderer
against the reference, FLIP (when ``flip-evaluator`` is installed), wall time of each; and the
time icbtool needs to reach Mitsuba's RMSE at the highest spp (log-log interpolation of its
RMSE over time: "time to equal RMSE"). A side-by-side PNG per scene (icbtool | Mitsuba | |diff|
x 4, at the highest spp).

    nice -n 10 .venv/bin/python -m benchmarks.mitsuba_materials --out /tmp/mm [--size 128]

Writes ``OUT/mitsuba_materials.json`` and ``OUT/<scene>.png``, with the machine, versions and the
load (``os.getloadavg``) of every render. Mitsuba is a benchmark peer only.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import icbtool as icb
from icbtool.provenance import run_info
from icbtool.trace import TraceConfig

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "mitsuba_materials"

SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="16"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="35"/>
    <transform name="to_world">
      <lookat origin="0, 1.2, 4" target="0, 0.1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/>
      <integer name="height" value="{size}"/><rfilter type="box"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.8, 0.85, 0.9"/></emitter>
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.8"/><rotate x="1" angle="90"/>
      <translate y="2.5" z="0.5"/></transform>
    <emitter type="area"><rgb name="radiance" value="4, 4, 4"/></emitter>
  </shape>
  <shape type="rectangle">
    <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
      <translate y="-1"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.5"/><rgb name="color1" value="0.2"/>
      <transform name="to_uv"><scale x="6" y="6"/></transform></texture></bsdf>
  </shape>
  <shape type="sphere">{bsdf}</shape>
</scene>"""

BSDFS = {
    "diffuse": '<bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.3, 0.2"/></bsdf>',
    "plastic": '<bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.6, 0.2, 0.1"/>'
    "</bsdf>",
    "roughplastic": '<bsdf type="roughplastic"><rgb name="diffuse_reflectance" '
    'value="0.1, 0.3, 0.6"/><float name="alpha" value="0.2"/></bsdf>',
    "conductor_cu": '<bsdf type="conductor"><string name="material" value="Cu"/></bsdf>',
    "roughconductor_au": '<bsdf type="roughconductor"><string name="material" value="Au"/>'
    '<string name="distribution" value="ggx"/><float name="alpha" value="0.25"/></bsdf>',
    "dielectric": '<bsdf type="dielectric"/>',
    "thindielectric": '<bsdf type="thindielectric"/>',
    "roughdielectric": '<bsdf type="roughdielectric"><float name="alpha" value="0.15"/></bsdf>',
    "blendbsdf": '<bsdf type="blendbsdf"><float name="weight" value="0.4"/>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.2, 0.2"/></bsdf>'
    '<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf></bsdf>',
    "mask": '<bsdf type="mask"><float name="opacity" value="0.5"/>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.6, 0.2"/></bsdf></bsdf>',
}


def blur(img: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, sigma=(sigma, sigma, 0), mode="nearest")


def rel_rmse(img: np.ndarray, ref: np.ndarray) -> float:
    d = blur(img) - blur(ref)
    return float(np.sqrt(np.mean(d**2)) / max(float(ref.mean()), 1e-12))


def flip_or_none(ref: np.ndarray, img: np.ndarray) -> float | None:
    try:
        return float(icb.metrics.flip(ref, img))
    except Exception:  # noqa: BLE001 - FLIP is optional (extra 'metrics')
        return None


def time_to_rmse(times: list[float], rmses: list[float], target: float) -> float | None:
    """Time at which the log-log line through (time, RMSE) reaches ``target`` RMSE."""
    t, e = np.log(np.asarray(times)), np.log(np.asarray(rmses))
    if len(t) < 2 or not np.all(np.isfinite(e)):
        return None
    slope, icept = np.polyfit(t, e, 1)
    if slope > -0.2:  # error not falling with time (bias-dominated): no meaningful answer
        return None
    return float(np.exp((np.log(target) - icept) / slope))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, nargs="+", default=[16, 64])
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--scenes", nargs="+", default=list(BSDFS), choices=list(BSDFS))
    args = ap.parse_args(argv)
    import mitsuba as mi

    from icbtool.imageio import to_display

    mi.set_variant("scalar_rgb")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            xml = Path(tmp) / f"{name}.xml"
            xml.write_text(SCENE.format(size=args.size, bsdf=BSDFS[name]))
            mscene = mi.load_file(str(xml))
            ref = np.array(mi.render(mscene, spp=args.ref_spp, seed=100))[..., :3]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scene = icb.scene.load(xml)
            cam = scene.default_camera
            icb.trace.render(scene, cam, TraceConfig(spp=1))  # kernels loaded before timing
            row = {"scene": name, "runs": []}
            for spp in args.spp:
                t0 = time.perf_counter()
                theirs = np.array(mi.render(mscene, spp=spp, seed=7))[..., :3]
                t_mi = time.perf_counter() - t0
                t0 = time.perf_counter()
                r = icb.trace.render(scene, cam, TraceConfig(spp=spp, max_depth=16, seed=7))
                t_ours = time.perf_counter() - t0
                ours = r.gi + r.direct
                bias = ours.reshape(-1, 3).mean(0) / ref.reshape(-1, 3).mean(0) - 1
                row["runs"].append({
                    "spp": spp, "bias_per_channel": bias.tolist(),
                    "rel_rmse_icbtool": rel_rmse(ours, ref),
                    "rel_rmse_mitsuba": rel_rmse(theirs, ref),
                    "flip_icbtool": flip_or_none(ref, ours),
                    "flip_mitsuba": flip_or_none(ref, theirs),
                    "time_s_icbtool": t_ours, "time_s_mitsuba": t_mi, "load": os.getloadavg()[0],
                    "kernel_note": [s for s in r.stats.skipped if "kernel" in s],
                })  # fmt: skip
            runs = row["runs"]
            row["time_s_icbtool_to_mitsuba_rmse"] = time_to_rmse(
                [x["time_s_icbtool"] for x in runs], [x["rel_rmse_icbtool"] for x in runs],
                runs[-1]["rel_rmse_mitsuba"],
            )  # fmt: skip
            row["time_s_mitsuba"] = runs[-1]["time_s_mitsuba"]
            rows.append(row)
            side = np.concatenate([ours, theirs, np.abs(ours - theirs) * 4], 1)
            from PIL import Image

            Image.fromarray(to_display(side)).save(args.out / f"{name}.png")
            last = runs[-1]
            print(name, "bias", np.round(last["bias_per_channel"], 4).tolist(), "rmse ours/mi",
                  round(last["rel_rmse_icbtool"], 4), round(last["rel_rmse_mitsuba"], 4),
                  "t ours/mi", round(last["time_s_icbtool"], 2), round(last["time_s_mitsuba"], 2),
                  "t_eq", row["time_s_icbtool_to_mitsuba_rmse"], flush=True)  # fmt: skip
    out = {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows, "run_info": run_info()}
    (args.out / "mitsuba_materials.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
