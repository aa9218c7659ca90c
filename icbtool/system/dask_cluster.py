"""Dask clusters with closed doors: the local cluster a server or bake starts, and the security
of a cluster it joins (docs/network.md).

A Dask scheduler, worker or nanny runs any function a connected client sends it, as its user:
whoever reaches one of their ports owns the account. So:

* :func:`local_cluster` starts every process on 127.0.0.1 with TLS and mutual authentication
  under a per-cluster key and certificate made in memory (:meth:`distributed.security.Security.
  temporary`): a process of the machine that does not hold them (another user's, or one of ours
  started without them) cannot connect, a plain ``distributed.Client`` included. And it keeps no
  HTTP port: Dask starts an HTTP server on every scheduler (port 8787) and worker even with
  ``dashboard_address=None`` (``Node.start_http_server`` listens on ``dashboard_address or
  default_port``), so the workers here are :class:`QuietWorker` (started by
  :class:`QuietNanny`), whose HTTP server is made but never listens, and the scheduler's (in
  this process) is stopped as soon as the cluster is up, before its address is handed out.
* :func:`join_security` gives the :class:`~distributed.security.Security` for joining a cluster
  at ``tls://`` with the CA, certificate and key given (files, or a Dask config file holding
  ``distributed.comm.tls``); a plain ``tcp://`` scheduler is refused unless ``insecure`` is
  passed explicitly.

Worker memory: each local worker gets a Dask memory limit (``memory_limit``): Dask's nanny
restarts a worker whose memory stays above 95 % of it. Each runs with
:data:`icbtool.system.memory.WORKER_ENVIRON` (two malloc arenas) and trims its heap every
:data:`TRIM_EVERY_MS` (``malloc_trim``), so a render's memory goes back to the OS once the server
has its result (docs/network.md, section Memory).

Dask is imported only inside these functions (the ``cloud`` extra).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from icbtool.optional import require

log = logging.getLogger(__name__)

#: Memory limit of each local worker unless told otherwise (bytes; Dask restarts a worker whose
#: memory stays above 95 % of it).
DEFAULT_WORKER_MEMORY = 4 * 2**30


@dataclass(frozen=True)
class JoinSecurity:
    """How to authenticate to a Dask cluster the server joins (``--scheduler``).

    Attributes:
        tls_ca: PEM file of the CA that signed the cluster's certificates.
        tls_cert: PEM certificate of this client (signed by that CA).
        tls_key: PEM private key of ``tls_cert`` (None: in ``tls_cert``).
        config: a Dask config file (YAML) whose ``distributed.comm.tls`` section names the
            three above (instead of them).
        insecure: allow a plain ``tcp://`` scheduler: no encryption, no authentication; anyone
            who reaches the cluster's ports runs code as its workers' user.
    """

    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    config: str | None = None
    insecure: bool = False

    def __post_init__(self) -> None:
        for k in ("tls_ca", "tls_cert", "tls_key", "config"):
            v = getattr(self, k)
            if v is not None and not Path(v).is_file():
                raise ValueError(f"Dask security: {k} {v!r}: no such file")
        if self.config is not None and (self.tls_ca or self.tls_cert or self.tls_key):
            raise ValueError(
                "Dask security: give a config file or tls_ca/tls_cert/tls_key, not both"
            )
        if self.tls_key is not None and self.tls_cert is None:
            raise ValueError("Dask security: tls_key needs tls_cert")


def check_join(scheduler: str, how: JoinSecurity) -> None:
    """Refuse a join that would not be secure, before anything connects (no Dask import).

    Raises:
        ValueError: no protocol, a ``tcp://`` address without ``how.insecure``, a protocol
            other than tls:// or tcp://, or ``tls://`` without a CA and a certificate (given,
            or a config file to hold them).
    """
    proto, sep, _ = scheduler.partition("://")
    if not sep:
        raise ValueError(
            f"--scheduler {scheduler!r}: name the protocol, tls://HOST:PORT (or tcp:// with "
            "--dask-insecure)"
        )
    if proto == "tcp":
        if not how.insecure:
            raise ValueError(
                f"--scheduler {scheduler!r}: a plain tcp:// Dask cluster lets anyone who reaches "
                "its ports run code as its user; use tls:// with --dask-tls-ca and "
                "--dask-tls-cert (and --dask-tls-key), or --dask-config; or pass --dask-insecure "
                "on a network you trust"
            )
        return
    if proto != "tls":
        raise ValueError(f"--scheduler {scheduler!r}: the protocol must be tls:// (or tcp://)")
    if how.config is None and not (how.tls_ca and how.tls_cert):
        raise ValueError(
            f"--scheduler {scheduler!r}: tls:// needs the cluster's CA and a client certificate "
            "(--dask-tls-ca and --dask-tls-cert, or --dask-config with distributed.comm.tls."
            "ca-file and distributed.comm.tls.client.cert)"
        )


def join_security(scheduler: str, how: JoinSecurity) -> Any:
    """The :class:`distributed.security.Security` to join ``scheduler`` with.

    Args:
        scheduler: the scheduler's address, ``tls://host:port`` (or ``tcp://host:port`` with
            ``how.insecure``).
        how: the credentials.

    Returns:
        A Security that requires encryption (tls://), or the default one (tcp://, insecure).

    Raises:
        ValueError: see :func:`check_join`; a config file without the TLS settings.
    """
    security_mod = require("distributed.security", "render workers on Dask distributed")
    check_join(scheduler, how)
    if scheduler.startswith("tcp://"):
        log.warning("joining %s without TLS (--dask-insecure): no authentication", scheduler)
        return security_mod.Security()
    if how.config is not None:
        dask = require("dask", "render workers on Dask distributed")
        if not Path(how.config).is_file():
            raise ValueError(f"--dask-config {how.config!r}: no such file")
        try:  # dask's own YAML reader (an empty file is no settings)
            loaded = list(dask.config.collect_yaml([str(how.config)]))
        except Exception as e:  # the YAML parser's error, whatever its class
            raise ValueError(f"--dask-config {how.config!r}: not readable as YAML: {e}") from None
        settings = loaded[0] if loaded else {}
        if not isinstance(settings, dict):
            raise ValueError(f"--dask-config {how.config!r}: not a mapping of Dask settings")
        with dask.config.set(_dotted(settings)):
            sec = security_mod.Security(require_encryption=True)
    else:
        sec = security_mod.Security(
            require_encryption=True,
            tls_ca_file=how.tls_ca,
            tls_client_cert=how.tls_cert,
            tls_client_key=how.tls_key,
        )
    if not (sec.tls_ca_file and sec.tls_client_cert):
        raise ValueError(
            f"--scheduler {scheduler!r}: tls:// needs the cluster's CA and a client certificate "
            "(--dask-tls-ca and --dask-tls-cert, or --dask-config with distributed.comm.tls."
            "ca-file and distributed.comm.tls.client.cert)"
        )
    return sec


def _dotted(settings: dict, prefix: str = "") -> dict[str, Any]:
    """Nested Dask settings as dotted keys: ``dask.config.set`` given a nested mapping replaces
    whole subtrees (the TLS cipher defaults beside a file's CA would be lost)."""
    out: dict[str, Any] = {}
    for k, v in settings.items():
        if isinstance(v, dict):
            out.update(_dotted(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _quiet(cls: type) -> type:
    """``cls`` with an HTTP server that is made (Dask's code reads its attributes) but never
    listens."""

    class Quiet(cls):  # type: ignore[misc, valid-type]
        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            if hasattr(self, "periodic_callbacks"):  # a worker: trim its heap every few seconds
                _add_trim_callback(self)

        def start_http_server(self, routes: Any, dashboard_address: Any, *a: Any, **k: Any) -> None:
            routing = require("distributed.http.routing", "render workers on Dask distributed")
            httpserver = require("tornado.httpserver", "render workers on Dask distributed")
            self.http_application = routing.RoutingApplication(routes)
            self.http_server = httpserver.HTTPServer(self.http_application)
            self.http_server.address, self.http_server.port = None, None

    Quiet.__name__ = Quiet.__qualname__ = f"Quiet{cls.__name__}"
    return Quiet


#: How often a local worker trims its heap (ms): the buffers of a render's result are freed
#: only once the server has fetched it, after the task that could trim has returned.
TRIM_EVERY_MS = 2000


def _add_trim_callback(worker: Any) -> None:
    from icbtool.system.memory import trim_heap

    ioloop = require("tornado.ioloop", "render workers on Dask distributed")
    worker.periodic_callbacks["icb-trim-heap"] = ioloop.PeriodicCallback(trim_heap, TRIM_EVERY_MS)


def _nanny(worker: type) -> type:
    """A :class:`distributed.Nanny` whose worker processes are ``worker``."""
    Nanny = require("distributed", "render workers on Dask distributed").Nanny

    class QuietNanny(Nanny):  # type: ignore[misc]
        def __init__(self, *a: Any, **k: Any) -> None:
            from icbtool.system.memory import WORKER_ENVIRON

            k["worker_class"] = worker
            super().__init__(*a, **k)
            # set before the worker process starts (glibc reads them once, at its start)
            self.pre_spawn_env.update(WORKER_ENVIRON)
            self.env.update(WORKER_ENVIRON)

    QuietNanny.__qualname__ = "QuietNanny"
    return QuietNanny


def _classes() -> dict[str, type]:
    worker = _quiet(require("distributed", "render workers on Dask distributed").Worker)
    return {
        "QuietWorker": worker,
        "QuietNanny": _nanny(worker),
    }


def __getattr__(name: str) -> Any:  # the classes exist once Dask is imported
    if name in ("QuietWorker", "QuietNanny"):
        if "QuietWorker" not in globals():
            globals().update(_classes())
        return globals()[name]
    raise AttributeError(name)


def local_cluster(
    workers: int, memory_limit: int = DEFAULT_WORKER_MEMORY, log_level: int = logging.WARNING
) -> Any:
    """A Dask cluster of ``workers`` worker processes (one thread each) on 127.0.0.1, TLS with a
    fresh in-memory key, no HTTP port (see the module docstring).

    Args:
        workers: number of worker processes (>= 1).
        memory_limit: Dask memory limit of each worker, bytes.
        log_level: level of Dask's log lines shown.

    Returns:
        The started :class:`distributed.LocalCluster` (``.security`` holds its credentials;
        ``.scheduler_address`` is ``tls://127.0.0.1:PORT``).
    """
    distributed = require("distributed", "render workers on Dask distributed")
    Security = require("distributed.security", "render workers on Dask distributed").Security

    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"local_cluster: workers must be an integer >= 1, got {workers!r}")
    if not isinstance(memory_limit, int) or memory_limit < 2**28:
        raise ValueError(f"local_cluster: memory_limit must be >= 256 MiB, got {memory_limit!r}")
    cluster = distributed.LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        security=Security.temporary(),
        worker_class=globals_class("QuietNanny"),
        memory_limit=memory_limit,
        silence_logs=log_level,
    )
    # the scheduler runs in this process: its HTTP server (made by Dask in any case) stops
    # listening before anyone is told the cluster's address
    http = getattr(cluster.scheduler, "http_server", None)
    if http is not None:
        cluster.sync(_stop_http, http)
    return cluster


async def _stop_http(http: Any) -> None:
    http.stop()


def globals_class(name: str) -> type:
    """:class:`QuietWorker` or :class:`QuietNanny` (made on first use)."""
    return __getattr__(name)  # type: ignore[no-any-return]


__all__ = [
    "DEFAULT_WORKER_MEMORY",
    "check_join",
    "JoinSecurity",
    "join_security",
    "local_cluster",
]
