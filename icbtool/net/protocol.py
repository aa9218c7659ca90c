"""The wire format of icbtool's networked ICB system (docs/protocol.md is its reference).

One WebSocket *binary* message is one :class:`Message`::

    u32 big-endian header length N | N bytes: header, a UTF-8 JSON object | payload (the rest)

The header always holds ``"v"`` (:data:`PROTOCOL_VERSION`) and ``"kind"``; the other keys are the
kind's fields, listed with their types in :data:`KINDS` (which :func:`decode` and :func:`encode`
check). After the handshake every message is sealed by a :class:`icbtool.net.crypto.Channel`: the
header gains ``"ctr"`` (the sender's message counter) and the payload becomes the AES-256-GCM
ciphertext of the plain payload, with the header's exact bytes as associated data, so neither the
header nor the payload can be changed, and no message can be replayed, without detection.

Nothing here is Python-specific (no pickle): a browser client can be written from
docs/protocol.md alone.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import math
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from icbtool.camera import Camera
from icbtool.net.errors import ERROR_CODES, MAX_SAFE_INTEGER, ProtocolError, b64, safe_ref, unb64
from icbtool.system.messages import GIRequest

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.net.crypto import Channel

#: Version of the wire format; a peer speaking another version gets an error ``"version"``.
PROTOCOL_VERSION = 1
#: Default limit on one whole WebSocket message (header + payload), bytes.
DEFAULT_MAX_MESSAGE = 64 * 2**20
#: Limit on the JSON header of one message, bytes.
MAX_HEADER = 64 * 2**10
#: Header keys that belong to the frame, not to a kind's fields.
RESERVED_KEYS = ("v", "kind", "ctr")


@dataclass(frozen=True)
class Message:
    """One protocol message.

    Attributes:
        kind: one of :data:`KINDS`.
        fields: the kind's fields (JSON values: str, int, float, bool, None, list, dict).
        payload: the binary payload, plain (before sealing / after opening); empty for kinds
            that have none.
    """

    kind: str
    fields: dict[str, Any] = field(default_factory=dict)
    payload: bytes = b""


# ---------------------------------------------------------------------------------- schema
FieldType = Literal["string", "integer", "number", "boolean", "array", "object", "base64", "hex"]


@dataclass(frozen=True)
class Field:
    """One field of a message kind (or of a nested object, or an array's element).

    Attributes:
        name: the JSON key (ignored for an array's ``items``).
        type: JSON type: ``"string"``, ``"integer"`` (no fraction, not a boolean), ``"number"``
            (integer or float, finite), ``"boolean"``, ``"array"``, ``"object"``, ``"base64"``
            (a string, standard base64 with padding, RFC 4648 section 4) or ``"hex"`` (a string
            of lowercase hexadecimal digits).
        doc: what it means, with units.
        required: False: it may be absent.
        nullable: True: it may be JSON ``null``.
        items: an array's element.
        fields: an object's known keys (None: any object); other keys are allowed and ignored.
        minimum: an integer's or number's smallest value.
        maximum: an integer's or number's largest value (a documented limit, section Limits).
        exclusive: the minimum itself is not allowed (``> minimum``).
        length: an array's length, or the byte length of a base64/hex value, when fixed.
    """

    name: str
    type: FieldType
    doc: str
    required: bool = True
    nullable: bool = False
    items: Field | None = None
    fields: tuple[Field, ...] | None = None
    minimum: float | None = None
    length: int | None = None
    maximum: float | None = None
    exclusive: bool = False


@dataclass(frozen=True)
class KindSpec:
    """A message kind: who sends it, its fields, its payload.

    Attributes:
        kind: its name (the header's ``kind``).
        sender: ``"client"``, ``"server"`` or ``"both"``.
        doc: what it does.
        fields: its header fields.
        payload: what the payload holds, or None when it has none (it must then be empty).
        sealed: whether it travels sealed (False only for the three handshake kinds).
    """

    kind: str
    sender: Literal["client", "server", "both"]
    doc: str
    fields: tuple[Field, ...] = ()
    payload: str | None = None
    sealed: bool = True


def _f(name: str, type: FieldType, doc: str, **kw: Any) -> Field:
    return Field(name, type, doc, **kw)


#: Largest image side of any camera object, pixels (a gi_request's camera has a server limit
#: below it: ``scene_info.limits.max_request_side``).
MAX_IMAGE_SIDE = 32768
#: Largest magnitude of a velocity component of a gi_request (scene units/s or rad/s): beyond
#: it no reference camera can be predicted (docs/protocol.md, section Limits).
MAX_VELOCITY = 1e6

_NAT = {"minimum": 0}
_VEC3 = {"items": Field("", "number", ""), "length": 3}
_VELOCITY = {
    "items": Field("", "number", "", minimum=-MAX_VELOCITY, maximum=MAX_VELOCITY),
    "length": 3,
}
_SIDE = {"minimum": 1, "maximum": MAX_IMAGE_SIDE}
_CAMERA_FIELDS = (
    _f("height", "integer", "image height, pixels", **_SIDE),
    _f("width", "integer", "image width, pixels", **_SIDE),
    _f("fx", "number", "focal length along x, pixels", minimum=0, exclusive=True),
    _f("fy", "number", "focal length along y, pixels", minimum=0, exclusive=True),
    _f("cx", "number", "principal point x, continuous pixel coordinates"),
    _f("cy", "number", "principal point y, continuous pixel coordinates"),
    _f(
        "world_from_cam",
        "array",
        "4x4 rigid transform, camera to world, row-major: 4 rows of 4 numbers",
        items=Field("", "array", "", items=Field("", "number", ""), length=4),
        length=4,
    ),
)
_REQUEST_FIELDS = (
    _f("camera", "object", "the client's camera when it sent the request", fields=_CAMERA_FIELDS),
    _f(
        "velocity_t",
        "array",
        "translation velocity in the camera frame, scene units/s",
        **_VELOCITY,
    ),
    _f("velocity_r", "array", "angular velocity (pitch, yaw, roll rates), rad/s", **_VELOCITY),
    _f("time_s", "number", "the client's clock when it sent the request, s"),
    _f("seq", "integer", "the request's sequence number (seeds the server's render)", **_NAT),
    _f(
        "depth_range",
        "array",
        "(near, far) view depths the client sees, scene units, or null",
        nullable=True,
        items=Field("", "number", ""),
        length=2,
    ),
)
_PART_FIELDS = (
    _f(
        "name",
        "string",
        '"gi" ([H, W, 3] linear radiance), "depth" ([H, W] or [H, W, 1] view-space z) or "mask" '
        "([H, W] or [H, W, 1], 1 where the reference camera sees geometry)",
    ),
    _f("codec", "string", "codec of this part (section Codecs)"),
    _f("shape", "array", "array shape, e.g. [H, W, 3]", items=Field("", "integer", "", minimum=1)),
    _f("dtype", "string", 'element type after decoding: "float32"'),
    _f("bytes", "integer", "encoded size of this part in the payload, bytes", **_NAT),
)
_LEVEL_FIELDS = (
    _f("level", "integer", "LPM level, 0 = coarsest", **_NAT),
    _f("triangles", "integer", "triangles in this level", **_NAT),
    _f("bytes", "integer", "total plain bytes of this level's chunks", **_NAT),
    _f("chunks", "integer", "number of lpm_chunk messages of this level", **_NAT),
)
_B64_KEY = {"length": 32}
_LIMIT_FIELDS = (
    _f(
        "max_message_bytes",
        "integer",
        "largest message the server accepts (more: closed with 1009)",
        minimum=1,
    ),
    _f(
        "max_request_side",
        "integer",
        "largest height or width of a gi_request's camera (more: error bad_field)",
        minimum=1,
    ),
    _f(
        "max_render_side",
        "integer",
        "largest side of a rendered reference: a wider prefetch camera is scaled down to it "
        "(same field of view), and gi_reply.camera states the size rendered",
        minimum=1,
    ),
    _f("spp", "integer", "path-tracing samples per pixel of every render", minimum=1),
    _f(
        "max_queued_renders",
        "integer",
        "cache misses the server queues for its render workers, all clients together "
        "(more: error busy)",
        minimum=1,
    ),
)

_MODEL_FIELDS = (
    _f("kind", "string", '"gan" (image in, image out) or "radiance" (per surface point)'),
    _f("format", "string", 'file format of the model: "onnx"'),
    _f("sha256", "hex", "SHA-256 of the whole model file", length=32),
    _f("bytes", "integer", "size of the model file, bytes", **_NAT),
    _f("chunks", "integer", "number of generator_chunk messages of the file", minimum=1),
    _f(
        "inputs",
        "array",
        "the client buffers the model reads, in input order (section Client models)",
        items=Field("", "string", ""),
    ),
    _f(
        "demodulated",
        "boolean",
        "true: the model's GI is divided by the albedo, the client multiplies by its albedo",
    ),
    _f(
        "size_multiple",
        "integer",
        "image height and width the model takes are multiples of this (pad by edge "
        "replication, crop back)",
        minimum=1,
    ),
    _f(
        "encoding",
        "object",
        "how the gan model's inputs are normalised and its output decoded (section Client "
        "models); null for radiance",
        nullable=True,
        fields=(
            _f(
                "hdr",
                "object",
                "the HDR curve of dl and of the output",
                fields=(
                    _f(
                        "scale",
                        "number",
                        "radiance where the curve turns logarithmic",
                        minimum=0,
                        exclusive=True,
                    ),  # fmt: skip
                    _f(
                        "max_value",
                        "number",
                        "largest radiance represented",
                        minimum=0,
                        exclusive=True,
                    ),  # fmt: skip
                ),
            ),
            _f("depth_max", "number", "view depth mapped to +1", minimum=0, exclusive=True),
            _f("position_center", "array", "world point mapped to 0", **_VEC3),
            _f(
                "position_half_extent",
                "number",
                "world distance mapped to 1",
                minimum=0,
                exclusive=True,
            ),
        ),
    ),
    _f(
        "test_ssim",
        "number",
        "the recorded test SSIM it was chosen by (section Client models), or null",
        nullable=True,
        required=False,
    ),
)

#: Every message kind, by name.
KINDS: dict[str, KindSpec] = {
    s.kind: s
    for s in (
        KindSpec(
            "hello",
            "client",
            "opens the handshake (first message of the client)",
            (
                _f("client", "string", "client software name and version, free text"),
                _f("pub", "base64", "client's ephemeral X25519 public key, 32 bytes", **_B64_KEY),
                _f("nonce", "base64", "32 random bytes", **_B64_KEY),
                _f(
                    "codecs",
                    "array",
                    "GI/depth codecs the client can decode, by preference",
                    items=Field("", "string", ""),
                ),
            ),
            sealed=False,
        ),
        KindSpec(
            "welcome",
            "server",
            "answers hello (second message of the handshake)",
            (
                _f("session", "string", "session id chosen by the server (1-64 ASCII chars)"),
                _f("pub", "base64", "server's ephemeral X25519 public key, 32 bytes", **_B64_KEY),
                _f("nonce", "base64", "32 random bytes", **_B64_KEY),
                _f("server", "string", "server software name and version, free text"),
            ),
            sealed=False,
        ),
        KindSpec(
            "auth",
            "client",
            "proves the client holds the token (third and last handshake message)",
            (
                _f(
                    "mac",
                    "base64",
                    "HMAC-SHA256(auth_key, transcript), 32 bytes (auth_key: section 4.2)",
                    **_B64_KEY,
                ),
            ),
            sealed=False,
        ),
        KindSpec(
            "scene_info",
            "server",
            "describes the scene after a successful auth (first sealed message)",
            (
                _f("name", "string", "scene name"),
                _f(
                    "bounds",
                    "array",
                    "axis-aligned bounds [[xmin,ymin,zmin],[xmax,ymax,zmax]], scene units",
                    items=Field("", "array", "", **_VEC3),
                    length=2,
                ),
                _f(
                    "lights",
                    "array",
                    "light sources, one object each: kind (directional, point, spot or area) "
                    "and that light's parameters (section Scene)",
                    items=Field("", "object", ""),
                ),
                _f(
                    "camera",
                    "object",
                    "default camera of the scene (camera object, section Camera)",
                    fields=_CAMERA_FIELDS,
                ),
                _f(
                    "lpm",
                    "object",
                    "the LPM levels the server can stream",
                    fields=(
                        _f(
                            "levels",
                            "array",
                            "one entry per level, coarsest first",
                            items=Field("", "object", "", fields=_LEVEL_FIELDS),
                        ),
                    ),
                ),
                _f(
                    "generator",
                    "object",
                    "the client model on offer (a GAN generator or a world-space radiance "
                    "model, as ONNX; section Client models), or null",
                    nullable=True,
                    fields=_MODEL_FIELDS,
                ),
                _f(
                    "codecs",
                    "array",
                    "GI/depth codecs the server can encode",
                    items=Field("", "string", ""),
                ),
                _f(
                    "sky",
                    "object",
                    "the sky (section Scene), or null",
                    required=False,
                    nullable=True,
                ),
                _f(
                    "up",
                    "array",
                    "the scene's up direction, a unit 3-vector",
                    required=False,
                    **_VEC3,
                ),
                _f(
                    "default_camera",
                    "object",
                    "the scene's own default camera, or null",
                    required=False,
                    nullable=True,
                    fields=_CAMERA_FIELDS,
                ),
                _f(
                    "max_pending",
                    "integer",
                    "most gi_requests a client may have unanswered (more: error busy)",
                    required=False,
                    minimum=1,
                ),
                _f(
                    "limits",
                    "object",
                    "the server's limits (section Limits)",
                    required=False,
                    fields=_LIMIT_FIELDS,
                ),
            ),
            payload='UTF-8 JSON object {"paths": {name: path}}: the named camera paths '
            "(section Scene; in the payload, not the header: a path of a few hundred poses is "
            "larger than the header limit), or empty",
        ),
        KindSpec(
            "lpm_request",
            "client",
            "asks for the LPM levels min_level..max_level, streamed coarse to fine",
            (
                _f("max_level", "integer", "finest level wanted (inclusive)", **_NAT),
                _f(
                    "min_level",
                    "integer",
                    "coarsest level wanted (inclusive; default 0): e.g. the finest level alone",
                    required=False,
                    **_NAT,
                ),
            ),
        ),
        KindSpec(
            "lpm_chunk",
            "server",
            "one piece of one file of an LPM level",
            (
                _f("level", "integer", "LPM level", **_NAT),
                _f("index", "integer", "index of this chunk within its level, from 0", **_NAT),
                _f("count", "integer", "number of chunks of the level", minimum=1),
                _f(
                    "part",
                    "string",
                    'what the file is: "materials", "geometry" or "texture" (docs/lpm.md)',
                ),
                _f(
                    "name",
                    "string",
                    "file name within the level (chunks of one name, in index "
                    "order, concatenate to the file)",
                ),
                _f("sha256", "hex", "SHA-256 of this chunk's plain payload", length=32),
            ),
            payload="the chunk's bytes",
        ),
        KindSpec(
            "lpm_done",
            "server",
            "all chunks of a level were sent",
            (_f("level", "integer", "LPM level", **_NAT),),
        ),
        KindSpec(
            "gi_request",
            "client",
            "asks for a GI map for the client's camera and motion",
            (
                _f(
                    "id",
                    "integer",
                    "request id, unique per connection, echoed in the reply",
                    **_NAT,
                ),
                _f(
                    "request",
                    "object",
                    "the client's camera and motion (section GI request)",
                    fields=_REQUEST_FIELDS,
                ),
                _f("codec", "string", "codec wanted for the GI part"),
                _f(
                    "depth_codec",
                    "string",
                    "codec wanted for the depth and mask parts, one that carries depth "
                    "(section Codecs; default: the server's choice)",
                    required=False,
                ),
            ),
        ),
        KindSpec(
            "gi_reply",
            "server",
            "the reference GI map and depth for a gi_request",
            (
                _f("id", "integer", "id of the gi_request answered", **_NAT),
                _f(
                    "camera",
                    "object",
                    "reference camera the maps were rendered for",
                    fields=_CAMERA_FIELDS,
                ),
                _f("cache_hit", "boolean", "true: found in the server's store, no render"),
                _f(
                    "coalesced",
                    "boolean",
                    "true: answered by a render or lookup shared with "
                    "identical concurrent requests",
                    required=False,
                ),
                _f(
                    "stale",
                    "boolean",
                    "true: the reference was rendered under another state of an animated scene "
                    "that the change since may alter (docs/dynamic.md): show it marked as stale; "
                    "absent: false",
                    required=False,
                ),
                _f(
                    "state",
                    "string",
                    'id of the scene state the reference was rendered under ("static": a '
                    "static scene); references of different states are not combined",
                    required=False,
                ),
                _f(
                    "spp",
                    "integer",
                    "path-tracing samples per pixel of the GI map (0: unknown); a first render "
                    "after a change has fewer than the server's and is refined",
                    required=False,
                    **_NAT,
                ),
                _f(
                    "refining",
                    "boolean",
                    "true: a better reference for this view is being rendered (fresh after a "
                    "stale one, all samples after a cheap one): a later gi_request for the "
                    "view gets it (section Scene states); absent: false",
                    required=False,
                ),
                _f(
                    "timings_ms",
                    "object",
                    "server-side time per stage, ms (e.g. lookup, render, encode)",
                ),
                _f(
                    "parts",
                    "array",
                    "the encoded arrays, in payload order",
                    items=Field("", "object", "", fields=_PART_FIELDS),
                ),
            ),
            payload="the parts' encoded bytes, concatenated in the order of parts",
        ),
        KindSpec(
            "generator_request",
            "client",
            "asks for the client model on offer: every chunk, or the one chunk index",
            (
                _f(
                    "index",
                    "integer",
                    "only this chunk (0 .. scene_info.generator.chunks - 1), e.g. to fetch one "
                    "again; absent: every chunk",
                    required=False,
                    **_NAT,
                ),
            ),
        ),
        KindSpec(
            "generator_chunk",
            "server",
            "one piece of the client model's file",
            (
                _f("index", "integer", "index of this chunk, from 0", **_NAT),
                _f("count", "integer", "number of chunks", minimum=1),
                _f("sha256", "hex", "SHA-256 of this chunk's plain payload", length=32),
            ),
            payload="the chunk's bytes",
        ),
        KindSpec(
            "error",
            "both",
            "reports a failure; the sender may close the connection after it",
            (
                _f("code", "string", "one of the error codes (section Errors)"),
                _f("message", "string", "human-readable explanation"),
                _f("ref", "integer", "id of the request concerned, or null", nullable=True),
            ),
        ),
        KindSpec("bye", "both", "the sender closes the session cleanly"),
    )
}

#: The kinds exchanged before the session keys exist (never sealed).
HANDSHAKE_KINDS = frozenset(k for k, s in KINDS.items() if not s.sealed)


def _type_text(f: Field) -> str:
    t = f.type
    if t == "array":
        inner = _type_text(f.items) if f.items is not None else "any"
        t = f"array[{f.length}] of {inner}" if f.length is not None else f"array of {inner}"
    elif t in ("base64", "hex") and f.length is not None:
        t = f"{t} ({f.length} bytes)"
    elif t in ("integer", "number") and f.minimum is not None:
        op = ">" if f.exclusive else ">="
        t = f"{t} {op} {f.minimum:g}"
        if f.maximum is not None:
            t = f"{f.type} in [{f.minimum:g}, {f.maximum:g}]"
    return t + (" or null" if f.nullable else "")


def _field_rows(fields: tuple[Field, ...], prefix: str) -> list[str]:
    rows = []
    for f in fields:
        name = prefix + f.name
        req = "yes" if f.required else "no"
        rows.append(f"| `{name}` | {_type_text(f)} | {req} | {f.doc} |")
        sub = f.fields if f.type == "object" else None
        if f.type == "array" and f.items is not None and f.items.fields is not None:
            sub, name = f.items.fields, name + "[]"
        if sub is not None and sub is not _CAMERA_FIELDS and sub is not _REQUEST_FIELDS:
            rows += _field_rows(sub, name + ".")
    return rows


def schema_markdown() -> str:
    """The message kinds as Markdown (the generated block of docs/protocol.md).

    Every kind gets a ``### `kind` `` section: sender, whether it is sealed, what it does, a
    table of its fields (nested objects flattened as ``a.b`` / ``a[].b``), its payload.
    """
    out = []
    for spec in KINDS.values():
        sealed = "sealed" if spec.sealed else "plain (handshake)"
        if spec.kind == "error":
            sealed = "plain during the handshake, sealed after it"
        sender = "either side" if spec.sender == "both" else f"the {spec.sender}"
        out += [
            f"### `{spec.kind}`",
            "",
            f"Sent by {sender}; {sealed}. {spec.doc[0].upper()}{spec.doc[1:]}.",
            "",
        ]
        if spec.fields:
            out += ["| field | type | required | meaning |", "| --- | --- | --- | --- |"]
            out += _field_rows(spec.fields, "")
        else:
            out.append("No fields.")
        payload = spec.payload if spec.payload is not None else "none (must be empty)"
        out += ["", f"Payload: {payload}.", ""]
    out += ["### Nested objects", "", "Camera object (`camera`, `gi_reply.camera`, ...):", ""]
    out += ["| field | type | required | meaning |", "| --- | --- | --- | --- |"]
    out += _field_rows(_CAMERA_FIELDS, "")
    out += ["", "GI request object (`gi_request.request`):", ""]
    out += ["| field | type | required | meaning |", "| --- | --- | --- | --- |"]
    out += _field_rows(_REQUEST_FIELDS, "")
    out += ["", "### Error codes", "", "| code | meaning |", "| --- | --- |"]
    out += [f"| `{c}` | {m} |" for c, m in ERROR_CODES.items()]
    return "\n".join(out) + "\n"


def _type_ok(value: Any, f: Field) -> bool:
    t = f.type
    if t in ("string", "base64", "hex"):
        return isinstance(value, str)
    if t == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if t == "number":
        return (
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        )
    if t == "boolean":
        return isinstance(value, bool)
    if t == "array":
        return isinstance(value, list)
    if t == "object":
        return isinstance(value, dict)
    raise AssertionError(f"unknown field type {t!r}")  # pragma: no cover


def _check_value(value: Any, f: Field, where: str, ref: int | None) -> None:
    def bad(why: str) -> ProtocolError:
        return ProtocolError("bad_field", f"{where}: {why}", ref)

    if value is None:
        if f.nullable:
            return
        raise bad(f"must be {f.type}, got null")
    if not _type_ok(value, f):
        shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:40] + "..."
        raise bad(
            f"must be {'a finite ' if f.type == 'number' else ''}{f.type}, got "
            f"{type(value).__name__} {shown}"
        )
    if f.type == "integer" and abs(value) > MAX_SAFE_INTEGER:
        raise bad(f"must be within +-(2^53 - 1) (a JavaScript-safe integer), got {value}")
    if f.minimum is not None and (value <= f.minimum if f.exclusive else value < f.minimum):
        raise bad(f"must be {'>' if f.exclusive else '>='} {f.minimum:g}, got {value}")
    if f.maximum is not None and value > f.maximum:
        raise bad(f"must be <= {f.maximum:g} (section Limits), got {value:g}")
    if f.type == "base64":
        try:
            raw = base64.b64decode(value.encode("ascii"), validate=True)
        except (binascii.Error, UnicodeEncodeError, ValueError):
            raise bad("is not valid base64 (RFC 4648, with padding)") from None
        if f.length is not None and len(raw) != f.length:
            raise bad(f"must decode to {f.length} bytes, got {len(raw)}")
    elif f.type == "hex":
        if any(c not in "0123456789abcdef" for c in value) or len(value) % 2:
            raise bad("must be lowercase hexadecimal")
        if f.length is not None and len(value) != 2 * f.length:
            raise bad(f"must be {2 * f.length} hex digits, got {len(value)}")
    elif f.type == "array":
        if f.length is not None and len(value) != f.length:
            raise bad(f"must have {f.length} elements, got {len(value)}")
        if f.items is not None:
            for i, v in enumerate(value):
                _check_value(v, f.items, f"{where}[{i}]", ref)
    elif f.type == "object" and f.fields is not None:
        _check_object(value, f.fields, where, ref)


def _check_object(obj: dict[str, Any], fields: tuple[Field, ...], where: str, ref: int | None):
    for f in fields:
        if f.name not in obj:
            if f.required:
                raise ProtocolError("bad_field", f"{where}.{f.name}: missing", ref)
            continue
        _check_value(obj[f.name], f, f"{where}.{f.name}", ref)


def validate(msg: Message) -> None:
    """Check a message against its kind's schema (:data:`KINDS`).

    Fields not in the schema are allowed (a newer peer may add optional ones) and kept.

    Raises:
        ProtocolError: ``"unknown_kind"`` or ``"bad_field"`` (the message names kind and field).
    """
    spec = KINDS.get(msg.kind)
    if spec is None:
        raise ProtocolError(
            "unknown_kind", f"unknown message kind {msg.kind!r}; known: {sorted(KINDS)}"
        )
    ref = _ref_of(msg.fields)
    if not isinstance(msg.fields, dict):
        raise ProtocolError("bad_field", f"{msg.kind}: fields must be a dict", ref)
    for k in RESERVED_KEYS:
        if k in msg.fields:
            raise ProtocolError("bad_field", f"{msg.kind}.{k}: reserved header key", ref)
    _check_object(msg.fields, spec.fields, msg.kind, ref)
    if not isinstance(msg.payload, (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_field", f"{msg.kind}.payload: must be bytes", ref)
    if spec.payload is None and len(msg.payload):
        raise ProtocolError(
            "bad_field",
            f"{msg.kind}.payload: this kind has no payload, got {len(msg.payload)} bytes",
            ref,
        )
    if msg.kind in ("lpm_chunk", "generator_chunk"):
        f = msg.fields
        if f["index"] >= f["count"]:
            raise ProtocolError(
                "bad_field", f"{msg.kind}.index: {f['index']} is not below count {f['count']}", ref
            )
        digest = hashlib.sha256(msg.payload).hexdigest()
        if digest != f["sha256"]:
            raise ProtocolError(
                "bad_field",
                f"{msg.kind}.sha256: does not match the payload (payload hashes to {digest})",
                ref,
            )
    if msg.kind == "gi_reply":
        total = sum(p["bytes"] for p in msg.fields["parts"])
        if total != len(msg.payload):
            raise ProtocolError(
                "bad_field",
                f"gi_reply.parts: the parts' bytes add up to {total} "
                f"but the payload has {len(msg.payload)}",
                ref,
            )
    if msg.kind == "error" and msg.fields["code"] not in ERROR_CODES:
        raise ProtocolError(
            "bad_field",
            f"error.code: {msg.fields['code']!r} is not one of {sorted(ERROR_CODES)}",
            ref,
        )


def _ref_of(fields: Any) -> int | None:
    # only an id the reply can carry (an error about an id out of range says ref: null)
    return safe_ref(fields.get("id")) if isinstance(fields, dict) else None


# ---------------------------------------------------------------------------------- framing
def _header_bytes(header: dict[str, Any], kind: str) -> bytes:
    try:
        text = json.dumps(header, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
        return text.encode("utf-8")
    except (TypeError, ValueError) as e:  # UnicodeEncodeError (lone surrogate) is a ValueError
        raise ProtocolError(
            "bad_field", f"{kind}: fields are not JSON-serialisable ({e})", _ref_of(header)
        ) from None


def encode(
    msg: Message, channel: Channel | None = None, *, max_bytes: int = DEFAULT_MAX_MESSAGE
) -> bytes:
    """Encode a message into one WebSocket binary message.

    Args:
        msg: the message (validated against :data:`KINDS` first).
        channel: the session's channel once the handshake is done: the payload is sealed (the
            header gains ``ctr`` and is the associated data). None: plain (handshake kinds).
        max_bytes: limit on the whole frame.

    Returns:
        ``u32 BE header length | header JSON (UTF-8) | payload``.

    Raises:
        ProtocolError: ``"unknown_kind"`` / ``"bad_field"`` (invalid message) or
            ``"too_large"`` (header over :data:`MAX_HEADER` or frame over ``max_bytes``).
    """
    validate(msg)
    header: dict[str, Any] = {"v": PROTOCOL_VERSION, "kind": msg.kind, **msg.fields}
    payload = bytes(msg.payload)
    if channel is not None:
        with channel.lock:  # the counter in the header is the one seal() uses
            header["ctr"] = channel.next_counter
            hb = _header_bytes(header, msg.kind)
            _check_header_size(len(hb), msg.kind)
            ctr, payload = channel.seal(payload, hb)
        if ctr != header["ctr"]:  # pragma: no cover - Channel contract
            raise ProtocolError("internal", "channel counter moved while sealing")
    else:
        hb = _header_bytes(header, msg.kind)
        _check_header_size(len(hb), msg.kind)
    total = 4 + len(hb) + len(payload)
    if total > max_bytes:
        raise ProtocolError(
            "too_large",
            f"{msg.kind}: message of {total} bytes is over the limit of {max_bytes} bytes",
            _ref_of(msg.fields),
        )
    return struct.pack(">I", len(hb)) + hb + payload


def _check_header_size(n: int, kind: str) -> None:
    if n > MAX_HEADER:
        raise ProtocolError(
            "too_large", f"{kind}: header of {n} bytes is over the limit of {MAX_HEADER} bytes"
        )


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


def _no_constants(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def decode(
    data: bytes, channel: Channel | None = None, *, max_bytes: int = DEFAULT_MAX_MESSAGE
) -> Message:
    """Decode and check one WebSocket binary message.

    Args:
        data: the message's bytes.
        channel: the session's channel after the handshake (the message must be sealed; it is
            opened); None before it (the message must be plain). Which kinds may come when is
            the session's business (:attr:`KindSpec.sealed`), not the codec's.
        max_bytes: limit on the whole frame.

    Returns:
        The message, with its plain payload; ``fields`` has neither ``v``, ``kind`` nor ``ctr``.

    Raises:
        ProtocolError: ``"too_large"``, ``"malformed"``, ``"version"``, ``"unknown_kind"``,
            ``"bad_field"``, ``"crypto"`` (tampered, or sealed/plain where it must not be) or
            ``"replay"`` (see :data:`ERROR_CODES`).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("malformed", f"a message must be binary, got {type(data).__name__}")
    data = bytes(data)
    if len(data) > max_bytes:
        raise ProtocolError(
            "too_large", f"message of {len(data)} bytes is over the limit of {max_bytes} bytes"
        )
    if len(data) < 4:
        raise ProtocolError(
            "malformed", f"message of {len(data)} bytes is shorter than its 4-byte header length"
        )
    (n,) = struct.unpack_from(">I", data, 0)
    if n > MAX_HEADER:
        raise ProtocolError("too_large", f"header length {n} is over the limit of {MAX_HEADER}")
    if 4 + n > len(data):
        raise ProtocolError(
            "malformed", f"header length {n} runs past the end of the {len(data)}-byte message"
        )
    hb = data[4 : 4 + n]
    payload = data[4 + n :]
    try:
        header = json.loads(
            hb.decode("utf-8"), object_pairs_hook=_no_duplicates, parse_constant=_no_constants
        )
    except (UnicodeDecodeError, ValueError) as e:
        raise ProtocolError("malformed", f"header is not UTF-8 JSON: {e}") from None
    if not isinstance(header, dict):
        raise ProtocolError(
            "malformed", f"header must be a JSON object, got {type(header).__name__}"
        )
    ref = _ref_of(header)
    v = header.pop("v", None)
    kind = header.pop("kind", None)
    if v is None or kind is None:
        raise ProtocolError("malformed", "header has no 'v' or no 'kind'", ref)
    if v != PROTOCOL_VERSION or isinstance(v, bool):
        raise ProtocolError(
            "version",
            f"protocol version {v!r} is not supported; this peer speaks version {PROTOCOL_VERSION}",
            ref,
        )
    if not isinstance(kind, str) or kind not in KINDS:
        raise ProtocolError(
            "unknown_kind", f"unknown message kind {kind!r}; known: {sorted(KINDS)}", ref
        )
    ctr = header.pop("ctr", None)
    if channel is None:
        if ctr is not None:
            raise ProtocolError(
                "crypto",
                f"{kind} is sealed but no session keys exist yet (handshake not finished)",
                ref,
            )
    else:
        if ctr is None:
            raise ProtocolError(
                "crypto", f"{kind} is not sealed (no 'ctr') after the handshake", ref
            )
        if not isinstance(ctr, int) or isinstance(ctr, bool) or not 0 <= ctr <= MAX_SAFE_INTEGER:
            raise ProtocolError(
                "crypto", f"{kind}.ctr must be an integer in [0, 2^53 - 1], got {ctr!r}", ref
            )
        payload = channel.open(ctr, payload, hb)
    msg = Message(kind, header, payload)
    validate(msg)
    return msg


def error_message(err: ProtocolError) -> Message:
    """The ``error`` message that reports ``err`` to the peer."""
    return Message("error", {"code": err.code, "message": err.message, "ref": err.ref})


def raise_for_error(msg: Message) -> Message:
    """Raise the peer's ``error`` message as a :class:`ProtocolError`; other messages pass.

    Raises:
        ProtocolError: with the peer's code, message and ref.
    """
    if msg.kind == "error":
        raise ProtocolError(msg.fields["code"], msg.fields["message"], msg.fields["ref"])
    return msg


# ---------------------------------------------------------------------------------- helpers
def camera_to_json(cam: Camera) -> dict[str, Any]:
    """A camera as the protocol's camera object (exact: floats keep every bit through JSON); a
    thin lens or an orthographic camera as its :meth:`~icbtool.camera.Camera.pinhole`.

    Returns:
        ``{height, width, fx, fy, cx, cy, world_from_cam}``: OpenCV axes (+x right, +y down,
        +z forward), pixel centres at half-integers, ``world_from_cam`` 4x4 row-major.
    """
    cam = cam.pinhole()
    d = cam.to_dict()
    return {
        "height": int(d["height"]),
        "width": int(d["width"]),
        "fx": float(d["fx"]),
        "fy": float(d["fy"]),
        "cx": float(d["cx"]),
        "cy": float(d["cy"]),
        "world_from_cam": [[float(x) for x in row] for row in cam.world_from_cam],
    }


def camera_from_json(d: Any, where: str = "camera") -> Camera:
    """Inverse of :func:`camera_to_json`.

    Raises:
        ProtocolError: ``"bad_field"`` naming ``where`` and the field: missing or extra keys,
            wrong types, or a camera :class:`Camera` rejects (non-rigid pose, fx <= 0, ...).
    """
    if not isinstance(d, dict):
        raise ProtocolError("bad_field", f"{where}: must be an object, got {type(d).__name__}")
    _check_object(d, _CAMERA_FIELDS, where, None)
    extra = set(d) - {f.name for f in _CAMERA_FIELDS}
    if extra:
        raise ProtocolError("bad_field", f"{where}: unknown keys {sorted(extra)}")
    try:
        return Camera(
            d["height"],
            d["width"],
            d["fx"],
            d["fy"],
            d["cx"],
            d["cy"],
            np.array(d["world_from_cam"], dtype=np.float64),
        )
    except ValueError as e:
        raise ProtocolError("bad_field", f"{where}: {e}") from None


def request_to_json(req: GIRequest) -> dict[str, Any]:
    """A :class:`GIRequest` as the protocol's request object (exact)."""
    return {
        "camera": camera_to_json(req.camera),
        "velocity_t": [float(x) for x in req.velocity_t],
        "velocity_r": [float(x) for x in req.velocity_r],
        "time_s": float(req.time_s),
        "seq": int(req.seq),
        "depth_range": None if req.depth_range is None else [float(x) for x in req.depth_range],
    }


def request_from_json(d: Any, where: str = "request") -> GIRequest:
    """Inverse of :func:`request_to_json`.

    Raises:
        ProtocolError: ``"bad_field"`` naming ``where`` and the field.
    """
    if not isinstance(d, dict):
        raise ProtocolError("bad_field", f"{where}: must be an object, got {type(d).__name__}")
    _check_object(d, _REQUEST_FIELDS, where, None)
    extra = set(d) - {f.name for f in _REQUEST_FIELDS}
    if extra:
        raise ProtocolError("bad_field", f"{where}: unknown keys {sorted(extra)}")
    cam = camera_from_json(d["camera"], f"{where}.camera")
    dr = d.get("depth_range")
    try:
        return GIRequest(
            cam,
            np.array(d["velocity_t"], dtype=np.float64),
            np.array(d["velocity_r"], dtype=np.float64),
            time_s=float(d["time_s"]),
            seq=d["seq"],
            depth_range=None if dr is None else (float(dr[0]), float(dr[1])),
        )
    except ValueError as e:
        raise ProtocolError("bad_field", f"{where}: {e}") from None


DOC_BEGIN = "<!-- BEGIN GENERATED: icbtool.net.protocol.schema_markdown() -->"
DOC_END = "<!-- END GENERATED -->"


def update_doc(path: str) -> bool:
    """Rewrite the generated block of docs/protocol.md from :data:`KINDS`; True if it changed.

    ``python -m icbtool.net docs/protocol.md`` runs it.
    """
    from pathlib import Path

    p = Path(path)
    text = p.read_text()
    head, rest = text.split(DOC_BEGIN, 1)
    _, tail = rest.split(DOC_END, 1)
    new = f"{head}{DOC_BEGIN}\n\n{schema_markdown()}\n{DOC_END}{tail}"
    if new != text:
        p.write_text(new)
    return new != text


__all__ = [
    "DEFAULT_MAX_MESSAGE",
    "ERROR_CODES",
    "HANDSHAKE_KINDS",
    "KINDS",
    "MAX_HEADER",
    "MAX_IMAGE_SIDE",
    "MAX_SAFE_INTEGER",
    "MAX_VELOCITY",
    "PROTOCOL_VERSION",
    "Field",
    "KindSpec",
    "Message",
    "ProtocolError",
    "b64",
    "camera_from_json",
    "camera_to_json",
    "decode",
    "encode",
    "error_message",
    "raise_for_error",
    "request_from_json",
    "request_to_json",
    "schema_markdown",
    "unb64",
    "update_doc",
]
