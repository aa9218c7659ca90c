"""The cloud as a WebSocket server (asyncio + ``websockets``): ``icbtool serve``.

Per connection (the protocol is :mod:`icbtool.net.protocol`):

1. handshake: ``hello`` -> ``welcome`` -> ``auth``; a client whose token does not verify gets one
   ``error`` (code ``auth``) and the connection closes; it never sees a byte of the scene.
2. ``scene_info`` (sealed, like everything after the handshake): the scene's base (lights, paths),
   the mesh levels, the codecs, the generator on offer.
3. on request: the mesh levels coarse to fine (``lpm_chunk`` ... ``lpm_done`` per level), the GI
   of a client request (``gi_request`` -> ``gi_reply``), the generator (``generator_chunk``, once).

Threads. The :class:`~icbtool.system.Cloud` (octree store + rasterizer + path tracer) lives on ONE
worker thread that opens it and runs every lookup and render: its SQLite connection may only be
used by the thread that opened it, its OpenGL context is current on one thread, and a render
already uses both cores (the tracer's two Embree threads), so a second render thread would only
make both slower. The event loop only parses, coalesces, queues and sends; encoding the GI maps
(zstd releases the GIL) runs in a small second pool so the cloud thread goes on rendering.

Coalescing: requests whose prefetch cameras are the same (the cloud rounds the FOV; poses rounded
to 1e-6) while one is being answered share that answer: one lookup or render, every requester
gets its reply. Bounds: at most :attr:`ServerConfig.max_pending` GI requests per client (more:
``error busy``), a bounded send queue per connection (a client that does not read stalls only
its own producers and is dropped after :attr:`ServerConfig.send_timeout_s`), a maximum message
size, a handshake timeout. Any error of one connection ends that connection only.

Shutdown (:meth:`Server.stop`, SIGINT/SIGTERM in :meth:`Server.serve_forever`): stop accepting,
close the connections, cancel the renders not started, let the running one finish (its record is
committed by the store's atomic put), close the store.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import hashlib
import itertools
import json
import logging
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icbtool._optional import require
from icbtool.net import codec as codec_mod
from icbtool.net import crypto, protocol
from icbtool.net.mesh_stream import MeshStream
from icbtool.system.cloud import Cloud, CloudConfig

log = logging.getLogger(__name__)


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

    def __post_init__(self) -> None:
        for k in ("max_message_bytes", "chunk_bytes", "max_pending", "send_queue"):
            v = getattr(self, k)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"ServerConfig.{k} must be an integer >= 1, got {v!r}")
        if not 0 <= self.port < 65536:
            raise ValueError(f"ServerConfig.port must be in [0, 65535], got {self.port}")
        for k in ("send_timeout_s", "handshake_timeout_s"):
            if not getattr(self, k) > 0:
                raise ValueError(f"ServerConfig.{k} must be > 0")


@dataclass
class ServerStats:
    """Counters since the server started (read them after :meth:`Server.stop`, or any time for an
    approximate view)."""

    connections: int = 0
    authenticated: int = 0
    auth_failures: int = 0
    protocol_errors: int = 0
    gi_requests: int = 0
    gi_replies: int = 0
    busy: int = 0
    coalesced: int = 0
    renders: int = 0
    cache_hits: int = 0
    generator_sent: int = 0
    dropped_slow: int = 0
    bytes_sent: dict[str, int] = field(default_factory=dict)


def camera_key(cam: Any) -> str:
    """The coalescing key of a reference camera: size, intrinsics and pose rounded to 1e-6."""
    d = cam.to_dict()
    d = {k: np.round(np.asarray(v, np.float64), 6).tolist() for k, v in d.items()}
    return json.dumps(d, sort_keys=True)


class _Closing(Exception):
    """This connection ends (the reason was logged / sent)."""


class Server:
    """The ICB cloud behind a WebSocket.

    Args:
        scene: the full-detail :class:`icbtool.scene.Scene` (never leaves the server).
        store_dir: the cloud's CRT-buffer store directory (:func:`icbtool.store.open`).
        token: the shared secret clients authenticate with.
        config: :class:`ServerConfig`.
        cloud_config: :class:`~icbtool.system.CloudConfig` of the answers (spp, prefetch, ...).
        generator: a trained GAN run directory (with ``generator.pt``) offered to clients, or
            that file; None offers none.

    Use :meth:`start` / :meth:`stop` (a background thread; also a context manager) or
    :meth:`serve_forever` (this thread, until SIGINT/SIGTERM).

    Example:
        >>> with Server(scene, "out/cache", token="s3cret") as srv:  # doctest: +SKIP
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
        if not isinstance(token, str) or not token:
            raise ValueError("Server token must be a non-empty string")
        self.scene = scene
        self.store_dir = Path(store_dir)
        self.token = token
        self.config = config or ServerConfig()
        self.cloud_config = cloud_config or CloudConfig()
        self.stats = ServerStats()
        self.mesh = MeshStream(
            scene,
            lpm=self.config.lpm,
            send_full=self.config.send_full_mesh,
            max_chunk_bytes=self.config.chunk_bytes,
        )
        self._generator: bytes | None = None
        self._generator_sha = ""
        self._generator_inputs: tuple[str, ...] = ()
        if generator is not None:
            g = Path(generator)
            g = g / "generator.pt" if g.is_dir() else g
            if not g.is_file():
                raise FileNotFoundError(f"generator {generator}: no generator.pt there")
            from icbtool.gan import Generator

            self._generator_inputs = Generator.load(g).inputs  # checks the file too
            self._generator = g.read_bytes()
            self._generator_sha = hashlib.sha256(self._generator).hexdigest()
        self.port: int | None = None
        self._cloud: Cloud | None = None
        self._worker: concurrent.futures.ThreadPoolExecutor | None = None
        self._encoder: concurrent.futures.ThreadPoolExecutor | None = None
        self._jobs: set[concurrent.futures.Future[Any]] = set()
        self._inflight: dict[str, asyncio.Future[Any]] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._conn_ids = itertools.count(1)
        self._stop_requested = False
        #: Called with :attr:`url` once the server accepts connections.
        self.on_listening: Any = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def url(self) -> str:
        if self.port is None:
            raise RuntimeError("server is not listening")
        return f"ws://{self.config.host}:{self.port}"

    @property
    def generator_offered(self) -> bool:
        return self._generator is not None

    def _open_cloud(self) -> None:
        self._cloud = Cloud(self.scene, str(self.store_dir), self.cloud_config)

    def _close_cloud(self) -> None:
        if self._cloud is not None:
            self._cloud.close()
            self._cloud = None

    async def serve(self) -> None:
        """Serve until :meth:`stop` (or the stop event) is set; then shut down cleanly."""
        serve = require("websockets.asyncio.server", "icbtool.net.Server").serve

        cfg = self.config
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self._stop_requested:
            self._stop.set()
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="icb-cloud")
        self._encoder = concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="icb-encode")
        try:
            # the cloud is opened on its own thread (SQLite and GL are bound to it)
            await asyncio.wrap_future(self._worker.submit(self._open_cloud))
            async with serve(
                self._handle,
                cfg.host,
                cfg.port,
                max_size=cfg.max_message_bytes,
                max_queue=4,
                write_limit=2**16,
                compression=None,
                ping_interval=20,
                ping_timeout=60,
                close_timeout=2,
                process_request=self._http_handler(),
            ) as ws_server:
                self.port = int(next(iter(ws_server.sockets)).getsockname()[1])
                log.info("icbtool server on %s (scene %s)", self.url, self.scene.name)
                self._ready.set()
                if self.on_listening is not None:
                    self.on_listening(self.url)
                await self._stop.wait()
                log.info("shutting down: closing connections")
                ws_server.close(close_connections=True)
                await ws_server.wait_closed()
        except BaseException as e:
            self._start_error = e
            raise
        finally:
            self._ready.set()
            await self._shutdown_worker()

    async def _shutdown_worker(self) -> None:
        """Cancel the renders not started, let the running one commit, close the store."""
        if self._worker is None:
            return
        cancelled = sum(f.cancel() for f in list(self._jobs))
        if cancelled:
            log.info("cancelled %d queued cloud jobs", cancelled)
        closing = self._worker.submit(self._close_cloud)
        self._worker.shutdown(wait=False)
        await asyncio.wrap_future(closing)  # after the running job: FIFO, one thread
        if self._encoder is not None:
            self._encoder.shutdown(wait=False, cancel_futures=True)
        self._worker = None
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
            "generator": (
                {
                    "sha256": self._generator_sha,
                    "bytes": len(self._generator),
                    "inputs": list(self._generator_inputs),
                }
                if self._generator is not None
                else None
            ),
            "codecs": self.codecs,
            # beyond the schema's required fields: what a client needs to shade and move
            "sky": base["sky"],
            "up": base["up"],
            "default_camera": base["default_camera"],
            "max_pending": self.config.max_pending,
        }

    def scene_paths(self) -> bytes:
        """The ``scene_info`` payload: the camera paths as UTF-8 JSON (empty without paths)."""
        paths = self.mesh.base["paths"]
        return json.dumps({"paths": paths}, separators=(",", ":")).encode() if paths else b""

    # ------------------------------------------------------------------ the cloud, coalesced
    def _cloud_job(self, fn: Any, *args: Any) -> asyncio.Future[Any]:
        if self._worker is None:
            raise _Closing("server is shutting down")
        f = self._worker.submit(fn, *args)
        self._jobs.add(f)
        f.add_done_callback(self._jobs.discard)
        return asyncio.wrap_future(f)

    def _answer_on_worker(self, req: Any, queued_at: float) -> Any:
        started = time.perf_counter()
        assert self._cloud is not None
        reply = self._cloud.request(req)
        reply.timings_ms["queue"] = 1e3 * (started - queued_at)
        return reply

    async def answer(self, req: Any) -> tuple[Any, bool]:
        """The cloud's reply to ``req``, coalesced with an identical request in flight.

        Returns:
            (reply, coalesced): ``coalesced`` is True when another request's answer was shared.
        """
        assert self._cloud is not None
        ref_cam = self._cloud.reference_camera(req)
        key = camera_key(ref_cam)
        fut = self._inflight.get(key)
        if fut is not None:
            self.stats.coalesced += 1
            return await asyncio.shield(fut), True
        fut = self._cloud_job(self._answer_on_worker, req, time.perf_counter())
        self._inflight[key] = fut
        try:
            reply = await asyncio.shield(fut)
        finally:
            if self._inflight.get(key) is fut:
                del self._inflight[key]
        if reply.cache_hit:
            self.stats.cache_hits += 1
        else:
            self.stats.renders += 1
        return reply, False

    def encode_reference(
        self, ref: Any, gi_codec: str, depth_codec: str
    ) -> tuple[list[dict[str, Any]], bytes]:
        """Encode a reference's GI, depth and mask: (part descriptions, payload)."""
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

    # ------------------------------------------------------------------ connections
    async def _handle(self, ws: Any) -> None:
        ConnectionClosed = require("websockets.exceptions", "icbtool.net.Server").ConnectionClosed

        self.stats.connections += 1
        conn = _Connection(self, ws, next(self._conn_ids))
        try:
            await conn.run()
        except _Closing as e:
            log.info("connection %d closed: %s", conn.id, e)
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
            data = protocol.encode(msg, self.channel)
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
            data = data.encode()
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
            await self.error(e.code, e.message, e.ref, sealed=False)
            raise _Closing(f"handshake: {e.code}: {e.message}") from None
        except TimeoutError:
            await self.error("auth", "handshake not completed in time", sealed=False)
            raise _Closing("handshake timeout") from None
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
                data = data.encode()
            try:
                msg = protocol.decode(data, self.channel, max_bytes=srv.config.max_message_bytes)
            except protocol.ProtocolError as e:
                srv.stats.protocol_errors += 1
                await self.error(e.code, e.message, e.ref)
                if e.code in ("crypto", "replay", "auth"):
                    raise _Closing(f"{e.code}: {e.message}") from None
                continue
            if msg.kind == "bye":
                return
            await self.dispatch(msg)

    async def dispatch(self, msg: protocol.Message) -> None:
        srv = self.server
        if msg.kind == "gi_request":
            rid = msg.fields.get("id")
            srv.stats.gi_requests += 1
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
            if srv._generator is None:
                await self.error("not_found", "this server offers no generator")
            elif self.generator_sent:
                await self.error("bad_field", "the generator was already sent on this connection")
            else:
                self.generator_sent = True
                self._spawn(self.send_generator())
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
            req = protocol.request_from_json(fields["request"])
            gi_codec = fields.get("codec") or srv.config.gi_codec
            depth_codec = fields.get("depth_codec") or srv.config.depth_codec
            for c in (gi_codec, depth_codec):
                if c not in srv.codecs:
                    raise protocol.ProtocolError(
                        "bad_field", f"gi_request.codec: {c!r} is not one of {srv.codecs}", rid
                    )
            reply, coalesced = await srv.answer(req)
            t0 = time.perf_counter()
            assert srv._encoder is not None
            parts, payload = await asyncio.wrap_future(
                srv._encoder.submit(srv.encode_reference, reply.reference, gi_codec, depth_codec)
            )
            timings = dict(reply.timings_ms)
            timings["encode"] = 1e3 * (time.perf_counter() - t0)
            timings["server"] = 1e3 * (time.perf_counter() - t_in)
            out = protocol.Message(
                "gi_reply",
                {
                    "id": rid,
                    "camera": protocol.camera_to_json(reply.reference.camera),
                    "cache_hit": bool(reply.cache_hit),
                    "coalesced": coalesced,
                    "timings_ms": timings,
                    "parts": parts,
                },
                payload,
            )
            srv.stats.gi_replies += 1
            self.pending.discard(rid)
            await self.send(out)
        except protocol.ProtocolError as e:
            await self.error(e.code, e.message, rid)
        except (ValueError, KeyError, TypeError) as e:
            await self.error("bad_field", f"gi_request {rid!r}: {e}", rid)
        finally:
            self.pending.discard(rid)

    async def stream_lpm(self, fields: dict[str, Any]) -> None:
        """Levels 0..max_level, coarse to fine, each file in pieces of at most ``chunk_bytes``."""
        srv = self.server
        top = fields["max_level"]
        low = fields.get("min_level", 0)  # optional (beyond the schema): skip coarser levels
        if not isinstance(low, int) or isinstance(low, bool):
            await self.error("bad_field", "lpm_request.min_level: must be an integer")
            self.streaming_lpm = False
            return
        try:
            for lv in srv.mesh.levels:
                if lv.index > top:
                    break
                if lv.index < low:
                    continue
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

    async def send_generator(self) -> None:
        srv = self.server
        data = srv._generator
        assert data is not None
        step = srv.config.chunk_bytes
        n = max(1, -(-len(data) // step))
        for i in range(n):
            piece = data[i * step : (i + 1) * step]
            await self.send(
                protocol.Message(
                    "generator_chunk",
                    {"index": i, "count": n, "sha256": hashlib.sha256(piece).hexdigest()},
                    piece,
                )
            )
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
            await self.ws.close()


def stats_dict(stats: ServerStats) -> dict[str, Any]:
    return asdict(stats)


__all__ = ["Server", "ServerConfig", "ServerStats", "camera_key"]
