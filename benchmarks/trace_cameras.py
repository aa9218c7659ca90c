"""What a thin lens and an orthographic camera cost the tracer, against the pinhole.

One process renders the Cornell box through three cameras of the same size, alternating them in
every round (the order rotates), so all three see the same machine load: the scene's pinhole, a
thin lens focused on the box's centre (an aperture of 5 % of the camera's distance to it) and an
orthographic camera that frames the box. Reported per camera: the median over rounds of the
tracer's rays per second of process CPU time (less sensitive to other processes' load than wall
time; single-threaded by default) and of wall time, and the median per-round ratio to the
pinhole's, with the 1-minute load of every render.

    .venv/bin/python -m benchmarks.trace_cameras [--size 128] [--spp 8] [--rounds 7]

Writes --out/cameras.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import replace

import numpy as np

from benchmarks.common import add_out_argument, load_average, write_results


def cameras(scene, size: int) -> dict:
    """The three cameras (name -> Camera): pinhole, thin lens, orthographic."""
    cam = scene.default_camera.resized(size, size)
    lo, hi = np.asarray(scene.bounds, np.float64)
    centre = (lo + hi) / 2
    depth = float((centre - cam.position) @ cam.forward)
    lens = replace(cam, aperture_radius=0.05 * depth, focus_distance=depth)
    extent = float(np.max(hi - lo)) * 1.05  # world units the orthographic image spans
    ortho = replace(
        cam,
        projection="orthographic",
        fx=size / extent,
        fy=size / extent,
        cx=size / 2,
        cy=size / 2,
        near_clip=0.0,
    )
    return {"pinhole": cam, "thinlens": lens, "orthographic": ortho}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    import icbtool as icb
    from icbtool.trace import TraceConfig, render

    load_start = load_average()
    scene = icb.scene.cornell_box()
    cams = cameras(scene, args.size)
    cfg = TraceConfig(spp=args.spp, spp_per_pass=4, max_depth=8, seed=0, threads=args.threads)
    for cam in cams.values():  # compiled and warm before timing
        render(scene, cam, TraceConfig(spp=1))
    names = list(cams)
    rounds = []
    for r in range(args.rounds):
        row = {}
        for name in names[r % 3 :] + names[: r % 3]:
            c0, t0 = time.process_time(), time.perf_counter()
            st = render(scene, cams[name], cfg).stats
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            row[name] = {
                "mrays_per_cpu_s": st.total_rays / cpu / 1e6,
                "mrays_wall": st.total_rays / wall / 1e6,
                "rays": st.total_rays,
                "load": os.getloadavg()[0],
            }
        rounds.append(row)
        print(r, "  ".join(f"{n} {row[n]['mrays_per_cpu_s']:.3f}" for n in names), flush=True)
    summary = {}
    for n in names:
        summary[n] = {
            "median_mrays_per_cpu_s": statistics.median(x[n]["mrays_per_cpu_s"] for x in rounds),
            "median_mrays_wall": statistics.median(x[n]["mrays_wall"] for x in rounds),
            "median_cpu_ratio_to_pinhole": statistics.median(
                x[n]["mrays_per_cpu_s"] / x["pinhole"]["mrays_per_cpu_s"] for x in rounds
            ),
            "rays_per_render": rounds[0][n]["rays"],
        }
    path = write_results(
        args.out / "cameras.json",
        {
            "args": {k: (str(v) if k == "out" else v) for k, v in vars(args).items()},
            "cameras": {n: c.to_dict() for n, c in cams.items()},
            "summary": summary,
            "rounds": rounds,
            "load_1min": [x[n]["load"] for x in rounds for n in names],
        },
        load_start,
    )
    print("wrote", path)


if __name__ == "__main__":
    main()
