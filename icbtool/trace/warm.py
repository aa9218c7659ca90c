"""Compile the tracer's kernels ahead of their first use: ``python -m icbtool.trace.warm``.

numba compiles a kernel on its first call and caches the machine code on disk (``cache=True``,
next to the kernels' sources). On a fresh checkout that first call is minutes on two cores: the
Lambert kernel and the general (BSDF) kernel take about as long each (both measured by
``python -m benchmarks.trace_compile``). ``make install`` runs this module, which renders one
tiny image per kernel, each in a process of its own and both at once, so that the compiles share
the machine's cores and a user's (or the test suite's) first trace only loads the cache. Where
the cache is already there, it loads in seconds and nothing is compiled.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor

#: Each kernel and the built-in scene whose render compiles it.
KERNELS = {
    "lambert": "cornell_box",  # every material Lambertian: the Lambert kernel
    "general": "cornell_box_glossy",  # declared Mitsuba BSDFs: the general BSDF kernel
}


def _render(kernel: str) -> float:
    """Render a 4x4, 1-spp image of ``kernel``'s scene; the seconds it took."""
    from icbtool import scene as sc
    from icbtool.trace import TraceConfig, render

    t0 = time.perf_counter()
    scene = sc.PROCEDURAL[KERNELS[kernel]]()
    render(scene, scene.default_camera.resized(4, 4), TraceConfig(spp=1))
    return time.perf_counter() - t0


def warm(kernels: tuple[str, ...] = tuple(KERNELS), jobs: int = 2) -> dict[str, float]:
    """Compile (or load) ``kernels``, up to ``jobs`` processes at once; seconds per kernel."""
    unknown = [k for k in kernels if k not in KERNELS]
    if unknown:
        raise ValueError(f"unknown kernel(s) {unknown}: choose from {sorted(KERNELS)}")
    ctx = multiprocessing.get_context("spawn")  # a clean numba in each process
    with ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=ctx) as pool:
        return dict(zip(kernels, pool.map(_render, kernels)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m icbtool.trace.warm", description=__doc__)
    ap.add_argument("--jobs", type=int, default=2, help="processes at once (default 2)")
    args = ap.parse_args(argv)
    for k, scene in KERNELS.items():
        print(f"compiling or loading the {k} kernel (a render of {scene}) ...", flush=True)
    t0 = time.perf_counter()
    times = warm(jobs=args.jobs)
    for k, s in times.items():
        print(f"  {k}: {s:.1f} s", flush=True)
    print(f"tracer kernels ready ({time.perf_counter() - t0:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
