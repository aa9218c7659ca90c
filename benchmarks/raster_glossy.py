"""Client raster: ms per ``dl`` frame on the Cornell box (Lambert) and its glossy variant.

For ``cornell_box`` and ``cornell_box_glossy`` from their default cameras at ``--size`` (256):
one :class:`icbtool.raster.Rasterizer` per configuration (shadow maps cached), 2 warm-up frames,
then the median of ``--frames`` frames of ``dl`` alone; on the glossy box also with
``glossy_area_samples`` 4 and 16 (default 8). Configurations are interleaved round by round so
that they see the same machine load, which is recorded (``os.getloadavg()``) at the start and
end; ``cornell_box_glossy_as_lambert`` is the glossy box with its Lambert stand-ins (no BSDF).
Run it in a checkout from before glossy support (``--label before``: the Lambert box only) and
with it (``--label after``) to compare the Lambert path.

Writes --out/results_<label>.json.

Usage: .venv/bin/python -m benchmarks.raster_glossy [--frames 10] [--size 256] [--label after]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

from benchmarks.common import add_out_argument, load_average, write_results


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="timed frames per configuration")
    ap.add_argument("--size", type=int, default=256, help="image height and width")
    ap.add_argument(
        "--lambert-only", action="store_true", help="time the Lambertian Cornell box alone"
    )
    ap.add_argument("--label", default="after", help="name of this run (results_<label>.json)")
    add_out_argument(ap, "raster_glossy")
    args = ap.parse_args(argv)

    import icbtool as icb
    from icbtool.raster import RasterConfig, Rasterizer

    load_start = load_average()
    n = args.size
    runs = {"cornell_box": (icb.scene.PROCEDURAL["cornell_box"](n, n), {})}
    if not args.lambert_only and "cornell_box_glossy" in icb.scene.PROCEDURAL:
        glossy = icb.scene.PROCEDURAL["cornell_box_glossy"](n, n)
        runs["cornell_box_glossy"] = (glossy, {})
        # the same box with the Lambert stand-ins (no BSDF): what glossy shading adds
        stand_in = [dataclasses.replace(m, bsdf=None) for m in glossy.materials]
        runs["cornell_box_glossy_as_lambert"] = (
            dataclasses.replace(glossy, materials=stand_in),
            {},
        )
        for k in (4, 16):
            runs[f"cornell_box_glossy_n{k}"] = (glossy, {"glossy_area_samples": k})
    rasters = {
        name: Rasterizer(scene, RasterConfig(backend="osmesa", **kw))
        for name, (scene, kw) in runs.items()
    }
    times: dict[str, list[float]] = {name: [] for name in runs}
    try:
        for name, r in rasters.items():
            for _ in range(2):
                r.render(runs[name][0].default_camera, "dl")
        for _ in range(args.frames):
            for name, r in rasters.items():
                t0 = time.perf_counter()
                r.render(runs[name][0].default_camera, "dl")
                times[name].append(1e3 * (time.perf_counter() - t0))
    finally:
        for r in rasters.values():
            r.close()
    out = {
        "label": args.label,
        "lambert_only": args.lambert_only,
        "size": n,
        "frames": args.frames,
        "ms_median": {k: statistics.median(v) for k, v in times.items()},
        "ms": times,
    }
    path = write_results(args.out / f"results_{args.label}.json", out, load_start)
    for k, v in out["ms_median"].items():
        print(f"{k}: {v:.1f} ms")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
