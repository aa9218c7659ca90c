"""HDR codecs for the arrays of a ``gi_reply``: GI maps and depth.

GI maps are (H, W, 3) float32 linear radiance (>= 0); depth is (H, W) or (H, W, 1) float32
view-space z, with 0 or +inf where there is no surface (which one a producer uses is kept
exactly by every depth codec). Every codec decodes to float32 of the shape given.

=====================  =====  =====  =====================================================
codec                  GI     depth  what it does (max relative error, normal range)
=====================  =====  =====  =====================================================
``f32-zstd``           yes    yes    float32 LE, byte-shuffled, zstd: exact
``f16-zstd``           yes    yes    float16 LE, byte-shuffled, zstd: 2^-11 = 4.9e-4;
                                     finite values saturate at +-65504; inf, 0, NaN exact
``f16-diff-zstd``      yes    yes    the float16 bit patterns of f16-zstd, 2-D differenced,
                                     zigzagged, byte-shuffled, zstd: same values as f16-zstd
``f16m7-diff-zstd``    yes    yes    as f16-diff-zstd after rounding the mantissa to 7 bits:
                                     2^-8 + 2^-11 = 4.4e-3; inf, 0 exact
``log-u16-png``        yes    yes    16-bit PNG of log2 codes: 2.1e-4 in [2^-20, 2^20];
                                     0 and +inf exact; negatives -> 0
``rgbe-png``           yes    no     Ward's RGBE in an 8-bit RGBA PNG: 2^-8 = 3.9e-3 of
                                     the pixel's largest channel; negatives -> 0
=====================  =====  =====  =====================================================

Byte shuffle (as in HDF5/Blosc): the array's bytes are regrouped by byte position, all first
bytes of the little-endian elements, then all second bytes, and so on, before compression; the
decoder undoes it. 2-D differences (the diff codecs): with ``u`` the uint16 codes in C order of
the (H, W[, C]) array and zeros outside it, ``r[i, j] = u[i, j] - u[i, j-1] - u[i-1, j] +
u[i-1, j-1]`` modulo 2^16 (the residual of the predictor left + up - up-left), stored as zigzag
``(s << 1) ^ (s >> 15)`` of its int16 value ``s``; the decoder takes cumulative sums over both
axes. zstd frames carry their content size. PNGs hold channels in R, G, B(, A)
order, as a PNG decoder returns them. Which codec is the default for GI and for depth was chosen
by ``python -m benchmarks.gi_codec`` (results in ``benchmarks/results/net/``):
:data:`DEFAULT_GI_CODEC`,
:data:`DEFAULT_DEPTH_CODEC`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from icbtool.net.errors import ProtocolError
from icbtool.optional import require

#: Largest array (elements) a part may decode to: 64 Mi elements (256 MiB of float32).
MAX_ELEMENTS = 64 * 2**20
#: Log range of ``log-u16-png``: codes 1..65534 cover log2 values in [LOG_MIN, LOG_MAX].
LOG_MIN, LOG_MAX = -20.0, 20.0
_F16_MAX = 65504.0
_ZSTD_LEVEL = 3
_PNG_LEVEL = 3


def _zstd() -> Any:
    return require("zstandard", "the GI codecs of the ICB protocol")


def _cv2() -> Any:
    import cv2

    return cv2


# ---------------------------------------------------------------------------------- helpers
def shuffle(raw: bytes, itemsize: int) -> bytes:
    """Regroup ``raw`` by byte position: all byte 0 of the items, then all byte 1, ..."""
    a = np.frombuffer(raw, np.uint8)
    return a.reshape(-1, itemsize).T.tobytes()


def unshuffle(raw: bytes, itemsize: int) -> bytes:
    """Inverse of :func:`shuffle`."""
    a = np.frombuffer(raw, np.uint8)
    return a.reshape(itemsize, -1).T.tobytes()


def _zstd_pack(raw: bytes, level: int) -> bytes:
    return _zstd().ZstdCompressor(level=level, write_content_size=True).compress(raw)


def _zstd_unpack(data: bytes, n: int, codec: str) -> bytes:
    zstd = _zstd()
    try:
        declared = zstd.frame_content_size(data)
    except zstd.ZstdError as e:
        raise ProtocolError("malformed", f"{codec}: not a zstd frame ({e})") from None
    if declared not in (-1, n):
        raise ProtocolError(
            "malformed", f"{codec}: the zstd frame holds {declared} bytes, the shape needs {n}"
        )
    try:
        raw = zstd.ZstdDecompressor().decompress(data, max_output_size=n)
    except zstd.ZstdError as e:
        raise ProtocolError("malformed", f"{codec}: corrupt zstd data ({e})") from None
    if len(raw) != n:
        raise ProtocolError("malformed", f"{codec}: decoded {len(raw)} bytes, the shape needs {n}")
    return raw


def _png_encode(img: np.ndarray, level: int) -> bytes:
    cv2 = _cv2()
    if img.ndim == 3 and img.shape[2] in (3, 4):  # cv2 writes BGR(A): store R, G, B(, A)
        img = img[..., [2, 1, 0, 3][: img.shape[2]]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, level])
    if not ok:  # pragma: no cover
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def _png_decode(data: bytes, shape: tuple[int, ...], dtype: Any, codec: str) -> np.ndarray:
    cv2 = _cv2()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ProtocolError("malformed", f"{codec}: not a PNG (bad signature)")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise ProtocolError("malformed", f"{codec}: corrupt PNG ({e})") from None
    if img is None:
        raise ProtocolError("malformed", f"{codec}: corrupt PNG")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[..., [2, 1, 0, 3][: img.shape[2]]]
    if img.dtype != dtype or img.shape != shape:
        raise ProtocolError(
            "malformed",
            f"{codec}: the PNG is {img.dtype} {img.shape}, expected {np.dtype(dtype)} {shape}",
        )
    return img


def _image_shape(shape: tuple[int, ...], channels: tuple[int, ...], codec: str) -> tuple:
    """(H, W) or (H, W, C) as a PNG holds it, for a part of ``shape``."""
    if len(shape) == 2 and 1 in channels:
        return shape
    if len(shape) == 3 and shape[2] in channels:
        return shape if shape[2] != 1 else shape[:2]
    raise ValueError(
        f"{codec} encodes (H, W) or (H, W, C) arrays with C in {list(channels)}, got shape {shape}"
    )


# ---------------------------------------------------------------------------------- codecs
def _f32_encode(a: np.ndarray, level: int) -> bytes:
    return _zstd_pack(shuffle(a.astype("<f4").tobytes(), 4), level)


def _f32_decode(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    n = math.prod(shape)
    raw = unshuffle(_zstd_unpack(data, 4 * n, "f32-zstd"), 4)
    return np.frombuffer(raw, "<f4").astype(np.float32).reshape(shape)


def _f16_encode(a: np.ndarray, level: int) -> bytes:
    return _zstd_pack(shuffle(_f16_bits(a).tobytes(), 2), level)


def _f16_decode(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    n = math.prod(shape)
    raw = unshuffle(_zstd_unpack(data, 2 * n, "f16-zstd"), 2)
    return np.frombuffer(raw, "<f2").astype(np.float32).reshape(shape)


def _f16_bits(a: np.ndarray) -> np.ndarray:
    """float16 bit patterns (uint16) of ``a``, finite values saturated at +-65504."""
    return np.where(np.isfinite(a), np.clip(a, -_F16_MAX, _F16_MAX), a).astype("<f2").view("<u2")


def _diff2(u: np.ndarray) -> np.ndarray:
    """2-D difference over the first two axes, modulo 2^16: ``x - left - up + up_left`` with
    zeros outside the array (the residual of the predictor left + up - up_left)."""
    z = np.uint16(0)
    return np.diff(np.diff(u, axis=0, prepend=z), axis=1, prepend=z)


def _undiff2(r: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_diff2`: cumulative sums over both axes, modulo 2^16."""
    return np.cumsum(np.cumsum(r, axis=0, dtype=np.uint16), axis=1, dtype=np.uint16)


def _zigzag(r: np.ndarray) -> np.ndarray:
    s = r.view(np.int16).astype(np.int32)
    return ((s << 1) ^ (s >> 15)).astype(np.uint16)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    return (z >> 1) ^ (np.uint16(0) - (z & np.uint16(1)))


def _diff_encoder(drop: int) -> Callable[[np.ndarray, int], bytes]:
    """float16 (mantissa rounded to ``10 - drop`` bits), 2-D differences, zigzag, shuffle, zstd."""

    def enc(a: np.ndarray, level: int) -> bytes:
        if a.ndim < 2:
            raise ValueError(f"the diff codecs encode arrays of 2 or more axes, got {a.shape}")
        u = _f16_bits(a)
        if drop:
            sign = u & np.uint16(0x8000)
            m = (u & np.uint16(0x7FFF)).astype(np.uint32)
            finite = m < 0x7C00
            m = np.where(m > 0x7C00, 0x7E00, m)  # any NaN -> the quiet NaN (keeps it a NaN)
            rounded = np.minimum((m + (1 << (drop - 1))) >> drop, 0x7BFF >> drop)
            u = sign | np.where(finite, rounded, m >> drop).astype(np.uint16)
        return _zstd_pack(shuffle(_zigzag(_diff2(u)).tobytes(), 2), level)

    return enc


def _diff_decoder(drop: int, name: str) -> Callable[[bytes, tuple[int, ...]], np.ndarray]:
    def dec(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
        if len(shape) < 2:
            raise ProtocolError(
                "bad_field", f"{name} decodes arrays of 2 or more axes, not {shape}"
            )
        raw = unshuffle(_zstd_unpack(data, 2 * math.prod(shape), name), 2)
        u = _undiff2(_unzigzag(np.frombuffer(raw, "<u2").reshape(shape)))
        if drop:
            u = (u & np.uint16(0x8000)) | ((u & np.uint16(0x7FFF)) << np.uint16(drop))
        return u.astype("<u2").view("<f2").astype(np.float32)

    return dec


def log_codes(a: np.ndarray) -> np.ndarray:
    """``log-u16-png`` codes: 0 for <= 0, 65535 for +inf, else 1 + round((log2 x - LOG_MIN) /
    (LOG_MAX - LOG_MIN) * 65533), clamped to [1, 65534].

    Raises:
        ValueError: NaN or -inf in ``a``.
    """
    if np.isnan(a).any() or np.isneginf(a).any():
        raise ValueError("log-u16-png cannot encode NaN or -inf")
    pos = a > 0
    lg = np.log2(np.where(pos, a, 1.0), dtype=np.float64)
    q = np.rint((lg - LOG_MIN) / (LOG_MAX - LOG_MIN) * 65533.0) + 1.0
    codes = np.clip(q, 1, 65534).astype(np.uint16)
    codes[~pos] = 0
    codes[np.isposinf(a)] = 65535
    return codes


def log_values(codes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`log_codes` (float32)."""
    c = codes.astype(np.float64)
    v = np.exp2((c - 1.0) / 65533.0 * (LOG_MAX - LOG_MIN) + LOG_MIN)
    v[codes == 0] = 0.0
    v[codes == 65535] = np.inf
    return v.astype(np.float32)


def _log_encode(a: np.ndarray, level: int) -> bytes:
    img_shape = _image_shape(a.shape, (1, 3, 4), "log-u16-png")
    return _png_encode(log_codes(a).reshape(img_shape), level)


def _log_decode(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    img_shape = _image_shape(shape, (1, 3, 4), "log-u16-png")
    return log_values(_png_decode(data, img_shape, np.uint16, "log-u16-png")).reshape(shape)


def rgbe_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float -> (H, W, 4) uint8 RGBE (Ward): negatives and values below 1e-32 -> 0.

    Raises:
        ValueError: non-finite values.
    """
    if not np.isfinite(rgb).all():
        raise ValueError("rgbe-png cannot encode NaN or inf")
    c = np.maximum(rgb.astype(np.float64), 0.0)
    m = c.max(axis=-1)
    mant, exp = np.frexp(m)  # m = mant * 2^exp, mant in [0.5, 1)
    ok = m > 1e-32
    scale = np.where(ok, mant * 256.0 / np.where(ok, m, 1.0), 0.0)
    out = np.zeros((*rgb.shape[:-1], 4), np.uint8)
    out[..., :3] = np.clip(np.floor(c * scale[..., None]), 0, 255).astype(np.uint8)
    out[..., 3] = np.where(ok, np.clip(exp + 128, 0, 255), 0).astype(np.uint8)
    return out


def rgb_from_rgbe(rgbe: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rgbe_from_rgb` (float32; pixel centres of the mantissa bins)."""
    e = rgbe[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((rgbe[..., :3].astype(np.float64) + 0.5) * f[..., None]).astype(np.float32)


def _rgbe_encode(a: np.ndarray, level: int) -> bytes:
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"rgbe-png encodes (H, W, 3) arrays, got shape {a.shape}")
    return _png_encode(rgbe_from_rgb(a), level)


def _rgbe_decode(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    if len(shape) != 3 or shape[2] != 3:
        raise ProtocolError("bad_field", f"rgbe-png decodes (H, W, 3) arrays, not {list(shape)}")
    return rgb_from_rgbe(_png_decode(data, (*shape[:2], 4), np.uint8, "rgbe-png"))


#: Half a code step of ``log-u16-png`` as a ratio, plus float32 rounding of the decoded value.
_LOG_REL_ERROR = 2.0 ** ((LOG_MAX - LOG_MIN) / 65533 / 2) - 1 + 2.0**-23


@dataclass(frozen=True)
class Codec:
    """One codec of :data:`CODECS`.

    Attributes:
        name: its wire name.
        doc: what it does.
        lossless: decodes to the exact input.
        for_depth: it keeps 0 and +inf exactly, so it may carry depth.
        max_rel_error: largest relative error on values in its normal range (0: exact).
        level: default compression level (zstd 1-22, PNG 0-9).
    """

    name: str
    doc: str
    lossless: bool
    for_depth: bool
    max_rel_error: float
    level: int
    _encode: Callable[[np.ndarray, int], bytes]
    _decode: Callable[[bytes, tuple[int, ...]], np.ndarray]


#: Every codec, by wire name.
CODECS: dict[str, Codec] = {
    c.name: c
    for c in (
        Codec("f32-zstd", "float32 LE, byte-shuffled, zstd", True, True, 0.0, _ZSTD_LEVEL,
              _f32_encode, _f32_decode),
        Codec("f16-zstd", "float16 LE, byte-shuffled, zstd", False, True, 2.0**-11, _ZSTD_LEVEL,
              _f16_encode, _f16_decode),
        Codec("f16-diff-zstd", "float16, 2-D differences, zigzag, byte-shuffled, zstd", False,
              True, 2.0**-11, _ZSTD_LEVEL, _diff_encoder(0), _diff_decoder(0, "f16-diff-zstd")),
        Codec("f16m7-diff-zstd", "float16 with 7 mantissa bits, then as f16-diff-zstd", False,
              True, 2.0**-8 + 2.0**-11, _ZSTD_LEVEL, _diff_encoder(3),
              _diff_decoder(3, "f16m7-diff-zstd")),
        Codec("log-u16-png", "16-bit PNG of log2 codes", False, True,
              _LOG_REL_ERROR, _PNG_LEVEL, _log_encode, _log_decode),
        Codec("rgbe-png", "Ward RGBE in an 8-bit RGBA PNG", False, False, 2.0**-8, _PNG_LEVEL,
              _rgbe_encode, _rgbe_decode),
    )
}  # fmt: skip
#: Codec of GI maps unless a client asks for another, chosen by benchmarks.gi_codec: the
#: fewest bytes among codecs whose displayed GI keeps SSIM >= 0.999 on every view (the bytes
#: per map: benchmarks/results/net/gi_codec.json).
DEFAULT_GI_CODEC = "f16m7-diff-zstd"
#: Codec of depth (and masks) unless a client asks for another: the fewest bytes among codecs
#: that keep 0 and inf exactly with relative error <= 1e-3 (benchmarks/results/net/gi_codec.json).
DEFAULT_DEPTH_CODEC = "f16-diff-zstd"


def _codec(name: Any) -> Codec:
    c = CODECS.get(name) if isinstance(name, str) else None
    if c is None:
        raise ProtocolError("bad_field", f"unknown codec {name!r}; known: {sorted(CODECS)}")
    return c


def encode(array: np.ndarray, codec: str, *, level: int | None = None) -> bytes:
    """Encode a float array with ``codec``.

    Args:
        array: (H, W, 3) GI or (H, W) / (H, W, 1) depth (any float; encoded as float32 values).
        codec: a name in :data:`CODECS`.
        level: compression level (default: the codec's).

    Returns:
        The encoded bytes (decode with the same shape).

    Raises:
        ProtocolError: ``"bad_field"`` for an unknown codec.
        ValueError: a shape or values the codec cannot carry (e.g. NaN in ``rgbe-png``).
    """
    c = _codec(codec)
    a = np.asarray(array)
    if a.dtype.kind != "f":
        raise ValueError(f"{c.name}: expects a float array, got {a.dtype}")
    if a.size == 0 or a.size > MAX_ELEMENTS:
        raise ValueError(f"{c.name}: array of {a.size} elements is empty or over {MAX_ELEMENTS}")
    return c._encode(a.astype(np.float32, copy=False), c.level if level is None else int(level))


def _check_shape(shape: Any, codec: str) -> tuple[int, ...]:
    ok = isinstance(shape, (list, tuple)) and 1 <= len(shape) <= 4
    ok = ok and all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) for s in shape)
    if not ok or any(s < 1 for s in shape):
        raise ProtocolError("bad_field", f"{codec}: shape must be 1-4 integers >= 1, got {shape!r}")
    n = math.prod(int(s) for s in shape)
    if n > MAX_ELEMENTS:
        raise ProtocolError(
            "too_large", f"{codec}: shape {list(shape)} has {n} elements, over {MAX_ELEMENTS}"
        )
    return tuple(int(s) for s in shape)


def decode(data: bytes, codec: str, shape: Sequence[int], dtype: str = "float32") -> np.ndarray:
    """Decode bytes written by :func:`encode`.

    Args:
        data: the encoded bytes.
        codec: a name in :data:`CODECS`.
        shape: the array's shape, e.g. ``[H, W, 3]``.
        dtype: ``"float32"`` (the only element type of the protocol's arrays).

    Returns:
        A float32 array of ``shape`` (writable, C-contiguous).

    Raises:
        ProtocolError: ``"bad_field"`` (unknown codec or dtype, bad shape), ``"too_large"``
            (shape over :data:`MAX_ELEMENTS`) or ``"malformed"`` (corrupt data, or data of
            another size than the shape; the message names the codec).
    """
    c = _codec(codec)
    if dtype != "float32":
        raise ProtocolError("bad_field", f"{c.name}: dtype must be 'float32', got {dtype!r}")
    shp = _check_shape(shape, c.name)
    try:
        out = c._decode(bytes(data), shp)
    except ValueError as e:
        if isinstance(e, ProtocolError):
            raise
        raise ProtocolError("malformed", f"{c.name}: {e}") from None
    return np.array(out, dtype=np.float32, order="C")


def pack_parts(
    items: Sequence[tuple[str, np.ndarray, str]], *, level: int | None = None
) -> tuple[list[dict[str, Any]], bytes]:
    """Encode named arrays for a ``gi_reply``.

    Args:
        items: (name, array, codec) per part, in payload order.

    Returns:
        (the ``parts`` field, the payload).
    """
    parts, blobs = [], []
    for name, array, codec in items:
        blob = encode(array, codec, level=level)
        a = np.asarray(array)
        parts.append(
            {"name": name, "codec": codec, "shape": list(a.shape), "dtype": "float32",
             "bytes": len(blob)}
        )  # fmt: skip
        blobs.append(blob)
    return parts, b"".join(blobs)


def unpack_parts(parts: Sequence[dict[str, Any]], payload: bytes) -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_parts` (the ``parts`` of a decoded ``gi_reply`` and its payload).

    Raises:
        ProtocolError: as :func:`decode`, or ``"malformed"`` when the sizes do not add up.
    """
    out: dict[str, np.ndarray] = {}
    pos = 0
    for p in parts:
        n = p["bytes"]
        if pos + n > len(payload):
            raise ProtocolError("malformed", f"part {p['name']!r} runs past the payload")
        out[p["name"]] = decode(payload[pos : pos + n], p["codec"], p["shape"], p["dtype"])
        pos += n
    if pos != len(payload):
        raise ProtocolError("malformed", f"{len(payload) - pos} payload bytes after the parts")
    return out


__all__ = [
    "CODECS",
    "DEFAULT_DEPTH_CODEC",
    "DEFAULT_GI_CODEC",
    "Codec",
    "decode",
    "encode",
    "pack_parts",
    "unpack_parts",
]
