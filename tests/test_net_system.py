"""The networked ICB system on loopback: icbtool.net.Server + NetworkSource with the Cornell box.

Every wait is bounded (client timeouts, thread joins, subprocess timeouts); nothing asserts a
wall-clock time.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")
pytest.importorskip("zstandard")

from icbtool import scene as sc  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.net import codec, crypto, protocol  # noqa: E402
from icbtool.net.client import NetClientConfig, NetError, NetworkSource  # noqa: E402
from icbtool.net.server import Server, ServerConfig  # noqa: E402
from icbtool.net.shaper import Link, ShaperConfig  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.gl]

TOKEN = "test-token-" + "x" * 32  # long enough: the server refuses short tokens
#: Tiny renders: the tests check the system, not the images.
CLOUD = system.CloudConfig(spp=1, denoise=False, max_depth=2)
T = 120.0  # every client wait


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


def _camera(scene, t: float = 0.5, size: int = 32):
    p = scene.paths["test"]
    return p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)


def _request(scene, t: float = 0.5, seq: int = 0):
    return system.GIRequest(_camera(scene, t), time_s=t, seq=seq, depth_range=(0.5, 8.0))


@pytest.fixture(scope="module")
def server(scene, tmp_path_factory):
    srv = Server(
        scene,
        tmp_path_factory.mktemp("store"),
        TOKEN,
        ServerConfig(max_pending=2, send_queue=4, send_timeout_s=5.0, max_message_bytes=2**20),
        CLOUD,
    ).start()
    yield srv
    srv.stop()


def _client(server, **kw) -> NetworkSource:
    return NetworkSource(server.url, TOKEN, NetClientConfig(timeout_s=T, **kw))


# ---------------------------------------------------------------------------- known answers
def test_scene_info_lpm_and_gi_equal_the_in_process_cloud(server, scene, tmp_path):
    with _client(server, gi_codec="f32-zstd", depth_codec="f32-zstd") as src:
        info = src.scene_info
        assert info["name"] == "cornell_box"
        assert info["lpm"]["levels"][0]["triangles"] <= scene.n_triangles
        src.request_lpm()
        src.wait_level(len(src.levels) - 1, T)
        level, mesh = src.best_scene()
        assert level == len(src.levels) - 1
        assert set(mesh.paths) == set(scene.paths) and len(mesh.lights) == len(scene.lights)
        req = _request(scene, 0.3, seq=7)
        reply = src.request(req)
        for k in ("lookup", "render", "encode", "server", "transfer", "decode", "request"):
            assert k in reply.timings_ms
    # the same request to an in-process cloud with the same config: the same reference
    with system.Cloud(scene, tmp_path / "store", CLOUD) as cloud:
        ref = cloud.request(req).reference
    assert reply.reference.camera == ref.camera
    np.testing.assert_array_equal(reply.reference.gi, ref.gi)  # f32-zstd is exact
    np.testing.assert_array_equal(reply.reference.depth, ref.depth)


def test_f16_codec_reply_is_the_rounded_reference(server, scene):
    with _client(server, gi_codec="f32-zstd") as a, _client(server, gi_codec="f16-zstd") as b:
        exact = a.request(_request(scene, 0.6, seq=1)).reference.gi
        rounded = b.request(_request(scene, 0.6, seq=1))  # a cache hit now
        assert rounded.cache_hit
        np.testing.assert_array_equal(rounded.reference.gi, exact.astype(np.float16))


def test_wrong_token_gets_auth_error_and_no_scene_data(server):
    with pytest.raises(NetError) as e:
        NetworkSource(server.url, "wrong", NetClientConfig(timeout_s=T))
    assert e.value.code == "auth"


async def _raw_session(url: str, frames: list[bytes], token: str = TOKEN) -> list:
    """Handshake by hand, send ``frames`` (raw bytes) sealed or not, collect replies."""
    from websockets.asyncio.client import connect

    async with connect(url, proxy=None, compression=None, open_timeout=T) as ws:
        hs = crypto.ClientHandshake(token)
        await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
        welcome = protocol.decode(await asyncio.wait_for(ws.recv(), T))
        channel, auth = hs.finish(welcome.fields)
        await ws.send(protocol.encode(protocol.Message("auth", auth)))
        info = protocol.decode(await asyncio.wait_for(ws.recv(), T), channel)
        got = [info]
        for f in frames:
            await ws.send(f(channel) if callable(f) else f)
            try:
                got.append(protocol.decode(await asyncio.wait_for(ws.recv(), T), channel))
            except Exception as e:  # closed
                got.append(e)
                break
        return got


def _header_frame(header: bytes, payload: bytes = b"") -> bytes:
    return struct.pack(">I", len(header)) + header + payload


@pytest.mark.parametrize(
    "frame, code",
    [
        (_header_frame(b"{not json"), "malformed"),
        (_header_frame(b'{"v":1,"kind":"no_such_kind"}'), "unknown_kind"),
        (_header_frame(b'{"v":1,"kind":"gi_request"', b""), "malformed"),
        (struct.pack(">I", 1000) + b'{"v":1}', "malformed"),  # header length past the end
    ],
    ids=["bad-json", "unknown-kind", "truncated", "truncated-payload"],
)
def test_malformed_messages_get_an_error_and_the_server_keeps_serving(server, scene, frame, code):
    got = asyncio.run(asyncio.wait_for(_raw_session(server.url, [frame]), T))
    assert got[0].kind == "scene_info"
    assert got[1].kind == "error" and got[1].fields["code"] == code
    with _client(server) as src:  # a second client is served
        assert src.request(_request(scene, 0.6)).reference.gi.shape[-1] == 3


def test_wrong_field_type_is_a_bad_field_error_and_the_connection_goes_on(server):
    def bad(channel):  # sealed correctly, but request.camera is a number
        import json

        h = {"v": 1, "kind": "gi_request", "id": 3, "request": {"camera": 1}, "codec": "f16-zstd"}
        h["ctr"] = channel.next_counter
        hb = json.dumps(h).encode()
        _, ct = channel.seal(b"", hb)
        return _header_frame(hb, ct)

    ok = protocol.Message("lpm_request", {"max_level": 0})
    got = asyncio.run(
        asyncio.wait_for(_raw_session(server.url, [bad, lambda ch: protocol.encode(ok, ch)]), T)
    )
    assert got[1].kind == "error" and got[1].fields["code"] == "bad_field"
    assert got[1].fields["ref"] == 3
    assert got[2].kind == "lpm_chunk"  # the same connection is still served


def test_oversized_frame_closes_only_that_connection(server, scene):
    big = b"\0" * (server.config.max_message_bytes + 10)
    got = asyncio.run(asyncio.wait_for(_raw_session(server.url, [big]), T))
    assert isinstance(got[-1], Exception)  # closed (1009 message too big)
    with _client(server) as src:
        assert src.request(_request(scene, 0.6)).reference is not None


def test_client_disconnecting_mid_stream_and_one_never_reading(server, scene):
    before = server.stats.connections
    # mid-stream: ask for the mesh and a render, then drop the socket
    src = _client(server)
    src.request_lpm()
    src._call(src._ws.transport.abort() or asyncio.sleep(0))
    src.close()

    # never reads: a raw client that asks for many things and reads nothing
    async def never_read() -> None:
        from websockets.asyncio.client import connect

        # close_timeout: this client never reads the server's close frame either, so its own
        # close would wait websockets' default 10 s for it
        async with connect(
            server.url, proxy=None, compression=None, max_queue=1, close_timeout=1
        ) as ws:
            hs = crypto.ClientHandshake(TOKEN)
            await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
            welcome = protocol.decode(await ws.recv())
            ch, auth = hs.finish(welcome.fields)
            await ws.send(protocol.encode(protocol.Message("auth", auth)))
            ws.transport.pause_reading()  # nothing more is read from the socket
            for _ in range(30):
                await ws.send(
                    protocol.encode(protocol.Message("lpm_request", {"max_level": 0}), ch)
                )
            await asyncio.sleep(1.0)

    asyncio.run(asyncio.wait_for(never_read(), T))
    with _client(server) as src2:
        assert src2.request(_request(scene, 0.6)).reference is not None
    assert server.stats.connections >= before + 3


def test_busy_when_too_many_pending(server, scene):
    with _client(server) as src:
        reqs = [_request(scene, 0.05 + 0.02 * i, seq=100 + i) for i in range(6)]

        async def burst():
            return await asyncio.gather(*(src._ask(r) for r in reqs), return_exceptions=True)

        res = src._call(burst(), T)
    errors = [r for r in res if isinstance(r, Exception)]
    assert any(getattr(e, "code", None) == "busy" for e in errors)
    assert len(errors) < len(res)  # the first ones are answered


def test_concurrent_clients_all_get_answers(server, scene):
    n = 32  # the count; each waits at most T
    results: list = [None] * n

    def one(i: int) -> None:
        try:
            with _client(server) as src:
                results[i] = src.request(_request(scene, 0.9, seq=i)).reference.gi.shape
        except Exception as e:  # reported below
            results[i] = e

    threads = [threading.Thread(target=one, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(T)
    assert all(isinstance(r, tuple) for r in results), results


def test_identical_concurrent_requests_render_once(scene, tmp_path):
    srv = Server(scene, tmp_path / "store", TOKEN, ServerConfig(), CLOUD).start()
    try:
        with _client(srv) as a, _client(srv) as b:
            req = _request(scene, 0.45, seq=5)

            async def both():
                return await asyncio.gather(a._ask(req), b._ask(req))

            # both requests go out before either is answered (one event loop per client:
            # send from a's loop and b's loop at once)
            fa = asyncio.run_coroutine_threadsafe(a._ask(req), a._loop)
            fb = asyncio.run_coroutine_threadsafe(b._ask(req), b._loop)
            ra, rb = fa.result(T), fb.result(T)
        assert srv.stats.renders == 1
        assert srv.stats.coalesced + srv.stats.cache_hits == 1
        assert ra[0].payload == rb[0].payload  # the same reference, encoded the same
    finally:
        srv.stop()


def test_a_record_of_another_scene_state_arrives_marked_stale(tmp_path):
    from icbtool.store import invalidation

    moving = sc.PROCEDURAL["cornell_box_moving_light"]()
    later = system.GIRequest(_camera(moving, 0.5, 16), time_s=1.0, seq=3, depth_range=(0.5, 8.0))
    with system.Cloud(moving, tmp_path / "store", CLOUD) as cloud:
        cloud.request(later)  # a record of the box at t = 1 s: its light moved
    srv = Server(moving, tmp_path / "store", TOKEN, ServerConfig(), CLOUD).start()
    try:  # the server answers the box at t = 0 s
        with _client(srv) as src:
            got = src.request(later)
            assert got.cache_hit and got.stale
            msg, _ = asyncio.run_coroutine_threadsafe(src._ask(later), src._loop).result(T)
            f = msg.fields
            assert f["stale"] and not f["refining"] and f["spp"] == CLOUD.spp
            assert f["state"] == invalidation.state_id(moving.at(1.0))
            fresh = src.request(_request(moving, 0.2, seq=4))  # rendered now, at t = 0
            assert not fresh.cache_hit and not fresh.stale
        assert srv.stats.renders == 1
    finally:
        srv.stop()


def test_shaper_link_arithmetic():
    link = Link(ShaperConfig(latency_ms=100, bandwidth_mbit=8))
    assert link.arrival(1_000_000, now=0.0) == pytest.approx(1.0 + 0.05)
    # the second message waits for the first to leave the link
    assert link.arrival(1_000_000, now=0.0) == pytest.approx(2.0 + 0.05)
    assert Link(ShaperConfig(latency_ms=40)).arrival(10**9, now=1.0) == pytest.approx(1.02)
    with pytest.raises(ValueError):
        ShaperConfig(bandwidth_mbit=0)


def test_shaped_transfer_adds_the_latency(server, scene):
    with _client(server, shaper=ShaperConfig(latency_ms=200)) as src:
        src.request(_request(scene, 0.6))  # warm (cache)
        r = src.request(_request(scene, 0.6))
    assert r.timings_ms["transfer"] >= 200.0 * 0.95


def test_codec_round_trip_known_answer():
    a = np.array([[[0.0, 1.5, 65504.0]]], np.float32)
    assert np.array_equal(codec.decode(codec.encode(a, "f32-zstd"), "f32-zstd", a.shape), a)


# ---------------------------------------------------------------------------- across processes
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_sigterm_keeps_every_committed_record(scene, tmp_path):
    from icbtool import store

    repo = Path(__file__).resolve().parents[1]
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(repo), "ICBTOOL_GL_BACKEND": "osmesa"}
    cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(tmp_path / "s"),
           "--port", str(port), "--token", TOKEN, "--spp", "1", "--no-denoise",
           "--log-level", "WARNING"]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        line = proc.stdout.readline().decode()
        assert "listening" in line, line
        with NetworkSource(f"ws://127.0.0.1:{port}", TOKEN, NetClientConfig(timeout_s=T)) as src:
            rendered = sum(
                not src.request(_request(scene, 0.1 + 0.3 * i, seq=i)).cache_hit for i in range(3)
            )
            # one more in flight while the server is told to stop
            fut = asyncio.run_coroutine_threadsafe(
                src._ask(_request(scene, 0.95, seq=9)), src._loop
            )
            time.sleep(0.05)
            proc.send_signal(signal.SIGTERM)
            try:
                msg, _ = fut.result(T)
                rendered += not msg.fields["cache_hit"]  # answered: committed before replying
            except Exception:
                pass  # aborted by the shutdown: also clean
        assert proc.wait(T) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(T)
    with store.open(tmp_path / "s", store.StoreConfig(readonly=True)) as st:
        # every render answered was committed (the one aborted by the stop may be too)
        assert rendered >= 1 and rendered <= len(st) <= rendered + 1
        assert all(st.get_intact(r) is not None for r in st.ids())


def _serve(port: int, store_dir: Path) -> subprocess.Popen:
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(repo), "ICBTOOL_GL_BACKEND": "osmesa"}
    cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(store_dir),
           "--port", str(port), "--token", TOKEN, "--spp", "1", "--no-denoise",
           "--log-level", "WARNING"]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    line = proc.stdout.readline().decode()
    if "listening" not in line:
        proc.kill()
        raise AssertionError(f"server did not start: {line!r}")
    return proc


def test_killed_server_restarts_with_every_committed_record(scene, tmp_path):
    """kill -9 (no clean shutdown) while a render may be in flight, then a restart on the same
    store: every record the first server answered from is intact and answers again as a hit."""
    from icbtool import store

    port = _free_port()
    proc = _serve(port, tmp_path / "s")
    reqs = [_request(scene, 0.1 + 0.3 * i, seq=i) for i in range(3)]
    try:
        with NetworkSource(f"ws://127.0.0.1:{port}", TOKEN, NetClientConfig(timeout_s=T)) as src:
            first = [src.request(r) for r in reqs]
            asyncio.run_coroutine_threadsafe(src._ask(_request(scene, 0.95, seq=9)), src._loop)
            time.sleep(0.05)
            proc.kill()  # SIGKILL: nothing of the server's own shutdown runs
            proc.wait(T)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(T)
    rendered = sum(not f.cache_hit for f in first)  # (nearby requests may share a record)
    with store.open(tmp_path / "s", store.StoreConfig(readonly=True)) as st:
        assert rendered >= 1 and rendered <= len(st) <= rendered + 1
        assert all(st.get_intact(r) is not None for r in st.ids())
    port = _free_port()
    proc = _serve(port, tmp_path / "s")
    try:
        with NetworkSource(f"ws://127.0.0.1:{port}", TOKEN, NetClientConfig(timeout_s=T)) as src:
            again = [src.request(r) for r in reqs]
        assert all(a.cache_hit for a in again)
        for a, f in zip(again, first):
            np.testing.assert_array_equal(a.reference.gi, f.reference.gi)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(T) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(T)


# ---------------------------------------------------------------------------- the client model
def _runs(tmp_path: Path, scene, gan_ssim, radiance_ssim) -> tuple[Path, Path]:
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from client_models import write_gan_run, write_radiance_run

    b = np.asarray(scene.bounds)
    return (
        write_gan_run(tmp_path / "gan", b, ssim=gan_ssim),
        write_radiance_run(tmp_path / "radiance", b, ssim=radiance_ssim),
    )


@pytest.mark.parametrize("winner", ["gan", "radiance"])
def test_client_model_chosen_by_test_ssim_shipped_in_chunks_and_used_like_the_local_run(
    scene, tmp_path, caplog, winner
):
    """Two runs; the one with the better recorded test SSIM is offered (and logged with both
    candidates' numbers), sent in chunks, hash-checked, and makes the same GI as the run loaded
    locally (onnxruntime against torch)."""
    import logging

    from icbtool import raster
    from icbtool.pipeline import load_client_model

    gan, rad = _runs(tmp_path, scene, 0.9 if winner == "gan" else 0.8, 0.85)
    chosen = gan if winner == "gan" else rad
    cfg = ServerConfig(models=(str(gan), str(rad)), chunk_bytes=16384)
    with caplog.at_level(logging.INFO, logger="icbtool.net.client_model"):
        srv = Server(scene, tmp_path / "store", TOKEN, cfg, CLOUD).start()
    log = caplog.text
    gan_ssim = 0.9 if winner == "gan" else 0.8
    assert "CHOSEN" in log and '"test_ssim": 0.85' in log and f'"test_ssim": {gan_ssim}' in log
    assert f"client model offered: {winner} run {chosen}" in log
    try:
        with _client(srv) as src:
            info = src.scene_info["generator"]
            assert info["kind"] == winner and info["format"] == "onnx"
            assert info["chunks"] == -(-info["bytes"] // 16384) and info["chunks"] >= 2
            assert info["test_ssim"] == (0.9 if winner == "gan" else 0.85)
            if winner == "gan":
                assert info["inputs"] == ["dl", "albedo", "normal_world", "depth", "position"]
                assert info["size_multiple"] == 32 and info["demodulated"] is True
                assert set(info["encoding"]) == {
                    "hdr", "depth_max", "position_center", "position_half_extent"
                }  # fmt: skip
            else:
                assert info["inputs"] == ["position", "normal_world"] and info["encoding"] is None
            src.request_generator()
            assert src.wait_generator(T)
            assert src.generator_bytes == info["bytes"]
            assert src.served_model.kind == winner
            cam = _camera(scene, 0.5, size=48)  # not a multiple of 32: padded like the local
            with raster.Rasterizer(scene) as rz:
                wrt = rz.render(cam)
            sent = dict(src.bytes_sent)
            req = system.GIRequest(cam, time_s=0.5, seq=0, depth_range=(0.5, 8.0))
            reply = src.request(req, wrt)
            assert src.bytes_sent == sent  # nothing asked of the server
            assert reply.timings_ms["generate"] > 0
            local = system.GeneratorSource(load_client_model(chosen)).request(req, wrt)
            want = local.reference.gi
            assert want.std() > 0  # the model's output varies over the view
            np.testing.assert_allclose(reply.reference.gi, want, rtol=1e-5, atol=1e-5)
        assert srv.stats.generator_sent == 1
        assert srv.stats.bytes_sent["generator_chunk"] > info["bytes"]
    finally:
        srv.stop()


def test_client_model_choice_rule():
    """Best test SSIM; within SSIM_TIE of it the fewest bytes; runs without numbers last."""
    from icbtool.net.client_model import SSIM_TIE, Candidate, choose

    def c(name, ssim, n):
        return Candidate(Path(name), "gan", ssim, 3, 1, b"x" * n, {})

    a, b, none = c("a", 0.90, 1000), c("b", 0.90 - SSIM_TIE / 2, 10), c("n", None, 1)
    assert choose([a, b, none]).run.name == "b"  # tied: the smaller
    far = c("far", 0.90 - 2 * SSIM_TIE, 5)
    assert choose([a, far, none]).run.name == "a"  # better by more than the tie
    assert choose([none, c("m", None, 7)]).run.name == "n"  # no numbers: the smallest
    with pytest.raises(ValueError, match="no client-model candidates"):
        choose([])


def test_a_run_of_another_scene_is_logged(scene, tmp_path, caplog):
    import json
    import logging

    from icbtool.net.client_model import offer

    gan, _ = _runs(tmp_path, scene, 0.9, None)
    (gan / "config.json").write_text(json.dumps({"scene": "sponza"}))
    with caplog.at_level(logging.INFO, logger="icbtool.net.client_model"):
        offer([gan], 2**20, scene=scene)
    assert "trained on scene 'sponza', not on the served 'cornell_box'" in caplog.text
    (gan / "config.json").write_text(json.dumps({"scene": scene.name}))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="icbtool.net.client_model"):
        offer([gan], 2**20, scene=scene)
    assert "trained on scene" not in caplog.text and "CHOSEN" in caplog.text


def test_model_runs_a_client_cannot_use_are_refused(scene, tmp_path):
    from client_models import write_gan_run

    from icbtool.net.client_model import ModelRunError

    pytest.importorskip("onnx")
    with pytest.raises(FileNotFoundError, match="no generator.pt .* or radiance.pt"):
        Server(scene, tmp_path / "s", TOKEN, ServerConfig(models=(str(tmp_path),)), CLOUD)
    run = write_gan_run(tmp_path / "g", np.asarray(scene.bounds), warped=True)
    with pytest.raises(ModelRunError, match="warped reference"):
        Server(scene, tmp_path / "s", TOKEN, ServerConfig(models=(str(run),)), CLOUD)


def test_a_model_its_announcement_does_not_describe_is_refused(scene, tmp_path, monkeypatch):
    """Were the generator's encoding to change beyond what the announcement states, the
    server's self-check (the ONNX file run from the announcement against the run's own
    generate) refuses the run instead of serving wrong GI."""
    from icbtool.net import client_model

    gan, _ = _runs(tmp_path, scene, 0.9, None)
    right = client_model._gan_announce

    def wrong(gen):
        a = right(gen)
        a["encoding"]["depth_max"] *= 2
        return a

    monkeypatch.setattr(client_model, "_gan_announce", wrong)
    with pytest.raises(client_model.ModelRunError, match="does not describe this model"):
        client_model.read_candidate(gan)


def test_served_model_refuses_an_announcement_it_cannot_follow():
    from icbtool.net.client_model import ServedModel

    a = {"kind": "gan", "format": "onnx", "inputs": ["dl"], "encoding": {"hdr": {}}}
    for bad, match in (
        ({"kind": "nerf"}, "kind 'nerf' is not 'gan' or 'radiance'"),
        ({"format": "pt"}, "format 'pt' is not 'onnx'"),
        ({"inputs": ["gi"]}, r"inputs \['gi'\] are not client buffers"),
        ({"encoding": None}, "encoding is required"),
    ):
        with pytest.raises(ValueError, match=match):
            ServedModel(b"", {**a, **bad})


def _gen_request(fields):
    """A generator_request sealed by hand (the encoder would refuse the invalid ones)."""

    def frame(channel):
        import json

        h = {"v": 1, "kind": "generator_request", **fields, "ctr": channel.next_counter}
        hb = json.dumps(h).encode()
        _, ct = channel.seal(b"", hb)
        return _header_frame(hb, ct)

    return frame


def test_model_requests_without_a_model_are_not_found(server):
    frames = [_gen_request({}), _gen_request({"index": 0})]
    got = asyncio.run(asyncio.wait_for(_raw_session(server.url, frames), T))
    assert got[0].fields["generator"] is None
    for m in got[1:]:
        assert m.kind == "error" and m.fields["code"] == "not_found", m
        assert "offers no client model" in m.fields["message"]


def test_malformed_model_requests_get_the_documented_errors(scene, tmp_path):
    gan, _ = _runs(tmp_path, scene, 0.9, None)
    cfg = ServerConfig(models=(str(gan),), chunk_bytes=65536)
    with Server(scene, tmp_path / "store", TOKEN, cfg, CLOUD) as srv:
        n = srv.model.chunks
        frames = [
            _gen_request({"index": n}),  # no such chunk
            _gen_request({"index": -1}),  # not an index
            _gen_request({"index": "0"}),
            _gen_request({"index": n - 1}),  # one chunk again: fine
            _gen_request({"index": n - 1}),  # twice: refused
        ]
        got = asyncio.run(asyncio.wait_for(_raw_session(srv.url, frames), T))
    assert got[0].fields["generator"]["chunks"] == n
    codes = [m.fields.get("code") if m.kind == "error" else m.kind for m in got[1:]]
    assert codes == ["not_found", "bad_field", "bad_field", "generator_chunk", "bad_field"]
    assert f"no chunk {n}" in got[1].fields["message"]
    assert "generator_request.index" in got[2].fields["message"]
    last = got[4]
    assert last.fields["index"] == n - 1 and last.payload == srv.model.chunk(n - 1)


# ---------------------------------------------------------------------------- the command line
def test_cli_client_runs_against_a_server_and_refusals_are_one_line(server, tmp_path, capsys):
    from icbtool.cli import main

    out = tmp_path / "c"
    argv = ["client", server.url, "--token", TOKEN, "--path", "test", "--frames", "2",
            "--height", "32", "--width", "32", "--out", str(out),
            "--timeout-s", str(T)]  # fmt: skip
    assert main(argv) == 0
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == ["000.png", "001.png"]
    rows = (out / "latency.csv").read_text().strip().splitlines()
    assert len(rows) == 3  # header + one row per frame
    capsys.readouterr()
    bad = ["client", server.url, "--token", "not-it", "--frames", "1", "--height", "32",
           "--width", "32", "--out", str(tmp_path / "bad"), "--timeout-s", str(T)]  # fmt: skip
    assert main(bad) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("icbtool client: error:") and "auth" in err and "\n" not in err
    gone = ["client", f"ws://127.0.0.1:{_free_port()}", "--token", TOKEN, "--frames", "1",
            "--height", "32", "--width", "32", "--out", str(tmp_path / "gone"),
            "--timeout-s", "10"]  # fmt: skip
    assert main(gone) == 1
    assert "cannot connect" in capsys.readouterr().err


def test_mesh_stream_without_levels_sends_the_full_mesh_in_the_lpm_layout(scene):
    """lpm=False (as without open3d): one level, the full scene, in the same chunk layout the
    client reads for LPM levels; it assembles back exactly, with the base's paths."""
    from icbtool.net import mesh_stream as ms

    stream = ms.MeshStream(scene, lpm=False)
    assert len(stream.levels) == 1 and stream.levels[0].triangles == scene.n_triangles
    chunks = list(stream.levels[0].chunks)
    assert all(name.startswith("L0/") for name, _, _ in chunks)
    assert {part for _, part, _ in chunks} <= {"materials", "geometry", "texture"}
    back = ms.assemble(chunks, stream.base)
    np.testing.assert_array_equal(back.vertices, scene.vertices)
    np.testing.assert_array_equal(back.faces, scene.faces)
    np.testing.assert_array_equal(back.face_material, scene.face_material)
    assert sorted(back.paths) == sorted(scene.paths) and len(back.lights) == len(scene.lights)
    with pytest.raises(ValueError, match="LPM"):
        ms.assemble(chunks[1:], stream.base)  # a chunk missing
