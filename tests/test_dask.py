"""Render workers on Dask distributed (icbtool.system.workers): known answers against the
single-process path, a worker killed mid-render, the scene lost with every worker.

One local cluster (two worker processes of one thread, every socket on 127.0.0.1, TLS with its own
key, no HTTP port) serves the whole module; images are tiny. Its doors are tested too: a process
without the cluster's key cannot connect to any of its ports.
Every wait is bounded; nothing asserts a time.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from icbtool import bake as B  # noqa: E402
from icbtool import scene as sc  # noqa: E402
from icbtool import store as st  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.system.dask_cluster import JoinSecurity, check_join, local_cluster  # noqa: E402
from icbtool.system.workers import DaskPool, LocalPool, open_pool  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.gl]

T = 180.0
MAPS = ("gi", "dl", "albedo", "normal_world", "normal_view", "depth", "position", "mask")


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


@pytest.fixture(scope="module")
def cluster():
    """Started once for the module: 2 workers, 1 thread each, loopback only, TLS with its own
    key (the cluster a server starts with ``workers=2``)."""
    with local_cluster(2) as c:
        yield c


@pytest.fixture(scope="module")
def creds(cluster, tmp_path_factory):
    """The cluster's credentials as PEM files, as an operator hands them to a joining server."""
    d = tmp_path_factory.mktemp("dask-tls")
    sec = cluster.security
    files = {"ca": sec.tls_ca_file, "cert": sec.tls_client_cert, "key": sec.tls_client_key}
    for name, pem in files.items():
        (d / f"{name}.pem").write_text(pem)
    return JoinSecurity(str(d / "ca.pem"), str(d / "cert.pem"), str(d / "key.pem"))


@pytest.fixture(scope="module")
def watcher(cluster):
    """A client of the test's own, to look at and kill workers."""
    with distributed.Client(
        cluster.scheduler_address, set_as_default=False, security=cluster.security
    ) as c:
        yield c


def _wait_workers(client, n: int) -> None:
    client.wait_for_workers(n, timeout=T)


def _bake_cfg(limit: int = 4) -> B.BakeConfig:
    return B.BakeConfig(
        spp=2, max_depth=2, resolution=(20, 24), limit=limit, progress=False, seed=7
    )


def test_dask_bake_equals_the_single_process_bake_bit_for_bit(scene, cluster, creds, tmp_path):
    with st.open(tmp_path / "one") as s1:
        r1 = B.bake(scene, "test", s1, _bake_cfg())
        one = [s1.get(i) for i in r1.rendered]
    with open_pool(scene, scheduler=cluster.scheduler_address, security=creds) as pool:
        assert isinstance(pool, DaskPool) and pool.capacity == 2
        with st.open(tmp_path / "two") as s2:
            r2 = B.bake(scene, "test", s2, _bake_cfg(limit=2), pool=pool)  # interrupted...
            r3 = B.bake(scene, "test", s2, _bake_cfg(), pool=pool)  # ...and resumed
            assert r3.skipped == [0, 1] and len(r3.rendered) == 2
            two = [s2.get(i) for i in r2.rendered + r3.rendered]
    assert r1.rendered == r2.rendered + r3.rendered  # same ids: written in path order
    for a, b in zip(one, two, strict=True):
        assert a.camera.to_dict() == b.camera.to_dict()
        assert a.meta.tags == b.meta.tags
        for name in MAPS:
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_trace_gbuffers_on_workers_equal_the_local_pool(scene, cluster, creds):
    job = B.RenderJob(
        scene.paths["test"].camera_at(1.0).resized(12, 16),
        _tcfg(),
        "trace",
    )
    there = DaskPool(scene, scheduler=cluster.scheduler_address, security=creds)
    with LocalPool(scene) as here, there:
        a, b = here.submit(job).result(T), there.submit(job).result(T)
    for name in ("gi", "dl", "depth", "mask"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def _worker_memory_settings(dask_worker=None) -> dict:
    import os

    return {
        "arenas": os.environ.get("MALLOC_ARENA_MAX"),
        "trims": "icb-trim-heap" in dask_worker.periodic_callbacks,
    }


def test_local_workers_run_with_few_arenas_and_trim_their_heap(cluster, watcher):
    """Set before each worker process starts (glibc reads them once), and a periodic trim that
    gives a render's result buffers back once the server has fetched them."""
    from icbtool.system.memory import WORKER_ENVIRON

    got = watcher.run(_worker_memory_settings)
    assert len(got) == 2
    for v in got.values():
        assert v == {"arenas": WORKER_ENVIRON["MALLOC_ARENA_MAX"], "trims": True}


def _tcfg():
    from icbtool import trace

    return trace.TraceConfig(spp=2, seed=3, max_depth=2)


def test_worker_killed_mid_render_the_request_is_answered_store_intact(
    scene, cluster, creds, watcher, tmp_path
):
    pytest.importorskip("websockets")
    from icbtool.net.client import NetClientConfig, NetError, NetworkSource
    from icbtool.net.server import Server, ServerConfig, new_token

    _wait_workers(watcher, 2)
    token = new_token()
    slow = system.CloudConfig(spp=64, denoise=False, max_depth=4)
    cfg = ServerConfig(
        scheduler=cluster.scheduler_address,
        dask_tls_ca=creds.tls_ca,
        dask_tls_cert=creds.tls_cert,
        dask_tls_key=creds.tls_key,
    )
    store_dir = tmp_path / "store"
    with Server(scene, store_dir, token, cfg, slow) as srv:
        assert srv.workers_address == cluster.scheduler_address
        with NetworkSource(srv.url, token, NetClientConfig(timeout_s=T)) as src:
            p = scene.paths["test"]
            cam = p.with_intrinsics(p.intrinsics.resized(64, 64)).camera_at(1.5)
            req = system.GIRequest(cam, time_s=1.5, seq=1, depth_range=(0.5, 8.0))
            fut = asyncio.run_coroutine_threadsafe(src._ask(req), src._loop)
            busy = _wait_processing(watcher)
            pids = watcher.run(os.getpid)
            os.kill(pids[busy], signal.SIGKILL)
            try:
                msg, _ = fut.result(T)
                answered = msg.fields["cache_hit"] is False
            except NetError as e:  # refused, in the protocol's words
                answered = False
                assert e.code == "internal"
            assert answered or srv.stats.render_failures == 1
            _wait_workers(watcher, 2)
            nxt = src.request(system.GIRequest(cam, time_s=1.5, seq=2, depth_range=(0.5, 8)))
            assert np.isfinite(nxt.reference.gi).all()
    with st.open(store_dir, st.StoreConfig(readonly=True)) as s:
        report = s.check()
        assert report.ok and len(s) >= 1


def _wait_processing(client) -> str:
    """The address of a worker that is running a task (bounded wait)."""
    deadline = time.monotonic() + T
    while time.monotonic() < deadline:
        for addr, keys in client.processing().items():
            if keys:
                return addr
        time.sleep(0.02)
    raise AssertionError("no task started on the workers")


# ---------------------------------------------------------------------------- doors
def _ports(cluster, watcher) -> list[str]:
    """Every address the cluster accepts Dask connections on: scheduler, workers, nannies."""
    info = watcher.scheduler_info()["workers"]
    nannies = [w["nanny"] for w in info.values() if w.get("nanny")]
    return [cluster.scheduler_address, *info, *nannies]


def test_a_process_without_the_clusters_key_cannot_connect(cluster, watcher):
    from distributed.comm import connect
    from distributed.security import Security

    _wait_workers(watcher, 2)
    addrs = _ports(cluster, watcher)
    assert len(addrs) == 5 and all(a.startswith("tls://127.0.0.1:") for a in addrs)
    stranger = Security.temporary()  # a valid certificate, of another cluster

    async def attempt(address, **connection_args):
        # what a Client does first; the outer bound holds even where a handshake never answers
        comm = await asyncio.wait_for(connect(address, timeout=5, **connection_args), 30)
        await comm.close()

    for addr in addrs:
        # the cluster's own key opens each port: the attempts below fail for their key alone
        asyncio.run(attempt(addr, **cluster.security.get_connection_args("client")))
        for address, args in (
            (addr, {}),  # a plain connection, as any local process could open
            (addr.replace("tls://", "tcp://"), {}),
            (addr, stranger.get_connection_args("client")),
        ):
            # TimeoutError is an OSError: a connection still unanswered is not a connection
            with pytest.raises((OSError, TypeError, AssertionError)):
                asyncio.run(attempt(address, **args))


def test_the_cluster_listens_on_its_dask_ports_only_no_http(cluster, watcher):
    import psutil

    _wait_workers(watcher, 2)
    pids = {os.getpid(), *watcher.run(os.getpid).values()}  # scheduler + nannies, workers
    listening = {
        (c.laddr.ip, c.laddr.port)
        for c in psutil.net_connections("tcp")
        if c.status == psutil.CONN_LISTEN and c.pid in pids
    }
    dask_ports = {
        (a.split("://")[1].rsplit(":", 1)[0], int(a.rsplit(":", 1)[1]))
        for a in _ports(cluster, watcher)
    }
    # no HTTP server (Dask starts one on every scheduler and worker): nothing beyond the
    # scheduler's, the nannies' and the workers' own ports, all on loopback
    assert listening == dask_ports, listening - dask_ports


@pytest.mark.parametrize(
    "address, how, words",
    [
        ("tcp://10.0.0.1:8786", JoinSecurity(), "--dask-insecure"),
        ("10.0.0.1:8786", JoinSecurity(), "name the protocol"),
        ("ucx://10.0.0.1:8786", JoinSecurity(), "tls://"),
        ("tls://10.0.0.1:8786", JoinSecurity(), "--dask-tls-ca"),
    ],
)
def test_joining_without_tls_or_credentials_is_refused_before_connecting(address, how, words):
    with pytest.raises(ValueError, match=words):
        check_join(address, how)
    check_join("tcp://10.0.0.1:8786", JoinSecurity(insecure=True))  # said explicitly: allowed


def test_scene_lost_with_every_worker_is_scattered_again(scene, cluster, creds, watcher):
    """Last in the module: it kills every worker and needs only one of them back (a restart
    can take minutes on a loaded machine; no later test waits for the others)."""
    _wait_workers(watcher, 1)
    job = B.RenderJob(scene.paths["test"].camera_at(2.0).resized(12, 12), _tcfg(), "trace")
    with DaskPool(scene, scheduler=cluster.scheduler_address, retries=2, security=creds) as pool:
        before = pool.submit(job).result(T)
        killed = watcher.run(os.getpid)
        for pid in killed.values():  # every holder of the scene dies
            os.kill(pid, signal.SIGKILL)
        _wait_replaced(watcher, set(killed))  # the scheduler knows, a new worker is there
        after = pool.submit(job).result(T)  # restarted workers, the scene sent again
    assert np.array_equal(before.gi, after.gi)


def _wait_replaced(client, gone: set[str]) -> None:
    """Until the scheduler lists none of the workers ``gone`` and at least one other (bounded:
    under load, noticing the deaths and restarting a worker each take seconds to minutes)."""
    deadline = time.monotonic() + T
    while time.monotonic() < deadline:
        now = set(client.scheduler_info()["workers"])
        if now and not now & gone:
            return
        time.sleep(0.1)
    raise AssertionError(f"the killed workers {sorted(gone)} were not replaced")
