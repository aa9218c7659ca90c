"""Image files: float32 EXR (exact), PNG previews, and the one display transform of icbtool.

Display transform (used for every PNG and for every image comparison in 0-255 RGB, as docs/design.md
decides): ``display = round(255 * srgb_oetf(clip(exposure * linear, 0, 1)))``: a linear exposure,
a hard clip, the sRGB transfer curve (IEC 61966-2-1), 8 bits.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: RGB colour of each hole cause of a warp (:class:`icbtool.warp.WarpResult`) in pictures of its
#: holes (the demo's frame strips, the desktop app): outside every reference frustum,
#: disoccluded, no geometry. Kept here, with the display transform, so that code that only draws
#: pictures (the desktop app's window) need not import the warp and torch; ``icbtool.warp``
#: exports the same dict.
HOLE_COLOURS: dict[str, tuple[int, int, int]] = {
    "outside": (255, 64, 64),
    "disoccluded": (255, 200, 0),
    "no_geometry": (40, 40, 40),
}


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (float32; the exact piecewise curve)."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(
        np.float32
    )


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear [0, 1] (float32)."""
    x = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def to_display(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """The display transform: (H, W, C) linear float -> (H, W, C) uint8 sRGB (see module doc).

    NaN/Inf map to 0 / 255 rather than propagating.
    """
    x = np.nan_to_num(np.asarray(linear, dtype=np.float32) * exposure, nan=0.0, posinf=1.0)
    return np.round(srgb_encode(x) * 255.0).astype(np.uint8)


def auto_exposure(linear: np.ndarray, mask: np.ndarray | None = None, pct: float = 99.0) -> float:
    """An exposure that maps the ``pct`` percentile of luminance (within ``mask``) to 1."""
    x = np.asarray(linear, dtype=np.float32)
    lum = x.mean(-1) if x.ndim == 3 else x
    if mask is not None:
        lum = lum[np.asarray(mask, bool).reshape(lum.shape)]
    lum = lum[np.isfinite(lum)]
    if lum.size == 0:
        return 1.0
    p = float(np.percentile(lum, pct))
    return 1.0 / p if p > 1e-12 else 1.0


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a (H, W), (H, W, 1) or (H, W, 3) uint8 image (RGB order) as PNG."""
    import cv2

    path = Path(path)
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"write_png wants uint8, got {img.dtype} for {path}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise OSError(f"could not write PNG {path}")
    return path


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read an 8-bit PNG/JPEG as (H, W, 3) uint8 RGB (or (H, W) for grey)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f"could not read image {path} (missing, truncated or not an image)")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1]
    return np.ascontiguousarray(img)


def write_exr(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a float image losslessly as float32 OpenEXR.

    Args:
        image: (H, W), (H, W, 1) or (H, W, 3) float array (stored as float32).
    """
    import OpenEXR

    path = Path(path)
    img = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 2:
        channels = {"Y": img}
    elif img.ndim == 3 and img.shape[2] == 3:
        channels = {"RGB": img}
    else:
        raise ValueError(f"write_exr wants (H, W) or (H, W, 1|3), got {img.shape} for {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))
    return path


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an EXR written by :func:`write_exr`: (H, W, 3) or (H, W) float32."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path)) as f:
            ch = f.channels()
            if "RGB" in ch:
                return np.asarray(ch["RGB"].pixels, dtype=np.float32)
            if "RGBA" in ch:
                return np.ascontiguousarray(np.asarray(ch["RGBA"].pixels, np.float32)[..., :3])
            if "Y" in ch:
                return np.asarray(ch["Y"].pixels, dtype=np.float32)
            if all(k in ch for k in "RGB"):
                return np.stack([np.asarray(ch[k].pixels, np.float32) for k in "RGB"], -1)
            raise ValueError(f"EXR {path} has channels {sorted(ch)}, expected RGB or Y")
    except (OSError, RuntimeError) as e:
        raise OSError(f"could not read EXR {path}: {e}") from e


def read_hdr(path: str | os.PathLike) -> np.ndarray:
    """Read a linear HDR image, OpenEXR (``.exr``) or Radiance RGBE (``.hdr``, ``.pic``), as
    (H, W, 3) float32 (a one-channel EXR is repeated to three channels).

    Raises:
        FileNotFoundError: no such file.
        ValueError: another file type (names it and the types read).
        OSError: an unreadable or truncated file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"HDR image not found: {path}")
    ext = path.suffix.lower()
    if ext == ".exr":
        img = read_exr(path)
        return np.ascontiguousarray(np.repeat(img[..., None], 3, 2) if img.ndim == 2 else img)
    if ext in (".hdr", ".pic"):
        import cv2

        img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
        if img is None or img.ndim != 3:
            raise OSError(f"could not read Radiance HDR {path} (truncated or not RGBE)")
        return np.ascontiguousarray(img[..., ::-1], dtype=np.float32)
    raise ValueError(
        f"{path}: unsupported HDR image type {ext!r} (read: .exr (OpenEXR), .hdr/.pic (Radiance))"
    )


def preview(
    image: np.ndarray,
    kind: str = "color",
    exposure: float | None = None,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """An 8-bit RGB preview of a buffer.

    Args:
        image: (H, W, C) float32.
        kind: 'color' (linear HDR -> display transform, auto exposure unless given),
            'normal' ((n + 1) / 2), 'depth' (near bright, far dark, normalised over ``mask``),
            'position' (normalised per channel), 'mask' (white = set).
    Returns:
        (H, W, 3) uint8.
    """
    x = np.asarray(image, dtype=np.float32)
    if x.ndim == 2:
        x = x[..., None]
    m = None if mask is None else np.asarray(mask, bool).reshape(x.shape[:2])
    if kind == "color":
        e = auto_exposure(x, m) if exposure is None else exposure
        out = to_display(x, e)
    elif kind == "normal":
        out = np.round(np.clip((x + 1) / 2, 0, 1) * 255).astype(np.uint8)
    elif kind in ("depth", "position"):
        sel = np.isfinite(x).all(-1) if m is None else (m & np.isfinite(x).all(-1))
        if not sel.any():
            out = np.zeros(x.shape, np.uint8)
        else:
            v = x[sel]
            lo, hi = v.min(0), v.max(0)
            y = (x - lo) / np.maximum(hi - lo, 1e-12)
            if kind == "depth":
                y = 1.0 - y
            y = np.where(sel[..., None], y, 0.0)
            out = np.round(np.clip(y, 0, 1) * 255).astype(np.uint8)
    elif kind == "mask":
        out = (x > 0.5).astype(np.uint8) * 255
    else:
        raise ValueError(f"preview kind must be color|normal|depth|position|mask, got {kind!r}")
    if out.shape[2] == 1:
        out = np.repeat(out, 3, axis=2)
    return out
