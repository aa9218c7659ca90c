"""The server's limits, refusals and close codes (docs/protocol.md, sections Limits, Errors,
Close codes, Threat model), one test per malformed case, on loopback with the Cornell box.

Every wait is bounded; nothing asserts a wall-clock time (ordering only).
"""

from __future__ import annotations

import asyncio
import datetime
import ipaddress
import json
import os
import socket
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")
pytest.importorskip("zstandard")

from icbtool import scene as sc  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.net import crypto, protocol  # noqa: E402
from icbtool.net.client import NetClientConfig, NetError, NetworkSource  # noqa: E402
from icbtool.net.server import MIN_TOKEN_CHARS, Server, ServerConfig, new_token  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.gl]

TOKEN = new_token()
CLOUD = system.CloudConfig(spp=1, denoise=False, max_depth=2)
T = 120.0


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


def _camera(scene, t: float = 0.5, size: int = 32):
    p = scene.paths["test"]
    return p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)


def _request(scene, t: float = 0.5, seq: int = 0, size: int = 32):
    return system.GIRequest(_camera(scene, t, size), time_s=t, seq=seq, depth_range=(0.5, 8.0))


@pytest.fixture(scope="module")
def server(scene, tmp_path_factory):
    cfg = ServerConfig(max_request_side=64, max_render_side=64, max_message_bytes=2**20)
    srv = Server(scene, tmp_path_factory.mktemp("store"), TOKEN, cfg, CLOUD).start()
    yield srv
    srv.stop()


def _client(url: str, **kw) -> NetworkSource:
    return NetworkSource(url, TOKEN, NetClientConfig(timeout_s=T, **kw))


def _sealed(header: dict, payload: bytes = b""):
    """A frame sealed by hand (any header, even one our encoder refuses)."""

    def make(channel):
        h = {"v": 1, **header, "ctr": channel.next_counter}
        hb = json.dumps(h).encode()
        _, ct = channel.seal(payload, hb)
        return struct.pack(">I", len(hb)) + hb + ct

    return make


def _gi_request(scene, rid, t: float = 0.5, **changes) -> dict:
    req = protocol.request_to_json(_request(scene, t))
    for k, v in changes.items():
        if k in req["camera"]:
            req["camera"][k] = v
        else:
            req[k] = v
    return {"kind": "gi_request", "id": rid, "request": req, "codec": "f16-zstd"}


async def _session(
    url: str, frames: list, token: str = TOKEN, replies: int | None = None, closes: bool = False
):
    """Handshake by hand, send ``frames``, then read ``replies`` messages (default: one per
    frame) and, with ``closes``, wait for the server to close. Returns (messages after
    scene_info, the close code or None if still open)."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    async with connect(url, proxy=None, compression=None, open_timeout=T, max_size=2**24) as ws:
        hs = crypto.ClientHandshake(token)
        await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
        welcome = protocol.decode(await asyncio.wait_for(ws.recv(), T))
        channel, auth = hs.finish(welcome.fields)
        await ws.send(protocol.encode(protocol.Message("auth", auth)))
        got: list = []
        try:
            first = await asyncio.wait_for(ws.recv(), T)
            try:
                protocol.decode(first, channel)  # scene_info
            except protocol.ProtocolError:
                got.append(protocol.decode(first))  # a refusal (plain error)
                await asyncio.wait_for(ws.recv(), T)  # then the close
            for f in frames:
                await ws.send(f(channel) if callable(f) else f)
            for _ in range(len(frames) if replies is None else replies):
                got.append(protocol.decode(await asyncio.wait_for(ws.recv(), T), channel))
            if closes:
                await asyncio.wait_for(ws.wait_closed(), T)
        except ConnectionClosed:
            pass
        if ws.close_code is None and not got:
            await ws.close()
        return got, ws.close_code


def _run(coro):
    return asyncio.run(asyncio.wait_for(coro, 2 * T))


def _lpm_ok(msgs) -> bool:
    return any(m.kind == "lpm_chunk" for m in msgs)


# ---------------------------------------------------------------------------- ids
def test_id_beyond_2_53_is_a_bad_field_with_null_ref_and_the_session_goes_on(server, scene):
    got, code = _run(
        _session(
            server.url,
            [_sealed(_gi_request(scene, 2**53)), _sealed({"kind": "lpm_request", "max_level": 0})],
            replies=2,
        )
    )
    assert code is None
    assert got[0].kind == "error" and got[0].fields["code"] == "bad_field"
    assert got[0].fields["ref"] is None and "gi_request.id" in got[0].fields["message"]
    assert got[1].kind == "lpm_chunk"  # still served: the error reply was valid


def test_duplicate_pending_id_is_refused_once_and_the_first_is_answered(server, scene):
    req = _gi_request(scene, 7, t=2.0)  # a miss: still pending when the duplicate arrives
    got, _ = _run(_session(server.url, [_sealed(req), _sealed(req)], replies=2))
    kinds = sorted(m.kind for m in got)
    assert kinds == ["error", "gi_reply"]
    err = next(m for m in got if m.kind == "error")
    assert err.fields["code"] == "bad_field" and "already pending" in err.fields["message"]
    assert err.fields["ref"] is None  # the pending request 7 is not the one refused
    assert next(m for m in got if m.kind == "gi_reply").fields["id"] == 7


# ---------------------------------------------------------------------------- LPM ranges
@pytest.mark.parametrize(
    "fields, code",
    [
        ({"min_level": 99, "max_level": 99}, "not_found"),
        ({"min_level": 2, "max_level": 1}, "bad_field"),
        ("full", "not_found"),
    ],
    ids=["no-such-level", "min-above-max", "full-level-not-offered"],
)
def test_lpm_request_without_a_matching_level_is_answered(server, fields, code):
    if fields == "full":  # the full-detail level stays on the server (send_full_mesh=False)
        n = len(server.mesh.levels)
        fields = {"min_level": n, "max_level": n}
    got, close = _run(_session(server.url, [_sealed({"kind": "lpm_request", **fields})]))
    assert close is None
    assert got[0].kind == "error" and got[0].fields["code"] == code
    assert "lpm_request" in got[0].fields["message"]


# ---------------------------------------------------------------------------- limits
def test_zero_focal_length_is_refused_as_documented(server, scene):
    got, _ = _run(_session(server.url, [_sealed(_gi_request(scene, 1, fx=0.0))]))
    assert got[0].fields["code"] == "bad_field"
    assert "request.camera.fx: must be > 0" in got[0].fields["message"]


def test_huge_velocity_is_a_bad_field_in_the_protocols_words(server, scene):
    got, _ = _run(_session(server.url, [_sealed(_gi_request(scene, 2, velocity_t=[1e308, 0, 0]))]))
    msg = got[0].fields["message"]
    assert got[0].fields["code"] == "bad_field" and got[0].fields["ref"] == 2
    assert "velocity_t[0]" in msg and "1e+06" in msg
    assert "NaN" not in msg and "convert" not in msg


def test_request_over_the_size_limit_names_the_limit(server, scene):
    got, _ = _run(_session(server.url, [_sealed(_gi_request(scene, 3, height=8192, width=8192))]))
    assert got[0].fields["code"] == "bad_field"
    assert "max_request_side" in got[0].fields["message"] and "64" in got[0].fields["message"]


def test_reference_wider_than_the_render_cap_is_scaled_and_the_reply_says_so(server, scene):
    req = _request(scene, 3.0, size=64)  # a miss; the prefetch widens it beyond 64
    with _client(server.url) as src:
        assert src.scene_info["limits"]["max_render_side"] == 64
        reply = src.request(req)
    cam = reply.reference.camera
    assert max(cam.height, cam.width) == 64
    assert cam.fov_y_deg > req.camera.fov_y_deg  # still the wider prefetch frustum


# ---------------------------------------------------------------------------- hits vs misses
class _GatedPool:
    """A render pool whose renders wait for :attr:`go` (a miss that lasts as long as the test
    wants, with no clock); :attr:`started` is set when a render begins."""

    def __init__(self, scene):
        import threading

        from icbtool.system.workers import LocalPool

        self._inner = LocalPool(scene)
        self.capacity, self.address = 1, "gated"
        self.started, self.go = threading.Event(), threading.Event()

    def submit(self, job):
        def gated(fut):
            self.started.set()
            self.go.wait(2 * T)
            return fut.result()

        import concurrent.futures

        inner = self._inner.submit(job)
        return concurrent.futures.ThreadPoolExecutor(1).submit(gated, inner)

    def close(self):
        self.go.set()
        self._inner.close()


def test_a_hit_is_answered_while_a_long_miss_renders(scene, tmp_path, monkeypatch):
    from icbtool.system import workers

    pool: list[_GatedPool] = []
    monkeypatch.setattr(workers, "open_pool", lambda s, *a: pool.append(_GatedPool(s)) or pool[0])
    srv = Server(scene, tmp_path / "s", TOKEN, ServerConfig(), CLOUD).start()
    try:
        gate = pool[0]
        with _client(srv.url) as a, _client(srv.url) as b:
            hit_req = _request(scene, 0.5, size=16)
            gate.go.set()
            b.request(hit_req)  # rendered once: now a hit
            gate.go.clear()
            gate.started.clear()
            miss = asyncio.run_coroutine_threadsafe(
                a._ask(_request(scene, 4.0, seq=1, size=48)), a._loop
            )
            assert gate.started.wait(T)  # the miss is rendering (and stays so)
            hit_reply, _ = asyncio.run_coroutine_threadsafe(b._ask(hit_req), b._loop).result(T)
            assert hit_reply.fields["cache_hit"] is True
            assert not miss.done()  # answered before the miss
            gate.go.set()
            miss_reply, _ = miss.result(T)
            assert miss_reply.fields["cache_hit"] is False
        assert srv.stats.cache_hits == 1 and srv.stats.renders == 2
    finally:
        gate.go.set()
        srv.stop()


# ---------------------------------------------------------------------------- close codes
def test_close_code_1008_after_a_failed_handshake(server):
    got, code = _run(_session(server.url, [], token="x" * 40))
    assert got[0].kind == "error" and got[0].fields["code"] == "auth"
    assert code == 1008


def test_close_code_1008_after_a_tampered_message(server):
    def tampered(channel):
        frame = bytearray(
            protocol.encode(protocol.Message("lpm_request", {"max_level": 0}), channel)
        )
        frame[-1] ^= 1
        return bytes(frame)

    got, code = _run(_session(server.url, [tampered], closes=True))
    assert got[0].fields["code"] == "crypto" and code == 1008


def test_close_code_1000_after_bye(server):
    _, code = _run(_session(server.url, [lambda ch: protocol.encode(protocol.Message("bye"), ch)]))
    assert code == 1000


def test_close_code_1009_for_a_message_over_the_limit(server):
    _, code = _run(_session(server.url, [b"\0" * (server.config.max_message_bytes + 1)]))
    assert code == 1009


def test_close_code_1001_when_the_server_shuts_down(scene, tmp_path):
    srv = Server(scene, tmp_path / "s", TOKEN, ServerConfig(), CLOUD).start()

    async def wait_for_close():
        from websockets.asyncio.client import connect

        async with connect(srv.url, proxy=None, open_timeout=T) as ws:
            hs = crypto.ClientHandshake(TOKEN)
            await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
            channel, auth = hs.finish(protocol.decode(await ws.recv()).fields)
            await ws.send(protocol.encode(protocol.Message("auth", auth)))
            await ws.recv()  # scene_info
            await asyncio.get_running_loop().run_in_executor(None, srv.stop)
            await ws.wait_closed()
            return ws.close_code

    assert _run(wait_for_close()) == 1001


# ---------------------------------------------------------------------------- tokens and TLS
def test_short_tokens_are_refused_unless_allowed(scene, tmp_path):
    with pytest.raises(ValueError, match="too short"):
        Server(scene, tmp_path / "s", "two words", ServerConfig(), CLOUD)
    Server(scene, tmp_path / "s", "two words", ServerConfig(allow_weak_token=True), CLOUD)
    t = new_token()
    assert len(t) >= MIN_TOKEN_CHARS and t != new_token()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_without_a_token_prints_a_256_bit_one_once(tmp_path):
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(repo), "ICBTOOL_GL_BACKEND": "osmesa"}
    env.pop("ICBTOOL_TOKEN", None)
    port = _free_port()
    cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(tmp_path / "s"),
           "--port", str(port), "--spp", "1", "--no-denoise", "--no-lpm"]  # fmt: skip
    short = subprocess.run([*cmd, "--token", "guessable"], env=env, capture_output=True,
                           text=True, timeout=T)  # fmt: skip
    assert short.returncode != 0 and "too short" in short.stderr
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)  # fmt: skip
    try:
        lines = [proc.stdout.readline(), proc.stdout.readline()]
        assert lines[0].startswith("token: ") and lines[1].startswith("listening on ")
        token = lines[0].split()[1]
        assert len(token) == 43  # 32 random bytes, URL-safe base64
        with NetworkSource(f"ws://127.0.0.1:{port}", token, NetClientConfig(timeout_s=T)) as s:
            assert s.scene_info["name"] == "cornell_box"
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=T)
    assert token not in out  # printed once


def test_new_tokens_never_start_with_a_dash_so_they_paste_after_token(monkeypatch):
    # "--token -abc" is a missing value then an unknown option to argparse: a dash-led draw
    # (one in 64) is redrawn. Force two of them first.
    import secrets

    from icbtool.cli import build_parser
    from icbtool.net.server import new_token

    draws = iter(["-" + "a" * 42, "-" + "b" * 42, "c" * 43])
    monkeypatch.setattr(secrets, "token_urlsafe", lambda n: next(draws))
    assert new_token() == "c" * 43
    monkeypatch.undo()
    tokens = [new_token() for _ in range(2000)]  # about 31 dash-led draws were redrawn
    assert all(not t.startswith("-") and len(t) == 43 for t in tokens)
    assert len(set(tokens)) == len(tokens)
    args = build_parser().parse_args(["client", "ws://127.0.0.1:1", "--token", tokens[0]])
    assert args.token == tokens[0]


def _self_signed(tmp_path: Path) -> tuple[Path, Path]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "icbtool test")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    c, k = tmp_path / "cert.pem", tmp_path / "key.pem"
    c.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    k.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return c, k


def test_tls_with_a_certificate_the_test_makes(scene, tmp_path):
    cert, key = _self_signed(tmp_path)
    cfg = ServerConfig(tls_cert=str(cert), tls_key=str(key))
    with Server(scene, tmp_path / "s", TOKEN, cfg, CLOUD) as srv:
        assert srv.url.startswith("wss://127.0.0.1:")
        with _client(srv.url, ca_file=str(cert)) as src:
            reply = src.request(_request(scene, 0.5))
        assert np.isfinite(reply.reference.gi).all()
        with pytest.raises(NetError, match="cannot connect"):  # not trusted: refused
            NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=10))
        with pytest.raises(NetError, match="cannot connect"):  # plain ws to a TLS port
            NetworkSource(srv.url.replace("wss://", "ws://"), TOKEN, NetClientConfig(timeout_s=10))
    with pytest.raises(ValueError, match="tls_cert and tls_key"):
        ServerConfig(tls_cert=str(cert))


def test_a_coarser_stored_reference_does_not_answer_a_finer_request(server, scene):
    """A 16 x 16 record covers the 64 x 64 request's frustum but has a quarter of its pixel
    density: a miss (rendered at 64), after which the 16 x 16 request is a hit."""
    with _client(server.url) as src:
        small = src.request(_request(scene, 5.0, size=16))
        big = src.request(_request(scene, 5.0, seq=1, size=64))
        again = src.request(_request(scene, 5.0, seq=2, size=16))
    assert not small.cache_hit and not big.cache_hit and again.cache_hit
    assert big.reference.camera.height >= 64


def test_render_slots_go_round_robin_over_clients_and_the_queue_is_bounded():
    """Client 1 queues three misses, then client 2 one: with one worker, client 2's miss is the
    second to render, not the fourth; beyond the limit a miss is refused busy."""
    from icbtool.net.server import _FairQueue

    async def scenario() -> list[str]:
        q = _FairQueue(capacity=1, limit=4)
        order: list[str] = []

        async def job(client: int, name: str) -> None:
            q.admit()
            await q.acquire(client)
            order.append(name)
            await asyncio.sleep(0)
            q.release()

        await q.acquire(0)  # a render is running: everything below waits
        tasks = [asyncio.create_task(job(1, f"a{i}")) for i in range(3)]
        await asyncio.sleep(0)
        tasks.append(asyncio.create_task(job(2, "b0")))
        await asyncio.sleep(0)
        assert q.queued == 4
        with pytest.raises(protocol.ProtocolError) as e:
            q.admit()
        assert e.value.code == "busy" and "max_queued_renders" in e.value.message
        q.release()
        await asyncio.gather(*tasks)
        assert q.running == 0 and q.queued == 0
        return order

    assert _run(scenario()) == ["a0", "b0", "a1", "a2"]


def test_render_threads_run_at_a_lower_priority():
    """Linux priorities are per thread: the render thread's nice value rises, the caller's
    does not (threads it starts, such as the tracer's, inherit it)."""
    import threading

    from icbtool.system.workers import lower_priority

    if not hasattr(os, "getpriority"):
        pytest.skip("no thread priorities on this OS")
    me = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: list[int] = []

    def render_thread() -> None:
        lower_priority(5)
        child = threading.Thread(
            target=lambda: seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        )
        child.start()
        child.join()

    t = threading.Thread(target=render_thread)
    t.start()
    t.join(T)
    assert seen == [min(19, me + 5)]
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == me
