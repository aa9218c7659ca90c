"""Render workers: the cloud's renders in this process or as tasks on Dask distributed.

A render is a pure function of serialisable inputs (:func:`icbtool.bake.render_job`: the scene,
a :class:`~icbtool.bake.RenderJob` with the camera and the trace config and its seed) returning a
CRT-buffer, so the same jobs give the same maps wherever they run (docs/protocol.md, section
Scaling out). Two pools behind one interface (``submit(job) -> concurrent.futures.Future``,
``capacity``, ``close``):

* :class:`LocalPool` (``workers=0``): one render thread in this process, with its own
  rasterizer (the tracer already uses every core of the machine).
* :class:`DaskPool`: tasks on a Dask cluster, either a local one that it starts
  (``workers=N``: N worker processes of one thread each, every socket on 127.0.0.1, TLS with a
  per-cluster key, no HTTP port: :func:`icbtool.system.dask_cluster.local_cluster`) or an
  existing one (``scheduler="tls://host:8786"`` with credentials: workers started with ``dask
  worker`` on other machines, or any deployment Dask supports; docs/network.md). The scene
  goes to the workers once (scattered to every worker, no shared filesystem assumed); each
  worker process keeps one rasterizer per scene.

A server runs its renders at a lower CPU priority (``nice``: :data:`RENDER_NICE` on the render
thread of a :class:`LocalPool` or in the workers of a local cluster; Linux priorities are per
thread and the tracer's threads inherit them): on a machine whose cores the renders fill, its
lookups and replies still get a core at once (docs/protocol.md, section Scaling out). A bake
leaves priorities alone (``nice=0``, the default), and so does a pool on a cluster joined with
``scheduler``.

The pools never touch a store: the process that owns it (server or baker) is its only writer.
A task whose worker dies is retried by the scheduler on another worker; if the scene itself was
lost with it (every worker holding it died) the pool scatters it again and resubmits the job,
``retries`` times at most; after that the job's future raises :class:`RenderError`.

After each render a pool gives its memory back (:func:`icbtool.system.memory.
release_after_render`: the tracer's kept workspaces dropped, the heap trimmed); docs/network.md,
section Memory, says where a render's memory goes and the bound.

Dask is imported only here, and only when a :class:`DaskPool` is made (the ``cloud`` extra).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import threading
from typing import Any

from icbtool.bake import RenderJob, render_job
from icbtool.optional import require
from icbtool.system.dask_cluster import (
    DEFAULT_WORKER_MEMORY,
    JoinSecurity,
    join_security,
    local_cluster,
)
from icbtool.system.memory import release_after_render

log = logging.getLogger(__name__)


class RenderError(RuntimeError):
    """A render job failed on the workers (after the pool's retries)."""


class ShippedScene:
    """A scene in the form that travels to the workers (the init fields of the immutable
    :class:`icbtool.scene.Scene`; built again once per worker process, same content hash).

    Args:
        scene: the scene to ship.
    """

    def __init__(self, scene: Any) -> None:
        self.kind = type(scene)
        self.fields = {f.name: getattr(scene, f.name) for f in dataclasses.fields(scene)}
        self.fields["paths"] = dict(scene.paths)
        self.content_hash = scene.content_hash

    def build(self) -> Any:
        """The scene (cached per process: a worker builds each scene once)."""
        with _CACHE_LOCK:
            s = _SCENES.get(self.content_hash)
            if s is None:
                s = _SCENES[self.content_hash] = self.kind(**self.fields)
            return s


_CACHE_LOCK = threading.Lock()
_SCENES: dict[str, Any] = {}
_RASTERIZERS: dict[tuple[str, int], Any] = {}


def _rasterizer_for(scene: Any) -> Any:
    """This thread's rasterizer of ``scene`` (a worker opens one GL context per scene)."""
    from icbtool import raster

    key = (scene.content_hash, threading.get_ident())
    with _CACHE_LOCK:
        r = _RASTERIZERS.get(key)
    if r is None:
        r = raster.Rasterizer(scene, raster.RasterConfig())
        with _CACHE_LOCK:
            _RASTERIZERS[key] = r
    return r


#: Nice value of render threads (see the module docstring).
RENDER_NICE = 10
_niced: set[int] = set()


def lower_priority(nice: int) -> None:
    """Add ``nice`` to this thread's nice value once (at most 19; threads it starts inherit
    it); 0: no change. Relative, so a server started under ``nice`` keeps its edge over its
    renders. An OS that refuses is logged, not fatal."""
    tid = threading.get_native_id()
    if nice <= 0 or tid in _niced:
        return
    _niced.add(tid)
    try:
        import os

        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (AttributeError, OSError) as e:  # not Linux, or not allowed
        log.info("render thread priority unchanged: %r", e)


def run_job(shipped: ShippedScene, job: RenderJob, nice: int = 0) -> Any:
    """The task a worker runs: :func:`icbtool.bake.render_job` with this worker's scene and
    rasterizer, at ``nice`` priority. Returns the :class:`~icbtool.store.record.CRTBuffer`."""
    lower_priority(nice)
    scene = shipped.build()
    rasterizer = _rasterizer_for(scene) if job.gbuffer == "raster" else None
    try:
        return render_job(scene, job, rasterizer)
    finally:
        release_after_render()


class LocalPool:
    """Renders in this process, on one thread (``workers=0``).

    Args:
        scene: the scene every job renders.
        nice: nice value of the render thread (0: unchanged).
    """

    capacity = 1

    def __init__(self, scene: Any, nice: int = 0) -> None:
        self.scene = scene
        self.nice = nice
        self._rasterizer: Any = None
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="icb-render")
        self.address = "in-process"

    def _run(self, job: RenderJob) -> Any:
        lower_priority(self.nice)
        if job.gbuffer == "raster" and self._rasterizer is None:
            from icbtool import raster

            self._rasterizer = raster.Rasterizer(self.scene, raster.RasterConfig())
        try:
            return render_job(self.scene, job, self._rasterizer)
        finally:
            release_after_render()

    def submit(self, job: RenderJob) -> concurrent.futures.Future[Any]:
        """Queue ``job``; the future holds its CRT-buffer."""
        return self._pool.submit(self._run, job)

    def close(self) -> None:
        """Finish the running job, drop the queued ones, close the rasterizer."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._rasterizer is not None:
            self._rasterizer.close()
            self._rasterizer = None

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class DaskPool:
    """Renders as tasks on a Dask cluster (see the module docstring).

    Args:
        scene: the scene every job renders (scattered to the workers once).
        workers: start a local cluster of this many worker processes (one thread each) on
            127.0.0.1; ignored with ``scheduler``.
        scheduler: address of an existing scheduler (``tcp://host:port``) to join instead.
        retries: how many times a job whose scene or worker was lost is submitted again.
        timeout_s: how long to wait for the scheduler and for a first worker.
        nice: nice value of the render threads of a local cluster (0: unchanged); ignored with
            ``scheduler`` (a joined cluster's workers are left as their owner started them).
        security: credentials to join ``scheduler`` (:class:`~icbtool.system.dask_cluster.
            JoinSecurity`; None: none, which only an insecure ``tcp://`` join accepts).
        memory_limit: Dask memory limit of each worker of a local cluster, bytes.

    Raises:
        MissingOptionalDependency: dask/distributed are not installed (the ``cloud`` extra).
        ValueError: neither a positive ``workers`` nor a ``scheduler``; a ``scheduler`` that is
            not ``tls://`` with credentials (or ``tcp://`` with ``security.insecure``).
    """

    def __init__(
        self,
        scene: Any,
        workers: int = 1,
        scheduler: str | None = None,
        retries: int = 1,
        timeout_s: float = 60.0,
        nice: int = 0,
        security: JoinSecurity | None = None,
        memory_limit: int = DEFAULT_WORKER_MEMORY,
    ) -> None:
        distributed = require("distributed", "render workers on Dask distributed")
        if scheduler is None and (not isinstance(workers, int) or workers < 1):
            raise ValueError(f"DaskPool: workers must be an integer >= 1, got {workers!r}")
        self.cluster: Any = None
        if scheduler is None:
            self.cluster = local_cluster(workers, memory_limit)
            scheduler = self.cluster.scheduler_address
            sec = self.cluster.security
        else:
            sec = join_security(scheduler, security or JoinSecurity())
        self.address = scheduler
        self.client = distributed.Client(
            scheduler, timeout=timeout_s, set_as_default=False, security=sec
        )
        try:
            self.client.wait_for_workers(1, timeout=timeout_s)
            self.capacity = max(1, sum(self.client.nthreads().values()))
            self._shipped = ShippedScene(scene)
            self._lock = threading.Lock()
            self._scene_future = self._scatter()
        except BaseException:
            self.close()
            raise
        self.retries = retries
        self.timeout_s = timeout_s
        self.resubmitted = 0
        self.nice = nice if self.cluster is not None else 0

    def _scatter(self) -> Any:
        return self.client.scatter(self._shipped, broadcast=True, hash=False)

    def submit(self, job: RenderJob) -> concurrent.futures.Future[Any]:
        """Queue ``job`` on the cluster; the future holds its CRT-buffer or raises
        :class:`RenderError` once the retries are spent."""
        out: concurrent.futures.Future[Any] = concurrent.futures.Future()
        out.set_running_or_notify_cancel()
        self._submit(job, out, 0)
        return out

    def _submit(self, job: RenderJob, out: concurrent.futures.Future[Any], attempt: int) -> None:
        with self._lock:
            scene_f = self._scene_future
        fut = self.client.submit(run_job, scene_f, job, self.nice, pure=False, retries=0)
        fut.add_done_callback(lambda f: self._done(f, job, out, attempt, scene_f))

    def _done(
        self,
        fut: Any,
        job: RenderJob,
        out: concurrent.futures.Future[Any],
        attempt: int,
        scene_f: Any,
    ) -> None:
        # runs on a thread of the dask client, never on its event loop
        try:
            out.set_result(fut.result())
            return
        except Exception as e:
            err: Exception = e
        if out.done():
            return
        if attempt >= self.retries:
            out.set_exception(RenderError(f"render failed after {attempt + 1} attempts: {err!r}"))
            return
        log.warning("render job failed (%r); submitting it again", err)
        self.resubmitted += 1
        try:
            with self._lock:
                if self._scene_future is scene_f and scene_f.status != "finished":
                    # the scene was lost with its workers: send it again once one is back (a
                    # scatter to a cluster with no worker fails, and can take the nannies down)
                    self.client.wait_for_workers(1, timeout=self.timeout_s)
                    self._scene_future = self._scatter()
            self._submit(job, out, attempt + 1)
        except Exception as e:  # the cluster is gone
            out.set_exception(RenderError(f"render failed and could not be retried: {e!r}"))

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> process id (e.g. to watch or stop one)."""
        import os

        return self.client.run(os.getpid)

    def close(self) -> None:
        """Disconnect (and stop the local cluster this pool started)."""
        if getattr(self, "client", None) is not None:
            self.client.close()
            self.client = None
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def __enter__(self) -> DaskPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_pool(
    scene: Any,
    workers: int = 0,
    scheduler: str | None = None,
    nice: int = 0,
    security: JoinSecurity | None = None,
    memory_limit: int = DEFAULT_WORKER_MEMORY,
) -> LocalPool | DaskPool:
    """The render pool for ``workers`` / ``scheduler`` (see the module docstring).

    Args:
        scene: the scene every job renders.
        workers: 0: :class:`LocalPool` (this process); N >= 1: a local Dask cluster of N workers.
        scheduler: join this Dask scheduler instead (``workers`` is then ignored).
        nice: nice value of the render threads this pool starts (a server: :data:`RENDER_NICE`).
        security: credentials to join ``scheduler`` (see :class:`DaskPool`).
        memory_limit: Dask memory limit of each local worker, bytes.

    Raises:
        ValueError: ``workers`` < 0; a ``scheduler`` refused (see :class:`DaskPool`).
    """
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 0:
        raise ValueError(f"workers must be an integer >= 0, got {workers!r}")
    if scheduler is None and workers == 0:
        return LocalPool(scene, nice)
    return DaskPool(
        scene, workers, scheduler, nice=nice, security=security, memory_limit=memory_limit
    )


__all__ = ["DaskPool", "LocalPool", "RenderError", "ShippedScene", "open_pool", "run_job"]
