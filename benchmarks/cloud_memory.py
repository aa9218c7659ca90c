"""Where a cloud render's memory goes, and whether the cloud gives it back.

1. ``breakdown``: one 1024^2 miss rendered in this process as a server's in-process pool does
   (:func:`icbtool.bake.render_job`, raster G-buffers + path-traced GI): RSS and peak RSS
   (``VmHWM``, reset before each step) after the tracer alone, after the whole CRT-buffer, after
   the outputs are dropped, after the tracer's kept workspace is dropped, after
   ``malloc_trim(0)``, after Open Image Denoise's kept device and filter are dropped; the sizes
   of the tracer's workspace and outputs and of the CRT-buffer.
2. ``burst``: ``icbtool serve`` (a subprocess; ``--workers`` 0, 1, 2) gets a burst of
   ``--burst`` 1024^2 misses from 2 clients (distinct cameras), after one small warm-up miss; the
   RSS of the server and its workers (psutil, every ``--sample-s``) from before the burst to
   ``--after-s`` seconds after its last reply: the delta after vs before, and the peak.

Writes --out/cloud_memory.json and cloud_memory.png (RSS over time); docs/benchmarks.md's
``cloud-memory`` block is generated from them. Each part replaces its own entry only. The load
averages are recorded: on a shared machine the renders are slow, the memory is not.

    nice -n 10 .venv/bin/python -m benchmarks.cloud_memory [--part breakdown|burst|all]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks.common import add_out_argument
from benchmarks.net_scale import ServeProcess, request_at
from icbtool.net.client import NetClientConfig, NetworkSource
from icbtool.net.server import new_token
from icbtool.provenance import run_info, write_json

MB = 1e6


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:  # resets VmHWM to the current RSS
        f.write("5")


def _mem() -> dict[str, float]:
    return {"rss_mb": _status_kb("VmRSS") * 1e3 / MB, "peak_mb": _status_kb("VmHWM") * 1e3 / MB}


def run_breakdown(scene: Any, args: argparse.Namespace) -> dict[str, Any]:
    """RSS step by step through one in-process miss (see the module docstring)."""
    from icbtool import raster, trace
    from icbtool.bake import RenderJob, render_job
    from icbtool.system.memory import trim_heap
    from icbtool.trace import tracer as tracer_mod

    size, spp = args.size, args.spp
    req = request_at(scene, 2.0, size)
    small = request_at(scene, 2.0, 32)
    cfg = trace.TraceConfig(spp=spp, denoise=True, seed=1)
    rast = raster.Rasterizer(scene, raster.RasterConfig())
    render_job(scene, RenderJob(small.camera, cfg), rast)  # kernels, GL context, caches
    tracer_mod.release_workspaces()
    tracer_mod.release_denoiser()
    trim_heap()
    steps: dict[str, Any] = {"warm": _mem()}
    _reset_peak()
    tr = trace.render(scene, req.camera.pinhole(), cfg)
    steps["trace_render"] = _mem()
    outs = (tr.gi, tr.direct, tr.full, tr.variance, tr.mask, tr.gi_raw)
    out_bytes = sum(a.nbytes for a in outs if a is not None)
    del tr, outs
    steps["trace_dropped"] = _mem()
    ws = tracer_mod.release_workspaces()  # the workspace the render kept, dropped
    _reset_peak()
    ref = render_job(scene, RenderJob(req.camera, cfg), rast)
    steps["crt_buffer"] = _mem()
    crt_bytes = sum(
        getattr(ref, n).nbytes
        for n in ("gi", "dl", "depth", "normal", "albedo", "mask")
        if getattr(ref, n, None) is not None
    )
    del ref
    steps["crt_dropped"] = _mem()
    dropped = tracer_mod.release_workspaces()
    steps["workspace_dropped"] = _mem()
    trim_heap()
    steps["trimmed"] = _mem()
    tracer_mod.release_denoiser()
    steps["denoiser_dropped"] = _mem()
    trim_heap()
    steps["denoiser_dropped_trimmed"] = _mem()
    rast.close()
    return {
        "size": size,
        "spp": spp,
        "steps": steps,
        "workspace_mb": ws / MB,
        "workspace_dropped_mb": dropped / MB,
        "trace_outputs_mb": out_bytes / MB,
        "crt_buffer_mb": crt_bytes / MB,
        "load_average": list(os.getloadavg()),
    }


def _tree_rss_mb(pid: int) -> tuple[float, list[float]]:
    """(server RSS, [each child's RSS]), MB (Dask's nanny and worker processes are children)."""
    import psutil

    p = psutil.Process(pid)
    kids = []
    for c in p.children(recursive=True):
        try:
            kids.append(c.memory_info().rss / MB)
        except psutil.NoSuchProcess:
            continue
    return p.memory_info().rss / MB, kids


def run_burst(scene: Any, workers: int, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """RSS over time through a burst of misses (see the module docstring)."""
    token = new_token()
    srv = ServeProcess(tmp / f"burst{workers}", token, "--workers", str(workers),
                       "--spp", str(args.spp))  # fmt: skip
    load_start = os.getloadavg()[0]
    samples: list[tuple[float, float, float]] = []  # (s, server MB, server + children MB)
    stop = threading.Event()
    t_origin = time.perf_counter()

    def sample() -> None:
        while not stop.wait(args.sample_s):
            try:
                own, kids = _tree_rss_mb(srv.proc.pid)
            except Exception:  # the server is gone: the run ends
                return
            samples.append((time.perf_counter() - t_origin, own, own + sum(kids)))

    cfg = NetClientConfig(timeout_s=1800.0)
    errors: list[str] = []
    try:
        with NetworkSource(srv.url, token, cfg) as warm:
            warm.request_remote(request_at(scene, 0.3, 64, seq=1))  # kernels loaded everywhere
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        time.sleep(args.before_s)
        t_burst = time.perf_counter() - t_origin
        before = [s for s in samples if s[0] <= t_burst]
        clients = [NetworkSource(srv.url, token, cfg) for _ in range(2)]

        def miss(i: int) -> None:
            for k in range(i, args.burst, 2):
                try:
                    rep = clients[i].request_remote(request_at(scene, 1.0 + 0.37 * k, args.size,
                                                             seq=10 + k))  # fmt: skip
                    assert not rep.cache_hit
                except Exception as e:  # recorded
                    errors.append(repr(e)[:120])

        threads = [threading.Thread(target=miss, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(1800.0)
        for c in clients:
            c.close()
        t_done = time.perf_counter() - t_origin
        time.sleep(args.after_s)
        stop.set()
        sampler.join(10.0)
    finally:
        stop.set()
        srv.stop()
    base = before[-1][2] if before else float("nan")
    after = [s for s in samples if s[0] >= t_done + args.after_s - 2 * args.sample_s]
    end = after[-1][2] if after else float("nan")
    return {
        "workers": workers,
        "burst_start_s": t_burst,
        "burst_end_s": t_done,
        "before_mb": base,
        "peak_mb": max(s[2] for s in samples),
        "after_mb": end,
        "delta_mb": end - base,
        "server_before_mb": before[-1][1] if before else None,
        "server_after_mb": after[-1][1] if after else None,
        "samples": samples,
        "errors": errors,
        "load_average_start": load_start,
        "load_average_end": os.getloadavg()[0],
    }


def plot(d: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    for r in d.get("burst", []):
        t = [s[0] - r["burst_start_s"] for s in r["samples"]]
        (line,) = ax.plot(t, [s[2] for s in r["samples"]], label=f"{r['workers']} workers")
        ax.axvline(r["burst_end_s"] - r["burst_start_s"], color=line.get_color(), ls=":")
    ax.set_xlabel("seconds since the burst started (dotted: its last reply)")
    ax.set_ylabel("RSS, server + workers (MB)")
    ax.set_title(
        f"{d['config']['burst']} misses at {d['config']['size']}^2, {d['config']['spp']} spp"
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=("breakdown", "burst", "all"), default="all")
    ap.add_argument("--size", type=int, default=1024, help="miss image size (square)")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--burst", type=int, default=4, help="misses in the burst (2 clients)")
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--before-s", type=float, default=5.0)
    ap.add_argument("--after-s", type=float, default=30.0)
    ap.add_argument("--sample-s", type=float, default=0.5)
    add_out_argument(ap, "net")
    args = ap.parse_args()
    from icbtool import scene as sc

    scene = sc.PROCEDURAL["cornell_box"]()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "cloud_memory.json"
    d: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    d["run"] = run_info()
    keys = ("size", "spp", "burst", "before_s", "after_s", "sample_s")
    d["config"] = {k: getattr(args, k) for k in keys}
    if args.part in ("breakdown", "all"):
        d["breakdown"] = run_breakdown(scene, args)
        write_json(path, d)
    if args.part in ("burst", "all"):
        with tempfile.TemporaryDirectory() as t:
            d["burst"] = [run_burst(scene, n, args, Path(t)) for n in args.workers]
        write_json(path, d)
    plot(d, args.out / "cloud_memory.png")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
