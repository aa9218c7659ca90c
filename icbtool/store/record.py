"""The CRT-buffer record (docs/design.md section 2) and its lossless binary payload.

Payload format (version 2), one file per record::

    b"ICBP" | u32 format version | u32 header length | header (UTF-8 JSON) | body | trailer

The header lists every present buffer as ``["buffers"]: [name, dtype, shape, offset, nbytes,
codec]`` and, since version 2, describes the record itself under ``["record"]``: its id, its
:class:`RecordMeta`, its camera (:meth:`~icbtool.camera.Camera.to_dict`, floats written as their
shortest exact repr, so the round trip is bit-exact) and its scene's octree geometry. A payload is
therefore *self-describing*: the store's index can be rebuilt from the payloads alone
(:func:`icbtool.store.rebuild`). The trailer is the 32-byte BLAKE2b-256 digest of every byte
before it, so a payload proves its own integrity without the index (a truncated or overwritten
file fails it). Version 1 payloads (no record, no trailer) are still read; they cannot be used to
rebuild an index. The body is the concatenation of each buffer's encoded bytes.

Codec ``"shuffle-zlib"``: the float32 array's bytes are split into 4 byte planes (all first
bytes, all second bytes, ...) and deflated with zlib (level from
:class:`~icbtool.store.StoreConfig`). Byte shuffling groups the slowly varying exponent bytes
together, which roughly doubles zlib's ratio on images and makes it faster. Every buffer is
stored float32 **exactly** (GI included: the round trip is bit-exact); a mask whose values are all
0 or 1 is stored as uint8 (also exact). No float16 anywhere: normals, depth and positions feed the
warp's depth test and the GAN, whose inputs we do not want to quantise behind the user's back.
"""

from __future__ import annotations

import hashlib
import json
import struct
import time
import zlib
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from icbtool.buffers import BUFFERS, CHANNELS
from icbtool.camera import Camera

PAYLOAD_MAGIC = b"ICBP"
PAYLOAD_VERSION = 2
#: Payload versions this module reads.
PAYLOAD_VERSIONS = (1, 2)
TRAILER_BYTES = 32

#: Buffer name -> number of channels (:mod:`icbtool.buffers`). The order is the payload order.
BUFFER_CHANNELS: dict[str, int] = CHANNELS
BUFFER_NAMES: tuple[str, ...] = tuple(BUFFER_CHANNELS)


@dataclass(frozen=True)
class RecordMeta:
    """What a record is: where it came from and how it was made.

    Attributes:
        scene_name: the scene's name (for people; matching uses the hashes).
        scene_hash: :attr:`icbtool.scene.Scene.content_hash` of the rendered scene.
        light_hash: :attr:`icbtool.scene.Scene.light_hash` of the light setup it was rendered under.
        spp: path-tracing samples per pixel of the GI map (0 if unknown).
        render_time_s: seconds spent rendering the record (raster + trace).
        created: creation time (seconds since the epoch).
        tags: free-form JSON-able tags; bake sets ``{"path": <path name>, "index": <camera idx>}``.
        scene_bounds: optional (2, 3) scene bounds [min, max]; the store uses them to size the
            octree the first time it sees ``scene_hash`` (see :meth:`Store.register_scene`).
    """

    scene_name: str
    scene_hash: str
    light_hash: str
    spp: int = 0
    render_time_s: float = 0.0
    created: float = field(default_factory=time.time)
    tags: dict[str, Any] = field(default_factory=dict)
    scene_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

    def __post_init__(self) -> None:
        for k in ("scene_name", "scene_hash", "light_hash"):
            if not isinstance(getattr(self, k), str) or not getattr(self, k):
                raise ValueError(
                    f"RecordMeta.{k} must be a non-empty string, got {getattr(self, k)!r}"
                )
        if int(self.spp) != self.spp or self.spp < 0:
            raise ValueError(f"RecordMeta.spp must be an integer >= 0, got {self.spp!r}")
        object.__setattr__(self, "spp", int(self.spp))
        if not np.isfinite(self.render_time_s) or self.render_time_s < 0:
            raise ValueError(
                f"RecordMeta.render_time_s must be finite and >= 0, got {self.render_time_s}"
            )
        try:
            tags = json.loads(json.dumps(self.tags))
        except (TypeError, ValueError) as e:
            raise ValueError(f"RecordMeta.tags must be JSON-serialisable: {e}") from e
        if not isinstance(tags, dict):
            raise ValueError(f"RecordMeta.tags must be a dict, got {type(self.tags).__name__}")
        object.__setattr__(self, "tags", tags)
        if self.scene_bounds is not None:
            b = np.asarray(self.scene_bounds, dtype=np.float64)
            if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
                raise ValueError(
                    f"RecordMeta.scene_bounds must be finite (2, 3) [min, max], got {b}"
                )
            object.__setattr__(self, "scene_bounds", tuple(map(tuple, b.tolist())))

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RecordMeta:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"RecordMeta: unknown keys {sorted(unknown)}")
        return cls(**d)

    @classmethod
    def for_scene(cls, scene: Any, **kwargs: Any) -> RecordMeta:
        """Metadata for a record of ``scene`` (an :class:`icbtool.scene.Scene`)."""
        return cls(
            scene_name=scene.name,
            scene_hash=scene.content_hash,
            light_hash=scene.light_hash,
            scene_bounds=tuple(map(tuple, scene.bounds.tolist())),
            **kwargs,
        )


@dataclass(eq=False)
class CRTBuffer:
    """A cloud render texture buffer: the maps of one cloud camera (docs/design.md section 2).

    All present maps are (H, W, C) float32 with the camera's size; any map may be None (absent),
    and only present maps are stored.

    Attributes:
        camera: the camera that rendered the maps.
        meta: provenance (scene/light hashes, spp, time, tags).
        dl: (H, W, 3) direct lighting (with shadows).
        albedo: (H, W, 3) surface base colour.
        gi: (H, W, 3) global (indirect) illumination, path traced.
        normal_world: (H, W, 3) unit world-space normals.
        normal_view: (H, W, 3) unit view-space normals (OpenCV camera axes).
        depth: (H, W, 1) view-space z.
        position: (H, W, 3) world-space positions.
        mask: (H, W, 1) 1 where a surface was hit, 0 for background.
    """

    camera: Camera
    meta: RecordMeta
    dl: np.ndarray | None = None
    albedo: np.ndarray | None = None
    gi: np.ndarray | None = None
    normal_world: np.ndarray | None = None
    normal_view: np.ndarray | None = None
    depth: np.ndarray | None = None
    position: np.ndarray | None = None
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.camera, Camera):
            raise ValueError(f"CRTBuffer.camera must be an icbtool Camera, got {type(self.camera)}")
        if not isinstance(self.meta, RecordMeta):
            raise ValueError(f"CRTBuffer.meta must be a RecordMeta, got {type(self.meta)}")
        h, w = self.camera.height, self.camera.width
        for name, spec in BUFFERS.items():
            a = getattr(self, name)
            if a is not None:
                setattr(self, name, spec.check(a, h, w, "CRTBuffer"))

    @property
    def present(self) -> tuple[str, ...]:
        """Names of the maps that are not None, in payload order."""
        return tuple(n for n in BUFFER_NAMES if getattr(self, n) is not None)

    def buffers(self) -> dict[str, np.ndarray]:
        """The present maps by name."""
        return {n: getattr(self, n) for n in self.present}


# ---------------------------------------------------------------------------------- payload codec
def _shuffle(a: np.ndarray) -> bytes:
    b = a.view(np.uint8).reshape(-1, a.itemsize)
    return np.ascontiguousarray(b.T).tobytes()


def _unshuffle(raw: bytes, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    itemsize = dtype.itemsize
    n = int(np.prod(shape))
    b = np.frombuffer(raw, dtype=np.uint8)
    if b.size != n * itemsize:
        raise ValueError(f"buffer has {b.size} bytes, expected {n * itemsize}")
    return np.ascontiguousarray(b.reshape(itemsize, n).T).view(dtype).reshape(shape)


def _digest(data: bytes | memoryview) -> bytes:
    return hashlib.blake2b(data, digest_size=TRAILER_BYTES).digest()


def encode_payload(buf: CRTBuffer, level: int = 1, record: dict[str, Any] | None = None) -> bytes:
    """The payload bytes of a record's present maps (see the module docstring).

    Args:
        buf: the record.
        level: zlib level.
        record: what the header's ``"record"`` entry holds besides the meta and camera (the
            store adds ``id`` and ``scene``); the meta and camera are always written.
    """
    entries = []
    parts = []
    offset = 0
    for name, a in buf.buffers().items():
        if name == "mask" and np.all((a == 0.0) | (a == 1.0)) and not np.any(np.signbit(a)):
            arr, dtype = a.astype(np.uint8), "u1"
        else:
            arr, dtype = a, "<f4"
        data = zlib.compress(_shuffle(np.ascontiguousarray(arr)), level)
        entries.append([name, dtype, list(a.shape), offset, len(data), "shuffle-zlib"])
        parts.append(data)
        offset += len(data)
    rec = {**(record or {}), "meta": buf.meta.to_dict(), "camera": buf.camera.to_dict()}
    header = json.dumps({"buffers": entries, "record": rec}).encode()
    body = b"".join(
        [PAYLOAD_MAGIC, struct.pack("<II", PAYLOAD_VERSION, len(header)), header, *parts]
    )
    return body + _digest(body)


def payload_header(data: bytes, where: str = "payload", verify: bool = True) -> dict[str, Any]:
    """The parsed header of a payload (``{"version", "buffers", "record"?}``).

    Args:
        data: the payload file's bytes.
        where: names the payload in error messages.
        verify: check a version-2 payload's trailer digest (truncation, overwritten bytes).

    Raises:
        ValueError: naming ``where`` and the problem (bad magic, unsupported version,
            truncated, digest mismatch, unreadable header).
    """
    if len(data) < 12 or data[:4] != PAYLOAD_MAGIC:
        raise ValueError(f"{where}: not an icbtool payload (bad magic)")
    version, hlen = struct.unpack("<II", data[4:12])
    if version not in PAYLOAD_VERSIONS:
        raise ValueError(
            f"{where}: payload format {version} is not supported (this reads {PAYLOAD_VERSIONS})"
        )
    end = len(data)
    if version >= 2:
        end -= TRAILER_BYTES
        if end < 12 + hlen:
            raise ValueError(f"{where}: damaged payload: truncated ({len(data)} bytes)")
        if verify and _digest(memoryview(data)[:end]) != data[end:]:
            raise ValueError(
                f"{where}: damaged payload: digest mismatch (truncated or overwritten)"
            )
    try:
        header = json.loads(data[12 : 12 + hlen])
        if not isinstance(header, dict) or not isinstance(header.get("buffers"), list):
            raise ValueError("header has no buffer list")
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{where}: damaged payload: unreadable header ({e})") from e
    header["version"] = version
    header["_body"] = (12 + hlen, end)
    return header


def record_from_header(header: dict[str, Any], where: str = "payload") -> tuple[Camera, RecordMeta]:
    """The camera and metadata a version-2 payload header describes.

    Raises:
        ValueError: the payload is version 1 (no record in it) or its record entry is invalid.
    """
    rec = header.get("record")
    if rec is None:
        raise ValueError(
            f"{where}: format-{header.get('version')} payload carries no record metadata"
        )
    try:
        return Camera.from_dict(rec["camera"]), RecordMeta.from_dict(rec["meta"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where}: damaged payload: invalid record entry ({e})") from e


def decode_payload(
    data: bytes, where: str = "payload", verify: bool = True
) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_payload`: the maps by name, float32 (H, W, C).

    Args:
        data: the payload file's bytes.
        where: names the payload in error messages.
        verify: check a version-2 payload's trailer digest (the store skips it when the index's
            checksum of the whole file already matched).

    Raises:
        ValueError: naming ``where`` if the bytes are not a valid payload.
    """
    header = payload_header(data, where, verify)
    start, end = header["_body"]
    try:
        body = memoryview(data)[start:end]
        out: dict[str, np.ndarray] = {}
        for name, dtype, shape, offset, nbytes, codec in header["buffers"]:
            if name not in BUFFER_CHANNELS or codec != "shuffle-zlib":
                raise ValueError(f"unknown buffer {name!r} or codec {codec!r}")
            raw = zlib.decompress(body[offset : offset + nbytes])
            a = _unshuffle(raw, np.dtype(dtype), tuple(shape))
            out[name] = a.astype(np.float32, copy=False)
    except (ValueError, KeyError, TypeError, zlib.error) as e:
        raise ValueError(f"{where}: damaged payload: {e}") from e
    return out
