"""The cloud at scale: hits under misses, bake throughput on Dask, server
memory under attack. Everything on loopback (127.0.0.1; the sockets are listed with ``ss -tnp``
and checked).

0. ``profile``: where a hit's time goes: each step of a hit alone (median microseconds: open the
   request, prefetch camera, lookup, kept reply or payload read + encode, seal the reply; and a
   client's), then hits alone for ``--profile-s`` with 1 and 32 lean clients and 32
   ``NetworkSource`` clients: throughput, latency, CPU per hit of the server (its event-loop
   thread apart) and of the clients.
1. ``hits``: a server (``icbtool serve`` in a subprocess, ``--workers N`` local Dask workers,
   0: in-process renders) with 32 clients, each replaying a cache hit at its own camera (64 x 64,
   32 distinct cameras along the test path, prewarmed: every hit is a lookup of its own, none
   can be a reply shared with another client; replies marked ``coalesced`` are counted apart
   and never as hits; ``--hit-client lean``: all on one event loop, each reply opened and
   verified but its codecs not decoded, see :class:`LeanHitClients`) while 2 clients each ask
   for ``--misses`` cache misses at 1024 x 1024: hit latency p50/p99/max alone and during the
   misses, throughput and CPU per hit, miss latency, for N = 0, 1 and 2 (``--hit-workers``).
2. ``bake``: the same path baked single-process, on 1 and 2 local Dask workers, and on a
   scheduler plus two worker processes started separately (``dask scheduler`` / ``dask worker``,
   127.0.0.1): records/min (after one warm-up view per worker, which compiles the tracer there)
   and whether every record equals the single-process bake's bit for bit.
3. ``attack``: the server's RSS before and after the malformed / oversized / abusive inputs of
   docs/protocol.md's limits (and 80 more malformed frames), and whether it still answers.

``ab`` (not in ``all``): the server of an older checkout (``--ab-repo DIR``, e.g. ``git archive
COMMIT | tar -x -C DIR``) and this one, alternately, ``--ab-rounds`` times, 32 lean clients, hits
alone: before / after on the same machine state.

Writes --out/net_scale.json and net_scale.png; docs/benchmarks.md's
``net-scale`` block is generated from them (benchmarks/page.py). Each part replaces its own
entry only.

    nice -n 10 .venv/bin/python -m benchmarks.net_scale [--part profile|hits|bake|attack|all]
    nice -n 10 .venv/bin/python -m benchmarks.net_scale --part ab --ab-repo /tmp/net_before
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

from benchmarks.common import add_out_argument
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

    def __init__(self, store: Path, token: str, *extra: str, repo: str | None = None) -> None:
        self.port = _free_port()
        cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(store),
               "--port", str(self.port), "--no-lpm", *extra]  # fmt: skip
        env = {**ENV, "ICBTOOL_TOKEN": token}  # not on the command line (ps shows it)
        if repo is not None:  # another checkout's server (before / after)
            env["PYTHONPATH"] = str(repo)
        # cwd too: `python -m` puts the working directory before PYTHONPATH on sys.path
        self.proc = subprocess.Popen(cmd, env=env, cwd=repo or REPO, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)  # fmt: skip
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


def request_at(scene: Any, t: float, size: int, seq: int = 0) -> Any:
    """A GI request at time ``t`` of the test path, ``size`` x ``size``."""
    p = scene.paths["test"]
    cam = p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)
    return system.GIRequest(cam, time_s=t, seq=seq, depth_range=(0.5, 8.0))


def hit_cameras(scene: Any, n: int, size: int) -> list[Any]:
    """``n`` distinct hit requests, one per client: cameras spread along the test path (no two
    alike, so no reply can be shared between clients: every hit is a lookup of its own)."""
    span = scene.paths["test"].duration
    ts = [0.2 + (span - 0.4) * k / max(n - 1, 1) for k in range(n)]
    return [request_at(scene, t, size, seq=k) for k, t in enumerate(ts)]


# ------------------------------------------------------------------------------- hit clients
class LeanHitClients:
    """``n`` hit clients on one asyncio loop (a thread of this process), each on its own
    authenticated connection, each replaying one request: send it, wait for the reply, send it
    again (closed loop, no think time).

    A client does what any client must do with a reply and no more: open it (AES-GCM: decrypt
    and verify the tag), parse and validate its header, check that it is the hit it asked for.
    It does not decode the GI/depth/mask codecs: that is the client's own work on its own
    machine (the profile, ``--part profile``, measures it), not the server's, and here it would
    take the cores the server is measured on. A latency runs from sealing the request to the
    opened reply. ``NetworkSource`` clients (a thread and an event loop each, codec decode)
    are ``--hit-client full``.
    """

    def __init__(self, url: str, token: str, reqs: list[Any], n: int, max_hits: int) -> None:
        from icbtool.net import codec as codec_mod

        self.url, self.token, self.max_hits = url, token, max_hits
        self.fields = [
            {"request": protocol.request_to_json(reqs[i % len(reqs)]),
             "codec": codec_mod.DEFAULT_GI_CODEC, "depth_codec": codec_mod.DEFAULT_DEPTH_CODEC}
            for i in range(n)
        ]  # fmt: skip
        self.hits: list[tuple[float, float]] = []  # (sent at, ms): real hits
        self.coalesced: list[tuple[float, float]] = []  # replies shared with another request
        self.server_ms: list[dict[str, float]] = []
        self.errors: list[str] = []
        self.loop = asyncio.new_event_loop()
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name="hit-clients", daemon=True)

    def _main(self) -> None:
        self.loop.run_until_complete(self._run())

    async def _run(self) -> None:
        from websockets.asyncio.client import connect

        self._stop = asyncio.Event()
        conns = []
        for _ in self.fields:
            ws = await connect(self.url, proxy=None, max_size=2**26, compression=None,
                               open_timeout=T)  # fmt: skip
            hs = crypto.ClientHandshake(self.token)
            await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
            ch, auth = hs.finish(protocol.decode(await ws.recv()).fields)
            await ws.send(protocol.encode(protocol.Message("auth", auth)))
            info = protocol.decode(await ws.recv(), ch)
            assert info.kind == "scene_info", info.kind
            conns.append((ws, ch))
        self._ready.set()
        await asyncio.gather(*(self._client(ws, ch, f) for (ws, ch), f in zip(conns, self.fields)))
        for ws, _ in conns:
            await ws.close()

    async def _client(self, ws: Any, ch: Any, fields: dict[str, Any]) -> None:
        assert self._stop is not None
        for rid in range(1, self.max_hits + 1):
            if self._stop.is_set():
                return
            t0 = time.perf_counter()
            msg = protocol.Message("gi_request", {"id": rid, **fields})
            await ws.send(protocol.encode(msg, ch))
            reply = protocol.decode(await ws.recv(), ch, max_bytes=2**26)
            ms = 1e3 * (time.perf_counter() - t0)
            f = reply.fields
            if reply.kind != "gi_reply" or not f["cache_hit"] or f["id"] != rid:
                self.errors.append(f"{reply.kind}: {str(f)[:80]}")
                continue
            if f.get("coalesced"):  # shared with another client's request: not a lookup
                self.coalesced.append((t0, ms))
                continue
            self.hits.append((t0, ms))
            self.server_ms.append(f["timings_ms"])

    def start(self) -> LeanHitClients:
        self._thread.start()
        if not self._ready.wait(T):
            raise RuntimeError("hit clients did not connect")
        return self

    def stop(self) -> None:
        if self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(T)


class _FullHitClients:
    """``n`` ``NetworkSource`` hit clients (a thread and an event loop each; they decode the
    codecs as ``icbtool client`` does), with the interface of :class:`LeanHitClients`."""

    def __init__(self, url: str, token: str, reqs: list[Any], n: int, max_hits: int) -> None:
        self.hits: list[tuple[float, float]] = []
        self.coalesced: list[tuple[float, float]] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._srcs = [NetworkSource(url, token, NetClientConfig(timeout_s=T)) for _ in range(n)]
        self._threads = [
            threading.Thread(target=self._client, args=(s, reqs[i % len(reqs)], max_hits))
            for i, s in enumerate(self._srcs)
        ]

    def _client(self, src: Any, req: Any, max_hits: int) -> None:
        for _ in range(max_hits):
            if self._stop.is_set():
                return
            t0 = time.perf_counter()
            try:
                rep = src.request_remote(req)
            except Exception as e:  # recorded, the loop goes on
                self.errors.append(repr(e)[:80])
                continue
            if rep.cache_hit:
                kept = self.coalesced if getattr(rep, "coalesced", False) else self.hits
                kept.append((t0, 1e3 * (time.perf_counter() - t0)))

    def start(self) -> _FullHitClients:
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(T)
        for s in self._srcs:
            s.close()


# ------------------------------------------------------------------------------- 0. profile
def _median_us(fn: Any, n: int) -> float:
    fn()  # warm (imports, caches)
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e6)


def _channels() -> tuple[Any, Any]:
    """(client channel, server channel) of one handshake."""
    tok = new_token()
    c, s = crypto.ClientHandshake(tok), crypto.ServerHandshake(tok)
    cch, auth = c.finish(s.welcome(c.hello_fields()))
    return cch, s.verify(auth)


def profile_steps(scene: Any, store_dir: Path, hit_reqs: list[Any], n: int) -> dict[str, Any]:
    """Each step of a hit, alone, in this process (median microseconds of ``n`` runs): what the
    server does between the request's bytes and the reply's, and what a client does."""
    from icbtool import store as st
    from icbtool.net import codec as codec_mod
    from icbtool.net import server as server_mod
    from icbtool.net.reply_cache import EncodedReply, ReplyCache
    from icbtool.system.cloud import Cloud, CloudConfig

    scfg = st.StoreConfig(readonly=True, create=False, refresh_interval_s=0.0)
    reader = Cloud(scene, st.open(store_dir, scfg), CloudConfig())
    req = hit_reqs[0]
    gi_c, d_c = codec_mod.DEFAULT_GI_CODEC, codec_mod.DEFAULT_DEPTH_CODEC
    rq = protocol.Message(
        "gi_request",
        {"id": 1, "request": protocol.request_to_json(req), "codec": gi_c, "depth_codec": d_c},
    )
    ref_cam = reader.reference_camera(req)
    info, _ = reader.find(ref_cam)
    rec = reader.store.get(info.record_id)
    parts, payload = server_mod.encode_reference(rec, gi_c, d_c)
    kept = ReplyCache(2**26)
    key = (info.record_id, info.checksum, gi_c, d_c)
    kept.put(key, EncodedReply(protocol.camera_to_json(rec.camera), parts, payload))
    reply = protocol.Message(
        "gi_reply",
        {"id": 1, "camera": protocol.camera_to_json(rec.camera), "cache_hit": True,
         "coalesced": False, "timings_ms": {"lookup": 0.1, "encode": 0.1, "server": 0.2},
         "parts": parts},
        payload,
    )  # fmt: skip
    tx, rx = _channels()

    def opened_us(msg: Any) -> float:
        """Median time to open + parse + validate ``msg`` (frames sealed in advance: the
        receiver's replay check wants rising counters)."""
        a, b = _channels()
        frames = iter([protocol.encode(msg, a) for _ in range(n + 1)])
        return _median_us(lambda: protocol.decode(next(frames), b), n)

    def codec_decode() -> None:
        off = 0
        for p in parts:
            blob = payload[off : off + p["bytes"]]
            codec_mod.decode(blob, p["codec"], tuple(p["shape"]), p["dtype"])
            off += p["bytes"]

    server_us = {
        "request: open + parse + validate": opened_us(rq),
        "request_from_json": _median_us(
            lambda: protocol.request_from_json(rq.fields["request"]), n
        ),
        "reference (prefetch) camera": _median_us(lambda: reader.reference_camera(req), n),
        "coalescing key": _median_us(lambda: server_mod.camera_key(ref_cam), n),
        "lookup: octree + covering check + index row": _median_us(lambda: reader.find(ref_cam), n),
        "kept reply (reply cache get)": _median_us(lambda: kept.get(key), n),
        "not kept: payload read + checksum + decode (all maps)": _median_us(
            lambda: reader.store.get(info.record_id), n
        ),
        "not kept: encode gi/depth/mask": _median_us(
            lambda: server_mod.encode_reference(rec, gi_c, d_c), n
        ),
        "reply: validate + header + seal": _median_us(lambda: protocol.encode(reply, tx), n),
    }
    client_us = {
        "request: build + seal": _median_us(lambda: protocol.encode(rq, tx), n),
        "reply: open + parse + validate": opened_us(reply),
        "reply: codec decode (gi, depth, mask)": _median_us(codec_decode, n),
    }
    reader.store.close()
    return {
        "record": {
            "height": rec.camera.height,
            "width": rec.camera.width,
            "stored_bytes": info.nbytes,
            "reply_payload_bytes": len(payload),
            "reply_bytes": len(protocol.encode(reply, tx)),
            "request_bytes": len(protocol.encode(rq, tx)),
        },  # fmt: skip
        "server_us": server_us,
        "client_us": client_us,
        "repeats": n,
    }


def _cpu_s(pid: int) -> tuple[float, dict[int, float]]:
    """(CPU seconds of process ``pid``, user + system, and per thread id)."""
    import psutil

    p = psutil.Process(pid)
    t = p.cpu_times()
    return t.user + t.system, {th.id: th.user_time + th.system_time for th in p.threads()}


def _load_window(srv: ServeProcess, clients: Any, seconds: float) -> dict[str, Any]:
    """Hits of ``clients`` for ``seconds``: latency, throughput, CPU per hit of the server
    (its event loop thread, its other threads) and of this process (the clients)."""
    time.sleep(1.0)  # every client is replaying
    n0, t0 = len(clients.hits), time.perf_counter()
    s0, th0 = _cpu_s(srv.proc.pid)
    c0, _ = _cpu_s(os.getpid())
    time.sleep(seconds)
    n1, t1 = len(clients.hits), time.perf_counter()
    s1, th1 = _cpu_s(srv.proc.pid)
    c1, _ = _cpu_s(os.getpid())
    lat = [ms for _, ms in clients.hits[n0:n1]]
    n = max(1, n1 - n0)
    pid = srv.proc.pid
    loop_s = th1.get(pid, 0.0) - th0.get(pid, 0.0)
    others = sorted((th1[k] - th0.get(k, 0.0) for k in th1 if k != pid), reverse=True)
    out = {
        "hits": n1 - n0,
        "seconds": t1 - t0,
        "hits_per_s": (n1 - n0) / (t1 - t0),
        "p50_ms": float(np.percentile(lat, 50)) if lat else None,
        "p99_ms": float(np.percentile(lat, 99)) if lat else None,
        "mean_ms": float(np.mean(lat)) if lat else None,
        "server_cpu_ms_per_hit": 1e3 * (s1 - s0) / n,
        "server_event_loop_cpu_ms_per_hit": 1e3 * loop_s / n,
        "server_other_threads_cpu_ms_per_hit": [1e3 * x / n for x in others[:4]],
        "clients_cpu_ms_per_hit": 1e3 * (c1 - c0) / n,
        "load_average": _load(),
    }
    sm = getattr(clients, "server_ms", None)
    if sm:
        win = sm[n0:n1] or sm
        out["server_reported_ms_median"] = {
            k: float(np.median([d.get(k, 0.0) for d in win])) for k in win[0]
        }
    return out


def run_profile(scene: Any, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Where a hit's time goes: each step alone (:func:`profile_steps`), then hits alone (no
    misses): one lean client, ``hit_clients`` lean clients, as many ``NetworkSource`` ones."""
    token = new_token()
    store = tmp / "profile"
    srv = ServeProcess(store, token, "--workers", "0", "--spp", str(args.spp),
                       repo=args.server_repo)  # fmt: skip
    try:
        hit_reqs = [request_at(scene, 0.5 + 1.2 * k, args.hit_size, seq=k) for k in range(4)]
        with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as warm:
            for r in hit_reqs:
                warm.request_remote(r)
        steps = profile_steps(scene, store, hit_reqs, args.profile_repeats)
        loads = {}
        runs = [("1 lean client", LeanHitClients, 1),
                (f"{args.hit_clients} lean clients", LeanHitClients, args.hit_clients),
                (f"{args.hit_clients} NetworkSource clients", _FullHitClients,
                 args.hit_clients)]  # fmt: skip
        for name, cls, n in runs:
            c = cls(srv.url, token, hit_reqs, n, args.max_hits).start()
            try:
                loads[name] = _load_window(srv, c, args.profile_s)
            finally:
                c.stop()
            print(name, loads[name], flush=True)
    finally:
        srv.stop()
    return {**steps, "load": loads, "cores": os.cpu_count(), "load_average_end": _load()}


# ------------------------------------------------------------------------------- 1. hits
def _hit_clients(args: argparse.Namespace) -> Any:
    return LeanHitClients if args.hit_client == "lean" else _FullHitClients


def _cpu_window(srv: ServeProcess) -> tuple[float, float, float]:
    return time.perf_counter(), _cpu_s(srv.proc.pid)[0], _cpu_s(os.getpid())[0]


def _per_hit(a: tuple[float, float, float], b: tuple[float, float, float], n: int) -> dict:
    n = max(1, n)
    return {
        "hits_per_s": n / (b[0] - a[0]),
        "server_cpu_ms_per_hit": 1e3 * (b[1] - a[1]) / n,
        "clients_cpu_ms_per_hit": 1e3 * (b[2] - a[2]) / n,
    }


def run_hits(scene: Any, workers: int, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Hits alone for ``idle_s``, then the same hits while the miss clients' renders run."""
    token = new_token()
    srv = ServeProcess(tmp / f"hits{workers}", token, "--workers", str(workers),
                       "--spp", str(args.spp), "--max-pending", "4",
                       repo=args.server_repo)  # fmt: skip
    load_start = _load()
    miss_cfg = NetClientConfig(timeout_s=3 * T)  # niced renders on a loaded machine: slow
    try:
        hit_reqs = hit_cameras(scene, args.hit_clients, args.hit_size)
        with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as warm:
            for r in hit_reqs:
                warm.request_remote(r)  # rendered once: hits from now on
            assert all(warm.request_remote(r).cache_hit for r in hit_reqs)
        miss_clients = [NetworkSource(srv.url, token, miss_cfg) for _ in range(args.miss_clients)]
        window = {"start": float("inf"), "end": 0.0}
        misses: list[float] = []
        errors: list[str] = []
        lock = threading.Lock()

        def misser(i: int) -> None:
            for k in range(args.misses):
                req = request_at(scene, 2.0 + 1.7 * i + 0.45 * k, args.miss_size, seq=100 + k)
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

        clients = _hit_clients(args)(srv.url, token, hit_reqs, args.hit_clients, args.max_hits)
        clients.start()
        time.sleep(1.0)  # every hit client is replaying
        a, n_a = _cpu_window(srv), len(clients.hits)
        time.sleep(args.idle_s)  # the baseline: the same hits, no miss rendering
        b, n_b = _cpu_window(srv), len(clients.hits)
        idle = [ms for t0, ms in clients.hits if a[0] <= t0 <= b[0]]
        idle_coalesced = sum(a[0] <= t0 <= b[0] for t0, _ in clients.coalesced)
        idle_cost = _per_hit(a, b, n_b - n_a)
        mthreads = [threading.Thread(target=misser, args=(i,)) for i in range(args.miss_clients)]
        c = _cpu_window(srv)
        for t in mthreads:
            t.start()
        time.sleep(2.0)
        net = sockets_on_loopback([os.getpid(), *_tree_pids(srv.proc.pid)])
        for t in mthreads:
            t.join(T)
        d = _cpu_window(srv)
        clients.stop()
        for m in miss_clients:
            m.close()
        errors += clients.errors
        during = [ms for t0, ms in clients.hits if window["start"] <= t0 <= window["end"]]
        coalesced = sum(window["start"] <= t0 <= window["end"] for t0, _ in clients.coalesced)
        during_cost = _per_hit(c, d, len(during))
        rss = _rss_mb(srv.proc.pid)
    finally:
        srv.stop()
    pct = lambda x, q: float(np.percentile(x, q)) if x else None  # noqa: E731
    return {
        "workers": workers,
        "hit_client": args.hit_client,
        "hit_clients": args.hit_clients,
        "miss_clients": args.miss_clients,
        "hit_cameras": len({json.dumps(protocol.request_to_json(r)["camera"]) for r in hit_reqs}),
        "hits_without_misses": len(idle),
        "coalesced_without_misses": idle_coalesced,
        "idle_hit_p50_ms": pct(idle, 50),
        "idle_hit_p99_ms": pct(idle, 99),
        "idle_hit_max_ms": float(np.max(idle)) if idle else None,
        "idle": idle_cost,
        "hits_during_misses": len(during),
        "coalesced_during_misses": coalesced,
        "hit_p50_ms": pct(during, 50),
        "hit_p99_ms": pct(during, 99),
        "hit_max_ms": float(np.max(during)) if during else None,
        # the server's CPU here includes receiving, storing and encoding the misses' renders
        "during": during_cost,
        "misses": len(misses),
        "miss_ms": misses,
        "miss_median_ms": float(np.median(misses)) if misses else None,
        "errors": errors[:20],
        "n_errors": len(errors),
        "sockets": net,
        "server_rss_mb": rss,
        "load_average_start": load_start,
        "load_average_end": _load(),
    }


def run_ab(scene: Any, args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Before / after on the same machine state: the server of ``--ab-repo`` (an older
    checkout) and this one, alternately, ``ab_rounds`` times each, the same lean hit clients
    for ``profile_s`` seconds (hits alone)."""
    rounds = []
    hit_reqs = [request_at(scene, 0.5 + 1.2 * k, args.hit_size, seq=k) for k in range(4)]
    for r in range(args.ab_rounds):
        for label, repo in (("before", args.ab_repo), ("after", str(REPO))):
            token = new_token()
            srv = ServeProcess(tmp / f"ab_{label}_{r}", token, "--workers", "0",
                               "--spp", str(args.spp), repo=repo)  # fmt: skip
            try:
                with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as warm:
                    for q in hit_reqs:
                        warm.request_remote(q)
                c = LeanHitClients(srv.url, token, hit_reqs, args.hit_clients, args.max_hits)
                c.start()
                try:
                    w = _load_window(srv, c, args.profile_s)
                finally:
                    c.stop()
            finally:
                srv.stop()
            w.pop("server_reported_ms_median", None)
            rounds.append({"server": label, "round": r, **w})
            print(label, r, {k: w[k] for k in ("hits_per_s", "p50_ms", "p99_ms")}, flush=True)
    summary = {}
    for label in ("before", "after"):
        xs = [x for x in rounds if x["server"] == label]
        summary[label] = {
            k: float(np.median([x[k] for x in xs]))
            for k in ("hits_per_s", "p50_ms", "p99_ms", "server_cpu_ms_per_hit",
                      "server_event_loop_cpu_ms_per_hit", "clients_cpu_ms_per_hit")
        }  # fmt: skip
    return {"before_repo": args.ab_repo, "rounds": rounds, "median": summary}


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
    from icbtool.system.dask_cluster import JoinSecurity
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
        # a plain tcp:// cluster on loopback, started here for the measurement: joined as
        # insecure explicitly (docs/network.md shows the tls:// way across machines)
        ext = stack.enter_context(
            DaskPool(scene, scheduler=addr, timeout_s=T, security=JoinSecurity(insecure=True))
        )
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
            src.request_remote(request_at(scene, 0.5, 64))  # warm: the server has rendered once
        before = _rss_mb(srv.proc.pid)
        req = protocol.request_to_json(request_at(scene, 4.0, 32))

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
            still = src.request_remote(request_at(scene, 0.5, 64)).cache_hit
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
    parts = ("profile", "ab", "hits", "bake", "attack", "all")
    ap.add_argument("--part", choices=parts, default="all", help="ab: not part of all")
    ap.add_argument("--hit-clients", type=int, default=32, help="each its own camera")
    ap.add_argument("--hit-workers", type=int, nargs="+", default=[0, 1, 2])
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
    ap.add_argument("--profile-s", type=float, default=10.0, help="each load window")
    ap.add_argument(
        "--hit-client", choices=("lean", "full"), default="lean",
        help="lean: 32 connections on one event loop, open + verify each reply, no codec "
        "decode; full: NetworkSource clients (a thread each, codec decode)",
    )  # fmt: skip
    ap.add_argument("--server-repo", default=None, help="run the server from this checkout")
    ap.add_argument("--ab-repo", default=None, help="--part ab: the older checkout")
    ap.add_argument("--ab-rounds", type=int, default=3)
    ap.add_argument("--profile-repeats", type=int, default=300, help="each step alone")
    ap.add_argument("--attack-rounds", type=int, default=3)
    ap.add_argument("--bake-repeats", type=int, default=3, help="interleaved rounds per mode")
    add_out_argument(ap, "net")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    from icbtool import scene as sc

    scene = sc.PROCEDURAL["cornell_box"]()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "net_scale.json"
    d: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {}
    d["run"] = run_info()
    d.setdefault("config", {})
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        if args.part in ("profile", "all"):
            d["profile"] = run_profile(scene, args, tmp)
            write_json(path, d)
        if args.part == "ab":
            if not args.ab_repo:
                ap.error("--part ab needs --ab-repo (a checkout of the version before)")
            d["ab"] = run_ab(scene, args, tmp)
            write_json(path, d)
        if args.part in ("hits", "all"):
            keys = ("hit_clients", "miss_clients", "misses", "miss_size", "hit_size", "spp",
                    "idle_s", "hit_client")  # fmt: skip
            d["config"]["hits"] = {k: getattr(args, k) for k in keys}
            d["hits"] = [run_hits(scene, n, args, tmp) for n in args.hit_workers]
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
