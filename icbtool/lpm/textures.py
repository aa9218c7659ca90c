"""Texture bytes of LPM levels: linear float textures <-> 8-bit sRGB PNG/JPEG files, and the
texture shrinking of coarse levels (docs/lpm.md). Used by :mod:`icbtool.lpm.build` (encoding)
and :mod:`icbtool.lpm.chunks` (decoding), which therefore do not import each other."""

from __future__ import annotations

import numpy as np

_SRGB_LUT: np.ndarray | None = None


def _srgb_lut() -> np.ndarray:
    global _SRGB_LUT
    if _SRGB_LUT is None:
        from icbtool.imageio import srgb_decode

        _SRGB_LUT = srgb_decode(np.arange(256, dtype=np.float32) / 255.0)
    return _SRGB_LUT


def encode_texture(texture: np.ndarray, fmt: str = "png", jpeg_quality: int = 90) -> bytes:
    """A linear (h, w, 3) float texture -> the bytes of an 8-bit sRGB PNG or JPEG file."""
    import cv2

    from icbtool.imageio import srgb_encode

    u8 = np.round(srgb_encode(texture) * 255.0).astype(np.uint8)
    bgr = np.ascontiguousarray(u8[..., ::-1])
    if fmt == "png":
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    elif fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        raise ValueError(f"texture format must be 'png' or 'jpeg', got {fmt!r}")
    if not ok:
        raise ValueError(f"cv2 could not encode a {texture.shape} texture as {fmt}")
    return buf.tobytes()


def decode_texture_bytes(data: bytes, where: str = "texture") -> np.ndarray:
    """PNG/JPEG bytes (8-bit sRGB) -> (h, w, 3) float32 linear texture.

    Raises:
        ValueError: the bytes are not an image cv2 can decode (``where`` names them).
    """
    import cv2

    arr = np.frombuffer(data, np.uint8)
    img = cv2.imdecode(arr, cv2.IMREAD_COLOR) if len(arr) else None
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{where}: not a decodable PNG/JPEG image ({len(data)} bytes)")
    return _srgb_lut()[img[..., ::-1]]


def shrink_texture(texture: np.ndarray, max_side: int) -> np.ndarray:
    """``texture`` (h, w, 3) shrunk (INTER_AREA, aspect kept) so its larger side is at most
    ``max_side`` (0: unchanged)."""
    import cv2

    h, w = texture.shape[:2]
    if max_side <= 0 or max(h, w) <= max_side:
        return texture
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(np.ascontiguousarray(texture), size, interpolation=cv2.INTER_AREA)
