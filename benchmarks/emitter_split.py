"""GI of a mesh emitter: icbtool's traced GI (full - direct) against Mitsuba 3's indirect light.

The classic Cornell box written as a glTF in millimetres (node scale 0.001) with an emissive
ceiling quad and no punctual lights (tests/cornell_gltf.py) is loaded with ``icbtool.scene.load``
(the quad is promoted to an area light, so its direct light is in ``direct``); our GI is
``render(...).gi`` (path depth unbounded). Mitsuba's indirect radiance is the same scene (built
from the loaded Scene: same triangles, albedos, emission) rendered with ``max_depth=-1`` minus
``max_depth=2`` (emission seen + direct light), same camera (``look_at`` from the icbtool
camera's position, forward and up; checked by the red wall being on the left in both).

Reports the mean relative bias of our GI against Mitsuba's per channel (mean over the image of
ours / mean of theirs - 1) and on the whole image (all channels), and writes
benchmarks/results/emitters/emitter_split.{json,png} (PNG: ours | Mitsuba | |difference| x 4).

    .venv/bin/python -m benchmarks.emitter_split [--size 96] [--spp 1024] [--mi-spp 2048]
        [--variant llvm_ad_rgb]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import icbtool.scene as sc
from benchmarks.common import add_out_argument, run_info, write_json
from benchmarks.cornell_gltf import cornell_camera_m, write_cornell_gltf
from benchmarks.trace_time_error import to_mitsuba
from icbtool.imageio import to_display, write_png
from icbtool.trace import TraceConfig, render

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "emitters"


def mitsuba_image(scene, cam, spp: int, max_depth: int, seed: int) -> np.ndarray:
    import mitsuba as mi

    d = to_mitsuba(scene, cam, spp, max_depth)
    d["integrator"]["rr_depth"] = 5
    img = mi.render(mi.load_dict(d), spp=spp, seed=seed)
    return np.asarray(img, np.float32)[..., :3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=1024, help="icbtool samples per pixel")
    ap.add_argument("--mi-spp", type=int, default=2048, help="Mitsuba samples per pixel")
    ap.add_argument("--variant", default="llvm_ad_rgb", choices=["llvm_ad_rgb", "scalar_rgb"])
    ap.add_argument("--seed", type=int, default=0)
    add_out_argument(ap, "emitters")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    try:
        import mitsuba as mi
    except ImportError as e:
        raise SystemExit(f"FAIL: mitsuba is not installed ({e}); run `make bench-deps`") from e
    if args.variant not in mi.variants():
        raise SystemExit(
            f"FAIL: Mitsuba variant {args.variant!r} is not available (have {mi.variants()}); "
            "no fallback: pick one with --variant"
        )
    mi.set_variant(args.variant)

    with tempfile.TemporaryDirectory() as tmp:
        scene = sc.load(write_cornell_gltf(Path(tmp) / "cornell_mm.gltf"))
    assert len(scene.lights_of("area")) == 1, scene.lights
    cam = cornell_camera_m(args.size, args.size)

    t0 = time.perf_counter()
    ours = render(scene, cam, TraceConfig(spp=args.spp, seed=args.seed, max_depth=-1, aux=False))
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    mi_full = mitsuba_image(scene, cam, args.mi_spp, -1, args.seed)
    mi_d2 = mitsuba_image(scene, cam, args.mi_spp, 2, args.seed + 1)
    t_mi = time.perf_counter() - t0
    theirs = mi_full - mi_d2

    # orientation check: the red wall (x = 556 mm) is on the left of both images
    red_left = bool(
        ours.full[:, : args.size // 8, 0].mean() > ours.full[:, -args.size // 8 :, 0].mean()
    )
    mi_red_left = bool(
        mi_full[:, : args.size // 8, 0].mean() > mi_full[:, -args.size // 8 :, 0].mean()
    )
    if not (red_left and mi_red_left):
        raise SystemExit(
            f"FAIL: camera mismatch (red wall left: ours {red_left}, mitsuba {mi_red_left})"
        )

    per_channel = ours.gi.mean((0, 1)) / theirs.mean((0, 1)) - 1.0
    whole = float(ours.gi.sum() / theirs.sum() - 1.0)
    full_bias = ours.full.mean((0, 1)) / mi_full.mean((0, 1)) - 1.0
    direct_bias = ours.direct.mean((0, 1)) / mi_d2.mean((0, 1)) - 1.0
    res = {
        "what": "mean relative bias of icbtool GI (full - direct, promoted mesh emitter) against "
        "Mitsuba indirect (max_depth -1 minus 2), Cornell box glTF in mm",
        "config": vars(args),
        "mitsuba_variant": mi.variant(),
        "mitsuba_version": mi.__version__,
        "gi_bias_per_channel": per_channel.tolist(),
        "gi_bias_whole_image": whole,
        "full_bias_per_channel": full_bias.tolist(),
        "direct_bias_per_channel": direct_bias.tolist(),
        "gi_mean_ours": ours.gi.mean((0, 1)).tolist(),
        "gi_mean_mitsuba": theirs.mean((0, 1)).tolist(),
        "target_abs_bias": 0.03,
        "within_target": bool(np.all(np.abs(per_channel) < 0.03) and abs(whole) < 0.03),
        "time_s": {"icbtool": t_ours, "mitsuba_two_renders": t_mi},
        "run": run_info(),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / "emitter_split.json", res)
    exp = 1.0 / max(float(np.percentile(theirs, 99)), 1e-6)
    diff = np.abs(ours.gi - theirs) * 4
    panel = np.concatenate(
        [to_display(ours.gi, exp), to_display(theirs, exp), to_display(diff, exp)], axis=1
    )
    write_png(OUT / "emitter_split.png", panel)
    print(f"GI bias per channel (ours / mitsuba - 1): {np.round(per_channel, 4).tolist()}")
    print(f"GI bias whole image: {whole:+.4f}   (target |bias| < 0.03: {res['within_target']})")
    print(f"full bias per channel: {np.round(full_bias, 4).tolist()}")
    print(f"direct bias per channel: {np.round(direct_bias, 4).tolist()}")
    print(f"wrote {OUT / 'emitter_split.json'} and emitter_split.png")


if __name__ == "__main__":
    main()
