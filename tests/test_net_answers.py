"""Every request answered as docs/protocol.md says: a property test drives a live server (loopback,
the Cornell box, tiny renders) with random sessions of valid and invalid messages, and checks the
kind and code of each answer against an oracle written from the doc (sections Framing, Message
kinds, Codecs, Limits), and that no invalid request reaches a lookup or a render.

Every wait is bounded; nothing asserts a wall-clock time.
"""

from __future__ import annotations

import asyncio
import json
import struct
from dataclasses import dataclass
from typing import Any

import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")
pytest.importorskip("zstandard")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from icbtool import scene as sc  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.net import codec, crypto, protocol  # noqa: E402
from icbtool.net.errors import MAX_SAFE_INTEGER  # noqa: E402
from icbtool.net.server import Server, ServerConfig, new_token  # noqa: E402

pytestmark = [pytest.mark.network, pytest.mark.gl]

TOKEN = new_token()
CLOUD = system.CloudConfig(spp=1, denoise=False, max_depth=2)
SIDE = 16  # the server's max_request_side: the bound tested exactly
T = 120.0
GI_CODECS = sorted(codec.CODECS)
DEPTH_CODECS = sorted(c for c, v in codec.CODECS.items() if v.for_depth)


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


@pytest.fixture(scope="module")
def server(scene, tmp_path_factory):
    cfg = ServerConfig(max_request_side=SIDE, max_render_side=SIDE, max_pending=4)
    srv = Server(scene, tmp_path_factory.mktemp("store"), TOKEN, cfg, CLOUD).start()
    works: list[int] = []
    inner = srv._lookup_or_render

    async def counted(*a: Any, **k: Any) -> Any:
        works.append(1)
        return await inner(*a, **k)

    srv._lookup_or_render = counted  # type: ignore[method-assign]
    srv.works = works  # type: ignore[attr-defined]
    yield srv
    srv.stop()


# ------------------------------------------------------------------------------ the oracle
@dataclass
class Case:
    """One frame sent and the answer the doc promises: ``kind`` ``gi_reply`` (with ``ref`` its
    id) or ``error`` with ``code`` and ``ref``."""

    frame: Any  # bytes, str (a text message), or a callable sealing with the channel
    kind: str
    code: str | None
    ref: Any
    what: str


def _sealed(header: dict[str, Any]) -> Any:
    def make(channel: Any) -> bytes:
        h = {"v": 1, **header, "ctr": channel.next_counter}
        hb = json.dumps(h).encode()
        _, ct = channel.seal(b"", hb)
        return struct.pack(">I", len(hb)) + hb + ct

    return make


# Valid requests come from a few cameras (most are hits once rendered: the test stays quick).
_T = st.sampled_from([0.5, 1.5, 2.5])
_VALID_ID = st.integers(0, 1000) | st.just(MAX_SAFE_INTEGER)  # 2^53 - 1 is the doc's bound
_BAD_ID = st.sampled_from([-1, MAX_SAFE_INTEGER + 1, 1.5, "7", True, None, "absent"])
_BAD_CODEC = st.sampled_from(["", "F32-ZSTD", "png", "zstd", 7, None]) | st.text(max_size=6)
_BAD_SIDE = st.sampled_from([0, -1, SIDE + 1, protocol.MAX_IMAGE_SIDE + 1, 8.5, "8"])
_BAD_VELOCITY = st.sampled_from([1e6 * (1 + 2**-20), -2e6, 1e308, "1"])

MUTATIONS = (
    "valid",
    "valid_side_bound",
    "valid_extra_key",
    "bad_id",
    "bad_codec",
    "bad_depth_codec",
    "rgbe_depth",
    "bad_side",
    "bad_focal",
    "bad_velocity",
    "request_extra_key",
    "missing_request",
)


@st.composite
def gi_case(draw: Any, scene: Any, rid: int) -> Case:
    """A gi_request, valid or broken in one way, with its documented answer."""
    m = draw(st.sampled_from(MUTATIONS))
    t = draw(_T)
    size = SIDE if m == "valid_side_bound" else 8
    p = scene.paths["test"]
    cam = p.with_intrinsics(p.intrinsics.resized(size, size)).camera_at(t)
    req = protocol.request_to_json(system.GIRequest(cam, time_s=t, seq=0, depth_range=(0.5, 8.0)))
    fields: dict[str, Any] = {"id": rid, "request": req, "codec": draw(st.sampled_from(GI_CODECS))}
    if draw(st.booleans()):
        fields["depth_codec"] = draw(st.sampled_from(DEPTH_CODECS))
    ok = Case(_sealed({"kind": "gi_request", **fields}), "gi_reply", None, rid, m)
    bad = Case(None, "error", "bad_field", rid, m)
    if m in ("valid", "valid_side_bound"):
        return ok
    if m == "valid_extra_key":  # forward compatibility: unknown header keys are ignored
        fields["future_option"] = draw(st.integers(0, 9) | st.text(max_size=4))
        return ok
    if m == "bad_id":
        v = draw(_BAD_ID)
        if v == "absent":
            del fields["id"]
        else:
            fields["id"] = v
        bad.ref = None  # an invalid id is never echoed
    elif m == "bad_codec":
        fields["codec"] = draw(_BAD_CODEC.filter(lambda c: c not in codec.CODECS))
    elif m == "bad_depth_codec":
        fields["depth_codec"] = draw(_BAD_CODEC.filter(lambda c: c not in codec.CODECS))
    elif m == "rgbe_depth":  # a GI-only codec cannot carry depth (section Codecs)
        fields["depth_codec"] = "rgbe-png"
    elif m == "bad_side":
        req["camera"][draw(st.sampled_from(["height", "width"]))] = draw(_BAD_SIDE)
    elif m == "bad_focal":
        req["camera"][draw(st.sampled_from(["fx", "fy"]))] = draw(st.sampled_from([0, -1.0, 0.0]))
    elif m == "bad_velocity":
        which = draw(st.sampled_from(["velocity_t", "velocity_r"]))
        req[which][draw(st.integers(0, 2))] = draw(_BAD_VELOCITY)
    elif m == "request_extra_key":
        req["colour"] = 1
    elif m == "missing_request":
        del fields["request"]
    bad.frame = _sealed({"kind": "gi_request", **fields})
    return bad


@st.composite
def other_case(draw: Any) -> Case:
    """A message that is not a gi_request: each broken in a documented way."""
    m = draw(st.sampled_from(["text", "unknown_kind", "version", "server_kind"]))
    if m == "text":  # section Transport: binary messages only
        return Case(draw(st.text(min_size=1, max_size=40)), "error", "bad_field", None, m)
    if m == "unknown_kind":
        return Case(_sealed({"kind": "teleport"}), "error", "unknown_kind", None, m)
    if m == "version":
        hb = json.dumps({"v": 2, "kind": "bye", "ctr": 0}).encode()
        return Case(struct.pack(">I", len(hb)) + hb, "error", "version", None, m)
    return Case(  # a kind only the server sends
        _sealed({"kind": "lpm_done", "level": 0}), "error", "unknown_kind", None, m
    )


@st.composite
def session(draw: Any, scene: Any) -> list[Case]:
    n = draw(st.integers(1, 4))  # at most max_pending gi_requests: never busy
    ids = draw(st.lists(_VALID_ID, min_size=n, max_size=n, unique=True))
    cases = [draw(gi_case(scene, rid)) for rid in ids]
    cases += draw(st.lists(other_case(), max_size=2))
    return draw(st.permutations(cases))


async def _exchange(url: str, cases: list[Case]) -> list[protocol.Message]:
    from websockets.asyncio.client import connect

    async with connect(url, proxy=None, compression=None, open_timeout=T, max_size=2**24) as ws:
        hs = crypto.ClientHandshake(TOKEN)
        await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
        welcome = protocol.decode(await asyncio.wait_for(ws.recv(), T))
        channel, auth = hs.finish(welcome.fields)
        await ws.send(protocol.encode(protocol.Message("auth", auth)))
        protocol.decode(await asyncio.wait_for(ws.recv(), T), channel)  # scene_info
        for c in cases:
            await ws.send(c.frame(channel) if callable(c.frame) else c.frame)
        got = [protocol.decode(await asyncio.wait_for(ws.recv(), T), channel) for _ in cases]
        await ws.close()
    return got


def _answer(m: protocol.Message) -> tuple[str, str | None, Any]:
    if m.kind == "gi_reply":
        return ("gi_reply", None, m.fields["id"])
    return (m.kind, m.fields.get("code"), m.fields.get("ref"))


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_every_message_gets_the_documented_answer_and_no_invalid_one_works(server, data):
    cases = data.draw(session(server.scene))
    before = len(server.works)
    got = asyncio.run(asyncio.wait_for(_exchange(server.url, cases), 2 * T))
    want = sorted(((c.kind, c.code, c.ref) for c in cases), key=str)
    assert sorted(map(_answer, got), key=str) == want, [c.what for c in cases]
    for m in got:  # errors in the protocol's words, naming what is wrong
        if m.kind == "error":
            msg = m.fields["message"]
            assert msg and "Traceback" not in msg and "Error(" not in msg
    valid = sum(c.kind == "gi_reply" for c in cases)
    assert len(server.works) - before <= valid  # refused requests were never looked up


def test_a_text_message_during_the_handshake_is_refused_and_closes(server):
    from websockets.asyncio.client import connect

    async def go() -> tuple[protocol.Message, int | None]:
        async with connect(server.url, proxy=None, compression=None, open_timeout=T) as ws:
            await ws.send('{"v":1,"kind":"hello"}')
            err = protocol.decode(await asyncio.wait_for(ws.recv(), T))
            await asyncio.wait_for(ws.wait_closed(), T)
            return err, ws.close_code

    err, code = asyncio.run(asyncio.wait_for(go(), 2 * T))
    assert err.fields["code"] == "bad_field" and "binary" in err.fields["message"]
    assert code == 1008


def test_server_config_refuses_a_depth_codec_that_cannot_carry_depth():
    with pytest.raises(ValueError, match="depth_codec.*rgbe-png"):
        ServerConfig(depth_codec="rgbe-png")
    with pytest.raises(ValueError, match="gi_codec"):
        ServerConfig(gi_codec="jpeg")


@pytest.mark.parametrize("how", ["flag", "env"])
def test_an_empty_token_is_a_usage_error_not_a_random_token(tmp_path, how):
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(repo), "ICBTOOL_GL_BACKEND": "osmesa"}
    cmd = [sys.executable, "-m", "icbtool", "serve", "cornell_box", "--store", str(tmp_path)]
    if how == "flag":
        env.pop("ICBTOOL_TOKEN", None)
        cmd += ["--token", ""]
    else:
        env["ICBTOOL_TOKEN"] = ""
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=T)
    assert p.returncode == 2, p.stderr
    assert "empty" in p.stderr and "Traceback" not in p.stderr
    assert "token: " not in p.stdout and "listening" not in p.stdout
