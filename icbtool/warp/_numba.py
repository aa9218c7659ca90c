"""numba kernels of the numpy warps: the whole backward warp fused into one pass per target pixel.

:func:`backward_rows` does, for each target pixel of a range of rows, everything
:func:`icbtool.warp.functional.warp_backward` does with whole-image tensors (lift, move, project,
four bilinear taps, each tap depth-tested on its own with its inverse depth extrapolated along its
own surface slope, blend of the passing taps, cause masks, weight, density), with the same rules
and thresholds, and writes straight into the caller's output arrays: no temporaries, each source
pixel read only by the taps that need it. The torch function stays the differentiable path and
the reference (tests/test_warp.py requires that both agree).

Arithmetic is float64 inside the kernel whatever the input dtype (scalar code: no slower).

Like :mod:`icbtool.trace.kernels`, the kernels release the GIL (``nogil``) and take a row range,
so the caller splits a warp over a few Python threads (no numba threading layer, so they are safe
to call from any thread and do not compete with torch's OpenMP pool); they are compiled on first
use and cached on disk (``cache=True``: next to this file, or in ``~/.cache/numba`` /
``$NUMBA_CACHE_DIR`` when that is read-only). One signature per input dtype (float32 or float64
image and depths); masks are always bool.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)

_Z_EPS = 1e-8  # as functional._Z_EPS
_BIG = 1e30  # inverse depth standing for "no geometry" in slope differences (as functional)


@nb.njit(inline="always", **_JIT)
def _valid(depth, mask, has_mask, r, c):
    if has_mask:
        return mask[r, c]
    d = depth[r, c]
    return d > 0.0 and d < np.inf


@nb.njit(inline="always", **_JIT)
def _inv_depth(depth, mask, has_mask, r, c):
    """1/z of a source pixel, -1 where it has no geometry (fails every depth test)."""
    if _valid(depth, mask, has_mask, r, c):
        return 1.0 / np.float64(depth[r, c])
    return -1.0


@nb.njit(inline="always", **_JIT)
def _big(iz):
    """1/z, or 1e30 where there is no geometry (a difference to it is then an edge)."""
    return iz if iz >= 0.0 else _BIG


@nb.njit(inline="always", **_JIT)
def _pick(g_prev, g_next, iz, limit):
    """The one-sided difference of smaller magnitude (the forward one on ties); 0 if it is
    larger than ``limit * iz`` (an edge, not a slope)."""
    g = g_next if abs(g_next) <= abs(g_prev) else g_prev
    return g if abs(g) <= limit * iz else 0.0


@nb.njit(**_JIT)
def source_rows(src_depth, src_mask, has_src_mask, slope_limit, feats, row_lo, row_hi):
    """Per source pixel of rows [row_lo, row_hi): ``feats[r, c]`` = (1/z, d(1/z)/dx, d(1/z)/dy).

    1/z is -1 where there is no geometry (fails every depth test). The slopes are those of
    :func:`icbtool.warp.functional.inverse_depth_slopes`: per axis the one-sided difference of
    smaller magnitude (forward on ties; the only one at a border), with 1e30 standing for a
    neighbour without geometry; 0 if larger than ``slope_limit * iz`` (an edge), along an axis
    shorter than 3 pixels, or if ``slope_limit`` is 0. Only rows [row_lo, row_hi) are written
    (the neighbours' 1/z outside them is recomputed), so row ranges can run concurrently.

    Args:
        src_depth: (Hs, Ws) float32/64; src_mask: (Hs, Ws) bool, read if ``has_src_mask``.
        feats: (Hs, Ws, 3) float64 output.
    """
    hs, ws = src_depth.shape
    for r in range(row_lo, row_hi):
        for c in range(ws):
            feats[r, c, 0] = _inv_depth(src_depth, src_mask, has_src_mask, r, c)
    for r in range(row_lo, row_hi):
        for c in range(ws):
            iz = feats[r, c, 0]
            b = _big(iz)
            gx = 0.0
            gy = 0.0
            if slope_limit > 0.0:
                if ws >= 3:
                    prev = b - _big(feats[r, c - 1, 0]) if c > 0 else 0.0
                    nxt = _big(feats[r, c + 1, 0]) - b if c < ws - 1 else 0.0
                    if c == 0:
                        prev = nxt
                    elif c == ws - 1:
                        nxt = prev
                    gx = _pick(prev, nxt, iz, slope_limit)
                if hs >= 3:
                    prev = nxt = 0.0
                    if r > 0:
                        up = (
                            feats[r - 1, c, 0]
                            if r > row_lo
                            else _inv_depth(src_depth, src_mask, has_src_mask, r - 1, c)
                        )
                        prev = b - _big(up)
                    if r < hs - 1:
                        down = (
                            feats[r + 1, c, 0]
                            if r + 1 < row_hi
                            else _inv_depth(src_depth, src_mask, has_src_mask, r + 1, c)
                        )
                        nxt = _big(down) - b
                    if r == 0:
                        prev = nxt
                    elif r == hs - 1:
                        nxt = prev
                    gy = _pick(prev, nxt, iz, slope_limit)
            feats[r, c, 1] = gx
            feats[r, c, 2] = gy


@nb.njit(inline="always", **_JIT)
def _tap_weight(bw, t, z, lo, hi, rel_depth_tol, soft_depth):
    """Bilinear weight ``bw`` of a tap whose extrapolated inverse depth is ``t``, times its depth
    test against the point's depth ``z``: hard, ``|z t - 1| <= tol`` as the bounds ``lo``, ``hi``
    on ``t`` (as functional.warp_backward), or the sigmoid of ``soft_depth`` width (if t > 0)."""
    if soft_depth > 0.0:
        if t <= 0.0:
            return 0.0
        rel = abs(t * z - 1.0)
        return bw * (1.0 / (1.0 + math.exp(-(rel_depth_tol - rel) / soft_depth)))
    if t >= lo and t <= hi:
        return bw
    return 0.0


@nb.njit(**_JIT)
def backward_rows(
    src_image,
    feats,
    dst_depth,
    dst_mask,
    has_dst_mask,
    m,
    kt,
    dens_num,
    dens_den,
    rel_depth_tol,
    soft_depth,
    min_weight,
    out_image,
    out_holes,
    out_outside,
    out_disoccluded,
    out_no_geometry,
    out_weight,
    out_density,
    out_source,
    row_lo,
    row_hi,
):
    """Backward-warp target rows [row_lo, row_hi) (see the module docstring).

    Args:
        src_image: (Hs, Ws, C) float32/64.
        feats: (Hs, Ws, 3) float64 per source pixel: 1/z (-1: no geometry) and the
            inverse-depth slopes d/dx, d/dy (:func:`source_rows`).
        dst_depth: (Hd, Wd) float32/64 target view-space depth.
        dst_mask: (Hd, Wd) bool geometry mask, read only if ``has_dst_mask`` (then every pixel it
            marks has a finite depth > 0: the caller checks).
        m: (3, 3) float64 ``K_src R K_dst^-1``; kt: (3,) float64 ``K_src t``.
        dens_num, dens_den: ``sqrt(fx_src fy_src)`` and ``sqrt(fx_dst fy_dst)``.
        out_image: (Hd, Wd, C) float32; out_holes ... out_no_geometry: (Hd, Wd) bool;
            out_weight, out_density: (Hd, Wd) float32; out_source: (Hd, Wd) int16.
    """
    hs, ws, nc = src_image.shape
    wd = dst_depth.shape[1]
    fws, fhs = np.float64(ws), np.float64(hs)
    acc = np.empty(nc, np.float64)  # float64 blend of the taps (one per call)
    for i in range(row_lo, row_hi):
        v = i + 0.5
        for j in range(wd):
            u = j + 0.5
            dvalid = _valid(dst_depth, dst_mask, has_dst_mask, i, j)
            d = np.float64(dst_depth[i, j]) if dvalid else 1.0
            q0 = (m[0, 0] * u + m[0, 1] * v + m[0, 2]) * d + kt[0]
            q1 = (m[1, 0] * u + m[1, 1] * v + m[1, 2]) * d + kt[1]
            q2 = (m[2, 0] * u + m[2, 1] * v + m[2, 2]) * d + kt[2]
            front = q2 > _Z_EPS
            z = q2 if front else 1.0
            us = q0 / z
            vs = q1 / z
            inside = front and us >= 0.0 and us <= fws and vs >= 0.0 and vs <= fhs
            covered = inside and dvalid
            out_no_geometry[i, j] = not dvalid
            out_outside[i, j] = dvalid and not inside
            wsum = 0.0
            if covered:
                # four taps, border replicated (the outer half pixel is inside the frustum)
                x = min(max(us - 0.5, -0.5), fws - 0.5)
                y = min(max(vs - 0.5, -0.5), fhs - 0.5)
                x0f = math.floor(x)
                y0f = math.floor(y)
                wx = x - x0f
                wy = y - y0f
                c0 = max(x0f, 0)
                c1 = min(x0f + 1, ws - 1)
                r0 = max(y0f, 0)
                r1 = min(y0f + 1, hs - 1)
                dx0 = x - c0
                dx1 = x - c1
                dy0 = y - r0
                dy1 = y - r1
                lo = (1.0 - rel_depth_tol) / z
                hi = (1.0 + rel_depth_tol) / z
                # each tap's 1/z extrapolated along its own slope to the sample, then tested
                t00 = feats[r0, c0, 0] + feats[r0, c0, 1] * dx0 + feats[r0, c0, 2] * dy0
                t01 = feats[r0, c1, 0] + feats[r0, c1, 1] * dx1 + feats[r0, c1, 2] * dy0
                t10 = feats[r1, c0, 0] + feats[r1, c0, 1] * dx0 + feats[r1, c0, 2] * dy1
                t11 = feats[r1, c1, 0] + feats[r1, c1, 1] * dx1 + feats[r1, c1, 2] * dy1
                w00 = _tap_weight(
                    (1.0 - wy) * (1.0 - wx), t00, z, lo, hi, rel_depth_tol, soft_depth
                )
                w01 = _tap_weight((1.0 - wy) * wx, t01, z, lo, hi, rel_depth_tol, soft_depth)
                w10 = _tap_weight(wy * (1.0 - wx), t10, z, lo, hi, rel_depth_tol, soft_depth)
                w11 = _tap_weight(wy * wx, t11, z, lo, hi, rel_depth_tol, soft_depth)
                wsum = (w00 + w01) + (w10 + w11)
                for ch in range(nc):
                    val = 0.0  # failing taps are skipped (a non-finite value there is not read)
                    if w00 != 0.0:
                        val += w00 * src_image[r0, c0, ch]
                    if w01 != 0.0:
                        val += w01 * src_image[r0, c1, ch]
                    if w10 != 0.0:
                        val += w10 * src_image[r1, c0, ch]
                    if w11 != 0.0:
                        val += w11 * src_image[r1, c1, ch]
                    acc[ch] = val
            ok = covered and wsum > min_weight
            out_holes[i, j] = not ok
            out_disoccluded[i, j] = covered and not ok
            if ok:
                scale = 1.0 / max(wsum, 1e-12)
                for ch in range(nc):
                    out_image[i, j, ch] = acc[ch] * scale
                out_weight[i, j] = wsum
                out_source[i, j] = 0
            else:
                for ch in range(nc):
                    out_image[i, j, ch] = 0.0
                out_weight[i, j] = 0.0
                out_source[i, j] = -1
            out_density[i, j] = (dens_num * d) / (dens_den * z) if covered else 0.0


@nb.njit(inline="always", **_JIT)
def _splat_target(src_depth, src_mask, has_src_mask, m, kt, r, c):
    """Where source pixel (r, c) lands in the target: (u, v, z, front) as in
    functional.warp_forward (``front``: has geometry and lies in front of the target camera)."""
    valid = _valid(src_depth, src_mask, has_src_mask, r, c)
    d = np.float64(src_depth[r, c]) if valid else 1.0
    u = c + 0.5
    v = r + 0.5
    q0 = (m[0, 0] * u + m[0, 1] * v + m[0, 2]) * d + kt[0]
    q1 = (m[1, 0] * u + m[1, 1] * v + m[1, 2]) * d + kt[1]
    q2 = (m[2, 0] * u + m[2, 1] * v + m[2, 2]) * d + kt[2]
    front = valid and q2 > _Z_EPS
    z = q2 if front else 1.0
    return q0 / z, q1 / z, q2, front


@nb.njit(**_JIT)
def forward_splat(
    src_image,
    src_depth,
    src_mask,
    has_src_mask,
    m,
    kt,
    footprint2,
    zbuf,
    out_image,
    out_depth,
    out_holes,
):
    """Forward warp (splat with a z-buffer) of a whole image, as functional.warp_forward: each
    source pixel centre goes to the target pixel containing it (or, with ``footprint2``, to the
    2x2 pixels around it); among points landing on one pixel the nearest wins (on exact ties,
    the last in row-major source order). Single-threaded (splats of different rows collide).

    Args:
        src_image: (Hs, Ws, C) float32/64; src_depth: (Hs, Ws) float32/64.
        src_mask: (Hs, Ws) bool, read if ``has_src_mask``.
        m: (3, 3) float64 ``K_dst R K_src^-1``; kt: (3,) float64 ``K_dst t``.
        zbuf: (Hd, Wd) float64 scratch. out_image: (Hd, Wd, C) float32; out_depth: (Hd, Wd)
            float32; out_holes: (Hd, Wd) bool.
    """
    hs, ws, nc = src_image.shape
    hd, wd = zbuf.shape
    zbuf[:, :] = np.inf
    half = 0.5 if footprint2 else 0.0
    n_off = 2 if footprint2 else 1
    for sweep in range(2):  # 1: nearest depth per target pixel, 2: the colour of the winner
        for r in range(hs):
            for c in range(ws):
                u, v, z, front = _splat_target(src_depth, src_mask, has_src_mask, m, kt, r, c)
                if not front:
                    continue
                bu = math.floor(min(max(u - half, -2.0), wd + 2.0))
                bv = math.floor(min(max(v - half, -2.0), hd + 2.0))
                for dv in range(n_off):
                    i = bv + dv
                    if i < 0 or i >= hd:
                        continue
                    for du in range(n_off):
                        j = bu + du
                        if j < 0 or j >= wd:
                            continue
                        if sweep == 0:
                            if z < zbuf[i, j]:
                                zbuf[i, j] = z
                        elif z <= zbuf[i, j]:
                            for ch in range(nc):
                                out_image[i, j, ch] = src_image[r, c, ch]
        if sweep == 0:
            for i in range(hd):
                for j in range(wd):
                    hole = zbuf[i, j] == np.inf
                    out_holes[i, j] = hole
                    out_depth[i, j] = 0.0 if hole else zbuf[i, j]
                    for ch in range(nc):
                        out_image[i, j, ch] = 0.0
