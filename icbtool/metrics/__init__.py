"""Image metrics on the display scale (0-255 RGB, after :func:`icbtool.imageio.to_display`).

SSIM: Gaussian window 11, sigma 1.5, ``padding='valid'`` (equal to pytorch-msssim; kornia's default
'same' padding reads about 1.4 % higher). MSE on 0-255 values. Both as in docs/design.md section 5.
"""

from __future__ import annotations

import numpy as np

from icbtool.imageio import to_display


def _as_display(x: np.ndarray, exposure: float) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype == np.uint8:
        return a.astype(np.float64)
    return to_display(a, exposure).astype(np.float64)


def mse(
    a: np.ndarray, b: np.ndarray, exposure: float = 1.0, mask: np.ndarray | None = None
) -> float:
    """Mean squared error on the display scale (0-255). Float inputs are linear HDR and go through
    the display transform with ``exposure``; uint8 inputs are used as they are.

    Args:
        a, b: (H, W, C) images of the same shape.
        mask: optional (H, W) bool: only these pixels count.
    """
    if np.shape(a) != np.shape(b):
        raise ValueError(f"mse: shapes differ: {np.shape(a)} vs {np.shape(b)}")
    d = (_as_display(a, exposure) - _as_display(b, exposure)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    return float(d.mean())


def ssim(a: np.ndarray, b: np.ndarray, exposure: float = 1.0) -> float:
    """Mean SSIM on the display scale (0-255, data range 255), valid padding (see module doc).

    Args:
        a, b: (H, W, C) images of the same shape, H and W >= 11.
    """
    import torch
    from kornia.metrics import ssim as kssim

    if np.shape(a) != np.shape(b):
        raise ValueError(f"ssim: shapes differ: {np.shape(a)} vs {np.shape(b)}")
    x = torch.from_numpy(_as_display(a, exposure)).float()
    y = torch.from_numpy(_as_display(b, exposure)).float()
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    x = x.permute(2, 0, 1)[None] / 255.0
    y = y.permute(2, 0, 1)[None] / 255.0
    with torch.no_grad():
        m = kssim(x, y, window_size=11, max_val=1.0, padding="valid")
    return float(m.mean())


#: Side of SSIM's Gaussian window; a 'valid' map is ``SSIM_WINDOW - 1`` pixels smaller per axis.
SSIM_WINDOW = 11


def ssim_map(
    a: np.ndarray, b: np.ndarray, exposure: float = 1.0, padding: str = "same"
) -> np.ndarray:
    """Per-pixel SSIM (mean over channels) on the display scale.

    Args:
        a, b: (H, W, C) images of the same shape.
        padding: ``"same"``: (H, W), aligned with the image (border windows read reflected
            pixels); ``"valid"``: (H - 10, W - 10), only whole windows, whose mean is exactly
            :func:`ssim` (up to float32 rounding).

    Returns:
        (H, W) or (H - 10, W - 10) float32.
    """
    import torch
    from kornia.metrics import ssim as kssim

    if np.shape(a) != np.shape(b):
        raise ValueError(f"ssim_map: shapes differ: {np.shape(a)} vs {np.shape(b)}")
    if padding not in ("same", "valid"):
        raise ValueError(f"ssim_map: padding must be 'same' or 'valid', got {padding!r}")
    x = torch.from_numpy(_as_display(a, exposure)).float()
    y = torch.from_numpy(_as_display(b, exposure)).float()
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    x = x.permute(2, 0, 1)[None] / 255.0
    y = y.permute(2, 0, 1)[None] / 255.0
    with torch.no_grad():
        m = kssim(x, y, window_size=SSIM_WINDOW, max_val=1.0, padding=padding)
    return m[0].mean(0).numpy()


def flip_map(reference: np.ndarray, test: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(H, W) per-pixel NVIDIA FLIP error (LDR, on the display transform); its mean is
    :func:`flip`. Needs the optional ``flip-evaluator`` (extra ``metrics``).

    Args:
        reference, test: (H, W, 3) images of the same shape (linear HDR floats or uint8).
    """
    from icbtool.optional import require

    fe = require("flip_evaluator", "the FLIP metric")
    if np.shape(reference) != np.shape(test):
        raise ValueError(f"flip_map: shapes differ: {np.shape(reference)} vs {np.shape(test)}")
    r = (_as_display(reference, exposure) / 255.0).astype(np.float32)
    t = (_as_display(test, exposure) / 255.0).astype(np.float32)
    err, _, _ = fe.evaluate(r, t, "LDR", applyMagma=False)
    return np.asarray(err, np.float32).reshape(r.shape[:2])


def flip(reference: np.ndarray, test: np.ndarray, exposure: float = 1.0) -> float:
    """Mean NVIDIA FLIP error (LDR, display transform): the mean of :func:`flip_map`."""
    return float(flip_map(reference, test, exposure).mean(dtype=np.float64))


def rmse_linear(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root mean squared error of linear HDR values (no display transform)."""
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(np.sqrt(d.mean()))


__all__ = ["SSIM_WINDOW", "flip", "flip_map", "mse", "rmse_linear", "ssim", "ssim_map"]
