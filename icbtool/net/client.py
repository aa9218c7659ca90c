"""The client's side of the networked ICB system: :class:`NetworkSource` (a
:class:`~icbtool.system.GISource` over a WebSocket) and :func:`run_client` (``icbtool client``).

:class:`NetworkSource` runs its asyncio WebSocket on a background thread, so the synchronous
``GISource.request`` works from the client's frame loop. It authenticates (the handshake of
:mod:`icbtool.net.crypto`), receives ``scene_info``, and then, on request, the mesh levels (coarse
to fine, rebuilt into scenes by :func:`icbtool.net.mesh_stream.assemble`), GI replies and the
generator. Every message it receives or sends is counted by kind (bytes as on the wire).

Timings of a reply (``GIReply.timings_ms``), the request -> reply time split:

* ``lookup``, ``render``, ``queue`` (waiting for the cloud thread), ``encode``: on the server;
* ``server``: the server's whole time, from the request's arrival to the reply's queuing;
* ``transfer``: the rest of the round trip: both directions on the (shaped) wire plus the
  server's send queue: ``request - server - decode``;
* ``decode``: opening nothing (the channel did that on arrival) but decoding the GI, depth and
  mask on the client;
* ``request``: the whole request -> reply time seen by the client.

Once the client holds the served client model (docs/design.md section 6; docs/protocol.md,
section Client models: a GAN generator or a world-space radiance model, as ONNX, run by
:class:`icbtool.net.client_model.ServedModel` from its announcement), a request whose client
buffers hold the model's inputs is answered by it locally (:class:`~icbtool.system.GeneratorSource`,
with this source as its fallback) and never sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import itertools
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from icbtool.camera import Camera
from icbtool.net import codec as codec_mod
from icbtool.net import crypto, protocol
from icbtool.net import mesh_stream as ms
from icbtool.net.shaper import DelayLine, ShaperConfig
from icbtool.optional import require
from icbtool.system.messages import GIReply, GIRequest
from icbtool.system.source import GISource

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NetClientConfig:
    """How a :class:`NetworkSource` talks to the server."""

    timeout_s: float = 120.0
    """Longest wait for any answer (connect, handshake, a GI reply, a mesh level)."""
    gi_codec: str = codec_mod.DEFAULT_GI_CODEC
    """Codec asked for the GI maps (:data:`icbtool.net.codec.CODECS`)."""
    depth_codec: str = codec_mod.DEFAULT_DEPTH_CODEC
    """Codec asked for the reference depth (and mask)."""
    shaper: ShaperConfig = field(default_factory=ShaperConfig)
    """Emulated latency and bandwidth on both directions."""
    max_message_bytes: int = 64 * 2**20
    """Largest message accepted from the server."""
    use_generator: bool = True
    """Fetch the client model when the server offers one (``scene_info.generator``: a GAN
    generator or a world-space radiance model, ONNX) and make GI with it locally, through
    onnxruntime (:class:`icbtool.net.client_model.ServedModel`), once it is here."""
    model_threads: int = 0
    """onnxruntime threads of the served model (0: onnxruntime's choice)."""
    ca_file: str | None = None
    """``wss://`` servers: the PEM certificate(s) to trust (e.g. a self-signed server's own
    certificate); None: the system's trust store."""

    def __post_init__(self) -> None:
        if not (isinstance(self.model_threads, int) and self.model_threads >= 0):
            raise ValueError(
                f"NetClientConfig.model_threads must be an integer >= 0, got {self.model_threads!r}"
            )
        if not self.timeout_s > 0:
            raise ValueError(f"NetClientConfig.timeout_s must be > 0, got {self.timeout_s}")
        if not isinstance(self.shaper, ShaperConfig):
            raise ValueError("NetClientConfig.shaper must be a ShaperConfig")
        for k in ("gi_codec", "depth_codec"):
            if getattr(self, k) not in codec_mod.CODECS:
                raise ValueError(
                    f"NetClientConfig.{k} {getattr(self, k)!r} is not one of "
                    f"{sorted(codec_mod.CODECS)}"
                )


@dataclass(frozen=True)
class NetReference:
    """A reference received from the server, shaped like a CRT-buffer for the warp.

    Attributes:
        camera: the reference (prefetch) camera.
        gi: (H, W, 3) float32 linear HDR GI.
        depth: (H, W, 1) float32 view depth.
        mask: (H, W, 1) float32 surface mask.
    """

    camera: Camera
    gi: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


class NetError(RuntimeError):
    """The server reported an error, or the connection failed (the message says which)."""

    def __init__(self, message: str, code: str | None = None) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class _Level:
    pieces: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)
    count: int = 0
    done: bool = False
    triangles: int = 0


class NetworkSource(GISource):
    """GI from an ICB server over a WebSocket (see the module docstring).

    Args:
        url: ``ws://host:port``.
        token: the shared secret.
        config: :class:`NetClientConfig`.

    Raises:
        NetError: the server refused the token (code ``auth``) or could not be reached.

    Attributes:
        scene_info: the server's ``scene_info`` fields.
        bytes_received, bytes_sent: bytes on the wire by message kind.
        generated, remote: frames answered by the local generator / by the server.
    """

    kind = "network"

    def __init__(self, url: str, token: str, config: NetClientConfig | None = None) -> None:
        require("websockets", "the networked ICB client")
        self.url = url
        self.config = cfg = config or NetClientConfig()
        self.bytes_received: dict[str, int] = {}
        self.bytes_sent: dict[str, int] = {}
        self.scene_info: dict[str, Any] = {}
        self.remote = 0
        self._ids = itertools.count(1)
        self._replies: dict[int, asyncio.Future[tuple[protocol.Message, float]]] = {}
        self._levels: dict[int, _Level] = {}
        self._level_cond = threading.Condition()
        self._scenes: dict[int, Any] = {}
        self._gen_pieces: dict[int, bytes] = {}
        self._gen_ready = threading.Event()
        self._gen_error: str | None = None
        self._gen_source: Any = None
        self._gen_bytes = 0
        self._fatal: NetError | None = None
        self._ws: Any = None
        self._channel: Any = None
        self._send_lock: asyncio.Lock | None = None
        self._up: DelayLine | None = None
        self._down: DelayLine | None = None
        self._reader: asyncio.Task[None] | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="icb-net", daemon=True)
        self._thread.start()
        try:
            self._call(self._connect(token), cfg.timeout_s)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ loop plumbing
    def _call(self, coro: Any, timeout_s: float | None = None) -> Any:
        fut = asyncio.run_coroutine_threadsafe(coro, self._loop)
        try:
            return fut.result(timeout_s if timeout_s is not None else self.config.timeout_s)
        except TimeoutError:
            fut.cancel()
            raise NetError(f"{self.url}: no answer within {timeout_s} s", "timeout") from None

    async def _connect(self, token: str) -> None:
        connect = require("websockets.asyncio.client", "the networked ICB client").connect
        wsx = require("websockets.exceptions", "the networked ICB client")

        cfg = self.config
        tls: Any = None
        if self.url.startswith("wss://"):
            import ssl

            tls = ssl.create_default_context(cafile=cfg.ca_file)
        try:
            self._ws = await connect(
                self.url,
                ssl=tls,
                max_size=cfg.max_message_bytes,
                compression=None,
                proxy=None,
                open_timeout=cfg.timeout_s,
                ping_interval=20,
                ping_timeout=60,
                close_timeout=2,
            )
        except (OSError, wsx.WebSocketException) as e:  # ssl.SSLError is an OSError
            raise NetError(f"cannot connect to {self.url}: {e}") from e
        self._send_lock = asyncio.Lock()
        hs = crypto.ClientHandshake(token)
        await self._send_raw(protocol.Message("hello", hs.hello_fields(), b""), sealed=False)
        welcome = await self._recv_plain()
        self._channel, auth = hs.finish(welcome.fields)
        await self._send_raw(protocol.Message("auth", auth, b""), sealed=False)
        info = await self._recv_plain(sealed=True)
        if info.kind != "scene_info":
            raise NetError(f"{self.url}: expected scene_info, got {info.kind!r}")
        self.scene_info = dict(info.fields)
        try:
            self.scene_info["paths"] = (
                json.loads(info.payload.decode("utf-8"))["paths"] if info.payload else {}
            )
        except (UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
            raise NetError(f"{self.url}: scene_info payload is not paths JSON: {e}") from e
        shaped = cfg.shaper.active
        if shaped:
            self._up = DelayLine(cfg.shaper, self._ws.send)
            self._down = DelayLine(cfg.shaper, self._dispatch)
            self._up.start()
            self._down.start()
        self._reader = asyncio.get_running_loop().create_task(self._read())

    async def _recv_plain(self, sealed: bool = False) -> protocol.Message:
        try:
            data = await self._ws.recv()
        except Exception as e:  # closed by the server after an error we did not see
            raise NetError(f"{self.url}: connection closed during the handshake: {e}") from e
        mb = self.config.max_message_bytes
        try:
            msg = protocol.decode(data, self._channel if sealed else None, max_bytes=mb)
        except protocol.ProtocolError:
            if not sealed:
                raise
            msg = protocol.decode(data, None, max_bytes=mb)  # a refusal comes before sealing
            if msg.kind != "error":
                raise
        self._count(self.bytes_received, msg.kind, len(data))
        if msg.kind == "error":
            raise NetError(
                f"{self.url}: server refused: [{msg.fields['code']}] {msg.fields['message']}",
                msg.fields["code"],
            )
        return msg

    @staticmethod
    def _count(table: dict[str, int], kind: str, n: int) -> None:
        table[kind] = table.get(kind, 0) + n

    async def _send_raw(self, msg: protocol.Message, sealed: bool = True) -> None:
        assert self._send_lock is not None
        async with self._send_lock:  # sealed in the order sent
            data = protocol.encode(
                msg, self._channel if sealed else None, max_bytes=self.config.max_message_bytes
            )
            self._count(self.bytes_sent, msg.kind, len(data))
            if self._up is not None and sealed:
                await self._up.put(data, len(data))
            else:
                await self._ws.send(data)

    async def _read(self) -> None:
        try:
            async for data in self._ws:
                if self._down is not None:
                    await self._down.put(data, len(data))
                else:
                    await self._dispatch(data)
            self._fail(NetError(f"{self.url}: the server closed the connection"))
        except Exception as e:
            self._fail(NetError(f"{self.url}: connection lost: {e!r}"))

    def _fail(self, err: NetError) -> None:
        if self._fatal is None:
            self._fatal = err
        for fut in self._replies.values():
            if not fut.done():
                fut.set_exception(err)
        with self._level_cond:
            self._level_cond.notify_all()
        self._gen_ready.set()

    async def _dispatch(self, data: bytes) -> None:
        t_arrival = time.perf_counter()
        try:
            msg = protocol.decode(data, self._channel, max_bytes=self.config.max_message_bytes)
        except protocol.ProtocolError as e:
            self._fail(NetError(f"{self.url}: bad message from the server: {e}", e.code))
            await self._ws.close()
            return
        self._count(self.bytes_received, msg.kind, len(data))
        k, f = msg.kind, msg.fields
        if k == "gi_reply":
            fut = self._replies.get(f["id"])
            if fut is not None and not fut.done():
                fut.set_result((msg, t_arrival))
        elif k == "lpm_chunk":
            with self._level_cond:
                lv = self._levels.setdefault(f["level"], _Level())
                lv.count = f["count"]
                lv.pieces[f["index"]] = (f["name"], f["part"], msg.payload)
        elif k == "lpm_done":
            with self._level_cond:
                lv = self._levels.setdefault(f["level"], _Level())
                lv.done = True
                self._level_cond.notify_all()
        elif k == "generator_chunk":
            self._gen_pieces[f["index"]] = msg.payload
            if len(self._gen_pieces) == f["count"]:
                self._generator_complete()
        elif k == "error":
            err = NetError(f"server error [{f['code']}]: {f['message']}", f["code"])
            ref = f.get("ref")
            fut = self._replies.get(ref) if ref is not None else None
            if fut is not None and not fut.done():
                fut.set_exception(err)
            else:
                log.warning("%s", err)
                if f["code"] == "not_found":
                    self._gen_error = str(err)
                    self._gen_ready.set()
        elif k == "bye":
            self._fail(NetError(f"{self.url}: the server said bye"))

    # ------------------------------------------------------------------ mesh levels
    @property
    def levels(self) -> list[dict[str, Any]]:
        """The levels the server offers (``scene_info.lpm.levels``), coarse to fine."""
        return list(self.scene_info["lpm"]["levels"])

    def base(self) -> dict[str, Any]:
        """The scene's base (lights, sky, paths) as :func:`icbtool.net.mesh_stream.assemble`
        takes it."""
        i = self.scene_info
        return {
            "name": i["name"],
            "lights": i["lights"],
            "sky": i.get("sky"),
            "paths": i.get("paths", {}),
            "default_camera": i.get("default_camera"),
            "up": i.get("up", [0.0, 1.0, 0.0]),
        }

    def request_lpm(self, max_level: int | None = None, min_level: int = 0) -> None:
        """Ask for the mesh levels min_level..max_level (default: all), streamed coarse to fine;
        they arrive in the background (:meth:`wait_level`, :meth:`best_scene`)."""
        top = len(self.levels) - 1 if max_level is None else int(max_level)
        fields = {"max_level": top}
        if min_level:
            fields["min_level"] = int(min_level)
        self._call(self._send_raw(protocol.Message("lpm_request", fields, b"")))

    def levels_done(self) -> list[int]:
        with self._level_cond:
            return sorted(i for i, lv in self._levels.items() if lv.done)

    def wait_level(self, level: int = 0, timeout_s: float | None = None) -> None:
        """Wait until ``level`` has arrived.

        Raises:
            NetError: it did not arrive in time, or the connection failed.
        """
        t = self.config.timeout_s if timeout_s is None else timeout_s
        with self._level_cond:
            ok = self._level_cond.wait_for(
                lambda: (
                    self._fatal is not None or (level in self._levels and self._levels[level].done)
                ),
                t,
            )
        if self._fatal is not None:
            raise self._fatal
        if not ok:
            raise NetError(f"mesh level {level} did not arrive within {t} s", "timeout")

    def scene(self, level: int) -> Any:
        """The scene of a received ``level`` (assembled once, then cached)."""
        if level not in self._scenes:
            with self._level_cond:
                lv = self._levels.get(level)
                if lv is None or not lv.done:
                    raise ValueError(f"mesh level {level} has not arrived")
                if len(lv.pieces) != lv.count:
                    raise NetError(
                        f"mesh level {level}: {len(lv.pieces)} of {lv.count} chunks arrived"
                    )
                files: dict[str, list[bytes]] = {}
                parts: dict[str, str] = {}
                for i in range(lv.count):
                    name, part, data = lv.pieces[i]
                    files.setdefault(name, []).append(data)
                    parts[name] = part
            chunks = [(n, parts[n], b"".join(d)) for n, d in files.items()]
            self._scenes[level] = ms.assemble(chunks, self.base())
        return self._scenes[level]

    def best_scene(self) -> tuple[int, Any] | None:
        """(level, scene) of the finest level held, or None before the first arrives."""
        done = self.levels_done()
        return (done[-1], self.scene(done[-1])) if done else None

    # ------------------------------------------------------------------ generator
    @property
    def generator_offered(self) -> bool:
        return self.scene_info.get("generator") is not None

    def request_generator(self, index: int | None = None) -> None:
        """Ask for the client model on offer (every chunk, or the one chunk ``index``); it
        arrives in the background (:meth:`wait_generator`, :meth:`has_generator`)."""
        if not self.generator_offered:
            raise NetError("the server offers no client model", "not_found")
        fields = {} if index is None else {"index": int(index)}
        self._call(self._send_raw(protocol.Message("generator_request", fields, b"")))

    def _generator_complete(self) -> None:
        data = b"".join(self._gen_pieces[i] for i in range(len(self._gen_pieces)))
        self._gen_pieces.clear()
        info = self.scene_info["generator"]
        want = info["sha256"]
        got = hashlib.sha256(data).hexdigest()
        if got != want or len(data) != info["bytes"]:
            self._gen_error = (
                f"client model: {len(data)} bytes hashing to {got}; scene_info.generator says "
                f"{info['bytes']} bytes, {want}"
            )
            log.warning("%s; not used", self._gen_error)
            self._gen_ready.set()
            return
        # creating the onnxruntime session takes a while: not on the network thread
        threading.Thread(
            target=self._load_generator, args=(data, info), name="icb-gen-load", daemon=True
        ).start()

    def _load_generator(self, data: bytes, info: dict[str, Any]) -> None:
        try:
            from icbtool.net.client_model import ServedModel
            from icbtool.system import GeneratorSource

            model = ServedModel(data, info, threads=self.config.model_threads)
            self._gen_source = GeneratorSource(model, fallback=None)
            self._gen_bytes = len(data)
        except Exception as e:
            self._gen_error = f"client model received but not usable: {e!r}"
            log.warning("%s", self._gen_error)
        finally:
            self._gen_ready.set()

    @property
    def served_model(self) -> Any:
        """The served model in use (:class:`icbtool.net.client_model.ServedModel`), or None."""
        return self._gen_source.generator if self._gen_source is not None else None

    def wait_generator(self, timeout_s: float | None = None) -> bool:
        """Wait for the client model requested; True when it is loaded and in use."""
        self._gen_ready.wait(self.config.timeout_s if timeout_s is None else timeout_s)
        return self._gen_source is not None

    @property
    def has_generator(self) -> bool:
        return self._gen_source is not None

    @property
    def generator_bytes(self) -> int:
        return self._gen_bytes

    # ------------------------------------------------------------------ GISource
    @property
    def needs(self) -> tuple[str, ...]:  # type: ignore[override]
        g = self._gen_source
        return g.needs if g is not None else ()

    def request(self, req: GIRequest, wrt: Any = None) -> GIReply:
        """Generate locally when the generator is held and ``wrt`` has its inputs, else ask the
        server (see the module docstring for the timings)."""
        g = self._gen_source
        if (
            g is not None
            and wrt is not None
            and all(getattr(wrt, n, None) is not None for n in g.needs)
        ):
            reply = g.request(req, wrt) if g._why_not(wrt) is None else None
            if reply is not None:
                return reply
        return self.request_remote(req)

    def request_remote(self, req: GIRequest) -> GIReply:
        """Ask the server for ``req``'s GI and wait for it.

        Raises:
            NetError: an error reply (e.g. ``busy``) or the connection failed.
        """
        if self._fatal is not None:
            raise self._fatal
        t0 = time.perf_counter()
        msg, t_arrival = self._call(self._ask(req), self.config.timeout_s)
        t1 = time.perf_counter()
        f = msg.fields
        arrays: dict[str, np.ndarray] = {}
        off = 0
        for p in f["parts"]:
            blob = msg.payload[off : off + p["bytes"]]
            off += p["bytes"]
            arrays[p["name"]] = np.asarray(
                codec_mod.decode(blob, p["codec"], tuple(p["shape"]), p["dtype"]), np.float32
            )
        decode_ms = 1e3 * (time.perf_counter() - t1)
        cam = protocol.camera_from_json(f["camera"], "gi_reply.camera")
        ref = NetReference(cam, arrays["gi"], arrays["depth"], arrays["mask"])
        timings = {k: float(v) for k, v in f["timings_ms"].items()}
        total_ms = 1e3 * (t1 - t0) + decode_ms
        waited_ms = 1e3 * (t_arrival - t0)
        timings["transfer"] = max(0.0, waited_ms - timings.get("server", 0.0))
        timings["decode"] = decode_ms
        timings["request"] = total_ms
        self.remote += 1
        stale = bool(f.get("stale", False))
        return GIReply(ref, bool(f["cache_hit"]), timings, req.seq, stale=stale)

    async def _ask(self, req: GIRequest) -> tuple[protocol.Message, float]:
        rid = next(self._ids)
        fut: asyncio.Future[tuple[protocol.Message, float]] = self._loop.create_future()
        self._replies[rid] = fut
        try:
            await self._send_raw(
                protocol.Message(
                    "gi_request",
                    {
                        "id": rid,
                        "request": protocol.request_to_json(req),
                        "codec": self.config.gi_codec,
                        "depth_codec": self.config.depth_codec,
                    },
                    b"",
                )
            )
            return await fut
        finally:
            self._replies.pop(rid, None)

    def close(self) -> None:
        """Say bye, close the socket and stop the network thread (idempotent)."""
        if self._loop.is_closed():
            return

        async def shutdown() -> None:
            if self._ws is not None and self._channel is not None and self._fatal is None:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(self._send_raw(protocol.Message("bye", {}, b"")), 2)
            for line in (self._up, self._down):
                if line is not None:
                    await line.aclose()
            if self._reader is not None:
                self._reader.cancel()
            if self._ws is not None:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(self._ws.close(), 3)

        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        if not self._thread.is_alive():
            self._loop.close()


Progress = Callable[[str], None]

__all__ = ["NetClientConfig", "NetError", "NetReference", "NetworkSource"]
