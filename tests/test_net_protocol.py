"""icbtool.net: framing, message schema, handshake and channel crypto, camera/request JSON, GI
codecs. Quick, no sockets."""

from __future__ import annotations

import hashlib
import json
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from icbtool.camera import Camera
from icbtool.net import codec, crypto
from icbtool.net import protocol as P
from icbtool.net.protocol import KINDS, Field, Message, ProtocolError
from icbtool.system import GIRequest

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"

# ------------------------------------------------------------------------- strategies from KINDS
_text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)
_json_scalar = st.none() | st.booleans() | st.integers(-(2**53) + 1, 2**53 - 1) | _text


def _value(f: Field) -> st.SearchStrategy[Any]:
    if f.type == "string":
        s = _text
    elif f.type == "integer":
        lo = int(f.minimum) if f.minimum is not None else -(2**53) + 1
        hi = int(f.maximum) if f.maximum is not None else 2**53 - 1
        s = st.integers(lo, hi)
    elif f.type == "number":
        lo = f.minimum if f.minimum is not None else None
        hi = f.maximum if f.maximum is not None else None
        s = st.floats(
            min_value=lo,
            max_value=hi,
            exclude_min=f.exclusive,
            allow_nan=False,
            allow_infinity=False,
        ) | st.integers(int(lo or 0) + f.exclusive, int(hi if hi is not None else 2**53 - 1))
    elif f.type == "boolean":
        s = st.booleans()
    elif f.type in ("base64", "hex"):
        n = f.length if f.length is not None else 8
        raw = st.binary(min_size=n, max_size=n)
        s = raw.map(P.b64) if f.type == "base64" else raw.map(bytes.hex)
    elif f.type == "array":
        item = _value(f.items) if f.items is not None else _json_scalar
        if f.length is not None:
            s = st.lists(item, min_size=f.length, max_size=f.length)
        else:
            s = st.lists(item, max_size=3)
    elif f.type == "object":
        s = (
            _object(f.fields)
            if f.fields is not None
            else st.dictionaries(_text, _json_scalar, max_size=3)
        )
    else:  # pragma: no cover
        raise AssertionError(f.type)
    return (st.none() | s) if f.nullable else s


def _object(fields: tuple[Field, ...]) -> st.SearchStrategy[dict[str, Any]]:
    required = {f.name: _value(f) for f in fields if f.required}
    optional = {f.name: _value(f) for f in fields if not f.required}
    return st.fixed_dictionaries(required, optional=optional)


@st.composite
def messages(draw: st.DrawFn, kind: str | None = None) -> Message:
    kind = kind or draw(st.sampled_from(sorted(KINDS)))
    spec = KINDS[kind]
    fields = draw(_object(spec.fields))
    payload = draw(st.binary(max_size=64)) if spec.payload is not None else b""
    if kind in ("lpm_chunk", "generator_chunk"):
        fields["count"] = max(fields["count"], fields["index"] + 1)
        if fields["count"] > 2**53 - 1:
            fields["index"], fields["count"] = 0, 1
        fields["sha256"] = hashlib.sha256(payload).hexdigest()
    if kind == "gi_reply":
        # split the payload among the parts
        n = len(fields["parts"])
        if n == 0:
            payload = b""
        cuts = sorted(
            draw(
                st.lists(
                    st.integers(0, len(payload)), min_size=max(n - 1, 0), max_size=max(n - 1, 0)
                )
            )
        )
        bounds = [0, *cuts, len(payload)] if n else [0]
        for i, part in enumerate(fields["parts"]):
            part["bytes"] = bounds[i + 1] - bounds[i]
    if kind == "error":
        fields["code"] = draw(st.sampled_from(sorted(P.ERROR_CODES)))
    return Message(kind, fields, payload)


def _pair(token: str = "s3cret-token", server_token: str | None = None):
    """(client channel, server channel) after a full handshake through encode/decode."""
    c = crypto.ClientHandshake(token)
    s = crypto.ServerHandshake(server_token if server_token is not None else token)
    hello = P.decode(P.encode(Message("hello", c.hello_fields())))
    welcome = P.decode(P.encode(Message("welcome", s.welcome(hello.fields))))
    cch, auth = c.finish(welcome.fields)
    auth = P.decode(P.encode(Message("auth", auth)))
    return cch, s.verify(auth.fields)


def _chunk(payload: bytes, **kw: Any) -> Message:
    f = {"level": 0, "index": 0, "count": 1, "part": "mesh", "name": "mesh.bin"}
    f.update(kw)
    f["sha256"] = hashlib.sha256(payload).hexdigest()
    return Message("lpm_chunk", f, payload)


def _frame(header: dict[str, Any] | bytes, payload: bytes = b"") -> bytes:
    hb = header if isinstance(header, bytes) else json.dumps(header).encode()
    return struct.pack(">I", len(hb)) + hb + payload


# ------------------------------------------------------------------------- round trips
_ROUND_TRIP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("kind", sorted(KINDS))
@_ROUND_TRIP
@given(data=st.data())
def test_every_kind_round_trips_plain(kind: str, data: st.DataObject):
    msg = data.draw(messages(kind))
    encoded = P.encode(msg)
    assert P.decode(encoded) == msg
    assert struct.unpack(">I", encoded[:4])[0] == len(encoded) - 4 - len(msg.payload)


_CHANNELS = _pair()


@pytest.mark.parametrize("kind", sorted(KINDS))
@_ROUND_TRIP
@given(data=st.data(), from_client=st.booleans())
def test_every_kind_round_trips_sealed(kind: str, data: st.DataObject, from_client: bool):
    msg = data.draw(messages(kind))
    cch, sch = _CHANNELS
    tx, rx = (cch, sch) if from_client else (sch, cch)
    encoded = P.encode(msg, tx)
    assert len(encoded) >= 4 + len(msg.payload) + crypto.TAG_BYTES
    assert P.decode(encoded, rx) == msg


# ------------------------------------------------------------------------- malformed input
_OK = {"v": 1, "kind": "lpm_done", "level": 2}


@pytest.mark.parametrize(
    "data, code, words",
    [
        (b"", "malformed", "shorter"),
        (b"\x00\x00\x00", "malformed", "shorter"),
        (struct.pack(">I", 50) + b"{}", "malformed", "runs past"),
        (struct.pack(">I", P.MAX_HEADER + 1) + b"{}", "too_large", "header length"),
        (_frame(b"\xff\xfe{}"), "malformed", "UTF-8"),
        (_frame(b'{"v":1,"kind":'), "malformed", "JSON"),
        (_frame(b"[1, 2]"), "malformed", "object"),
        (_frame(b'{"v":1,"v":1,"kind":"bye"}'), "malformed", "duplicate"),
        (_frame(b'{"v":1,"kind":"lpm_done","level":NaN}'), "malformed", "NaN"),
        (_frame({"kind": "bye"}), "malformed", "'v'"),
        (_frame({"v": 1}), "malformed", "'kind'"),
        (_frame({"v": 2, "kind": "bye"}), "version", "version 2"),
        (_frame({"v": "1", "kind": "bye"}), "version", "version '1'"),
        (_frame({"v": 1, "kind": "teleport"}), "unknown_kind", "teleport"),
        (_frame({"v": 1, "kind": 3}), "unknown_kind", "3"),
        (_frame({"v": 1, "kind": "lpm_done"}), "bad_field", "lpm_done.level: missing"),
        (_frame({**_OK, "level": "2"}), "bad_field", "lpm_done.level: must be integer, got str"),
        (_frame({**_OK, "level": True}), "bad_field", "lpm_done.level"),
        (_frame({**_OK, "level": 1.5}), "bad_field", "lpm_done.level"),
        (_frame({**_OK, "level": -1}), "bad_field", "lpm_done.level: must be >= 0"),
        (_frame({**_OK, "level": 2**60}), "bad_field", "JavaScript-safe"),
        (_frame(_OK, b"extra"), "bad_field", "lpm_done.payload"),
        (_frame({"v": 1, "kind": "bye", "ctr": 0}, b"x" * 16), "crypto", "no session keys"),
        (
            _frame(
                {
                    "v": 1,
                    "kind": "hello",
                    "client": "x",
                    "pub": "AAAA",
                    "nonce": "AAAA",
                    "codecs": [],
                }
            ),
            "bad_field",
            "hello.pub: must decode to 32 bytes",
        ),
        (
            _frame({"v": 1, "kind": "auth", "mac": "not base64!"}),
            "bad_field",
            "auth.mac: is not valid base64",
        ),
        (
            _frame({"v": 1, "kind": "gi_request", "id": 4, "request": {}, "codec": "f16-zstd"}),
            "bad_field",
            "gi_request.request.camera: missing",
        ),
        (
            _frame({"v": 1, "kind": "error", "code": "oops", "message": "", "ref": None}),
            "bad_field",
            "error.code",
        ),
    ],
)
def test_malformed_messages_get_the_right_code(data: bytes, code: str, words: str):
    with pytest.raises(ProtocolError) as e:
        P.decode(data)
    assert e.value.code == code
    assert words in str(e.value)


def test_bad_field_carries_the_request_id_as_ref():
    with pytest.raises(ProtocolError) as e:
        P.decode(_frame({"v": 1, "kind": "gi_request", "id": 17, "request": 3, "codec": "x"}))
    assert (e.value.code, e.value.ref) == ("bad_field", 17)
    err = P.error_message(e.value)
    assert err.kind == "error" and err.fields["ref"] == 17 and err.fields["code"] == "bad_field"
    back = P.decode(P.encode(err))
    with pytest.raises(ProtocolError) as e2:
        P.raise_for_error(back)
    assert (e2.value.code, e2.value.ref) == ("bad_field", 17)


def test_size_limits():
    big = _chunk(b"\x01" * 5000)
    with pytest.raises(ProtocolError, match="too_large"):
        P.encode(big, max_bytes=4096)
    data = P.encode(big)
    with pytest.raises(ProtocolError) as e:
        P.decode(data, max_bytes=4096)
    assert e.value.code == "too_large"
    with pytest.raises(ProtocolError) as e:
        P.encode(Message("error", {"code": "internal", "message": "x" * P.MAX_HEADER, "ref": None}))
    assert e.value.code == "too_large"


def test_chunk_hash_and_reply_sizes_are_checked():
    msg = _chunk(b"abc")
    good = P.encode(msg)
    n = struct.unpack(">I", good[:4])[0]
    with pytest.raises(ProtocolError, match=r"lpm_chunk\.sha256"):
        P.decode(good[: 4 + n] + b"abd")  # a changed plain payload no longer matches its hash
    with pytest.raises(ProtocolError, match=r"lpm_chunk\.index"):
        P.encode(_chunk(b"abc", index=3, count=3))
    part = {"name": "gi", "codec": "f32-zstd", "shape": [1, 1, 3], "dtype": "float32", "bytes": 5}
    cam = P.camera_to_json(Camera.from_fov(60, 4, 4))
    reply = {"id": 1, "camera": cam, "cache_hit": False, "timings_ms": {}, "parts": [part]}
    with pytest.raises(ProtocolError, match="add up to 5 but the payload has 4"):
        P.encode(Message("gi_reply", reply, b"abcd"))
    assert P.decode(P.encode(Message("gi_reply", reply, b"abcde"))).payload == b"abcde"
    # the scene-state fields (section Scene states): optional, typed
    dyn = {**reply, "stale": True, "state": "0123456789abcdef", "spp": 4, "refining": True}
    assert P.decode(P.encode(Message("gi_reply", dyn, b"abcde"))).fields == dyn
    for name, bad in (("stale", "yes"), ("spp", -1), ("state", 3), ("refining", 1)):
        with pytest.raises(ProtocolError, match=rf"gi_reply\.{name}"):
            P.encode(Message("gi_reply", {**reply, name: bad}, b"abcde"))


def test_reserved_and_unserialisable_fields_are_refused():
    with pytest.raises(ProtocolError, match="reserved"):
        P.encode(Message("lpm_done", {"level": 0, "ctr": 3}))
    with pytest.raises(ProtocolError, match="JSON"):
        P.encode(Message("bye", {"extra": object()}))
    with pytest.raises(ProtocolError, match="JSON"):
        P.encode(Message("bye", {"extra": float("nan")}))


# ------------------------------------------------------------------------- handshake and crypto
def test_handshake_gives_both_sides_working_channels():
    cch, sch = _pair()
    for i in range(3):
        m = _chunk(bytes([i]) * 100, index=i, count=3)
        assert P.decode(P.encode(m, sch), cch) == m
        r = Message("lpm_request", {"max_level": i})
        assert P.decode(P.encode(r, cch), sch) == r
    # the two directions use different keys: a client's own message does not open as a server's
    with pytest.raises(ProtocolError) as e:
        P.decode(P.encode(Message("bye"), cch), cch)
    assert e.value.code == "crypto"


def test_wrong_token_is_refused_and_never_sent():
    c = crypto.ClientHandshake("right token")
    s = crypto.ServerHandshake("wrong token")
    hello = c.hello_fields()
    welcome = s.welcome(hello)
    _, auth = c.finish(welcome)
    frames = P.encode(Message("hello", hello)) + P.encode(Message("auth", auth))
    assert b"right token" not in frames
    with pytest.raises(ProtocolError) as e:
        s.verify(auth)
    assert e.value.code == "auth"
    for bad in ({}, {"mac": "###"}, {"mac": P.b64(b"\x00" * 32)}):
        s2 = crypto.ServerHandshake("right token")
        s2.welcome(hello)
        with pytest.raises(ProtocolError, match="auth"):
            s2.verify(bad)
    with pytest.raises(ProtocolError, match="before hello"):
        crypto.ServerHandshake("t").verify(auth)


def test_right_token_twice_gives_one_session():
    c = crypto.ClientHandshake("t")
    s = crypto.ServerHandshake("t")
    _, auth = c.finish(s.welcome(c.hello_fields()))
    s.verify(auth)
    with pytest.raises(ProtocolError, match="repeated"):
        s.verify(auth)


def test_a_server_without_the_token_cannot_read_the_client():
    """The token is mixed into the keys: a man in the middle that runs the key exchange
    itself (and skips the mac check) still derives different keys."""
    c = crypto.ClientHandshake("t")
    mitm = crypto.ServerHandshake("guess")
    cch, _ = c.finish(mitm.welcome(c.hello_fields()))
    assert mitm._keys is not None
    c2s, s2c = mitm._keys
    fake = crypto.Channel(s2c, c2s, crypto.SERVER_TO_CLIENT, crypto.CLIENT_TO_SERVER)
    with pytest.raises(ProtocolError) as e:
        P.decode(P.encode(Message("lpm_request", {"max_level": 0}), cch), fake)
    assert e.value.code == "crypto"


def _tamper(data: bytes, at: int) -> bytes:
    b = bytearray(data)
    b[at] ^= 0x01
    return bytes(b)


def test_tampered_ciphertext_and_header_are_rejected():
    cch, sch = _pair()
    data = P.encode(_chunk(b"vertex data " * 20, level=1), sch)
    n = struct.unpack(">I", data[:4])[0]
    for at in (4 + n, len(data) - 20, len(data) - 1):  # payload start, middle, tag
        with pytest.raises(ProtocolError) as e:
            P.decode(_tamper(data, at), cch)
        assert e.value.code == "crypto"
    header = data[4 : 4 + n]
    forged = header.replace(b'"level":1', b'"level":2')
    assert forged != header
    with pytest.raises(ProtocolError) as e:
        P.decode(data[:4] + forged + data[4 + n :], cch)
    assert e.value.code == "crypto"
    stripped = data[4 + n :][: -crypto.TAG_BYTES]
    with pytest.raises(ProtocolError) as e:
        P.decode(data[: 4 + n] + stripped[:10], cch)
    assert e.value.code == "crypto"
    # rejections do not advance the counter: the genuine message still opens
    assert P.decode(data, cch).fields["level"] == 1


def test_replayed_and_unsealed_messages_are_rejected():
    cch, sch = _pair()
    first = P.encode(Message("lpm_done", {"level": 0}), sch)
    second = P.encode(Message("lpm_done", {"level": 1}), sch)
    assert P.decode(second, cch).fields == {"level": 1}  # a skipped counter is allowed
    for data in (second, first):
        with pytest.raises(ProtocolError) as e:
            P.decode(data, cch)
        assert e.value.code == "replay"
    with pytest.raises(ProtocolError) as e:
        P.decode(P.encode(Message("lpm_done", {"level": 3})), cch)
    assert e.value.code == "crypto"  # a plain message after the handshake
    with pytest.raises(ProtocolError) as e:
        cch.open(-1, b"x" * 16, b"")
    assert e.value.code == "crypto"


def test_captured_chunk_of_a_vertex_array_holds_no_plaintext_vertices():
    rng = np.random.default_rng(7)
    vertices = rng.uniform(-10, 10, (500, 3)).astype(np.float32)
    plain = vertices.tobytes()
    msg = _chunk(plain)
    cch, sch = _pair()
    captured = P.encode(msg, sch)
    # every 8-byte window of the vertex bytes (2 floats) is looked for
    windows = {plain[i : i + 8] for i in range(0, len(plain) - 8, 4)}
    assert sum(w in P.encode(msg) for w in list(windows)[:50]) == 50  # the check can fail
    assert not any(w in captured for w in windows)
    assert np.array_equal(
        np.frombuffer(P.decode(captured, cch).payload, np.float32), vertices.ravel()
    )


# ------------------------------------------------------------------------- camera and request JSON
_coord = st.floats(-100, 100, allow_nan=False).filter(lambda x: abs(x) > 1e-3)


@settings(max_examples=100, deadline=None)
@given(
    st.tuples(_coord, _coord, _coord),
    st.floats(1.0, 170.0),
    st.integers(1, 4096),
    st.integers(1, 4096),
    st.floats(-5, 5),
)
def test_camera_and_request_json_round_trip_exactly(eye, fov, h, w, t):
    cam = Camera.look_at(eye, (0.0, 0.0, 0.0), fov_y_deg=fov, height=h, width=w)
    back = P.camera_from_json(json.loads(json.dumps(P.camera_to_json(cam))))
    assert back == cam and back.world_from_cam.tobytes() == cam.world_from_cam.tobytes()
    req = GIRequest(cam, (0.1, -t, 1 / 3), (t, 0.0, 2e-9), time_s=t, seq=h, depth_range=(0.05, 1e3))
    r = P.request_from_json(json.loads(json.dumps(P.request_to_json(req))))
    assert r.camera == cam and r.seq == h and r.time_s == t and r.depth_range == (0.05, 1e3)
    assert r.velocity_t.tolist() == req.velocity_t.tolist()
    assert r.velocity_r.tolist() == req.velocity_r.tolist()
    assert P.request_from_json(P.request_to_json(GIRequest(cam))).depth_range is None


def test_bad_camera_and_request_json():
    good = P.camera_to_json(Camera.from_fov(60, 8, 8))
    cases = [
        ({**good, "height": "8"}, "camera.height"),
        ({**good, "fx": -1.0}, "camera.fx"),
        ({k: v for k, v in good.items() if k != "cy"}, "camera.cy: missing"),
        ({**good, "zoom": 2}, "unknown keys"),
        (
            {**good, "world_from_cam": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
            "rotation",
        ),
        ({**good, "world_from_cam": [[1, 0, 0]]}, "world_from_cam"),
        ([1, 2], "must be an object"),
    ]
    for d, words in cases:
        with pytest.raises(ProtocolError) as e:
            P.camera_from_json(d)
        assert e.value.code == "bad_field" and words in str(e.value), (words, str(e.value))
    req = P.request_to_json(GIRequest(Camera.from_fov(60, 8, 8)))
    for d, words in [
        ({**req, "seq": -1}, "request.seq"),
        ({**req, "velocity_t": [0, 0]}, "request.velocity_t"),
        ({**req, "depth_range": [2.0, 1.0]}, "depth_range"),
        ({**req, "camera": {**good, "fy": "x"}}, "request.camera.fy"),
    ]:
        with pytest.raises(ProtocolError) as e:
            P.request_from_json(d)
        assert e.value.code == "bad_field" and words in str(e.value), (words, str(e.value))


# ------------------------------------------------------------------------- documentation
def test_every_kind_field_and_error_code_is_documented():
    text = DOC.read_text()
    block = text.split(P.DOC_BEGIN, 1)[1].split(P.DOC_END, 1)[0]
    assert block.strip() == P.schema_markdown().strip(), (
        "docs/protocol.md is out of date: run python -m icbtool.net docs/protocol.md"
    )
    for kind, spec in KINDS.items():
        section = re.search(rf"^### `{kind}`.*?(?=^### |\Z)", text, re.M | re.S)
        assert section, f"docs/protocol.md has no '### `{kind}`' section"
        for f in spec.fields:
            assert f"`{f.name}`" in section.group(0), f"{kind}.{f.name} is not documented"
    for code in P.ERROR_CODES:
        assert f"`{code}`" in text, f"error code {code} is not documented"
    for name in codec.CODECS:
        assert f"`{name}`" in text, f"codec {name} is not documented"
    assert f"PROTOCOL_VERSION = {P.PROTOCOL_VERSION}" in text


def test_the_documented_test_vectors():
    """The handshake of docs/protocol.md section 10, recomputed from its keys."""
    x25519 = pytest.importorskip("cryptography.hazmat.primitives.asymmetric.x25519")
    text = DOC.read_text()
    raw = text.split("<!-- BEGIN TEST VECTORS -->", 1)[1].split("<!-- END TEST VECTORS -->")[0]
    v = json.loads(raw.strip().removeprefix("```json").removesuffix("```"))
    h = bytes.fromhex
    cpriv = x25519.X25519PrivateKey.from_private_bytes(h(v["client_private"]))
    spriv = x25519.X25519PrivateKey.from_private_bytes(h(v["server_private"]))
    assert cpriv.public_key().public_bytes_raw().hex() == v["client_pub"]
    assert spriv.public_key().public_bytes_raw().hex() == v["server_pub"]
    t = crypto.transcript(
        h(v["client_pub"]), h(v["client_nonce"]), h(v["server_pub"]), h(v["server_nonce"]),
        v["session"],
    )  # fmt: skip
    assert t.hex() == v["transcript"]
    shared = cpriv.exchange(spriv.public_key())
    assert shared.hex() == v["shared_secret"] == spriv.exchange(cpriv.public_key()).hex()
    auth_key = crypto.derive_auth_key(shared, v["token"], t)
    assert auth_key.hex() == v["auth_key"]
    assert crypto.auth_mac(auth_key, t).hex() == v["mac"]
    c2s, s2c = crypto.derive_keys(shared, v["token"], t)
    assert (c2s.hex(), s2c.hex()) == (v["key_c2s"], v["key_s2c"])
    ch = crypto.Channel(c2s, s2c, crypto.CLIENT_TO_SERVER, crypto.SERVER_TO_CLIENT)
    m = v["first_client_message"]
    assert P.encode(Message(m["kind"], m["fields"]), ch).hex() == m["frame"]
    server = crypto.Channel(s2c, c2s, crypto.SERVER_TO_CLIENT, crypto.CLIENT_TO_SERVER)
    assert P.decode(h(m["frame"]), server) == Message(m["kind"], m["fields"])


def client_model_vectors() -> dict:
    """The client-model vectors of docs/protocol.md section 10."""
    text = DOC.read_text()
    raw = text.split("<!-- BEGIN CLIENT MODEL VECTORS -->", 1)[1]
    raw = raw.split("<!-- END CLIENT MODEL VECTORS -->")[0]
    return json.loads(raw.strip().removeprefix("```json").removesuffix("```"))


def test_the_documented_client_model_vectors():
    """Every normalisation rule and the output decoding, as docs/protocol.md states them."""
    from icbtool.net.client_model import CHANNELS, GAN_MAP_RULES, decode_output, encode_map

    v = client_model_vectors()
    ann = {"encoding": v["encoding"]}
    assert set(v["inputs"]) == set(GAN_MAP_RULES) == set(CHANNELS)
    for name, x in v["inputs"].items():
        a = np.asarray(x, np.float32).reshape(1, 1, CHANNELS[name])
        got = encode_map(name, a, ann).ravel()
        np.testing.assert_array_equal(got, np.asarray(v["encoded"][name], np.float32), name)
    got = decode_output(np.asarray(v["outputs"], np.float32), ann)
    np.testing.assert_array_equal(got, np.asarray(v["decoded"], np.float32))


# ------------------------------------------------------------------------- GI / depth codecs
def _gi_and_depth(seed: int = 0, h: int = 24, w: int = 32):
    rng = np.random.default_rng(seed)
    gi = rng.lognormal(-1.0, 2.0, (h, w, 3)).astype(np.float32)
    gi[0, 0] = 0.0
    gi[1, 1] = [1e-3, 5.0, 1e3]
    depth = rng.uniform(0.05, 500.0, (h, w)).astype(np.float32)
    depth[:4, :4] = np.inf
    depth[4:6, 4:6] = 0.0
    return gi, depth


def test_f32_zstd_is_exact_for_gi_and_depth():
    gi, depth = _gi_and_depth()
    for a in (gi, depth, depth[..., None]):
        out = codec.decode(codec.encode(a, "f32-zstd"), "f32-zstd", list(a.shape))
        assert out.dtype == np.float32 and out.shape == a.shape
        assert out.tobytes() == a.tobytes()


@pytest.mark.parametrize("name", [c for c in codec.CODECS if c != "f32-zstd"])
def test_lossy_codecs_stay_within_their_relative_error(name: str):
    gi, depth = _gi_and_depth(1)
    c = codec.CODECS[name]
    out = codec.decode(codec.encode(gi, name), name, gi.shape)
    if name == "rgbe-png":  # relative to the pixel's largest channel
        err = np.abs(out - gi) / np.maximum(gi.max(-1, keepdims=True), 1e-30)
        assert err.max() <= c.max_rel_error
        assert np.all(out[0, 0] == 0)
    else:
        normal = gi > 2.0**-14
        err = np.abs(out[normal] - gi[normal]) / gi[normal]
        assert err.max() <= c.max_rel_error
        assert err.max() > c.max_rel_error / 4  # the bound is tight, not vacuous
    if c.for_depth:
        d = codec.decode(codec.encode(depth, name), name, depth.shape)
        assert np.array_equal(np.isposinf(d), np.isposinf(depth))  # no surface stays inf ...
        assert np.array_equal(d == 0, depth == 0)  # ... or 0, exactly
        fin = np.isfinite(depth) & (depth > 0)
        assert (np.abs(d[fin] - depth[fin]) / depth[fin]).max() <= c.max_rel_error


def test_diff_codecs_keep_the_float16_values_signs_and_specials():
    gi, depth = _gi_and_depth(4)
    gi[3, 3] = [np.nan, -2.5, 7e4]
    plain = codec.decode(codec.encode(gi, "f16-zstd"), "f16-zstd", gi.shape)
    diff = codec.decode(codec.encode(gi, "f16-diff-zstd"), "f16-diff-zstd", gi.shape)
    assert np.array_equal(plain, diff, equal_nan=True)  # the same values, other bytes
    m7 = codec.decode(codec.encode(gi, "f16m7-diff-zstd"), "f16m7-diff-zstd", gi.shape)
    assert np.isnan(m7[3, 3, 0]) and m7[3, 3, 1] == -2.5 and m7[3, 3, 2] == 65280.0
    with pytest.raises(ValueError, match="2 or more axes"):
        codec.encode(np.ones(5, np.float32), "f16-diff-zstd")


def test_f16_saturates_instead_of_overflowing_and_png_channels_are_rgb():
    a = np.array([[[7e4, 1.0, 0.0]]], np.float32)
    out = codec.decode(codec.encode(a, "f16-zstd"), "f16-zstd", [1, 1, 3])
    assert out.tolist() == [[[65504.0, 1.0, 0.0]]]
    import cv2

    red = np.zeros((2, 2, 3), np.float32)
    red[..., 0] = 1.0
    png = cv2.imdecode(np.frombuffer(codec.encode(red, "log-u16-png"), np.uint8), -1)
    assert png[0, 0, 2] > 0 and png[0, 0, 0] == 0  # cv2 reads BGR: the file holds R first


def test_corrupt_or_mismatched_codec_data_is_malformed():
    gi, depth = _gi_and_depth(2)
    for name in codec.CODECS:
        blob = codec.encode(gi, name)
        for bad, shape in (
            (blob[: len(blob) // 2], gi.shape),  # truncated
            (b"\x00" * 7 + blob[7:], gi.shape),  # header smashed
            (blob, (gi.shape[0] + 1, *gi.shape[1:])),  # wrong size
            (b"", gi.shape),
        ):
            with pytest.raises(ProtocolError) as e:
                codec.decode(bad, name, shape)
            assert e.value.code == "malformed" and name in str(e.value), (name, str(e.value))
    with pytest.raises(ProtocolError, match="bad_field.*unknown codec"):
        codec.decode(b"", "jpeg", [1])
    with pytest.raises(ProtocolError, match="dtype"):
        codec.decode(b"", "f32-zstd", [1], "float64")
    with pytest.raises(ProtocolError, match="too_large"):
        codec.decode(b"", "f32-zstd", [2**20, 2**20])
    with pytest.raises(ValueError, match="NaN"):
        codec.encode(np.full((2, 2, 3), np.nan, np.float32), "rgbe-png")
    with pytest.raises(ValueError, match="rgbe-png"):
        codec.encode(depth, "rgbe-png")


def test_gi_reply_parts_round_trip_through_a_sealed_message():
    gi, depth = _gi_and_depth(3)
    parts, payload = codec.pack_parts([("gi", gi, "f16-zstd"), ("depth", depth, "f32-zstd")])
    cam = P.camera_to_json(Camera.from_fov(60, *depth.shape))
    reply = Message(
        "gi_reply",
        {"id": 5, "camera": cam, "cache_hit": True, "timings_ms": {"lookup": 0.4}, "parts": parts},
        payload,
    )
    cch, sch = _pair()
    got = P.decode(P.encode(reply, sch), cch)
    arrays = codec.unpack_parts(got.fields["parts"], got.payload)
    assert arrays["depth"].tobytes() == depth.tobytes()
    assert np.allclose(arrays["gi"], gi, rtol=2.0**-11, atol=0)
    with pytest.raises(ProtocolError, match="after the parts"):
        codec.unpack_parts(parts[:1], payload)
