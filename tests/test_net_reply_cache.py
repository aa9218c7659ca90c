"""The cache-hit path's pieces: kept encoded replies (icbtool.net.reply_cache), hit
counts through the store's one writer, LPM manifests without the server's folders, and
``icbtool client --tls-ca`` (docs/protocol.md, section Scaling out; docs/lpm.md).

Known answers only: a kept reply equals a fresh encode byte for byte, a record that left the
store is never answered from a kept reply, N hits are N counts in the store. On loopback.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time

import numpy as np
import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")
pytest.importorskip("zstandard")

from icbtool import scene as sc  # noqa: E402
from icbtool import store as st  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.net import crypto, protocol  # noqa: E402
from icbtool.net.reply_cache import EncodedReply, ReplyCache  # noqa: E402
from icbtool.net.server import Server, ServerConfig, encode_reference, new_token  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.gl]

TOKEN = new_token()
CLOUD = system.CloudConfig(spp=1, denoise=False, max_depth=2)
T = 120.0
CODECS = ("f16-zstd", "f32-zstd")


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


def _request(scene, t: float, size: int = 32):
    p = scene.paths["test"]
    cam = p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)
    return system.GIRequest(cam, time_s=t, seq=0, depth_range=(0.5, 8.0))


async def _ask(url: str, asks: list[tuple]) -> list[protocol.Message]:
    """One session: each (request, gi codec, depth codec) in turn; the replies (opened)."""
    from websockets.asyncio.client import connect

    out = []
    async with connect(url, proxy=None, compression=None, open_timeout=T, max_size=2**24) as ws:
        hs = crypto.ClientHandshake(TOKEN)
        await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
        ch, auth = hs.finish(protocol.decode(await asyncio.wait_for(ws.recv(), T)).fields)
        await ws.send(protocol.encode(protocol.Message("auth", auth)))
        protocol.decode(await asyncio.wait_for(ws.recv(), T), ch)  # scene_info
        for i, (req, gi, depth) in enumerate(asks):
            f = {"id": i + 1, "request": protocol.request_to_json(req), "codec": gi,
                 "depth_codec": depth}  # fmt: skip
            await ws.send(protocol.encode(protocol.Message("gi_request", f), ch))
            msg = protocol.decode(await asyncio.wait_for(ws.recv(), T), ch, max_bytes=2**24)
            assert msg.kind == "gi_reply", msg.fields
            out.append(msg)
    return out


def ask(url: str, *asks: tuple) -> list[protocol.Message]:
    return asyncio.run(_ask(url, list(asks)))


def _fresh(store_dir, record_id: int, gi: str, depth: str) -> tuple[list, bytes]:
    """The record read from the store (a reader of its own) and encoded now."""
    with st.open(store_dir, st.StoreConfig(readonly=True)) as s:
        return encode_reference(s.get(record_id), gi, depth)


def _ids(store_dir) -> list[int]:
    with st.open(store_dir, st.StoreConfig(readonly=True)) as s:
        return s.ids()


# ------------------------------------------------------------------------ ReplyCache alone
def _entry(n: int) -> EncodedReply:
    return EncodedReply({"height": 1}, [{"name": "gi", "bytes": n}], bytes(n))


def test_reply_cache_is_an_lru_bounded_in_bytes():
    c = ReplyCache(400)
    for rid in (1, 2, 3):
        assert c.put((rid, "x", "a", "b"), _entry(100))
    assert c.nbytes == 300 and len(c) == 3
    assert c.get((1, "x", "a", "b")) is not None  # 1 is now the most recently used
    assert c.put((4, "x", "a", "b"), _entry(100)) and c.nbytes == 400
    c.put((5, "x", "a", "b"), _entry(100))  # over the bound: the least recently used (2) goes
    assert (2, "x", "a", "b") not in c and (1, "x", "a", "b") in c and c.nbytes == 400
    assert c.stats.evicted == 1
    assert not c.put((6, "x", "a", "b"), _entry(101))  # over a quarter of the bound: not kept
    assert c.get((6, "x", "a", "b")) is None and c.stats.too_large == 1
    assert c.discard([1, 3, 99]) == 2 and c.record_ids() == {4, 5} and c.nbytes == 200
    assert c.get((1, "x", "a", "b")) is None
    none = ReplyCache(0)
    assert not none.put((1, "x", "a", "b"), _entry(1)) and len(none) == 0
    with pytest.raises(ValueError, match="max_bytes"):
        ReplyCache(-1)
    with pytest.raises(ValueError, match="reply_cache_bytes"):
        ServerConfig(reply_cache_bytes=-5)


# ------------------------------------------------------------------------ through the server
def test_a_kept_reply_equals_a_fresh_encode_byte_for_byte(scene, tmp_path):
    store = tmp_path / "s"
    with Server(scene, store, TOKEN, ServerConfig(), CLOUD) as srv:
        r = _request(scene, 0.5)
        miss, hit, hit2, other = ask(
            srv.url, (r, *CODECS), (r, *CODECS), (r, *CODECS), (r, "f16-zstd", "f16-zstd")
        )
        assert not miss.fields["cache_hit"] and hit.fields["cache_hit"] and hit2.fields["cache_hit"]
        # the render's reply was kept: both hits come from it, the other codecs are encoded
        assert srv.stats.reply_cache_hits == 2 and srv.stats.cache_hits == 3
        assert srv._replies.stats.stored == 2
    (rid,) = _ids(store)
    for msg, codecs in ((hit, CODECS), (hit2, CODECS), (other, ("f16-zstd", "f16-zstd"))):
        parts, payload = _fresh(store, rid, *codecs)
        assert msg.payload == payload and msg.fields["parts"] == parts
    assert hit.fields["camera"] == miss.fields["camera"]  # the stored record's camera
    assert hit.payload == miss.payload  # the render's own encode, kept


def test_an_evicted_record_is_never_answered_from_a_kept_reply(scene, tmp_path):
    """A store of one record: a render elsewhere evicts the first; asking the first camera again
    renders anew (its kept reply was dropped with it), and that new record is what answers."""
    store = tmp_path / "s"
    with Server(scene, store, TOKEN, ServerConfig(), CLOUD) as srv:
        writer = srv._cloud.store  # a capacity of one record (LRU) on the server's writer
        writer.config = dataclasses.replace(writer.config, max_records=1)
        a, b = _request(scene, 0.5), _request(scene, 4.0)
        ask(srv.url, (a, *CODECS))
        (first_id,) = _ids(store)
        assert srv._replies.record_ids() == {first_id}
        (other,) = ask(srv.url, (b, *CODECS))  # evicts the first record
        assert first_id not in _ids(store) and first_id not in srv._replies.record_ids()
        again, hit = ask(srv.url, (a, *CODECS), (a, *CODECS))
        assert not other.fields["cache_hit"] and not again.fields["cache_hit"]
        assert hit.fields["cache_hit"]
        (new_id,) = _ids(store)
    assert new_id != first_id
    parts, payload = _fresh(store, new_id, *CODECS)
    assert hit.payload == payload and again.payload == payload


def test_a_damaged_record_is_rendered_again_and_its_replies_are_not_served(scene, tmp_path):
    """Its reply kept in one pair of codecs; the payload damaged; asked in another pair, the
    record is read, found damaged, rendered again and replaced: the first pair's kept reply is
    dropped and the new record answers it."""
    store = tmp_path / "s"
    with Server(scene, store, TOKEN, ServerConfig(), CLOUD) as srv:
        r = _request(scene, 0.5)
        ask(srv.url, (r, *CODECS))
        (old_id,) = _ids(store)
        with st.open(store, st.StoreConfig(readonly=True)) as s:
            path = s.info(old_id).payload
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
        (rerender,) = ask(srv.url, (r, "f16-zstd", "f16-zstd"))
        assert not rerender.fields["cache_hit"]
        (new_id,) = _ids(store)
        assert new_id != old_id and old_id not in srv._replies.record_ids()
        (hit,) = ask(srv.url, (r, *CODECS))
        assert hit.fields["cache_hit"]
    parts, payload = _fresh(store, new_id, *CODECS)
    assert hit.payload == payload and hit.fields["parts"] == parts


def test_hit_counts_reach_the_store_through_its_writer(scene, tmp_path):
    store = tmp_path / "s"
    r = _request(scene, 0.5)
    with Server(scene, store, TOKEN, ServerConfig(hit_flush_s=0.05), CLOUD) as srv:
        ask(srv.url, *[(r, *CODECS)] * 6)  # one render, five hits
        deadline = time.monotonic() + T
        while srv.stats.hit_counts_flushed < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert srv.stats.hit_counts_flushed == 5  # handed to the writer while serving
    with st.open(store, st.StoreConfig(readonly=True)) as s:
        (rid,) = s.ids()
        info = s.info(rid)
    assert info.hits == 5 and info.last_hit > info.meta.created


def test_store_add_hits_counts_and_refuses_a_reader(scene, tmp_path):
    from icbtool.store import ReadOnlyStoreError

    with Server(scene, tmp_path / "s", TOKEN, ServerConfig(), CLOUD) as srv:
        ask(srv.url, (_request(scene, 0.5), *CODECS))
    with st.open(tmp_path / "s") as s:
        (rid,) = s.ids()
        s.add_hits({rid: (3, 1e9), rid + 100: (7, 1e9)})  # an id not stored: skipped
        assert s.info(rid).hits == 3
    with st.open(tmp_path / "s", st.StoreConfig(readonly=True)) as s:
        assert s.info(rid).hits == 3  # flushed at close
        with pytest.raises(ReadOnlyStoreError):
            s.add_hits({rid: (1, 1e9)})


def test_the_servers_renders_run_at_its_render_nice(scene, tmp_path):
    """ServerConfig.render_nice reaches the render pool: the render thread's priority is that
    many nice levels below the server's (it was left at the server's: hits then competed with
    the renders for the cores)."""
    import os
    import threading

    if not hasattr(os, "getpriority"):
        pytest.skip("no thread priorities on this OS")
    me = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    with Server(scene, tmp_path / "s", TOKEN, ServerConfig(render_nice=7), CLOUD) as srv:
        (miss,) = ask(srv.url, (_request(scene, 0.5), *CODECS))
        assert not miss.fields["cache_hit"]
        render = [t for t in threading.enumerate() if t.name.startswith("icb-render")]
        assert len(render) == 1
        assert os.getpriority(os.PRIO_PROCESS, render[0].native_id) == min(19, me + 7)


# ------------------------------------------------------------------------ LPM manifests
def test_lpm_manifest_names_files_without_the_servers_folders(scene):
    from icbtool.net.mesh_stream import MeshStream
    from icbtool.scene.types import Material

    tex = np.full((4, 4, 3), 0.5, np.float32)
    mats = [
        Material(m.name, m.albedo, m.emission, tex if i == 0 else m.texture,
                 "/srv/secret/scenes/wood.png" if i == 0 else m.texture_path)
        for i, m in enumerate(scene.materials)
    ]  # fmt: skip
    uvs = np.zeros((len(scene.vertices), 2), np.float32)
    s = dataclasses.replace(
        scene, materials=mats, uvs=uvs, source="C:\\Users\\me\\scenes\\box.toml"
    )
    stream = MeshStream(s, lpm=False)
    (name, part, data) = stream.levels[0].chunks[0]
    assert part == "materials"
    from icbtool.lpm.chunks import chunk_header

    _, payload = chunk_header(data, name)
    text = payload.decode()
    man = json.loads(text)
    assert man["source"] == "box.toml"
    assert man["materials"][0]["texture_path"] == "wood.png"
    assert "/" not in man["source"] and "secret" not in text and "Users" not in text
    for m in man["materials"]:
        assert m["texture_path"] is None or ("/" not in m["texture_path"] and
                                             "\\" not in m["texture_path"])  # fmt: skip


# ------------------------------------------------------------------------ icbtool client --tls-ca
def test_cli_client_trusts_the_certificate_given_with_tls_ca(scene, tmp_path, capsys):
    from test_net_limits import _self_signed

    from icbtool.cli import main

    cert, key = _self_signed(tmp_path)
    cfg = ServerConfig(tls_cert=str(cert), tls_key=str(key), lpm=False)
    common = ["--token", TOKEN, "--path", "test", "--frames", "1", "--height", "32",
              "--width", "32", "--timeout-s", "30"]  # fmt: skip
    with Server(scene, tmp_path / "s", TOKEN, cfg, CLOUD) as srv:
        out = tmp_path / "c"
        assert main(["client", srv.url, *common, "--tls-ca", str(cert), "--out", str(out)]) == 0
        assert (out / "frames" / "000.png").is_file()
        capsys.readouterr()
        # without it the self-signed certificate is not trusted: one line, exit 1
        assert main(["client", srv.url, *common, "--out", str(tmp_path / "n")]) == 1
        assert "cannot connect" in capsys.readouterr().err
    # usage errors name the option, before any work: exit 2
    assert main(["client", "ws://127.0.0.1:1", *common, "--tls-ca", str(cert)]) == 2
    assert "--tls-ca applies to wss://" in capsys.readouterr().err
    missing = str(tmp_path / "nope.pem")
    assert main(["client", "wss://127.0.0.1:1", *common, "--tls-ca", missing]) == 2
    assert "no such file" in capsys.readouterr().err
