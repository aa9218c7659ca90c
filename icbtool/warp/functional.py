"""Differentiable, batched 3D warping in torch (BCHW tensors), and its ``nn.Module`` versions.

Conventions (those of :mod:`icbtool.camera`):

* Intrinsics ``K`` are (B, 3, 3) in icbtool's pixel convention: pixel centres at ``+0.5``, i.e. the
  centre of pixel (row i, col j) is ``(u, v) = (j + 0.5, i + 0.5)``. This is NOT kornia's
  convention (integer centres, :meth:`icbtool.camera.Camera.K_kornia`); do not mix them.
* Poses are (B, 4, 4) rigid transforms named ``a_from_b`` (OpenCV camera axes).
* Depth maps are (B, 1, H, W) view-space z.

Backward warp (:func:`warp_backward`): every target pixel is lifted with the target depth,
moved into the source camera and looked up there with bilinear interpolation. Each of the four
bilinear taps is depth-tested on its own (``|z_tap - z| <= rel_depth_tol * z``, with ``z`` the
point's depth in the source camera) and only passing taps are blended, with their weights
renormalised. A foreground tap therefore never bleeds into a background pixel (no ghosts) and a
point whose surface the source did not see gets no passing tap: it is *disoccluded*.

Forward warp (:func:`warp_forward`): every source pixel is splatted to the target with a
z-buffer (nearest depth wins). It needs no target depth; pixels that receive nothing are holes.

Differentiability: the backward warp is differentiable w.r.t. the source image (linear) and the
target depth (through the bilinear weights and the projection). The hard depth test has zero
gradient w.r.t. the source depth; with ``soft_depth > 0`` the tap test becomes a sigmoid and is
differentiable w.r.t. the source depth too. The forward warp is differentiable w.r.t. the
source image.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

__all__ = [
    "BackwardWarp",
    "BackwardWarpOutput",
    "ForwardWarp",
    "ForwardWarpOutput",
    "inverse_depth_slopes",
    "pixel_grid",
    "warp_backward",
    "warp_forward",
]

_Z_EPS = 1e-8


@functools.lru_cache(maxsize=16)
def _pixel_grid_cached(height: int, width: int, dtype: torch.dtype, device: str) -> Tensor:
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], 0)


def pixel_grid(height: int, width: int, dtype: torch.dtype, device: torch.device | str) -> Tensor:
    """(2, H*W) pixel-centre coordinates (u, v) in icbtool's convention (centres at +0.5).

    Cached per size, dtype and device (do not modify the returned tensor in place).
    """
    return _pixel_grid_cached(int(height), int(width), dtype, str(device))


@functools.lru_cache(maxsize=16)
def _pixel_grid_h_cached(height: int, width: int, dtype: torch.dtype, device: str) -> Tensor:
    g = _pixel_grid_cached(height, width, dtype, device)
    return torch.cat([g, torch.ones_like(g[:1])], 0)[None]


def pixel_grid_h(height: int, width: int, dtype: torch.dtype, device: torch.device | str) -> Tensor:
    """(1, 3, H*W) homogeneous pixel centres (u, v, 1), cached like :func:`pixel_grid`."""
    return _pixel_grid_h_cached(int(height), int(width), dtype, str(device))


def _pixel_transform(
    K_to: Tensor, K_from: Tensor, to_from_from: Tensor, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """(B, 3, 3) ``K_to R K_from^-1`` and (B, 3, 1) ``K_to t``, computed in float64."""
    k_to = K_to.double()
    r = to_from_from[:, :3, :3].double()
    t = to_from_from[:, :3, 3:].double()
    m = k_to @ r @ torch.linalg.inv(K_from.double())
    return m.to(dtype), (k_to @ t).to(dtype)


# --------------------------------------------------------------------------- input checks
def _check_bchw(x: Tensor, name: str, channels: int | None = None) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4:
        raise ValueError(f"{name} must be (B, C, H, W), got shape {tuple(x.shape)}")
    if channels is not None and x.shape[1] != channels:
        raise ValueError(f"{name} must have {channels} channel(s), got shape {tuple(x.shape)}")


def _batched_matrix(m: Tensor, name: str, n: int, batch: int) -> Tensor:
    if not isinstance(m, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(m).__name__}")
    if m.ndim == 2:
        m = m[None]
    if m.ndim != 3 or m.shape[1:] != (n, n) or m.shape[0] not in (1, batch):
        raise ValueError(
            f"{name} must be ({batch}, {n}, {n}) (or ({n}, {n})), got {tuple(m.shape)}"
        )
    return m.expand(batch, n, n)


def _valid_mask(depth: Tensor, mask: Tensor | None, name: str) -> Tensor:
    """(B, 1, H, W) bool geometry mask. Without ``mask``: finite depth > 0. With ``mask``: the mask,
    and a ValueError if it marks pixels valid whose depth is zero, negative or not finite."""
    good = (depth > 0) & (depth < float("inf"))  # False for NaN too
    if mask is None:
        return good
    _check_bchw(mask, f"{name}_mask", 1)
    if mask.shape != depth.shape:
        raise ValueError(
            f"{name}_mask shape {tuple(mask.shape)} differs from {name}_depth {tuple(depth.shape)}"
        )
    m = mask > 0.5 if mask.dtype != torch.bool else mask
    bad = int((m & ~good).sum())
    if bad:
        raise ValueError(
            f"{name}_depth: {bad} pixel(s) marked valid by {name}_mask have zero, negative or "
            "non-finite depth"
        )
    return m


def _inverse_depth_slopes(iz: Tensor, valid: Tensor, limit: float) -> tuple[Tensor, Tensor]:
    """Per-pixel slopes (d/dx, d/dy) of inverse depth (B, 1, H, W): the one-sided difference of
    smaller magnitude among those to valid neighbours; 0 if none, or if larger than
    ``limit * iz`` (an edge, not a slope)."""
    big = torch.where(valid, iz, 1e30)  # a difference to a missing neighbour is huge
    bound = limit * iz

    def one(dim: int) -> Tensor:
        if iz.shape[dim] < 3:
            return torch.zeros_like(iz)
        d = torch.diff(big, dim=dim)
        ad = d.abs()
        m = d.shape[dim]
        right, left = d.narrow(dim, 1, m - 1), d.narrow(dim, 0, m - 1)
        inner = torch.where(ad.narrow(dim, 1, m - 1) <= ad.narrow(dim, 0, m - 1), right, left)
        g = torch.cat([d.narrow(dim, 0, 1), inner, d.narrow(dim, m - 1, 1)], dim)
        return torch.where(g.abs() <= bound, g, 0.0)

    return one(3), one(2)


def inverse_depth_slopes(
    src_depth: Tensor, src_mask: Tensor | None = None, slope_limit: float = 0.25
) -> Tensor:
    """Per-pixel inverse-depth slopes of a reference, for :func:`warp_backward`'s ``src_slopes``.

    A reference (GI map) is warped to many client frames: compute this once per reference and
    pass it to every warp instead of recomputing it each time.

    Args:
        src_depth: (B, 1, H, W) view-space depth.
        src_mask: optional (B, 1, H, W) geometry mask.
        slope_limit: relative per-pixel slope above which a difference counts as an edge.

    Returns:
        (B, 2, H, W): d(1/z)/dx and d(1/z)/dy per pixel (0 at edges and invalid pixels).
    """
    _check_bchw(src_depth, "src_depth", 1)
    valid = _valid_mask(src_depth, src_mask, "src")
    iz = torch.where(valid, 1.0 / torch.where(valid, src_depth, 1.0), 0.0)
    return torch.cat(_inverse_depth_slopes(iz, valid, slope_limit), 1)


# --------------------------------------------------------------------------- backward warp
@dataclass
class BackwardWarpOutput:
    """Result of :func:`warp_backward`. All maps are (B, 1, H_dst, W_dst) unless stated.

    Attributes:
        image: (B, C, H_dst, W_dst) warped source image; 0 on holes.
        holes: bool, ``outside | disoccluded | no_geometry``.
        outside: bool, the target point projects outside the source image or behind its camera.
        disoccluded: bool, inside the source frustum but no bilinear tap passes the depth test
            (the source saw another surface, or no geometry, there).
        no_geometry: bool, the target pixel has no geometry (mask 0 / invalid depth).
        weight: float in [0, 1], the bilinear weight of the taps that passed the depth test
            (1 = all four agree; soft when ``soft_depth > 0``); 0 on holes.
        density: float, source pixels per target pixel (linear, fronto-parallel approximation:
            ``(f_src / z_src) / (f_dst / z_dst)``); < 1 means the source is magnified.
        src_uv: (B, 2, H_dst, W_dst) where each target pixel lands in the source (icbtool pixel
            coordinates); meaningful only where not ``no_geometry``.
        src_z: the target point's depth in the source camera.
    """

    image: Tensor
    holes: Tensor
    outside: Tensor
    disoccluded: Tensor
    no_geometry: Tensor
    weight: Tensor
    density: Tensor
    src_uv: Tensor
    src_z: Tensor


def warp_backward(
    src_image: Tensor,
    src_depth: Tensor,
    dst_depth: Tensor,
    K_src: Tensor,
    K_dst: Tensor,
    src_from_dst: Tensor,
    src_mask: Tensor | None = None,
    dst_mask: Tensor | None = None,
    rel_depth_tol: float = 0.02,
    soft_depth: float = 0.0,
    min_weight: float = 1e-3,
    slope_limit: float = 0.25,
    src_slopes: Tensor | None = None,
) -> BackwardWarpOutput:
    """Backward-warp a source image to a target camera whose depth is known.

    Args:
        src_image: (B, C, Hs, Ws) image seen by the source camera.
        src_depth: (B, 1, Hs, Ws) source view-space depth.
        dst_depth: (B, 1, Hd, Wd) target view-space depth.
        K_src: (B, 3, 3) source intrinsics (icbtool convention; (3, 3) is broadcast).
        K_dst: (B, 3, 3) target intrinsics.
        src_from_dst: (B, 4, 4) rigid transform, target camera coordinates to source camera.
        src_mask: optional (B, 1, Hs, Ws) geometry mask (> 0.5 or True = geometry). Without it,
            pixels with finite depth > 0 are geometry.
        dst_mask: optional (B, 1, Hd, Wd) likewise for the target.
        rel_depth_tol: a tap passes if ``|z / z_tap - 1| <= rel_depth_tol`` (``z``: the point's
            depth in the source camera, ``z_tap``: the tap's depth extrapolated to the sample).
        soft_depth: 0 for the hard test; > 0 replaces it by
            ``sigmoid((rel_depth_tol - |z / z_tap - 1|) / soft_depth)`` (differentiable w.r.t.
            the source depth).
        min_weight: a pixel whose passing tap weight is at most this is disoccluded.
        slope_limit: slope-aware test: each tap's inverse depth is extrapolated to the sample
            position with its own per-pixel slope (the smaller of the one-sided differences,
            so a depth edge does not count as slope); slopes above ``slope_limit`` (relative,
            per pixel) are treated as edges (0). 0 disables it (plain per-tap comparison).
        src_slopes: optional (B, 2, Hs, Ws) precomputed :func:`inverse_depth_slopes` of the
            source (used instead of computing them; ``slope_limit`` must then be > 0).

    Returns:
        A :class:`BackwardWarpOutput`.

    Raises:
        ValueError: on shape mismatches, or a mask marking pixels valid whose depth is <= 0 or
            not finite (the message gives the pixel count).
    """
    _check_bchw(src_image, "src_image")
    b, c, hs, ws = src_image.shape
    _check_bchw(src_depth, "src_depth", 1)
    _check_bchw(dst_depth, "dst_depth", 1)
    if src_depth.shape[0] != b or src_depth.shape[2:] != (hs, ws):
        raise ValueError(
            f"src_depth {tuple(src_depth.shape)} does not match src_image {tuple(src_image.shape)}"
        )
    if dst_depth.shape[0] != b:
        raise ValueError(f"dst_depth batch {dst_depth.shape[0]} differs from src_image batch {b}")
    if not (rel_depth_tol > 0 and soft_depth >= 0 and 0 <= min_weight < 1):
        raise ValueError(
            f"need rel_depth_tol > 0, soft_depth >= 0, 0 <= min_weight < 1; got {rel_depth_tol}, "
            f"{soft_depth}, {min_weight}"
        )
    hd, wd = dst_depth.shape[2:]
    K_src = _batched_matrix(K_src, "K_src", 3, b).to(src_image.dtype)
    K_dst = _batched_matrix(K_dst, "K_dst", 3, b).to(src_image.dtype)
    src_from_dst = _batched_matrix(src_from_dst, "src_from_dst", 4, b).to(src_image.dtype)
    dtype, device = src_image.dtype, src_image.device

    src_valid = _valid_mask(src_depth, src_mask, "src")
    dst_valid = _valid_mask(dst_depth, dst_mask, "dst")

    # lift target pixels and project them: q = (K_src R K_dst^-1 [u, v, 1]) * d + K_src t, with
    # the 3x3 products formed in float64 (an identity pose then gives exactly [u d, v d, d]).
    n = hd * wd
    d = torch.where(dst_valid, dst_depth, torch.ones_like(dst_depth)).reshape(b, 1, n)
    m, kt = _pixel_transform(K_src, K_dst, src_from_dst, dtype)
    q = torch.matmul(m, pixel_grid_h(hd, wd, dtype, device)) * d + kt  # (B, 3, N)
    zs = q[:, 2]
    front = zs > _Z_EPS
    z_safe = torch.where(front, zs, torch.ones_like(zs))
    us = q[:, 0] / z_safe
    vs = q[:, 1] / z_safe
    fx_s, fy_s = K_src[:, 0, 0, None], K_src[:, 1, 1, None]
    fx_d, fy_d = K_dst[:, 0, 0, None], K_dst[:, 1, 1, None]
    inside = front & (us >= 0) & (us <= ws) & (vs >= 0) & (vs <= hs)
    dv = dst_valid.reshape(b, n)

    # four bilinear taps (sample positions: centres at +0.5 -> array index = coordinate - 0.5),
    # border replicated (points in the outer half pixel are inside the frustum).
    x = (us - 0.5).clamp(-0.5, ws - 0.5)
    y = (vs - 0.5).clamp(-0.5, hs - 0.5)
    x0f, y0f = torch.floor(x.detach()), torch.floor(y.detach())
    wx, wy = x - x0f, y - y0f
    # taps are laid out (2 rows, 2 columns): index [i, j] = row y_i, column x_j
    cols = torch.stack([x0f.clamp_min(0), (x0f + 1).clamp_max(ws - 1)], 0)  # (2, B, N)
    rows = torch.stack([y0f.clamp_min(0), (y0f + 1).clamp_max(hs - 1)], 0)
    off = (torch.arange(b, device=device) * (hs * ws))[:, None]
    idx = ((rows * ws).long() + off)[:, None] + cols.long()[None]  # (2, 2, B, N)
    bw = torch.stack([1 - wy, wy], 0)[:, None] * torch.stack([1 - wx, wx], 0)[None]

    # per-tap depth test in inverse depth (affine in pixels on a plane): each tap's inverse
    # depth is extrapolated to the sample with its own surface slope, so grazing surfaces pass
    # while a tap across a depth edge (another surface) fails.
    # inverse depth, -1 where the source has no geometry (fails every depth test below)
    src_iz = torch.where(src_valid, torch.reciprocal(src_depth), -1.0)
    if slope_limit > 0:
        if src_slopes is None:
            gx, gy = _inverse_depth_slopes(src_iz, src_valid, slope_limit)
            extra = [src_iz, gx, gy]
        else:
            if src_slopes.shape != (b, 2, hs, ws):
                raise ValueError(
                    f"src_slopes must be ({b}, 2, {hs}, {ws}), got {tuple(src_slopes.shape)}"
                )
            extra = [src_iz, src_slopes.to(dtype)]
    else:
        extra = [src_iz]
    feats = torch.cat([src_image, *extra], 1)  # (B, k, Hs, Ws)
    k = feats.shape[1]
    feats = feats.transpose(0, 1).reshape(k, b * hs * ws)
    taps = feats.index_select(1, idx.reshape(-1)).view(k, 2, 2, b, n)
    tap_iz = taps[c]
    if slope_limit > 0:
        tap_iz = torch.addcmul(tap_iz, taps[c + 1], (x - cols)[None])
        tap_iz = torch.addcmul(tap_iz, taps[c + 2], (y - rows)[:, None])
    if soft_depth > 0:
        rel = (tap_iz * z_safe - 1.0).abs()  # |z / z_tap - 1| to first order
        w = bw * torch.sigmoid((rel_depth_tol - rel) / soft_depth) * (tap_iz > 0)
    else:  # the same test as bounds on the tap's inverse depth (fewer passes)
        lo, hi = (1.0 - rel_depth_tol) / z_safe, (1.0 + rel_depth_tol) / z_safe
        w = bw * ((tap_iz >= lo) & (tap_iz <= hi))
    wsum = w.sum((0, 1))  # (B, N)
    covered = inside & dv
    ok = covered & (wsum > min_weight)
    scale = ok / wsum.clamp_min(1e-12)  # renormalise the passing taps; 0 on holes
    img = (taps[:c] * w).sum((1, 2)) * scale  # (C, B, N)
    image = img.transpose(0, 1).reshape(b, c, hd, wd)

    def _map(t: Tensor) -> Tensor:
        return t.reshape(b, 1, hd, wd)

    no_geometry = ~dv
    outside = dv & ~inside
    disoccluded = covered & ~ok
    dens = (torch.sqrt(fx_s * fy_s) * d[:, 0]) / (torch.sqrt(fx_d * fy_d) * z_safe)
    return BackwardWarpOutput(
        image=image,
        holes=_map(~ok),
        outside=_map(outside),
        disoccluded=_map(disoccluded),
        no_geometry=_map(no_geometry),
        weight=_map(torch.where(ok, wsum, torch.zeros_like(wsum))),
        density=_map(torch.where(covered, dens, torch.zeros_like(dens))),
        src_uv=torch.stack([us, vs], 1).reshape(b, 2, hd, wd),
        src_z=_map(zs),
    )


# --------------------------------------------------------------------------- forward warp
@dataclass
class ForwardWarpOutput:
    """Result of :func:`warp_forward`. Maps are (B, 1, H_dst, W_dst) unless stated.

    Attributes:
        image: (B, C, H_dst, W_dst) splatted source image; 0 on holes.
        depth: splatted depth in the target camera (z-buffer); 0 on holes.
        holes: bool, target pixels that received no source pixel.
    """

    image: Tensor
    depth: Tensor
    holes: Tensor


def warp_forward(
    src_image: Tensor,
    src_depth: Tensor,
    K_src: Tensor,
    K_dst: Tensor,
    dst_from_src: Tensor,
    dst_size: tuple[int, int],
    src_mask: Tensor | None = None,
    splat: Literal["nearest", "footprint2"] = "nearest",
) -> ForwardWarpOutput:
    """Forward-warp (splat) a source image into a target camera with a z-buffer.

    Each source pixel centre is lifted with its depth, moved to the target camera and written to
    the target pixel containing it (``nearest``), or to the 2x2 target pixels around it
    (``footprint2``: closes cracks up to a magnification of 2, at the cost of dilating
    foreground edges by up to one pixel). Among points landing on one pixel the nearest wins.

    Args:
        src_image: (B, C, Hs, Ws).
        src_depth: (B, 1, Hs, Ws) view-space depth.
        K_src, K_dst: (B, 3, 3) intrinsics (icbtool convention).
        dst_from_src: (B, 4, 4) source camera coordinates to target camera coordinates.
        dst_size: (H_dst, W_dst).
        src_mask: optional (B, 1, Hs, Ws) geometry mask (see :func:`warp_backward`).
        splat: ``nearest`` or ``footprint2``.

    Returns:
        A :class:`ForwardWarpOutput`.
    """
    _check_bchw(src_image, "src_image")
    b, c, hs, ws = src_image.shape
    _check_bchw(src_depth, "src_depth", 1)
    if src_depth.shape[0] != b or src_depth.shape[2:] != (hs, ws):
        raise ValueError(
            f"src_depth {tuple(src_depth.shape)} does not match src_image {tuple(src_image.shape)}"
        )
    if splat not in ("nearest", "footprint2"):
        raise ValueError(f"splat must be 'nearest' or 'footprint2', got {splat!r}")
    hd, wd = (int(v) for v in dst_size)
    if hd < 1 or wd < 1:
        raise ValueError(f"dst_size must be positive, got {dst_size}")
    dtype, device = src_image.dtype, src_image.device
    K_src = _batched_matrix(K_src, "K_src", 3, b).to(dtype)
    K_dst = _batched_matrix(K_dst, "K_dst", 3, b).to(dtype)
    dst_from_src = _batched_matrix(dst_from_src, "dst_from_src", 4, b).to(dtype)
    src_valid = _valid_mask(src_depth, src_mask, "src").reshape(b, -1)

    n = hs * ws
    d = torch.where(src_valid, src_depth.reshape(b, n), torch.ones((), dtype=dtype))
    m, kt = _pixel_transform(K_dst, K_src, dst_from_src, dtype)
    q = torch.matmul(m, pixel_grid_h(hs, ws, dtype, device)) * d[:, None] + kt
    z = q[:, 2]
    front = src_valid & (z > _Z_EPS)
    zsafe = torch.where(front, z, torch.ones_like(z))
    u = q[:, 0] / zsafe
    v = q[:, 1] / zsafe
    if splat == "nearest":
        offsets = [(0, 0)]
        base_u, base_v = u.detach(), v.detach()
    else:
        offsets = [(0, 0), (1, 0), (0, 1), (1, 1)]
        base_u, base_v = u.detach() - 0.5, v.detach() - 0.5
    bu = torch.floor(base_u.clamp(-2, wd + 2)).long()
    bv = torch.floor(base_v.clamp(-2, hd + 2)).long()
    off = (torch.arange(b, device=device) * (hd * wd))[:, None]
    tgt, zz, src_i = [], [], []
    flat_src = torch.arange(b * n, device=device).reshape(b, n)
    for du, dv in offsets:
        j, i = bu + du, bv + dv
        ok = front & (j >= 0) & (j < wd) & (i >= 0) & (i < hd)
        tgt.append((i * wd + j + off)[ok])
        zz.append(z[ok])
        src_i.append(flat_src[ok])
    tgt_t, z_t, src_t = torch.cat(tgt), torch.cat(zz).detach(), torch.cat(src_i)
    zbuf = torch.full((b * hd * wd,), float("inf"), dtype=dtype, device=device)
    zbuf.scatter_reduce_(0, tgt_t, z_t, reduce="amin", include_self=True)
    win = z_t <= zbuf[tgt_t]
    tgt_w, src_w = tgt_t[win], src_t[win]
    colors = src_image.transpose(0, 1).reshape(c, b * n)
    out = torch.zeros((c, b * hd * wd), dtype=dtype, device=device)
    out = out.index_put((torch.arange(c, device=device)[:, None], tgt_w[None]), colors[:, src_w])
    holes = torch.isinf(zbuf)
    depth = torch.where(holes, torch.zeros_like(zbuf), zbuf)
    return ForwardWarpOutput(
        image=out.reshape(c, b, hd, wd).transpose(0, 1),
        depth=depth.reshape(b, 1, hd, wd),
        holes=holes.reshape(b, 1, hd, wd),
    )


# --------------------------------------------------------------------------- modules
class BackwardWarp(nn.Module):
    """``nn.Module`` form of :func:`warp_backward` (the tolerances are fixed at construction).

    ``forward(src_image, src_depth, dst_depth, K_src, K_dst, src_from_dst, src_mask=None,
    dst_mask=None) -> BackwardWarpOutput``; shapes as in :func:`warp_backward`.
    """

    def __init__(
        self,
        rel_depth_tol: float = 0.02,
        soft_depth: float = 0.0,
        min_weight: float = 1e-3,
        slope_limit: float = 0.25,
    ) -> None:
        super().__init__()
        self.slope_limit = slope_limit
        self.rel_depth_tol = rel_depth_tol
        self.soft_depth = soft_depth
        self.min_weight = min_weight

    def forward(
        self,
        src_image: Tensor,
        src_depth: Tensor,
        dst_depth: Tensor,
        K_src: Tensor,
        K_dst: Tensor,
        src_from_dst: Tensor,
        src_mask: Tensor | None = None,
        dst_mask: Tensor | None = None,
    ) -> BackwardWarpOutput:
        return warp_backward(
            src_image,
            src_depth,
            dst_depth,
            K_src,
            K_dst,
            src_from_dst,
            src_mask,
            dst_mask,
            self.rel_depth_tol,
            self.soft_depth,
            self.min_weight,
            self.slope_limit,
        )


class ForwardWarp(nn.Module):
    """``nn.Module`` form of :func:`warp_forward`.

    ``forward(src_image, src_depth, K_src, K_dst, dst_from_src, src_mask=None) ->
    ForwardWarpOutput``; shapes as in :func:`warp_forward`.
    """

    def __init__(self, dst_size: tuple[int, int], splat: str = "nearest") -> None:
        super().__init__()
        self.dst_size = (int(dst_size[0]), int(dst_size[1]))
        self.splat = splat

    def forward(
        self,
        src_image: Tensor,
        src_depth: Tensor,
        K_src: Tensor,
        K_dst: Tensor,
        dst_from_src: Tensor,
        src_mask: Tensor | None = None,
    ) -> ForwardWarpOutput:
        return warp_forward(
            src_image,
            src_depth,
            K_src,
            K_dst,
            dst_from_src,
            self.dst_size,
            src_mask,
            self.splat,  # type: ignore[arg-type]
        )
