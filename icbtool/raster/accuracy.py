"""How close the client's direct light is to a reference, in penumbrae and in full light.

The raster's DL (:class:`icbtool.raster.Rasterizer`, buffer ``dl``) is compared with an
independent reference of the same light, normally the path tracer's ``direct`` output at many
samples per pixel (box-filtered pixels, the filter the cloud's GI is combined with). Pixels are
classified by how much of the light reaches them in the reference: the ratio of the reference
to the *unshadowed* direct light (the raster with ``RasterConfig(shadows=False)``, whose
irradiance is exact for every light kind) is in (``penumbra_lo``, ``penumbra_hi``) in a penumbra
and at least ``lit_min`` in full light. Only *interior* pixels count: those whose whole footprint
(and a margin around it) sees one plane, so that geometric edges (where one point per pixel
and a box filter differ by what the pixel covers, not by the light) do not masquerade as
penumbrae. The bias of a class is the ratio of the sums over its pixels minus one, per channel.

Example:
    >>> # with Rasterizer(scene, RasterConfig(shadows=False, dl_supersample=4)) as r:
    >>> #     free = r.render(cam, "dl").dl
    >>> # with Rasterizer(scene) as r:
    >>> #     big = r.render(cam.resized(4 * h, 4 * w), ("normal_world", "position"))
    >>> #     dl = r.render(cam, "dl").dl
    >>> # bias = shadow_bias(dl, traced.direct, free, interior_pixels(big, 4))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icbtool.raster.config import RasterBuffers


@dataclass(frozen=True)
class ShadowBias:
    """Bias of a DL image against a reference, by class of pixel.

    Attributes:
        penumbra: (3,) float64 bias per channel over the penumbra pixels (sum ratio - 1).
        lit: (3,) float64 bias per channel over the fully lit pixels.
        penumbra_pixels: how many pixels are in the penumbra class.
        lit_pixels: how many pixels are in the lit class.
    """

    penumbra: np.ndarray
    lit: np.ndarray
    penumbra_pixels: int
    lit_pixels: int

    def as_dict(self) -> dict:
        """JSON-ready numbers (biases as fractions)."""
        return {
            "penumbra_bias_per_channel": self.penumbra.tolist(),
            "lit_bias_per_channel": self.lit.tolist(),
            "penumbra_pixels": self.penumbra_pixels,
            "lit_pixels": self.lit_pixels,
        }


def interior_pixels(fine: RasterBuffers, k: int, margin: int = 1) -> np.ndarray:
    """Pixels whose footprint sees one plane, from a k-times finer raster.

    Texture and material changes inside a footprint are allowed: they weigh the box filter and
    the pixel centre differently pixel by pixel, but not on average over many pixels.

    Args:
        fine: buffers of the camera resized to (k H, k W), with ``normal_world`` and
            ``position`` (any raster config).
        k: the refinement (k x k fine pixels per pixel).
        margin: fine pixels around the footprint that must see the same surface too.

    Returns:
        (H, W) bool.

    Raises:
        ValueError: for missing buffers or a size that is not a multiple of k.
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    for name in ("normal_world", "position"):
        if getattr(fine, name) is None:
            raise ValueError(f"interior_pixels needs the fine buffers' {name}")
    hk, wk = fine.mask.shape[:2]
    if k < 1 or hk % k or wk % k:
        raise ValueError(f"interior_pixels: fine size {hk}x{wk} is not a multiple of k = {k}")
    n = fine.normal_world.astype(np.float64)
    plane = (n * fine.position).sum(-1, keepdims=True)  # the plane's offset along its normal
    key = np.concatenate([n, plane], -1)
    size = k + 2 * margin
    # each fine pixel's window of ``size``: for fine pixel (k i + k // 2, k j + k // 2) it is
    # exactly pixel (i, j)'s k x k footprint plus the margin (scipy centres even windows so)
    same = minimum_filter(fine.mask[..., 0] > 0.5, size)
    # normals to 1e-3; the plane offset to 1e-3 of the largest one seen
    tol = [1e-3] * 3 + [1e-3 * max(1.0, float(np.abs(plane).max()))]
    for c in range(key.shape[-1]):
        spread = maximum_filter(key[..., c], size) - minimum_filter(key[..., c], size)
        same &= spread < tol[c]
    return same[k // 2 :: k, k // 2 :: k][: hk // k, : wk // k].copy()


def shadow_bias(
    dl: np.ndarray,
    reference: np.ndarray,
    unshadowed: np.ndarray,
    select: np.ndarray,
    penumbra_lo: float = 0.05,
    penumbra_hi: float = 0.95,
    lit_min: float = 0.98,
) -> ShadowBias:
    """Penumbra and full-light bias of ``dl`` against ``reference``.

    Args:
        dl: (H, W, 3) the DL to judge.
        reference: (H, W, 3) the reference direct light (e.g. the tracer's ``direct``).
        unshadowed: (H, W, 3) the same light without occlusion (classifies the pixels).
        select: (H, W) bool pixels that may count (e.g. :func:`interior_pixels`, without the
            emitters seen).
        penumbra_lo, penumbra_hi: a pixel is in the penumbra when its reference / unshadowed
            luminance ratio lies strictly between these.
        lit_min: a pixel is fully lit when that ratio is at least this.

    Returns:
        ShadowBias.

    Raises:
        ValueError: for mismatched shapes.
    """
    shape = reference.shape
    if dl.shape != shape or unshadowed.shape != shape or shape[-1:] != (3,):
        raise ValueError(
            f"shadow_bias wants (H, W, 3) images of one size, got dl {dl.shape}, reference "
            f"{reference.shape}, unshadowed {unshadowed.shape}"
        )
    if select.shape != shape[:2]:
        raise ValueError(f"shadow_bias: select is {select.shape}, the images {shape[:2]}")
    free = unshadowed.mean(-1)
    ratio = reference.mean(-1) / np.maximum(free, 1e-12)
    ok = select & (free > 1e-6 * max(float(free.max()), 1e-30))
    pen = ok & (ratio > penumbra_lo) & (ratio < penumbra_hi)
    lit = ok & (ratio >= lit_min)

    def bias(sel: np.ndarray) -> np.ndarray:
        if not sel.any():
            return np.full(3, np.nan)
        ref = reference[sel].astype(np.float64).sum(0)
        return dl[sel].astype(np.float64).sum(0) / np.maximum(ref, 1e-30) - 1.0

    return ShadowBias(bias(pen), bias(lit), int(pen.sum()), int(lit.sum()))
