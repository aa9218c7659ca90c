"""The cloud as a WebSocket server (asyncio + ``websockets``): ``icbtool serve``.

Per connection (the protocol is :mod:`icbtool.net.protocol`):

1. handshake: ``hello`` -> ``welcome`` -> ``auth``; a client whose token does not verify gets one
   ``error`` (code ``auth``) and the connection closes; it never sees a byte of the scene.
2. ``scene_info`` (sealed, like everything after the handshake): the scene's base (lights, paths),
   the mesh levels, the codecs, the client model on offer (:mod:`icbtool.net.client_model`).
3. on request: the mesh levels coarse to fine (``lpm_chunk`` ... ``lpm_done`` per level), the GI
   of a client request (``gi_request`` -> ``gi_reply``), the client model (``generator_chunk``).

Threads and processes (docs/protocol.md, sections Scaling out and Limits). Cache hits never wait
behind renders: every request is first looked up on its own thread over a *read-only* store
connection (it follows the writer's commits), a hit is encoded in a small pool and sent. A miss
becomes a render job (:class:`~icbtool.bake.RenderJob`) for the render workers
(:mod:`icbtool.system.workers`: one render thread here with ``workers=0``, else tasks on a Dask
cluster, local or joined with ``scheduler``); the misses wait in a fair queue (round robin over
clients: one client's burst cannot starve the others) bounded by
:attr:`ServerConfig.max_queued_renders`. A finished render is put by the store's one writer
thread (the store's crash safety is unchanged) and sent.

Coalescing: requests whose prefetch cameras are the same (the cloud rounds the FOV; poses rounded
to 1e-6) while one is being answered share that answer: one lookup or render, every requester
gets its reply. Bounds: at most :attr:`ServerConfig.max_pending` GI requests per client (more:
``error busy``), at most :attr:`ServerConfig.max_queued_renders` misses waiting for a worker
(more: ``busy``), a request camera of at most :attr:`ServerConfig.max_request_side` pixels a side
(more: ``bad_field``), references rendered at most :attr:`ServerConfig.max_render_side` a side
(a wider prefetch camera is scaled down; the reply's camera says so), a bounded send queue per
connection (a client that does not read stalls only its own producers and is dropped after
:attr:`ServerConfig.send_timeout_s`), a maximum message size, a handshake timeout. Any error of one
connection ends that connection only; the server never sends a message its own validator rejects.

Close codes: 1000 after ``bye``, 1001 when the server shuts down, 1008 after a failed handshake or
a sealing failure (``auth``, ``crypto``, ``replay``), 1009 for a message over the size limit.

Security: the token must be long (:data:`MIN_TOKEN_CHARS`; :func:`new_token` makes a 256-bit
one) unless :attr:`ServerConfig.allow_weak_token`; with :attr:`ServerConfig.tls_cert` the server
speaks ``wss://`` (TLS under the protocol's own sealing).

Shutdown (:meth:`Server.stop`, SIGINT/SIGTERM in :meth:`Server.serve_forever`): stop accepting,
close the connections, drop the misses not started, let the running renders finish and be
committed by the store's atomic put, close the workers and the store.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import hashlib
import itertools
import json
import logging
import math
import secrets
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.net import codec as codec_mod
from icbtool.net import crypto, protocol
from icbtool.net.doors import LoginThrottle, exposure_warning, origin_allowed, usable_host
from icbtool.net.mesh_stream import MeshStream
from icbtool.net.reply_cache import EncodedReply, ReplyCache
from icbtool.optional import require
from icbtool.store import invalidation
from icbtool.system.cloud import Cloud, CloudConfig
from icbtool.system.dask_cluster import DEFAULT_WORKER_MEMORY, JoinSecurity, check_join

log = logging.getLogger(__name__)

#: Shortest token a server accepts without :attr:`ServerConfig.allow_weak_token` (characters;
#: :func:`new_token` makes 43, 256 random bits). An eavesdropper who records one handshake can
#: test token guesses offline (docs/protocol.md, section Threat model): only a token that cannot
#: be guessed is safe.
MIN_TOKEN_CHARS = 32
#: How often the server looks whether renders finished and trims its heap (seconds).
TRIM_EVERY_S = 2.0


#: The error message of a WebSocket text message (every protocol message is binary).
TEXT_FRAME = (
    "a WebSocket text message: every protocol message is one binary message (docs/protocol.md, "
    "section Transport and framing)"
)


def new_token() -> str:
    """A fresh 256-bit token (43 URL-safe base64 characters), what ``icbtool serve`` prints.

    It never starts with ``-``: a command line reads ``--token -abc...`` as a missing value
    followed by an option (one token in 64 would not paste after ``--token``). Redrawing a
    uniform draw whose first character is ``-`` leaves 6 + 252 random bits.
    """
    while True:
        token = secrets.token_urlsafe(32)
        if not token.startswith("-"):
            return token


@dataclass(frozen=True)
class ServerConfig:
    """How the server listens and what it bounds."""

    host: str = "127.0.0.1"
    """Interface to listen on (loopback by default)."""
    port: int = 0
    """TCP port; 0 picks a free one (read it from :attr:`Server.port`)."""
    max_message_bytes: int = 8 * 2**20
    """Largest message accepted from a client (bigger: the connection is closed, code 1009)."""
    chunk_bytes: int = 2**20
    """Mesh and generator parts are sent in pieces of at most this many bytes."""
    max_pending: int = 4
    """GI requests one client may have queued or in flight (more are answered ``busy``)."""
    send_queue: int = 8
    """Messages waiting to be sent per connection (producers wait when it is full)."""
    send_timeout_s: float = 30.0
    """A connection whose messages cannot be sent for this long is closed (a client not reading)."""
    handshake_timeout_s: float = 10.0
    """Time a client has to complete the handshake."""
    gi_codec: str = codec_mod.DEFAULT_GI_CODEC
    """GI codec when the request names none."""
    depth_codec: str = codec_mod.DEFAULT_DEPTH_CODEC
    """Codec of the reference depth (and mask) when the request names none."""
    lpm: bool = True
    """Stream levels of detail (icbtool.lpm) when available, else the full mesh as one level."""
    send_full_mesh: bool = False
    """Also stream the LPM's finest level (the full-detail mesh itself); off: it stays here."""
    web: bool = False
    """Also answer plain HTTP GETs on the same host/port with the browser client's page
    (:mod:`icbtool.net.web`; ``icbtool serve --web``)."""
    workers: int = 0
    """Render workers: 0 renders on one thread of this process; N >= 1 starts a local Dask
    cluster of N worker processes on 127.0.0.1 (the ``cloud`` extra)."""
    scheduler: str | None = None
    """Address of an existing Dask scheduler (``tls://host:8786``, with the ``dask_tls_*`` or
    ``dask_config`` credentials; ``tcp://`` only with ``dask_insecure``) whose workers render the
    misses; overrides ``workers``."""
    dask_tls_ca: str | None = None
    """PEM file of the CA of the Dask cluster joined with ``scheduler`` (``tls://``;
    docs/network.md)."""
    dask_tls_cert: str | None = None
    """PEM certificate this server presents to that cluster (signed by its CA)."""
    dask_tls_key: str | None = None
    """PEM private key of ``dask_tls_cert`` (None: in the certificate file)."""
    dask_config: str | None = None
    """A Dask config file (YAML) whose ``distributed.comm.tls`` section gives the CA,
    certificate and key (instead of the three above)."""
    dask_insecure: bool = False
    """Join a plain ``tcp://`` scheduler: no encryption, no authentication, anyone who reaches
    the cluster runs code as its user (a network you trust only)."""
    worker_memory_bytes: int = DEFAULT_WORKER_MEMORY
    """Dask memory limit of each worker of the local cluster (``workers``): its nanny restarts a
    worker whose memory stays above 95 % of it."""
    max_queued_renders: int = 32
    """Cache misses waiting for a render worker, all clients together (more: ``error busy``)."""
    max_request_side: int = 2048
    """Largest height or width of a gi_request's camera (more: ``error bad_field``)."""
    max_render_side: int = 2560
    """Largest side of a rendered reference; a wider prefetch camera is scaled down to it (same
    field of view) and the reply's camera states the size rendered."""
    tls_cert: str | None = None
    """PEM certificate (chain) file: serve ``wss://`` (needs ``tls_key``)."""
    tls_key: str | None = None
    """PEM private key file of ``tls_cert``."""
    login_free_failures: int = 5
    """Failed logins (wrong token, handshake timeout) an address may make before its connections
    are refused (HTTP 429) for a pause that doubles with each further failure
    (:mod:`icbtool.net.doors`); a successful login clears the address."""
    login_backoff_max_s: float = 60.0
    """The longest pause of an address that keeps failing to log in."""
    allow_weak_token: bool = False
    """Accept a token shorter than :data:`MIN_TOKEN_CHARS` (tests, a trusted network only)."""
    models: tuple[str, ...] = ()
    """Client-model runs to choose from (GAN runs with ``generator.pt``, world-space radiance runs
    with ``radiance.pt``): the server offers the one the scene's numbers favour, as ONNX
    (:mod:`icbtool.net.client_model`: the best recorded test SSIM, ties within 0.001 to the
    fewest bytes; docs/protocol.md, section Client models). Empty: none offered."""
    reply_cache_bytes: int = 256 * 2**20
    """Encoded replies of stored records kept in memory (payload bytes, least recently used
    dropped first): a repeated hit skips reading, decoding and encoding the record. 0 keeps
    none."""
    hit_flush_s: float = 2.0
    """The lookups' hit counts go to the store's writer in batches at most this often (LRU and
    least-hit eviction see them; the read-only lookup connection cannot write)."""
    render_nice: int = 10
    """Added to the nice value (CPU priority) of the renders this server starts (its render
    thread or its local cluster's workers; capped at 19): hits then get a core at once while
    renders fill the others. A joined cluster's workers keep their own."""

    def __post_init__(self) -> None:
        for k in (
            "max_message_bytes",
            "chunk_bytes",
            "max_pending",
            "send_queue",
            "max_queued_renders",
            "max_request_side",
            "max_render_side",
        ):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"ServerConfig.{k} must be an integer >= 1, got {v!r}")
        if not 0 <= self.port < 65536:
            raise ValueError(f"ServerConfig.port must be in [0, 65535], got {self.port}")
        if not isinstance(self.reply_cache_bytes, int) or self.reply_cache_bytes < 0:
            raise ValueError(
                f"ServerConfig.reply_cache_bytes must be an integer >= 0, got "
                f"{self.reply_cache_bytes!r}"
            )
        if not isinstance(self.login_free_failures, int) or self.login_free_failures < 0:
            raise ValueError(
                f"ServerConfig.login_free_failures must be an integer >= 0, got "
                f"{self.login_free_failures!r}"
            )
        for k in ("send_timeout_s", "handshake_timeout_s", "hit_flush_s", "login_backoff_max_s"):
            if not getattr(self, k) > 0:
                raise ValueError(f"ServerConfig.{k} must be > 0")
        if not isinstance(self.workers, int) or isinstance(self.workers, bool) or self.workers < 0:
            raise ValueError(f"ServerConfig.workers must be an integer >= 0, got {self.workers!r}")
        if not isinstance(self.worker_memory_bytes, int) or self.worker_memory_bytes < 2**28:
            raise ValueError(
                f"ServerConfig.worker_memory_bytes must be >= 268435456 (256 MiB), got "
                f"{self.worker_memory_bytes!r}"
            )
        if self.scheduler is not None:
            check_join(self.scheduler, self.join_security())
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("ServerConfig.tls_cert and tls_key go together (both or neither)")
        for k in ("tls_cert", "tls_key"):
            v = getattr(self, k)
            if v is not None and not Path(v).is_file():
                raise ValueError(f"ServerConfig.{k}: no such file: {v}")
        if not (isinstance(self.render_nice, int) and 0 <= self.render_nice <= 19):
            raise ValueError(
                f"ServerConfig.render_nice must be in [0, 19], got {self.render_nice!r}"
            )
        if self.gi_codec not in codec_mod.CODECS:
            raise ValueError(
                f"ServerConfig.gi_codec: {self.gi_codec!r} is not one of {sorted(codec_mod.CODECS)}"
            )
        depth_ok = sorted(c for c, v in codec_mod.CODECS.items() if v.for_depth)
        if self.depth_codec not in depth_ok:
            raise ValueError(
                f"ServerConfig.depth_codec: {self.depth_codec!r} is not one of the depth codecs "
                f"{depth_ok}"
            )
        object.__setattr__(self, "models", tuple(str(m) for m in self.models))
        if any(not m for m in self.models):
            raise ValueError(f"ServerConfig.models holds an empty run path: {self.models!r}")
        if self.max_render_side < self.max_request_side:
            raise ValueError(
                f"ServerConfig.max_render_side ({self.max_render_side}) must be >= "
                f"max_request_side ({self.max_request_side})"
            )

    def join_security(self) -> JoinSecurity:
        """The credentials to join ``scheduler`` with (the ``dask_*`` fields)."""
        return JoinSecurity(
            self.dask_tls_ca, self.dask_tls_cert, self.dask_tls_key, self.dask_config,
            self.dask_insecure,
        )  # fmt: skip


@dataclass
class ServerStats:
    """Counters since the server started (read them after :meth:`Server.stop`, or any time for an
    approximate view)."""

    connections: int = 0
    authenticated: int = 0
    auth_failures: int = 0
    throttled: int = 0
    origin_refused: int = 0
    protocol_errors: int = 0
    gi_requests: int = 0
    gi_replies: int = 0
    busy: int = 0
    coalesced: int = 0
    renders: int = 0
    render_failures: int = 0
    cache_hits: int = 0
    reply_cache_hits: int = 0
    hit_counts_flushed: int = 0
    generator_sent: int = 0
    dropped_slow: int = 0
    bytes_sent: dict[str, int] = field(default_factory=dict)


def _peer(connection: Any) -> str:
    """The peer's IP address of a websockets connection ("?" when unknown)."""
    addr = getattr(connection, "remote_address", None)
    return str(addr[0]) if addr else "?"


def camera_key(cam: Any) -> str:
    """The coalescing key of a reference camera: size, intrinsics and pose rounded to 1e-6."""
    d = cam.to_dict()
    d = {k: np.round(np.asarray(v, np.float64), 6).tolist() for k, v in d.items()}
    return json.dumps(d, sort_keys=True)


def encode_reference(
    ref: Any, gi_codec: str, depth_codec: str
) -> tuple[list[dict[str, Any]], bytes]:
    """Encode a reference's GI, depth and mask for a ``gi_reply``.

    Args:
        ref: a CRT-buffer (or anything with ``gi`` (H, W, 3), ``depth`` (H, W, 1) and ``mask``
            (H, W, 1) or None: then depth > 0).
        gi_codec, depth_codec: codecs of :data:`icbtool.net.codec.CODECS`.

    Returns:
        (the ``parts`` descriptions, the payload: the parts' bytes one after the other).
    """
    parts, blobs = [], []
    mask = ref.mask if ref.mask is not None else (ref.depth > 0).astype(np.float32)
    for name, arr, c in (
        ("gi", ref.gi, gi_codec),
        ("depth", ref.depth, depth_codec),
        ("mask", mask, depth_codec),
    ):
        arr = np.ascontiguousarray(arr, np.float32)
        b = codec_mod.encode(arr, c)
        parts.append(
            {
                "name": name,
                "codec": c,
                "shape": list(arr.shape),
                "dtype": "float32",
                "bytes": len(b),
            }
        )
        blobs.append(b)
    return parts, b"".join(blobs)


@dataclass(frozen=True)
class Answer:
    """The cloud's answer to a GI request, before encoding (:meth:`Server.answer`).

    Attributes:
        cache_hit: found in the store (no render).
        timings_ms: the cloud's stages (lookup, queue, render), ms.
        record: the stored record's index entry (a hit's, or the render's once stored): its
            id and checksum key the kept encoded replies.
        reference: the rendered CRT-buffer (None for a hit: read from the store when its
            encoded reply is not kept).
    """

    cache_hit: bool
    timings_ms: dict[str, float]
    record: Any = None
    reference: Any = None


class _Damaged(Exception):
    """A stored record could not be read for its reply (damaged or gone): render it again."""

    def __init__(self, record_id: int) -> None:
        super().__init__(f"record {record_id} is damaged or gone")
        self.record_id = record_id


class _Closing(Exception):
    """This connection ends (the reason was logged / sent) with WebSocket close ``code``."""

    def __init__(self, reason: str, code: int = 1000, quiet: bool = False) -> None:
        super().__init__(reason)
        self.code = code
        self.quiet = quiet


class _FairQueue:
    """Render slots handed out round robin over clients (docs/protocol.md, Scaling out).

    ``capacity`` renders run at once (the workers' threads); the others wait, each client in
    its own FIFO, and a freed slot goes to the next client in turn, so a client with many
    misses queued delays another client's miss by at most one render per slot. At most
    ``limit`` misses wait (:meth:`admit` raises ``busy`` beyond). Event-loop only.
    """

    def __init__(self, capacity: int, limit: int) -> None:
        self.capacity = max(1, int(capacity))
        self.limit = limit
        self.running = 0
        self._waiting: collections.OrderedDict[int, collections.deque[asyncio.Future[None]]] = (
            collections.OrderedDict()
        )
        self._closed = False

    @property
    def queued(self) -> int:
        return sum(len(q) for q in self._waiting.values())

    def admit(self) -> None:
        """Raise ``busy`` when no miss may be added now."""
        if self._closed:
            raise _Closing("server is shutting down", 1001)
        if self.running >= self.capacity and self.queued >= self.limit:
            raise protocol.ProtocolError(
                "busy",
                f"the render queue is full ({self.limit} misses waiting, scene_info.limits."
                "max_queued_renders); try again later",
            )

    async def acquire(self, client: int) -> None:
        """Wait for a render slot, in this client's turn."""
        if self._closed:
            raise _Closing("server is shutting down", 1001)
        if self.running < self.capacity and not self._waiting:
            self.running += 1
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiting.setdefault(client, collections.deque()).append(fut)
        try:
            await fut  # release() hands the slot over: running was counted for us
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled():  # the slot was ours: pass it on
                self.release()
            else:
                q = self._waiting.get(client)
                if q is not None and fut in q:
                    q.remove(fut)
                    if not q:
                        del self._waiting[client]
            raise

    def release(self) -> None:
        """Free a slot: the next client in turn gets it."""
        self.running -= 1
        while self._waiting and self.running < self.capacity:
            client, q = next(iter(self._waiting.items()))
            fut = q.popleft()
            del self._waiting[client]
            if q:  # this client goes to the back of the line
                self._waiting[client] = q
            if not fut.done():
                self.running += 1
                fut.set_result(None)

    def close(self) -> int:
        """Refuse new work and cancel the waiting misses; how many were waiting."""
        self._closed = True
        n = 0
        for q in self._waiting.values():
            for fut in q:
                n += fut.cancel()
        self._waiting.clear()
        return n


class Server:
    """The ICB cloud behind a WebSocket.

    Args:
        scene: the full-detail :class:`icbtool.scene.Scene` (never leaves the server).
        store_dir: the cloud's CRT-buffer store directory (:func:`icbtool.store.open`).
        token: the shared secret clients authenticate with (at least :data:`MIN_TOKEN_CHARS`
            characters unless ``config.allow_weak_token``; :func:`new_token` makes one).
        config: :class:`ServerConfig`.
        cloud_config: :class:`~icbtool.system.CloudConfig` of the answers (spp, prefetch, ...).
        generator: one more client-model run, as in :attr:`ServerConfig.models` (a GAN run
            directory, its ``generator.pt``, or a radiance run); None adds none.

    Use :meth:`start` / :meth:`stop` (a background thread; also a context manager) or
    :meth:`serve_forever` (this thread, until SIGINT/SIGTERM).

    Raises:
        ValueError: an empty or short token (see ``token``), a model run no client can use
            (:class:`icbtool.net.client_model.ModelRunError`).
        FileNotFoundError: a model run without a model file.

    Example:
        >>> with Server(scene, "out/cache", token=new_token()) as srv:  # doctest: +SKIP
        ...     print(srv.url)
    """

    def __init__(
        self,
        scene: Any,
        store_dir: str | Path,
        token: str,
        config: ServerConfig | None = None,
        cloud_config: CloudConfig | None = None,
        generator: str | Path | None = None,
    ) -> None:
        self.config = config or ServerConfig()
        if not isinstance(token, str) or not token:
            raise ValueError("Server token must be a non-empty string")
        if len(token) < MIN_TOKEN_CHARS and not self.config.allow_weak_token:
            raise ValueError(
                f"Server token of {len(token)} characters is too short to resist offline "
                f"guessing (at least {MIN_TOKEN_CHARS}; icbtool.net.server.new_token() makes a "
                "256-bit one); ServerConfig(allow_weak_token=True) accepts it anyway"
            )
        self.scene = scene
        self.store_dir = Path(store_dir)
        self.token = token
        self.cloud_config = cloud_config or CloudConfig()
        self.stats = ServerStats()
        self.throttle = LoginThrottle(
            free=self.config.login_free_failures, max_s=self.config.login_backoff_max_s
        )
        self.mesh = MeshStream(
            scene,
            lpm=self.config.lpm,
            send_full=self.config.send_full_mesh,
            max_chunk_bytes=self.config.chunk_bytes,
        )
        runs = [*self.config.models, *([str(generator)] if generator is not None else [])]
        #: The client model on offer (None: none), chosen among the runs at start.
        self.model: Any = None
        if runs:
            from icbtool.net import client_model

            self.model = client_model.offer(runs, self.config.chunk_bytes, scene=scene)
        self.port: int | None = None
        self._cloud: Cloud | None = None  # the writer (store owner), on the _writer thread
        self._reader: Cloud | None = None  # lookups, read-only store, on the _lookup thread
        self._writer: concurrent.futures.ThreadPoolExecutor | None = None
        self._lookup: concurrent.futures.ThreadPoolExecutor | None = None
        self._encoder: concurrent.futures.ThreadPoolExecutor | None = None
        self._pool: Any = None
        self._renders: _FairQueue | None = None
        self._render_tasks: set[asyncio.Task[Any]] = set()
        self._inflight: dict[str, asyncio.Future[Any]] = {}
        self._replies = ReplyCache(self.config.reply_cache_bytes)
        self._hits: dict[int, tuple[int, float]] = {}  # record id: (hits, last), not yet flushed
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._conn_ids = itertools.count(1)
        self._stop_requested = False
        #: the signal that stopped serve_forever ("SIGINT", "SIGTERM"; None: none yet)
        self.stopped_by: str | None = None
        #: Called with :attr:`url` once the server accepts connections.
        self.on_listening: Any = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def url(self) -> str:
        if self.port is None:
            raise RuntimeError("server is not listening")
        scheme = "wss" if self.config.tls_cert is not None else "ws"
        host = usable_host(self.config.host)
        if ":" in host and not host.startswith("["):
            host = f"[{host}]"
        return f"{scheme}://{host}:{self.port}"

    @property
    def generator_offered(self) -> bool:
        return self.model is not None

    @property
    def workers_address(self) -> str:
        """Where the renders run: ``"in-process"`` or the Dask scheduler's address."""
        return str(getattr(self._pool, "address", "not started"))

    def _open_writer(self) -> None:
        self._cloud = Cloud(self.scene, str(self.store_dir), self.cloud_config)

    def _open_reader(self) -> None:
        from icbtool import store as store_mod

        c = self.cloud_config
        scfg = store_mod.StoreConfig(
            alpha_pos=c.alpha_pos,
            alpha_dir=c.alpha_dir,
            readonly=True,
            create=False,
            refresh_interval_s=0.0,  # a lookup sees every put committed before it
        )
        self._reader = Cloud(self.scene, store_mod.open(str(self.store_dir), scfg), c)

    def _close_reader(self) -> None:
        if self._reader is not None:
            self._reader.store.close()
            self._reader = None

    def _close_writer(self) -> None:
        if self._cloud is not None:
            self._cloud.close()
            self._cloud = None

    def _tls_context(self) -> Any:
        if self.config.tls_cert is None:
            return None
        import ssl

        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ctx.load_cert_chain(self.config.tls_cert, self.config.tls_key)
        return ctx

    def serve_options(self) -> dict[str, Any]:
        """Keyword arguments of ``websockets.asyncio.server.serve`` (one place to extend, e.g.
        with ``process_request``)."""
        return {
            "max_size": self.config.max_message_bytes,
            "max_queue": 4,
            "write_limit": 2**16,
            "compression": None,
            "ping_interval": 20,
            "ping_timeout": 60,
            "close_timeout": 2,
            "ssl": self._tls_context(),
            "process_request": self._process_request_hook(),
        }

    def _process_request_hook(self) -> Any:
        """``process_request`` of every HTTP request before the WebSocket handshake: a WebSocket
        upgrade passes the login throttle and the Origin check (:mod:`icbtool.net.doors`), any
        other request goes to the web page's handler (``--web``) or is refused by websockets."""
        web = self._http_handler()
        tls = self.config.tls_cert is not None

        def hook(connection: Any, request: Any) -> Any:
            if "upgrade" not in request.headers.get("Connection", "").lower():
                return None if web is None else web(connection, request)
            wait = self.throttle.admit(_peer(connection))
            if wait > 0:
                self.stats.throttled += 1
                r = connection.respond(
                    429, f"too many failed logins from this address; retry in {math.ceil(wait)} s\n"
                )
                r.headers["Retry-After"] = str(math.ceil(wait))
                return r
            if not origin_allowed(request.headers, tls):
                self.stats.origin_refused += 1
                return connection.respond(
                    403, "this server accepts WebSockets from its own pages (Origin) only\n"
                )
            return None

        return hook

    async def serve(self) -> None:
        """Serve until :meth:`stop` (or the stop event) is set; then shut down cleanly."""
        serve = require("websockets.asyncio.server", "icbtool.net.Server").serve
        from icbtool.system.workers import open_pool

        cfg = self.config
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self._stop_requested:
            self._stop.set()
        self._writer = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="icb-store")
        self._lookup = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="icb-lookup")
        self._encoder = concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="icb-encode")
        try:
            # each store connection is opened on its own thread (SQLite binds it there); the
            # writer first: it creates the store and registers the scene the reader follows
            await asyncio.wrap_future(self._writer.submit(self._open_writer))
            await asyncio.wrap_future(self._lookup.submit(self._open_reader))
            self._pool = await asyncio.to_thread(
                open_pool,
                self.scene,
                cfg.workers,
                cfg.scheduler,
                cfg.render_nice,
                cfg.join_security() if cfg.scheduler else None,
                cfg.worker_memory_bytes,
            )
            self._renders = _FairQueue(self._pool.capacity, cfg.max_queued_renders)
            async with serve(self._handle, cfg.host, cfg.port, **self.serve_options()) as ws:
                self.port = int(next(iter(ws.sockets)).getsockname()[1])
                log.info(
                    "icbtool server on %s (scene %s, renders: %s)",
                    self.url,
                    self.scene.name,
                    self.workers_address,
                )
                warning = exposure_warning(cfg.host, cfg.tls_cert is not None)
                if warning is not None:
                    log.warning(warning)
                self._ready.set()
                if self.on_listening is not None:
                    self.on_listening(self.url)
                flusher = asyncio.get_running_loop().create_task(self._flush_hits_every())
                trimmer = asyncio.get_running_loop().create_task(self._trim_after_renders())
                await self._stop.wait()
                await flusher
                await trimmer
                self.throttle.flush()
                log.info("shutting down: closing connections")
                ws.close(close_connections=True)
                await ws.wait_closed()
        except BaseException as e:
            self._start_error = e
            raise
        finally:
            self._ready.set()
            await self._shutdown_workers()

    async def _shutdown_workers(self) -> None:
        """Drop the misses not started, let the running renders commit, close everything."""
        if self._renders is not None:
            dropped = self._renders.close()
            if dropped:
                log.info("dropped %d queued renders", dropped)
        if self._render_tasks:
            await asyncio.wait(list(self._render_tasks), timeout=600)
        if self._pool is not None:
            await asyncio.to_thread(self._pool.close)
            self._pool = None
        await self._flush_hits()  # the last counts, before the writer closes the store
        for ex, close in ((self._lookup, self._close_reader), (self._writer, self._close_writer)):
            if ex is not None:
                with contextlib.suppress(Exception):
                    await asyncio.wrap_future(ex.submit(close))
                ex.shutdown(wait=False)
        if self._encoder is not None:
            self._encoder.shutdown(wait=False, cancel_futures=True)
        self._writer = self._lookup = None
        log.info("cloud closed (store committed)")

    def start(self, timeout_s: float = 60.0) -> Server:
        """Serve on a background thread; returns once listening (then :attr:`port` is set).

        Raises:
            RuntimeError: the server could not start (the cause is chained).
        """
        if self._thread is not None:
            raise RuntimeError("server already started")
        self._thread = threading.Thread(target=self._thread_main, name="icb-server", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise RuntimeError(f"server did not start within {timeout_s} s")
        if self._start_error is not None or self.port is None:
            raise RuntimeError(f"server failed to start: {self._start_error!r}") from (
                self._start_error
            )
        return self

    def _thread_main(self) -> None:
        with contextlib.suppress(Exception):
            asyncio.run(self.serve())

    def stop(self, timeout_s: float = 60.0) -> None:
        """Shut down (see module docstring) and wait for it, from any thread."""
        self._stop_requested = True
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(self._wake)
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def serve_forever(self) -> None:
        """Serve on this thread until SIGINT or SIGTERM, then shut down cleanly."""

        async def main() -> None:
            loop = asyncio.get_running_loop()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, self._signalled, sig)
            await self.serve()

        asyncio.run(main())

    def _signalled(self, sig: int) -> None:
        log.info("signal %s: stopping", signal.Signals(sig).name)
        self.stopped_by = signal.Signals(sig).name  # `icbtool serve`: SIGINT is exit 130
        self._stop_requested = True
        self._wake()

    def _wake(self) -> None:
        if self._stop is not None:
            self._stop.set()

    def __enter__(self) -> Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _http_handler(self) -> Any:
        """The page's HTTP hook when :attr:`ServerConfig.web` is on (icbtool.net.web), else None."""
        if not self.config.web:
            return None
        from icbtool.net import web

        return web.http_handler()

    @property
    def codecs(self) -> list[str]:
        """The codecs this server encodes."""
        return list(codec_mod.CODECS)

    def codecs_of(self, fields: dict[str, Any], rid: Any = None) -> tuple[str, str]:
        """The (GI, depth) codecs a ``gi_request`` asks for, checked before any work.

        Raises:
            ProtocolError: ``bad_field`` naming the field: a GI codec not in :attr:`codecs`, or
                a depth codec that is not one or cannot carry depth (keep 0 and inf exactly).
        """
        gi = fields.get("codec", self.config.gi_codec)
        depth = fields.get("depth_codec", self.config.depth_codec)
        if gi not in self.codecs:
            raise protocol.ProtocolError(
                "bad_field", f"gi_request.codec: {gi!r} is not one of {self.codecs}", rid
            )
        depth_ok = [c for c in self.codecs if codec_mod.CODECS[c].for_depth]
        if depth not in depth_ok:
            raise protocol.ProtocolError(
                "bad_field",
                f"gi_request.depth_codec: {depth!r} is not one of the depth codecs {depth_ok}",
                rid,
            )
        return gi, depth

    def scene_info(self) -> dict[str, Any]:
        """The fields of ``scene_info``: the base (lights, sky; the paths go in its payload,
        :meth:`scene_paths`), LPM levels, codecs, the generator on offer."""
        base = self.mesh.base
        cam = self.scene.default_camera
        if cam is None:  # the schema wants one: the first camera of a path
            cam = next(iter(self.scene.paths.values()))[0] if self.scene.paths else None
        if cam is None:
            raise ValueError(f"scene {self.scene.name!r} has no default camera and no path")
        return {
            "name": self.scene.name,
            "bounds": np.asarray(self.scene.bounds, float).tolist(),
            "lights": base["lights"],
            "camera": protocol.camera_to_json(cam),
            "lpm": {"levels": self.mesh.info(self.config.chunk_bytes)},
            "generator": self.model.scene_info() if self.model is not None else None,
            "codecs": self.codecs,
            # beyond the schema's required fields: what a client needs to shade and move
            "sky": base["sky"],
            "up": base["up"],
            "default_camera": base["default_camera"],
            "max_pending": self.config.max_pending,
            "limits": {
                "max_message_bytes": self.config.max_message_bytes,
                "max_request_side": self.config.max_request_side,
                "max_render_side": self.config.max_render_side,
                "spp": self.cloud_config.spp,
                "max_queued_renders": self.config.max_queued_renders,
            },
        }

    def scene_paths(self) -> bytes:
        """The ``scene_info`` payload: the camera paths as UTF-8 JSON (empty without paths)."""
        paths = self.mesh.base["paths"]
        return json.dumps({"paths": paths}, separators=(",", ":")).encode() if paths else b""

    # ------------------------------------------------------------------ the cloud, coalesced
    def state_fields(self, ans: Answer) -> dict[str, Any]:
        """The gi_reply fields of the reference's scene state (docs/protocol.md, section Scene
        states and progressive refinement). This server answers its scene at one time: a record
        of another state (a store filled at other times) is stale whatever the change
        (conservative), and no refinement is under way."""
        meta = getattr(ans.record, "meta", None) or getattr(ans.reference, "meta", None)
        if meta is None:
            return {}
        state, _t = invalidation.record_state(meta)
        current = invalidation.state_id(self.scene)
        return {"stale": state != current, "state": state, "spp": int(meta.spp), "refining": False}

    def reference_camera(self, req: Any) -> Any:
        """The camera rendered (or looked up) for ``req``, within the limits.

        Raises:
            ProtocolError: ``bad_field`` when the request's camera is over
                :attr:`ServerConfig.max_request_side`, or no reference camera can be predicted
                from its camera and motion.
        """
        cfg = self.config
        cam = req.camera
        if max(cam.height, cam.width) > cfg.max_request_side:
            raise protocol.ProtocolError(
                "bad_field",
                f"gi_request.request.camera: {cam.height}x{cam.width} is over this server's "
                f"limit of {cfg.max_request_side} pixels a side (scene_info.limits."
                "max_request_side)",
            )
        assert self._reader is not None
        try:
            ref = self._reader.reference_camera(req)
            ok = np.isfinite(ref.world_from_cam).all() and math.isfinite(ref.fx * ref.fy)
        except (ValueError, ArithmeticError):
            ok = False
        if not ok:
            raise protocol.ProtocolError(
                "bad_field",
                "gi_request.request: no reference camera can be predicted from this camera and "
                "motion (check velocity_t, velocity_r and depth_range)",
            )
        side = max(ref.height, ref.width)
        if side > cfg.max_render_side:  # same field of view, fewer pixels (the reply says so)
            k = cfg.max_render_side / side
            ref = ref.resized(max(1, int(ref.height * k)), max(1, int(ref.width * k)))
        return ref

    async def answer(
        self, req: Any, client: int = 0, damaged: int | None = None
    ) -> tuple[Answer, bool]:
        """The cloud's answer to ``req``, coalesced with an identical request in flight.

        Args:
            req: the :class:`~icbtool.system.GIRequest`.
            client: the requesting connection (misses are queued fairly per client).
            damaged: a stored record found damaged when it was read for this request: render
                (no lookup) and replace it.

        Returns:
            (answer, coalesced): ``coalesced`` is True when another request's answer was shared.

        Raises:
            ProtocolError: ``bad_field`` (limits), ``busy`` (render queue full) or ``internal``
                (the render failed on the workers after their retries).
        """
        ref_cam = self.reference_camera(req)
        key = camera_key(ref_cam) + ("" if damaged is None else f"#render {damaged}")
        fut = self._inflight.get(key)
        if fut is not None:
            self.stats.coalesced += 1
            return await asyncio.shield(fut), True
        fut = asyncio.get_running_loop().create_future()
        self._inflight[key] = fut
        try:
            ans = await self._lookup_or_render(req, ref_cam, client, damaged)
            fut.set_result(ans)
        except BaseException as e:
            if isinstance(e, asyncio.CancelledError):
                fut.cancel()
            else:
                fut.set_exception(e)
                fut.exception()  # retrieved here: the sharers get it too
            raise
        finally:
            if self._inflight.get(key) is fut:
                del self._inflight[key]
        return ans, False

    async def _lookup_or_render(
        self, req: Any, ref_cam: Any, client: int, damaged: int | None
    ) -> Answer:
        if self._lookup is None or self._reader is None:
            raise _Closing("server is shutting down")
        lookup_ms = 0.0
        if damaged is None:
            info, lookup_ms = await asyncio.wrap_future(
                self._lookup.submit(self._reader.find, ref_cam)
            )
            if info is not None:
                self.stats.cache_hits += 1
                self._count_hit(info.record_id)
                return Answer(True, {"lookup": lookup_ms, "render": 0.0}, record=info)
        assert self._renders is not None
        self._renders.admit()  # busy when the queue is full, before any work
        job = self._reader.job(ref_cam, req.seq)
        task = asyncio.get_running_loop().create_task(self._render_and_store(job, damaged, client))
        self._render_tasks.add(task)
        task.add_done_callback(self._render_tasks.discard)
        # shielded: a client that leaves does not cancel a render others may share, nor its put
        ref, info, timings = await asyncio.shield(task)
        return Answer(False, {"lookup": lookup_ms, **timings}, record=info, reference=ref)

    async def _render_and_store(
        self, job: Any, damaged: int | None, client: int
    ) -> tuple[Any, Any, dict[str, float]]:
        assert self._renders is not None
        t_queued = time.perf_counter()
        await self._renders.acquire(client)
        try:
            t0 = time.perf_counter()
            try:
                ref = await asyncio.wrap_future(self._pool.submit(job))
            except Exception as e:
                self.stats.render_failures += 1
                log.warning("render failed on the workers: %r", e)
                raise protocol.ProtocolError(
                    "internal", "the render failed on the render workers; send the request again"
                ) from None
            t1 = time.perf_counter()
            assert self._writer is not None
            info, gone = await asyncio.wrap_future(self._writer.submit(self._put, ref, damaged))
            self._replies.discard(gone)
            self.stats.renders += 1
        finally:
            self._renders.release()
        return ref, info, {"queue": 1e3 * (t0 - t_queued), "render": 1e3 * (t1 - t0)}

    def _put(self, ref: Any, damaged: int | None) -> tuple[Any, list[int]]:
        """On the writer thread: store a render; (its index entry, the ids of the kept replies
        whose records left the store with this put: a replaced damaged one, evicted ones)."""
        assert self._cloud is not None
        store = self._cloud.store
        rid = self._cloud.store_render(ref, damaged)
        gone = [i for i in self._replies.record_ids() if i not in store]
        return store.info(rid), gone

    async def encoded(self, ans: Answer, gi_codec: str, depth_codec: str) -> tuple[Any, bool]:
        """The reply contents of ``ans`` in these codecs: kept ones for a stored record when
        there are (:class:`~icbtool.net.reply_cache.ReplyCache`), else encoded now (a stored
        record is read first) and kept.

        Returns:
            (:class:`~icbtool.net.reply_cache.EncodedReply`, whether it was kept from before).

        Raises:
            _Damaged: the stored record's payload is damaged or gone (the answer is a miss).
        """
        rec = ans.record
        key = None if rec is None else (rec.record_id, rec.checksum, gi_codec, depth_codec)
        if key is not None:
            kept = self._replies.get(key)
            if kept is not None:
                self.stats.reply_cache_hits += 1
                return kept, True
        ref = ans.reference
        if ref is None:  # a stored record: read it (its lookup connection, its thread)
            if self._lookup is None or self._reader is None:
                raise _Closing("server is shutting down")
            ref = await asyncio.wrap_future(self._lookup.submit(self._load, rec.record_id))
            if ref is None:
                raise _Damaged(rec.record_id)
        assert self._encoder is not None
        parts, payload = await asyncio.wrap_future(
            self._encoder.submit(encode_reference, ref, gi_codec, depth_codec)
        )
        out = EncodedReply(protocol.camera_to_json(ref.camera), parts, payload)
        if key is not None:
            self._replies.put(key, out)
        return out, False

    def _load(self, record_id: int) -> Any:
        """On the lookup thread: a stored record, or None when damaged (logged) or gone."""
        from icbtool.store import RecordNotFoundError

        assert self._reader is not None
        try:
            return self._reader.store.get_intact(record_id)
        except RecordNotFoundError:  # evicted since its lookup
            return None

    # ------------------------------------------------------------------ hit counts
    def _count_hit(self, record_id: int) -> None:
        n, _ = self._hits.get(record_id, (0, 0.0))
        self._hits[record_id] = (n + 1, time.time())

    async def _flush_hits_every(self) -> None:
        assert self._stop is not None
        while not self._stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), self.config.hit_flush_s)
            await self._flush_hits()
            self.throttle.tick()

    async def _trim_after_renders(self) -> None:
        """Give a burst of renders' memory back: once the renders done have changed and none
        is running, trim the heap (a render's buffers are freed only after its reply is sent;
        docs/network.md, section Memory)."""
        from icbtool.system.memory import trim_heap

        assert self._stop is not None
        seen, left = self.stats.renders, 0
        while not self._stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), TRIM_EVERY_S)
            if self.stats.renders != seen:  # trim on the next two quiet ticks (the replies of
                seen, left = self.stats.renders, 2  # the last renders may still be encoding)
            if left and not self._render_tasks:
                left -= 1
                await asyncio.to_thread(trim_heap)

    async def _flush_hits(self) -> None:
        """Hand the hit counts gathered since the last call to the store's writer (one batch)."""
        if not self._hits or self._writer is None or self._cloud is None:
            return
        batch, self._hits = self._hits, {}
        try:
            await asyncio.wrap_future(self._writer.submit(self._cloud.store.add_hits, batch))
        except Exception as e:  # counts order evictions only: logged, never a request's failure
            log.warning("hit counts of %d records not stored: %r", len(batch), e)
            return
        self.stats.hit_counts_flushed += sum(n for n, _ in batch.values())

    def encode_reference(
        self, ref: Any, gi_codec: str, depth_codec: str
    ) -> tuple[list[dict[str, Any]], bytes]:
        """Encode a reference's GI, depth and mask (:func:`encode_reference`)."""
        return encode_reference(ref, gi_codec, depth_codec)

    # ------------------------------------------------------------------ connections
    async def _handle(self, ws: Any) -> None:
        ConnectionClosed = require("websockets.exceptions", "icbtool.net.Server").ConnectionClosed

        self.stats.connections += 1
        conn = _Connection(self, ws, next(self._conn_ids))
        try:
            await conn.run()
        except _Closing as e:
            conn.close_code, conn.close_reason = e.code, str(e)[:100]
            # a failed handshake is counted by the throttle, which sums them up in its log lines
            level = logging.DEBUG if e.quiet else logging.INFO
            log.log(level, "connection %d closed: %s", conn.id, e)
        except ConnectionClosed as e:
            log.info("connection %d lost: %s", conn.id, e)
        except Exception as e:  # one connection's failure never reaches the server
            log.warning("connection %d failed: %r", conn.id, e)
        finally:
            await conn.cleanup()


class _Connection:
    """One client's session on the server (see the module docstring)."""

    def __init__(self, server: Server, ws: Any, conn_id: int) -> None:
        self.server = server
        self.ws = ws
        self.id = conn_id
        self.channel: Any = None
        self.out: asyncio.Queue[protocol.Message | None] = asyncio.Queue(server.config.send_queue)
        self.pending: set[Any] = set()
        self.tasks: set[asyncio.Task[Any]] = set()
        self.writer: asyncio.Task[None] | None = None
        self.streaming_lpm = False
        self.generator_sent = False
        self.chunks_resent: set[int] = set()
        self.close_code = 1000
        self.close_reason = ""

    # -------------------------------------------------------------- sending
    async def send_plain(self, msg: protocol.Message) -> None:
        data = protocol.encode(msg)
        self._count(msg.kind, len(data))
        await asyncio.wait_for(self.ws.send(data), self.server.config.send_timeout_s)

    def _count(self, kind: str, n: int) -> None:
        b = self.server.stats.bytes_sent
        b[kind] = b.get(kind, 0) + n

    async def send(self, msg: protocol.Message) -> None:
        """Queue a sealed message (waits while the queue is full, up to the send timeout)."""
        try:
            await asyncio.wait_for(self.out.put(msg), self.server.config.send_timeout_s)
        except TimeoutError:
            self.server.stats.dropped_slow += 1
            await self.ws.close(1008, "client does not read")
            raise _Closing("send queue full for too long: the client does not read") from None

    async def _write(self) -> None:
        # sealed in sending order (the channel's nonces and replay check count messages)
        timeout = self.server.config.send_timeout_s
        while True:
            msg = await self.out.get()
            if msg is None:
                return
            try:
                data = protocol.encode(msg, self.channel)
            except protocol.ProtocolError as e:  # a bug of ours: report it, keep the session
                log.error("connection %d: cannot send %s: %s", self.id, msg.kind, e)
                data = protocol.encode(
                    protocol.error_message(
                        protocol.ProtocolError(
                            "internal", f"the server could not encode its {msg.kind} reply"
                        )
                    ),
                    self.channel,
                )
            self._count(msg.kind, len(data))
            try:
                await asyncio.wait_for(self.ws.send(data), timeout)
            except TimeoutError:
                self.server.stats.dropped_slow += 1
                log.info("connection %d: client does not read; closing", self.id)
                self.ws.transport.abort()
                return

    async def error(self, code: str, message: str, ref: Any = None, sealed: bool = True) -> None:
        msg = protocol.error_message(protocol.ProtocolError(code, message, ref))
        if sealed and self.channel is not None:
            await self.send(msg)
        else:
            await self.send_plain(msg)

    # -------------------------------------------------------------- receiving
    async def recv_plain(self, expect: str) -> protocol.Message:
        data = await asyncio.wait_for(self.ws.recv(), self.server.config.handshake_timeout_s)
        if isinstance(data, str):
            raise protocol.ProtocolError("bad_field", TEXT_FRAME, None)
        msg = protocol.decode(data, max_bytes=self.server.config.max_message_bytes)
        if msg.kind != expect:
            raise protocol.ProtocolError("auth", f"expected {expect!r}, got {msg.kind!r}", None)
        return msg

    async def handshake(self) -> None:
        hs = crypto.ServerHandshake(self.server.token)
        try:
            hello = await self.recv_plain("hello")
            await self.send_plain(protocol.Message("welcome", hs.welcome(hello.fields), b""))
            auth = await self.recv_plain("auth")
            self.channel = hs.verify(auth.fields)
        except protocol.ProtocolError as e:
            if e.code == "auth":
                self.server.stats.auth_failures += 1
            self.server.throttle.failed(_peer(self.ws))
            await self.error(e.code, e.message, e.ref, sealed=False)
            raise _Closing(f"handshake: {e.code}: {e.message}", 1008, quiet=True) from None
        except TimeoutError:
            self.server.throttle.failed(_peer(self.ws))
            await self.error("auth", "handshake not completed in time", sealed=False)
            raise _Closing("handshake timeout", 1008, quiet=True) from None
        self.server.throttle.succeeded(_peer(self.ws))
        self.server.stats.authenticated += 1

    async def run(self) -> None:
        srv = self.server
        await self.handshake()
        self.writer = asyncio.get_running_loop().create_task(self._write())
        await self.send(protocol.Message("scene_info", srv.scene_info(), srv.scene_paths()))
        async for data in self.ws:
            if self.writer.done():
                raise _Closing("writer stopped")
            if isinstance(data, str):
                srv.stats.protocol_errors += 1
                await self.error("bad_field", TEXT_FRAME)
                continue
            try:
                msg = protocol.decode(data, self.channel, max_bytes=srv.config.max_message_bytes)
            except protocol.ProtocolError as e:
                srv.stats.protocol_errors += 1
                await self.error(e.code, e.message, e.ref)
                if e.code in ("crypto", "replay", "auth"):
                    raise _Closing(f"{e.code}: {e.message}", 1008) from None
                continue
            if msg.kind == "bye":
                return
            await self.dispatch(msg)

    async def dispatch(self, msg: protocol.Message) -> None:
        srv = self.server
        if msg.kind == "gi_request":
            rid = msg.fields.get("id")
            srv.stats.gi_requests += 1
            if rid in self.pending:
                await self.error(
                    "bad_field",
                    f"gi_request.id: {rid} is already pending on this connection (ids of "
                    "unanswered requests must differ); this request is ignored",
                    None,
                )
                return
            if len(self.pending) >= srv.config.max_pending:
                srv.stats.busy += 1
                await self.error(
                    "busy", f"more than {srv.config.max_pending} GI requests pending", rid
                )
                return
            self.pending.add(rid)
            self._spawn(self.answer_gi(rid, msg.fields))
        elif msg.kind == "lpm_request":
            if self.streaming_lpm:
                await self.error("busy", "a mesh stream is already being sent")
                return
            self.streaming_lpm = True
            self._spawn(self.stream_lpm(msg.fields))
        elif msg.kind == "generator_request":
            await self.request_model(msg.fields)
        else:
            srv.stats.protocol_errors += 1
            await self.error("unknown_kind", f"a client does not send {msg.kind!r}")

    def _spawn(self, coro: Any) -> None:
        t = asyncio.get_running_loop().create_task(coro)
        self.tasks.add(t)
        t.add_done_callback(self._task_done)

    def _task_done(self, t: asyncio.Task[Any]) -> None:
        self.tasks.discard(t)
        if not t.cancelled() and t.exception() is not None:
            e = t.exception()
            if not isinstance(e, _Closing):
                log.warning("connection %d: task failed: %r", self.id, e)

    # -------------------------------------------------------------- the answers
    async def answer_gi(self, rid: Any, fields: dict[str, Any]) -> None:
        srv = self.server
        t_in = time.perf_counter()
        try:
            gi_codec, depth_codec = srv.codecs_of(fields, rid)  # before any lookup or render
            req = protocol.request_from_json(fields["request"])
            ans, coalesced = await srv.answer(req, self.id)
            t0 = time.perf_counter()
            try:
                enc, _ = await srv.encoded(ans, gi_codec, depth_codec)
            except _Damaged as e:  # read for this reply and found damaged: a miss after all
                ans, coalesced = await srv.answer(req, self.id, damaged=e.record_id)
                t0 = time.perf_counter()
                enc, _ = await srv.encoded(ans, gi_codec, depth_codec)
            timings = dict(ans.timings_ms)
            timings["encode"] = 1e3 * (time.perf_counter() - t0)
            timings["server"] = 1e3 * (time.perf_counter() - t_in)
            out = protocol.Message(
                "gi_reply",
                {
                    "id": rid,
                    "camera": enc.camera,
                    "cache_hit": bool(ans.cache_hit),
                    "coalesced": coalesced,
                    **srv.state_fields(ans),
                    "timings_ms": timings,
                    "parts": enc.parts,
                },
                enc.payload,
            )
            srv.stats.gi_replies += 1
            self.pending.discard(rid)
            await self.send(out)
        except protocol.ProtocolError as e:
            await self.error(e.code, e.message, rid)
        except _Closing:
            raise
        except Exception as e:  # never Python's words on the wire: log them, say "internal"
            log.exception("connection %d: gi_request %s failed: %r", self.id, rid, e)
            await self.error("internal", f"the server failed to answer gi_request {rid}", rid)
        finally:
            self.pending.discard(rid)

    async def stream_lpm(self, fields: dict[str, Any]) -> None:
        """Levels min_level..max_level offered, coarse to fine, each file in pieces of at most
        ``chunk_bytes``; a range with no level offered is ``not_found``, min > max
        ``bad_field``."""
        srv = self.server
        top = fields["max_level"]
        low = fields.get("min_level", 0)
        try:
            if low > top:
                await self.error(
                    "bad_field", f"lpm_request: min_level {low} is above max_level {top}"
                )
                return
            levels = [lv for lv in srv.mesh.levels if low <= lv.index <= top]
            if not levels:
                offered = [lv.index for lv in srv.mesh.levels]
                await self.error(
                    "not_found",
                    f"lpm_request: no level in [{low}, {top}]; this server offers levels "
                    f"{offered} (scene_info.lpm.levels)",
                )
                return
            for lv in levels:
                pieces = srv.mesh.pieces(lv, srv.config.chunk_bytes)
                for k, (name, part, piece, sha) in enumerate(pieces):
                    await self.send(
                        protocol.Message(
                            "lpm_chunk",
                            {
                                "level": lv.index,
                                "index": k,
                                "count": len(pieces),
                                "part": part,
                                "name": name,
                                "sha256": sha,
                            },
                            piece,
                        )
                    )
                await self.send(protocol.Message("lpm_done", {"level": lv.index}, b""))
        finally:
            self.streaming_lpm = False

    async def request_model(self, fields: dict[str, Any]) -> None:
        """``generator_request``: every chunk (once per connection) or one chunk ``index`` (each
        at most once more: a client re-fetches a piece, it does not stream the model twice)."""
        model = self.server.model
        if model is None:
            await self.error(
                "not_found",
                "generator_request: this server offers no client model (scene_info.generator "
                "is null)",
            )
            return
        index = fields.get("index")
        if index is None:
            if self.generator_sent:
                await self.error(
                    "bad_field",
                    "generator_request: the client model was already sent on this connection "
                    "(ask for one chunk with index)",
                )
                return
            self.generator_sent = True
            self._spawn(self.send_model(range(model.chunks), full=True))
        elif index >= model.chunks:
            await self.error(
                "not_found",
                f"generator_request.index: no chunk {index}; the client model has "
                f"{model.chunks} chunks (0 .. {model.chunks - 1}, scene_info.generator.chunks)",
            )
        elif index in self.chunks_resent:
            await self.error(
                "bad_field",
                f"generator_request.index: chunk {index} was already sent again on this connection",
            )
        else:
            self.chunks_resent.add(index)
            self._spawn(self.send_model([index], full=False))

    async def send_model(self, indices: Any, full: bool) -> None:
        srv = self.server
        model = srv.model
        n = model.chunks
        for i in indices:
            piece = model.chunk(i)
            await self.send(
                protocol.Message(
                    "generator_chunk",
                    {"index": i, "count": n, "sha256": hashlib.sha256(piece).hexdigest()},
                    piece,
                )
            )
        if full:
            srv.stats.generator_sent += 1

    async def cleanup(self) -> None:
        for t in list(self.tasks):
            t.cancel()
        if self.writer is not None and not self.writer.done():
            # let queued messages go out briefly, then stop
            with contextlib.suppress(asyncio.QueueFull):
                self.out.put_nowait(None)
            try:
                await asyncio.wait_for(asyncio.shield(self.writer), 1.0)
            except (TimeoutError, Exception):
                self.writer.cancel()
        with contextlib.suppress(Exception):
            await self.ws.close(self.close_code, self.close_reason)


def stats_dict(stats: ServerStats) -> dict[str, Any]:
    return asdict(stats)


__all__ = ["MIN_TOKEN_CHARS", "Server", "ServerConfig", "ServerStats", "camera_key", "new_token"]
