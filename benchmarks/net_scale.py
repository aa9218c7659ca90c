"""The cloud at scale (issue 18, "Measured"): hits under misses, bake throughput on Dask, server
memory under attack. Everything on loopback (127.0.0.1; the sockets are listed with ``ss -tnp``
and checked).

1. ``hits``: a server (``icbtool serve`` in a subprocess, ``--workers N`` local Dask workers)
   with 32 clients replaying cache hits (64 x 64, prewarmed) while 2 clients each ask for
   ``--misses`` cache misses at 1024 x 1024: hit latency p50/p99 during the misses, miss latency,
   for N = 1 and 2.
2. ``bake``: the same path baked single-process, on 1 and 2 local Dask workers, and on a
   scheduler plus two worker processes started separately (``dask scheduler`` / ``dask worker``,
   127.0.0.1): records/min (after one warm-up view per worker, which compiles the tracer there)
   and whether every record equals the single-process bake's bit for bit.
3. ``attack``: the server's RSS before and after the malformed / oversized / abusive inputs of
   issue 18 (and 80 more malformed frames), and whether it still answers.

Writes benchmarks/results/net/net_scale.json and net_scale.png; README's ``net-scale`` block is
generated from them (benchmarks/readme_tables.py).

    nice -n 10 .venv/bin/python benchmarks/net_scale.py [--part hits|bake|attack|all]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from icbtool import system
from icbtool.net import crypto, protocol
from icbtool.net.client import NetClientConfig, NetworkSource
from icbtool.net.server import new_token
from icbtool.provenance import run_info, write_json

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "net"
ENV = {**os.environ, "PYTHONPATH": str(REPO), "ICBTOOL_GL_BACKEND": "osmesa"}
T = 600.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _load() -> float:
    return os.getloadavg()[0]


def _tree_pids(pid: int) -> list[int]:
    import psutil

    p = psutil.Process(pid)
    return [pid, *(c.pid for c in p.children(recursive=True))]


def _rss_mb(pid: int) -> tuple[float, float]:
    """(this process's RSS, with its children), MB."""
    import psutil

    p = psutil.Process(pid)
    own = p.memory_info().rss
    total = own + sum(c.memory_info().rss for c in p.children(recursive=True) if c.is_running())
    return own / 1e6, total / 1e6


def sockets_on_loopback(pids: list[int]) -> dict[str, Any]:
    """``ss -tnp`` (and listening sockets) of ``pids``: all on 127.0.0.1?"""
    rows = []
    for args in (["ss", "-tnp"], ["ss", "-tlnp"]):
        out = subprocess.run(args, capture_output=True, text=True, timeout=30).stdout
        rows += [r for r in out.splitlines() if any(f"pid={p}," in r for p in pids)]
    addrs = []
    for r in rows:
        cols = r.split()
        addrs += [cols[3], cols[4]]
    bad = [a for a in addrs if not (a.startswith("127.0.0.1:") or a == "0.0.0.0:*")]
    return {"sockets": len(rows), "all_loopback": not bad and bool(rows), "not_loopback": bad}


class ServeProcess:
    """``icbtool serve`` in a subprocess, until :meth:`stop` (SIGTERM)."""

    def __init__(self, store: Path, token: str, *extra: str) -> None:
        self.port = _free_port()
        cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(store),
               "--port", str(self.port), "--no-lpm", *extra]  # fmt: skip
        env = {**ENV, "ICBTOOL_TOKEN": token}  # not on the command line (ps shows it)
        self.proc = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        deadline = time.monotonic() + T
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if line.startswith("listening on"):
                self.url = line.split()[-1]
                return
            if not line and self.proc.poll() is not None:
                break
        raise RuntimeError(f"server did not start: {cmd}")

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.communicate(timeout=T)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _request(scene: Any, t: float, size: int, seq: int = 0) -> Any:
    p = scene.paths["test"]
    cam = p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)
    return system.GIRequest(cam, time_s=t, seq=seq, depth_range=(0.5, 8.0))


# ------------------------------------------------------------------------------- 1. hits
def run_hits(scene: Any, workers: int, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    token = new_token()
    srv = ServeProcess(tmp / f"hits{workers}", token, "--workers", str(workers),
                       "--spp", str(args.spp), "--max-pending", "4")  # fmt: skip
    cfg = NetClientConfig(timeout_s=T)
    miss_cfg = NetClientConfig(timeout_s=3 * T)  # niced renders on a loaded machine: slow
    try:
        hit_reqs = [_request(scene, 0.5 + 1.2 * k, args.hit_size, seq=k) for k in range(4)]
        with NetworkSource(srv.url, token, cfg) as warm:
            for r in hit_reqs:
                warm.request_remote(r)  # rendered once: hits from now on
            assert all(warm.request_remote(r).cache_hit for r in hit_reqs)
        clients = [NetworkSource(srv.url, token, cfg) for _ in range(args.hit_clients)]
        miss_clients = [NetworkSource(srv.url, token, miss_cfg) for _ in range(args.miss_clients)]
        window = {"start": float("inf"), "end": 0.0}
        hits: list[tuple[float, float]] = []  # (sent at, ms)
        misses: list[float] = []
        errors: list[str] = []
        stop = threading.Event()
        lock = threading.Lock()

        def hitter(i: int) -> None:
            src, req = clients[i], hit_reqs[i % len(hit_reqs)]
            for _ in range(args.max_hits):
                if stop.is_set():
                    return
                t0 = time.perf_counter()
                try:
                    rep = src.request_remote(req)
                except Exception as e:  # recorded, the loop goes on
                    errors.append(repr(e)[:80])
                    continue
                with lock:
                    hits.append((t0, 1e3 * (time.perf_counter() - t0)))
                assert rep.cache_hit

        def misser(i: int) -> None:
            for k in range(args.misses):
                req = _request(scene, 2.0 + 1.7 * i + 0.45 * k, args.miss_size, seq=100 + k)
                t0 = time.perf_counter()
                with lock:
                    window["start"] = min(window["start"], t0)
                try:
                    rep = miss_clients[i].request_remote(req)
                    assert not rep.cache_hit
                    misses.append(1e3 * (time.perf_counter() - t0))
                except Exception as e:
                    errors.append(repr(e)[:80])
            with lock:
                window["end"] = max(window["end"], time.perf_counter())

        threads = [threading.Thread(target=hitter, args=(i,)) for i in range(args.hit_clients)]
        for t in threads:
            t.start()
        time.sleep(1.0)  # every hit client is replaying
        t_idle = time.perf_counter()
        time.sleep(args.idle_s)  # the baseline: the same hits, no miss rendering
        with lock:
            idle = [ms for t0, ms in hits if t0 >= t_idle]
        mthreads = [threading.Thread(target=misser, args=(i,)) for i in range(args.miss_clients)]
        for t in mthreads:
            t.start()
        time.sleep(2.0)
        net = sockets_on_loopback([os.getpid(), *_tree_pids(srv.proc.pid)])
        for t in mthreads:
            t.join(T)
        stop.set()
        for t in threads:
            t.join(T)
        for c in clients + miss_clients:
            c.close()
        during = [ms for t0, ms in hits if window["start"] <= t0 <= window["end"]]
        rss = _rss_mb(srv.proc.pid)
    finally:
        srv.stop()
    return {
        "workers": workers,
        "hit_clients": args.hit_clients,
        "miss_clients": args.miss_clients,
        "hits_without_misses": len(idle),
        "idle_hit_p50_ms": float(np.percentile(idle, 50)) if idle else None,
        "idle_hit_p99_ms": float(np.percentile(idle, 99)) if idle else None,
        "hits_during_misses": len(during),
        "hit_p50_ms": float(np.percentile(during, 50)) if during else None,
        "hit_p99_ms": float(np.percentile(during, 99)) if during else None,
        "hit_max_ms": float(np.max(during)) if during else None,
        "misses": len(misses),
        "miss_ms": misses,
        "miss_median_ms": float(np.median(misses)) if misses else None,
        "errors": errors[:20],
        "n_errors": len(errors),
        "sockets": net,
        "server_rss_mb": rss,
        "load_average_end": _load(),
    }


# ------------------------------------------------------------------------------- 2. bake
def _records(store_dir: Path) -> list[Any]:
    from icbtool import store as st

    with st.open(store_dir, st.StoreConfig(readonly=True)) as s:
        return [s.get(i) for i in s.ids()]


MAPS = ("gi", "dl", "albedo", "normal_world", "normal_view", "depth", "position", "mask")


def _same(a: list[Any], b: list[Any]) -> bool:
    if len(a) != len(b):
        return False
    return all(
        x.camera.to_dict() == y.camera.to_dict()
        and all(np.array_equal(getattr(x, m), getattr(y, m)) for m in MAPS)
        for x, y in zip(a, b, strict=True)
    )


def _bake_one(scene: Any, cfg: Any, store_dir: Path, pool: Any) -> float:
    from icbtool import bake as B
    from icbtool import store as st

    with st.open(store_dir) as s:
        t0 = time.perf_counter()
        rep = B.bake(scene, "test", s, cfg, pool=pool)
        dt = time.perf_counter() - t0
    assert len(rep.rendered) == cfg.limit
    return dt


def _warm(scene: Any, cfg: Any, pool: Any, tmp: Path) -> None:
    """One view per worker thread (each worker compiles the tracer once)."""
    import dataclasses

    from icbtool import bake as B
    from icbtool import store as st

    n = 1 if pool is None else pool.capacity
    w = dataclasses.replace(cfg, limit=n, seed=cfg.seed + 999, progress=False)
    d = Path(tempfile.mkdtemp(dir=tmp))
    with st.open(d) as s:
        B.bake(scene, "test", s, w, pool=pool)
    shutil.rmtree(d)


def run_bake(scene: Any, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Every mode's pool is opened and warmed first, then the modes bake in turn, ``repeats``
    rounds (interleaved: each sees the same load); records/min is the median over the rounds."""
    import contextlib

    from icbtool import bake as B
    from icbtool.system.workers import DaskPool

    cfg = B.BakeConfig(
        spp=args.bake_spp, resolution=(args.bake_size, args.bake_size), limit=args.bake_views,
        progress=False, seed=3,
    )  # fmt: skip
    dask = str(Path(sys.executable).with_name("dask"))
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    # --dashboard-address: the HTTP endpoint (health, metrics) listens on every interface
    # otherwise, even with --no-dashboard
    local = ["--host", "127.0.0.1", "--no-dashboard", "--dashboard-address", "127.0.0.1:0"]
    procs: list[subprocess.Popen] = []
    runs: dict[str, dict[str, Any]] = {}
    with contextlib.ExitStack() as stack:
        pools: dict[str, Any] = {"single": None}
        for n in (1, 2):
            t0 = time.perf_counter()
            pools[f"local {n} worker{'s' if n > 1 else ''}"] = stack.enter_context(
                DaskPool(scene, workers=n)
            )
            runs[list(pools)[-1]] = {"start_s": time.perf_counter() - t0}
        # a scheduler and two workers started by hand, as on separate machines
        procs.append(subprocess.Popen([dask, "scheduler", "--port", str(port), *local],
                                      env=ENV, stderr=subprocess.DEVNULL))  # fmt: skip
        stack.callback(_stop_all, procs)
        time.sleep(2.0)
        for _ in range(2):
            procs.append(subprocess.Popen(
                [dask, "worker", addr, *local, "--nthreads", "1", "--no-nanny"], env=ENV,
                stderr=subprocess.DEVNULL,
            ))  # fmt: skip
        t0 = time.perf_counter()
        ext = stack.enter_context(DaskPool(scene, scheduler=addr, timeout_s=T))
        ext.client.wait_for_workers(2, timeout=T)
        ext.capacity = 2
        pools["dask scheduler + 2 dask workers"] = ext
        runs["dask scheduler + 2 dask workers"] = {"start_s": time.perf_counter() - t0}
        for pool in pools.values():
            _warm(scene, cfg, pool, tmp)
        net = sockets_on_loopback([*_tree_pids(os.getpid()), *(p.pid for p in procs)])
        single: list[Any] = []
        for r in range(args.bake_repeats):
            for mode, pool in pools.items():
                d = tmp / f"bake_{r}_{mode.replace(' ', '_')}"
                dt = _bake_one(scene, cfg, d, pool)
                recs = _records(d)
                if mode == "single" and not single:
                    single = recs
                e = runs.setdefault(mode, {})
                e.setdefault("seconds", []).append(dt)
                e.setdefault("load_average", []).append(_load())
                e["identical_to_single"] = e.get("identical_to_single", True) and _same(
                    recs, single
                )
                e["records"] = len(recs)
                print(mode, r, f"{dt:.1f} s", e["identical_to_single"], flush=True)
                shutil.rmtree(d)
    out = []
    for mode, e in runs.items():
        med = float(np.median(e["seconds"]))
        out.append({
            "mode": mode, **e, "median_seconds": med,
            "records_per_min": 60.0 * e["records"] / med,
            "load_average_end": e["load_average"][-1],
        })  # fmt: skip
    out.sort(key=lambda x: list(pools).index(x["mode"]))
    return {
        "scene": scene.name,
        "views": args.bake_views,
        "size": args.bake_size,
        "spp": args.bake_spp,
        "repeats": args.bake_repeats,
        "sockets": net,
        "runs": out,
    }


def _stop_all(procs: list[subprocess.Popen]) -> None:
    for p in procs[::-1]:
        p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(60)
        except subprocess.TimeoutExpired:
            p.kill()


# ------------------------------------------------------------------------------- 3. attack
def _frame(header: dict, payload: bytes = b"") -> Any:
    def make(ch: Any) -> bytes:
        h = {"v": 1, **header, "ctr": ch.next_counter}
        hb = json.dumps(h).encode()
        _, ct = ch.seal(payload, hb)
        return struct.pack(">I", len(hb)) + hb + ct

    return make


async def _session(url: str, token: str, frames: list[Any], replies: int) -> list[str]:
    from websockets.asyncio.client import connect

    out: list[str] = []
    ws = None
    try:
        async with connect(url, proxy=None, open_timeout=60, max_size=2**26) as ws:
            hs = crypto.ClientHandshake(token)
            await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
            ch, auth = hs.finish(protocol.decode(await asyncio.wait_for(ws.recv(), 60)).fields)
            await ws.send(protocol.encode(protocol.Message("auth", auth)))
            await asyncio.wait_for(ws.recv(), 60)
            for f in frames:
                await ws.send(f(ch) if callable(f) else f)
            for _ in range(replies):
                m = protocol.decode(await asyncio.wait_for(ws.recv(), 120), ch)
                out.append(m.fields.get("code", m.kind))
    except Exception as e:  # closed by the server: part of the answer
        code = getattr(ws, "close_code", None)
        out.append(f"closed {code}" if code is not None else f"{type(e).__name__}: {e}"[:80])
    return out


def run_attack(scene: Any, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    token = new_token()
    srv = ServeProcess(tmp / "attack", token, "--spp", "4")
    cases: dict[str, list[str]] = {}
    try:
        with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as src:
            src.request_remote(_request(scene, 0.5, 64))  # warm: the server has rendered once
        before = _rss_mb(srv.proc.pid)
        req = protocol.request_to_json(_request(scene, 4.0, 32))

        def gi(rid: Any, **cam: Any) -> Any:
            r = json.loads(json.dumps(req))
            r["camera"].update({k: v for k, v in cam.items() if k in r["camera"]})
            r.update({k: v for k, v in cam.items() if k not in r["camera"]})
            return _frame({"kind": "gi_request", "id": rid, "request": r, "codec": "f16-zstd"})

        attacks = {
            "8192^2 request x8": ([gi(i, height=8192, width=8192) for i in range(8)], 8),
            "id 2^53": ([gi(2**53)], 1),
            "lpm min=max=99": (
                [_frame({"kind": "lpm_request", "min_level": 99, "max_level": 99})],
                1,
            ),  # fmt: skip
            "lpm min>max": ([_frame({"kind": "lpm_request", "min_level": 2, "max_level": 1})], 1),
            "velocity 1e308": ([gi(5, velocity_t=[1e308, 0, 0])], 1),
            "fx 0": ([gi(6, fx=0.0)], 1),
            "duplicate ids": ([gi(7, height=200, width=200), gi(7, height=200, width=200)], 2),
            "busy burst": ([gi(10 + i, height=40 + i, width=40 + i) for i in range(8)], 8),
            "80 malformed frames": (
                [struct.pack(">I", 5) + b"{bad}" for _ in range(40)]
                + [_frame({"kind": "no_such_kind"}) for _ in range(20)]
                + [_frame({"kind": "gi_request", "id": 1, "request": 3}) for _ in range(20)],
                80,
            ),
            "oversized message (9 MB)": ([b"\0" * (9 * 2**20)], 1),
        }

        # 30 connections that never finish the handshake, at once
        async def silent() -> None:
            from websockets.asyncio.client import connect

            conns = [await connect(srv.url, proxy=None) for _ in range(30)]
            await asyncio.sleep(12.0)  # past the handshake timeout
            for c in conns:
                await c.close()

        rounds = []
        for r in range(args.attack_rounds):  # bounded: the RSS levels off round after round
            for name, (frames, n) in attacks.items():
                cases[name] = asyncio.run(asyncio.wait_for(_session(srv.url, token, frames, n), T))
                print(r, name, cases[name][:6], flush=True)
            asyncio.run(silent())
            rounds.append(_rss_mb(srv.proc.pid)[0])
        with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as src:
            still = src.request_remote(_request(scene, 0.5, 64)).cache_hit
        after = _rss_mb(srv.proc.pid)
    finally:
        srv.stop()
    return {
        "rss_before_mb": before[0],
        "rss_after_mb": after[0],
        "rss_growth_mb": after[0] - before[0],
        "rss_after_each_round_mb": rounds,
        "answers": cases,
        "still_serving_hits": bool(still),
        "load_average_end": _load(),
    }


# ------------------------------------------------------------------------------- main
def plot(d: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    for h in d.get("hits", []):
        ax[0].bar(
            [f"{h['workers']}w p50", f"{h['workers']}w p99"],
            [h["hit_p50_ms"] or 0, h["hit_p99_ms"] or 0],
        )
    ax[0].axhline(100, color="k", ls="--", lw=1)
    ax[0].set_ylabel("hit latency during misses (ms)")
    ax[0].set_title("32 hit clients, 2 miss clients")
    runs = d.get("bake", {}).get("runs", [])
    ax[1].barh([r["mode"] for r in runs], [r["records_per_min"] for r in runs])
    ax[1].set_xlabel("records / min")
    ax[1].set_title("bake throughput")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=("hits", "bake", "attack", "all"), default="all")
    ap.add_argument("--hit-clients", type=int, default=32)
    ap.add_argument("--miss-clients", type=int, default=2)
    ap.add_argument("--misses", type=int, default=1, help="misses per miss client")
    ap.add_argument("--miss-size", type=int, default=1024)
    ap.add_argument("--hit-size", type=int, default=64)
    ap.add_argument("--max-hits", type=int, default=20000, help="per hit client (a bound)")
    ap.add_argument("--idle-s", type=float, default=20.0, help="hits alone first, for a baseline")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--bake-views", type=int, default=8)
    ap.add_argument("--bake-size", type=int, default=160)
    ap.add_argument("--bake-spp", type=int, default=16)
    ap.add_argument("--attack-rounds", type=int, default=3)
    ap.add_argument("--bake-repeats", type=int, default=3, help="interleaved rounds per mode")
    args = ap.parse_args()
    from icbtool import scene as sc

    scene = sc.PROCEDURAL["cornell_box"]()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "net_scale.json"
    d: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    d["run"] = run_info()
    d.setdefault("config", {})
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        if args.part in ("hits", "all"):
            keys = ("hit_clients", "miss_clients", "misses", "miss_size", "hit_size", "spp")
            d["config"]["hits"] = {k: getattr(args, k) for k in keys}
            d["hits"] = [run_hits(scene, n, args, tmp) for n in (1, 2)]
            write_json(path, d)
        if args.part in ("bake", "all"):
            d["bake"] = run_bake(scene, args, tmp)
            write_json(path, d)
        if args.part in ("attack", "all"):
            d["attack"] = run_attack(scene, args, tmp)
            write_json(path, d)
    plot(d, OUT / "net_scale.png")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
