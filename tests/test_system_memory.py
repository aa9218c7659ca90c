"""A render's memory goes back: the pools drop the tracer's workspace and trim the heap after
each render (icbtool.system.memory), so a process's RSS after renders returns to where it was."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from icbtool.system import memory

#: What two 256^2 renders may leave resident after them (MB); the tracer's workspace alone is
#: about 20 MB at that size and the denoiser's scratch more, so a render that keeps either, or a
#: heap that keeps its pages, fails.
BOUND_MB = 16

_SCRIPT = r"""
import json
from icbtool import scene as sc, trace
from icbtool.bake import RenderJob, render_job
from icbtool.system.memory import rss_bytes
from icbtool.system.workers import LocalPool

scene = sc.PROCEDURAL["cornell_box"]()
cam = scene.paths["test"].with_intrinsics(
    scene.paths["test"].intrinsics.resized(256, 256)).camera_at(1.0)
job = lambda spp, seed: RenderJob(cam, trace.TraceConfig(spp=spp, seed=seed, denoise=True))
out = {}
with LocalPool(scene) as pool:
    pool.submit(job(1, 0)).result()  # kernels, GL context and framebuffers at this size
    out["warm"] = rss_bytes()
    for seed in (1, 2):
        ref = pool.submit(job(1, seed)).result()
        del ref
    out["pool"] = rss_bytes()
    for seed in (3, 4):  # the same renders without the pool's release
        ref = render_job(scene, job(1, seed), pool._rasterizer)
        del ref
    out["kept"] = rss_bytes()
print(json.dumps(out))
"""


def test_trim_heap_runs():
    assert isinstance(memory.trim_heap(), bool)
    assert memory.rss_bytes() > 10 * 2**20


@pytest.mark.gl
def test_render_memory_returns_after_each_render():
    env = {**os.environ, "ICBTOOL_GL_BACKEND": os.environ.get("ICBTOOL_GL_BACKEND", "osmesa")}
    res = subprocess.run(
        [sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, timeout=600
    )
    assert res.returncode == 0, res.stderr[-2000:]
    rss = json.loads(res.stdout.strip().splitlines()[-1])
    grown = (rss["pool"] - rss["warm"]) / 1e6
    kept = (rss["kept"] - rss["pool"]) / 1e6
    assert grown < BOUND_MB, f"two renders through the pool left {grown:.0f} MB resident"
    # the check can fail: the same renders without the release keep their workspace
    assert kept > BOUND_MB, f"renders without the release left only {kept:.0f} MB"
