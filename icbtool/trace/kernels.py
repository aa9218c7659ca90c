"""numba kernels of the wavefront path tracer (one shading pass per path depth).

The Python driver in :mod:`icbtool.trace.tracer` alternates Embree queries (which release the GIL
and run on a few threads) with these kernels, which do all per-ray work: primary rays, hit
attributes, textures, emission with MIS, next-event estimation (sun, point/spot, emissive
triangles), cosine BSDF sampling, Russian roulette, compaction and accumulation.

Random numbers are a pure function of (seed, pixel, sample index, dimension), never of the thread
that computes them, so images do not depend on the number of threads. Two samplers:

- ``independent``: a splitmix64 hash per dimension (bit-compatible with the numpy tracer it
  replaced: same seeds give the same random numbers).
- ``sobol``: shuffled, Owen-scrambled 2D Sobol points per pair of dimensions (Burley 2020,
  "Practical Hash-based Owen Scrambling"), padded with independent per-pair scrambles: every
  sample is uniformly distributed (so the estimator stays unbiased) while the samples of one
  pixel are stratified in each pair (pixel area, BSDF direction, point on the light).

No ``fastmath``: NaN/Inf checks and IEEE behaviour must hold (stability stress tests). Every
kernel has ``cache=True``: numba writes its cache next to this file, or, when that directory is
read-only, in the user-wide cache (``~/.cache/numba`` or ``$NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_MASK32 = np.uint64(0xFFFFFFFF)
_U30 = np.uint64(30)
_U27 = np.uint64(27)
_U31 = np.uint64(31)
_U11 = np.uint64(11)
_U24 = np.uint64(24)
_U32 = np.uint64(32)
_U16 = np.uint64(16)
_U1 = np.uint64(1)
_U0 = np.uint64(0)
_INV53 = 1.0 / 9007199254740992.0
_INV32 = 1.0 / 4294967296.0
_PI = math.pi
_INV_PI = 1.0 / math.pi

#: dimensions per bounce (independent sampler): 0-1 bsdf direction, 2 light pick,
#: 3-4 point on light, 5 rr (as the numpy tracer)
DIMS_PER_BOUNCE = 8

SAMPLER_INDEPENDENT = 0
SAMPLER_SOBOL = 1

# destinations of a shadow ray's contribution
DEST_NONE = 0
DEST_GI = 1
DEST_DIRECT = 2


# ---------------------------------------------------------------------------------- random
@nb.njit(**_JIT)
def _mix(x):
    x = x ^ (x >> _U30)
    x = x * _M1
    x = x ^ (x >> _U27)
    x = x * _M2
    return x ^ (x >> _U31)


@nb.njit(**_JIT)
def _u01(base, salt):
    """Independent uniform in [0, 1) of one (sample base, dimension salt)."""
    return np.float64(_mix(base ^ salt) >> _U11) * _INV53


@nb.njit(**_JIT)
def _rev32(x):
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << _U1)
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | (
        (x & np.uint64(0x33333333)) << np.uint64(2)
    )
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | (
        (x & np.uint64(0x0F0F0F0F)) << np.uint64(4)
    )
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | (
        (x & np.uint64(0x00FF00FF)) << np.uint64(8)
    )
    x = ((x >> _U16) & np.uint64(0x0000FFFF)) | ((x & np.uint64(0x0000FFFF)) << _U16)
    return x & _MASK32


@nb.njit(**_JIT)
def _lk_perm(x, seed):
    """Laine-Karras style hash permutation (Burley 2020's improved constants), 32 bit."""
    x = x ^ ((x * np.uint64(0x3D20ADEA)) & _MASK32)
    x = (x + seed) & _MASK32
    x = (x * ((seed >> _U16) | _U1)) & _MASK32
    x = x ^ ((x * np.uint64(0x05526C56)) & _MASK32)
    x = x ^ ((x * np.uint64(0x53A22864)) & _MASK32)
    return x


@nb.njit(**_JIT)
def _nus(x, seed):
    """Nested uniform (Owen) scramble of a 32-bit fraction."""
    return _rev32(_lk_perm(_rev32(x), seed))


def _sobol1_rev_tables() -> np.ndarray:
    """(4, 256) uint64: XOR of the bit-reversed direction numbers of the second Sobol dimension
    (generator x + 1: w_0 = 1, w_{j+1} = w_j ^ (w_j << 1)) selected by each byte of the index."""
    w, x = [], 1
    for _ in range(32):
        w.append(x)
        x = (x ^ (x << 1)) & 0xFFFFFFFF
    t = np.zeros((4, 256), np.uint64)
    for k in range(4):
        for b in range(256):
            r = 0
            for j in range(8):
                if (b >> j) & 1:
                    r ^= w[8 * k + j]
            t[k, b] = r
    return t


_SOBOL1_REV = _sobol1_rev_tables()
_B8 = np.uint64(8)
_FF = np.uint64(0xFF)


def _splitmix_int(x: int) -> int:
    """splitmix64 finaliser on a Python int (as :func:`_mix`)."""
    m = (1 << 64) - 1
    x &= m
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & m
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & m
    return x ^ (x >> 31)


#: per-pair salts of the Sobol pair seeds (pairs 0 .. 63): mix((pair + 1) * golden ratio)
_PAIR_SALT = np.array([_splitmix_int((p + 1) * 0x9E3779B97F4A7C15) for p in range(64)], np.uint64)


@nb.njit(**_JIT)
def _sobol1_rev(i):
    """Bit-reversed second dimension of the Sobol sequence (4 table lookups, no branches)."""
    return (
        _SOBOL1_REV[0, i & _FF]
        ^ _SOBOL1_REV[1, (i >> _B8) & _FF]
        ^ _SOBOL1_REV[2, (i >> _U16) & _FF]
        ^ _SOBOL1_REV[3, (i >> np.uint64(24)) & _FF]
    )


@nb.njit(**_JIT)
def _pair_seed(pixseed, pair):
    return _mix(pixseed ^ _PAIR_SALT[pair])


@nb.njit(**_JIT)
def _shuffled_index(h, sid):
    """Owen-scrambled (bit-reversed) sample index: a per-pixel, per-pair shuffle that keeps
    every power-of-two prefix of samples a (0, m, 2)-net."""
    return _nus(np.uint64(sid) & _MASK32, h & _MASK32)


@nb.njit(**_JIT)
def _sobol2(pixseed, sid, pair):
    """Shuffled Owen-scrambled 2D Sobol point of sample ``sid`` in pair ``pair`` of a pixel.

    x0 = nus(rev(i)) = rev(lk(i)); x1 = nus(sobol1(i)) = rev(lk(rev(sobol1(i)))).
    """
    h = _pair_seed(pixseed, pair)
    i = _shuffled_index(h, sid)
    x0 = _rev32(_lk_perm(i, h >> _U32))
    x1 = _rev32(_lk_perm(_sobol1_rev(i), _mix(h + _GOLD) & _MASK32))
    return np.float64(x0) * _INV32, np.float64(x1) * _INV32


@nb.njit(**_JIT)
def _sobol1d(pixseed, sid, pair):
    """First coordinate of :func:`_sobol2` only (a 1D stratified, Owen-scrambled sample)."""
    h = _pair_seed(pixseed, pair)
    i = _shuffled_index(h, sid)
    return np.float64(_rev32(_lk_perm(i, h >> _U32))) * _INV32


#: the sobol sampler is used for the first LD_MAX_DEPTH vertices; deeper ones use hashes
LD_MAX_DEPTH = 2


@nb.njit(**_JIT)
def sample_base(seed_mix, pix, sid, out_base):
    """Per-sample hash base of the independent sampler (as the numpy tracer's ``_Rng``)."""
    for i in range(len(pix)):
        key = (np.uint64(pix[i]) << _U24) ^ np.uint64(sid[i])
        out_base[i] = _mix(key * _GOLD + seed_mix)


# ---------------------------------------------------------------------------------- camera
@nb.njit(**_JIT)
def primary_rays(
    pix, sid, base, salts, width, intr, r_wc, pos, jitter, sampler, pixseed0, o32, d32, d64, lo, hi
):
    """Primary rays of (pixel, sample) pairs lo..hi-1 into o32, d32 (P, 3) float32 and d64.

    intr = (fx, fy, cx, cy); r_wc (3, 3) world_from_cam rotation; pos (3,) camera centre.
    """
    for i in range(lo, hi):
        if jitter:
            if sampler == SAMPLER_SOBOL:
                ps = _mix(pixseed0 ^ (np.uint64(pix[i]) * _GOLD))
                jx, jy = _sobol2(ps, sid[i], 0)
            else:
                jx = _u01(base[i], salts[0])
                jy = _u01(base[i], salts[1])
        else:
            jx = 0.5
            jy = 0.5
        u = np.float64(pix[i] % width) + jx
        v = np.float64(pix[i] // width) + jy
        x = (u - intr[2]) / intr[0]
        y = (v - intr[3]) / intr[1]
        nrm = math.sqrt(x * x + y * y + 1.0)
        x /= nrm
        y /= nrm
        z = 1.0 / nrm
        for k in range(3):
            dk = r_wc[k, 0] * x + r_wc[k, 1] * y + r_wc[k, 2] * z
            d64[i, k] = dk
            d32[i, k] = dk
            o32[i, k] = pos[k]


# ---------------------------------------------------------------------------------- shading
@nb.njit(**_JIT)
def _sky(sky_kind, sky, dx, dy, dz):
    """Sky radiance along (dx, dy, dz); sky = [zenith, horizon, ground, up] (float32 values)."""
    if sky_kind == 1:
        return (
            np.float64(np.float32(sky[0, 0])),
            np.float64(np.float32(sky[0, 1])),
            np.float64(np.float32(sky[0, 2])),
        )
    c = dx * sky[3, 0] + dy * sky[3, 1] + dz * sky[3, 2]
    if c >= 0:
        w = math.sqrt(min(max(c, 0.0), 1.0))
        return (
            np.float64(np.float32((1 - w) * sky[1, 0] + w * sky[0, 0])),
            np.float64(np.float32((1 - w) * sky[1, 1] + w * sky[0, 1])),
            np.float64(np.float32((1 - w) * sky[1, 2] + w * sky[0, 2])),
        )
    return (
        np.float64(np.float32(sky[2, 0])),
        np.float64(np.float32(sky[2, 1])),
        np.float64(np.float32(sky[2, 2])),
    )


@nb.njit(**_JIT)
def _eps(px, py, pz, t, diag):
    mag = max(abs(px), max(abs(py), abs(pz)))
    return 3e-5 * (mag + abs(t)) + 1e-6 * diag


@nb.njit(**_JIT)
def shade(
    # path state (n alive paths)
    idx,
    d64,
    thr,
    pdf_prev,
    from_first,
    # hits
    h_t,
    h_prim,
    h_u,
    h_v,
    # per-sample data (P)
    pix,
    sid,
    base,
    salts,
    # scene
    tri,
    fn,
    vn,
    face_albedo,
    face_emission,
    face_mat,
    face_uv,
    tex_flat,
    tex_off,
    tex_hw,
    face_light_pmf,
    face_area,
    face_is_area,
    emit_faces,
    emit_cdf,
    suns,
    punct,
    sky_kind,
    sky,
    # parameters: ints = depth, limit, rr_depth, sampler, nearest, shading_normals, want_aux,
    # shadow slots per path
    iparams,
    diag,
    pixseed0,
    # outputs per sample
    direct,
    gi,
    first_hit,
    alb_out,
    nrm_out,
    # outputs per path: shadow slots (n * L) and the next ray
    s_o,
    s_d,
    s_tf,
    s_c,
    s_dest,
    n_o,
    n_d,
    n_thr,
    n_pdf,
    alive,
    lo,
    hi,
):
    """Shade the hits of segment ``depth`` of paths lo..hi-1 (see module doc). In place.

    Ranges of paths write disjoint outputs (each path owns its sample), so several threads can
    shade disjoint ranges at once (the kernels release the GIL).

    suns: (S, 6) direction, irradiance. punct: (Q, 12) position, intensity, axis, cos_in,
    cos_out, is_spot. Shadow slots: L = S + Q + (1 if emitters) per path, s_dest 0 = unused.
    """
    depth = iparams[0]
    limit = iparams[1]
    rr_depth = iparams[2]
    sampler = iparams[3]
    nearest = iparams[4]
    shading_normals = iparams[5]
    want_aux = iparams[6]
    n_s = suns.shape[0]
    n_q = punct.shape[0]
    n_e = len(emit_faces)
    L = iparams[7]  # shadow slots per path (>= n_s + n_q + (1 if n_e > 0 else 0), >= 1)
    dim0 = 2 + depth * DIMS_PER_BOUNCE
    pair0 = 1 + 3 * depth
    for i in range(lo, hi):
        s = idx[i]
        alive[i] = False
        for j in range(L):
            s_dest[i * L + j] = DEST_NONE
        dx = d64[i, 0]
        dy = d64[i, 1]
        dz = d64[i, 2]
        t0 = thr[i, 0]
        t1 = thr[i, 1]
        t2 = thr[i, 2]
        prim = h_prim[i]
        if prim < 0:
            if sky_kind != 0:
                le = _sky(sky_kind, sky, dx, dy, dz)
                if depth == 1:
                    direct[s, 0] += le[0] * t0
                    direct[s, 1] += le[1] * t1
                    direct[s, 2] += le[2] * t2
                else:
                    gi[s, 0] += le[0] * t0
                    gi[s, 1] += le[1] * t1
                    gi[s, 2] += le[2] * t2
            continue
        b1 = np.float64(h_u[i])
        b2 = np.float64(h_v[i])
        th = np.float64(h_t[i])
        w0 = 1.0 - b1 - b2
        x0 = w0 * tri[prim, 0, 0] + b1 * tri[prim, 1, 0] + b2 * tri[prim, 2, 0]
        x1 = w0 * tri[prim, 0, 1] + b1 * tri[prim, 1, 1] + b2 * tri[prim, 2, 1]
        x2 = w0 * tri[prim, 0, 2] + b1 * tri[prim, 1, 2] + b2 * tri[prim, 2, 2]
        g0 = fn[prim, 0]
        g1 = fn[prim, 1]
        g2 = fn[prim, 2]
        cos_o = -(g0 * dx + g1 * dy + g2 * dz)
        if g0 == 0 and g1 == 0 and g2 == 0:
            g0, g1, g2 = -dx, -dy, -dz
            cos_o = 1.0
        front = cos_o > 0
        if front:
            nf0, nf1, nf2 = g0, g1, g2
        else:
            nf0, nf1, nf2 = -g0, -g1, -g2
        if shading_normals:
            a0 = w0 * vn[prim, 0, 0] + b1 * vn[prim, 1, 0] + b2 * vn[prim, 2, 0]
            a1 = w0 * vn[prim, 0, 1] + b1 * vn[prim, 1, 1] + b2 * vn[prim, 2, 1]
            a2 = w0 * vn[prim, 0, 2] + b1 * vn[prim, 1, 2] + b2 * vn[prim, 2, 2]
            ln = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            if ln > 1e-20:
                ns0, ns1, ns2 = a0 / ln, a1 / ln, a2 / ln
            else:
                ns0, ns1, ns2 = nf0, nf1, nf2
            if ns0 * nf0 + ns1 * nf1 + ns2 * nf2 < 0:
                ns0, ns1, ns2 = -ns0, -ns1, -ns2
        else:
            ns0, ns1, ns2 = nf0, nf1, nf2
        # ---- emission seen (one-sided)
        e0 = face_emission[prim, 0]
        e1 = face_emission[prim, 1]
        e2 = face_emission[prim, 2]
        if front and (e0 > 0 or e1 > 0 or e2 > 0):
            if depth == 1:
                direct[s, 0] += e0 * t0
                direct[s, 1] += e1 * t1
                direct[s, 2] += e2 * t2
            else:
                pl = (
                    face_light_pmf[prim]
                    / max(face_area[prim], 1e-300)
                    * th
                    * th
                    / max(cos_o, 1e-12)
                )
                pb = pdf_prev[i]
                w = pb * pb / max(pb * pb + pl * pl, 1e-300) if pl > 0 else 1.0
                if from_first[i] and face_is_area[prim]:
                    direct[s, 0] += e0 * t0 * w
                    direct[s, 1] += e1 * t1 * w
                    direct[s, 2] += e2 * t2 * w
                else:
                    gi[s, 0] += e0 * t0 * w
                    gi[s, 1] += e1 * t1 * w
                    gi[s, 2] += e2 * t2 * w
        # ---- albedo (texture with repeat)
        al0 = face_albedo[prim, 0]
        al1 = face_albedo[prim, 1]
        al2 = face_albedo[prim, 2]
        m = face_mat[prim]
        if tex_off[m] >= 0:
            uu = w0 * face_uv[prim, 0, 0] + b1 * face_uv[prim, 1, 0] + b2 * face_uv[prim, 2, 0]
            vv = w0 * face_uv[prim, 0, 1] + b1 * face_uv[prim, 1, 1] + b2 * face_uv[prim, 2, 1]
            th_ = tex_hw[m, 0]
            tw_ = tex_hw[m, 1]
            off = tex_off[m]
            xx = uu * tw_ - 0.5
            yy = (1.0 - vv) * th_ - 0.5
            if nearest:
                xi = np.int64(math.floor(xx + 0.5)) % tw_
                yi = np.int64(math.floor(yy + 0.5)) % th_
                p = off + (yi * tw_ + xi) * 3
                al0 *= np.float64(tex_flat[p])
                al1 *= np.float64(tex_flat[p + 1])
                al2 *= np.float64(tex_flat[p + 2])
            else:
                fx0 = math.floor(xx)
                fy0 = math.floor(yy)
                fx = xx - fx0
                fy = yy - fy0
                xa = np.int64(fx0) % tw_
                ya = np.int64(fy0) % th_
                xb = (xa + 1) % tw_
                yb = (ya + 1) % th_
                p00 = off + (ya * tw_ + xa) * 3
                p01 = off + (ya * tw_ + xb) * 3
                p10 = off + (yb * tw_ + xa) * 3
                p11 = off + (yb * tw_ + xb) * 3
                ga = (1 - fy) * (1 - fx)
                gb = (1 - fy) * fx
                gc = fy * (1 - fx)
                gd = fy * fx
                al0 *= (ga * np.float64(tex_flat[p00]) + gb * np.float64(tex_flat[p01])) + (
                    gc * np.float64(tex_flat[p10]) + gd * np.float64(tex_flat[p11])
                )
                al1 *= (ga * np.float64(tex_flat[p00 + 1]) + gb * np.float64(tex_flat[p01 + 1])) + (
                    gc * np.float64(tex_flat[p10 + 1]) + gd * np.float64(tex_flat[p11 + 1])
                )
                al2 *= (ga * np.float64(tex_flat[p00 + 2]) + gb * np.float64(tex_flat[p01 + 2])) + (
                    gc * np.float64(tex_flat[p10 + 2]) + gd * np.float64(tex_flat[p11 + 2])
                )
        if depth == 1:
            first_hit[s] = True
            if want_aux:
                alb_out[s, 0] = al0
                alb_out[s, 1] = al1
                alb_out[s, 2] = al2
                nrm_out[s, 0] = ns0
                nrm_out[s, 1] = ns1
                nrm_out[s, 2] = ns2
        if depth >= limit:
            continue
        f0 = t0 * al0
        f1 = t1 * al1
        f2 = t2 * al2
        if not (f0 > 0 or f1 > 0 or f2 > 0):
            continue
        eps = _eps(x0, x1, x2, th, diag)
        xo0 = x0 + nf0 * eps
        xo1 = x1 + nf1 * eps
        xo2 = x2 + nf2 * eps
        fo0 = f0 * _INV_PI
        fo1 = f1 * _INV_PI
        fo2 = f2 * _INV_PI
        dest_dl = DEST_DIRECT if depth == 1 else DEST_GI
        slot = i * L
        # ---- suns
        for j in range(n_s):
            wi0 = -suns[j, 0]
            wi1 = -suns[j, 1]
            wi2 = -suns[j, 2]
            c = min(ns0 * wi0 + ns1 * wi1 + ns2 * wi2, 1.0)
            if c > 0 and nf0 * wi0 + nf1 * wi1 + nf2 * wi2 > 0:
                s_o[slot, 0] = xo0
                s_o[slot, 1] = xo1
                s_o[slot, 2] = xo2
                s_d[slot, 0] = wi0
                s_d[slot, 1] = wi1
                s_d[slot, 2] = wi2
                s_tf[slot] = np.inf
                s_c[slot, 0] = fo0 * suns[j, 3] * c
                s_c[slot, 1] = fo1 * suns[j, 4] * c
                s_c[slot, 2] = fo2 * suns[j, 5] * c
                s_dest[slot] = dest_dl
            slot += 1
        # ---- point and spot lights
        for j in range(n_q):
            v0 = punct[j, 0] - x0
            v1 = punct[j, 1] - x1
            v2 = punct[j, 2] - x2
            dist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            dd = max(dist, 1e-300)
            wi0 = v0 / dd
            wi1 = v1 / dd
            wi2 = v2 / dd
            c = min(ns0 * wi0 + ns1 * wi1 + ns2 * wi2, 1.0)
            fall = 1.0
            if punct[j, 11] > 0:
                ca = -(wi0 * punct[j, 6] + wi1 * punct[j, 7] + wi2 * punct[j, 8])
                xf = min(max((ca - punct[j, 10]) / (punct[j, 9] - punct[j, 10]), 0.0), 1.0)
                fall = xf * xf * (3.0 - 2.0 * xf)
            i0 = punct[j, 3] * fall
            i1 = punct[j, 4] * fall
            i2 = punct[j, 5] * fall
            if (
                c > 0
                and nf0 * wi0 + nf1 * wi1 + nf2 * wi2 > 0
                and dist > 0
                and (i0 > 0 or i1 > 0 or i2 > 0)
            ):
                s_o[slot, 0] = xo0
                s_o[slot, 1] = xo1
                s_o[slot, 2] = xo2
                s_d[slot, 0] = wi0
                s_d[slot, 1] = wi1
                s_d[slot, 2] = wi2
                s_tf[slot] = dist * (1 - 1e-5) - eps
                g = c / (dist * dist)
                s_c[slot, 0] = fo0 * i0 * g
                s_c[slot, 1] = fo1 * i1 * g
                s_c[slot, 2] = fo2 * i2 * g
                s_dest[slot] = dest_dl
            slot += 1
        # ---- emissive triangles (power-sampled, MIS with the BSDF)
        use_ld = sampler == SAMPLER_SOBOL and depth <= LD_MAX_DEPTH
        ps = _mix(pixseed0 ^ (np.uint64(pix[s]) * _GOLD)) if use_ld else _U0
        if n_e > 0:
            if use_ld:
                ul = _sobol1d(ps, sid[s], pair0 + 1)
                ra, r2 = _sobol2(ps, sid[s], pair0 + 2)
            else:
                ul = _u01(base[s], salts[dim0 + 2])
                ra = _u01(base[s], salts[dim0 + 3])
                r2 = _u01(base[s], salts[dim0 + 4])
            # first k with cdf[k] > ul (searchsorted side='right')
            lo = 0
            hi = n_e
            while lo < hi:
                mid = (lo + hi) // 2
                if emit_cdf[mid] <= ul:
                    lo = mid + 1
                else:
                    hi = mid
            k = min(lo, n_e - 1)
            lf = emit_faces[k]
            r1 = math.sqrt(ra)
            ca_ = r1 * (1 - r2)
            cb_ = r1 * r2
            y0 = (
                tri[lf, 0, 0]
                + ca_ * (tri[lf, 1, 0] - tri[lf, 0, 0])
                + cb_ * (tri[lf, 2, 0] - tri[lf, 0, 0])
            )
            y1 = (
                tri[lf, 0, 1]
                + ca_ * (tri[lf, 1, 1] - tri[lf, 0, 1])
                + cb_ * (tri[lf, 2, 1] - tri[lf, 0, 1])
            )
            y2 = (
                tri[lf, 0, 2]
                + ca_ * (tri[lf, 1, 2] - tri[lf, 0, 2])
                + cb_ * (tri[lf, 2, 2] - tri[lf, 0, 2])
            )
            v0 = y0 - x0
            v1 = y1 - x1
            v2 = y2 - x2
            dist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            dd = max(dist, 1e-300)
            wi0 = v0 / dd
            wi1 = v1 / dd
            wi2 = v2 / dd
            c = min(ns0 * wi0 + ns1 * wi1 + ns2 * wi2, 1.0)
            cl = -(fn[lf, 0] * wi0 + fn[lf, 1] * wi1 + fn[lf, 2] * wi2)
            if c > 0 and cl > 0 and nf0 * wi0 + nf1 * wi1 + nf2 * wi2 > 0 and dist > 0:
                pl = face_light_pmf[lf] / face_area[lf] * dist * dist / cl
                pb = c * _INV_PI
                w = pl * pl / (pl * pl + pb * pb)
                g = c * w / pl
                eps_l = _eps(y0, y1, y2, dist, diag)
                s_o[slot, 0] = xo0
                s_o[slot, 1] = xo1
                s_o[slot, 2] = xo2
                s_d[slot, 0] = wi0
                s_d[slot, 1] = wi1
                s_d[slot, 2] = wi2
                s_tf[slot] = max(dist - eps - eps_l, 0.0)
                s_c[slot, 0] = fo0 * face_emission[lf, 0] * g
                s_c[slot, 1] = fo1 * face_emission[lf, 1] * g
                s_c[slot, 2] = fo2 * face_emission[lf, 2] * g
                s_dest[slot] = DEST_DIRECT if (depth == 1 and face_is_area[lf]) else DEST_GI
            slot += 1
        # ---- bounce: cosine-weighted about the shading normal (Duff et al. basis)
        if use_ld:
            u1, u2 = _sobol2(ps, sid[s], pair0)
        else:
            u1 = _u01(base[s], salts[dim0])
            u2 = _u01(base[s], salts[dim0 + 1])
        sign = 1.0 if ns2 >= 0 else -1.0
        a = -1.0 / (sign + ns2)
        b = ns0 * ns1 * a
        ta0 = 1 + sign * ns0 * ns0 * a
        ta1 = sign * b
        ta2 = -sign * ns0
        tb0 = b
        tb1 = sign + ns1 * ns1 * a
        tb2 = -ns1
        r = math.sqrt(u1)
        phi = 2 * _PI * u2
        zc = math.sqrt(max(0.0, 1 - u1))
        rc = r * math.cos(phi)
        rs = r * math.sin(phi)
        wi0 = rc * ta0 + rs * tb0 + zc * ns0
        wi1 = rc * ta1 + rs * tb1 + zc * ns1
        wi2 = rc * ta2 + rs * tb2 + zc * ns2
        below = wi0 * nf0 + wi1 * nf1 + wi2 * nf2
        if below <= 0:
            wi0 -= 2 * below * nf0
            wi1 -= 2 * below * nf1
            wi2 -= 2 * below * nf2
        ln = math.sqrt(wi0 * wi0 + wi1 * wi1 + wi2 * wi2)
        if ln > 1e-20:
            wi0, wi1, wi2 = wi0 / ln, wi1 / ln, wi2 / ln
        else:
            wi0, wi1, wi2 = nf0, nf1, nf2
        pdf = max(ns0 * wi0 + ns1 * wi1 + ns2 * wi2, 1e-12) * _INV_PI
        if depth + 1 > rr_depth:  # Russian roulette for the next segment
            q = min(max(f0, max(f1, f2)), 0.95)
            if not (_u01(base[s], salts[dim0 + 5]) < q):
                continue
            f0 /= q
            f1 /= q
            f2 /= q
        alive[i] = True
        n_o[i, 0] = xo0
        n_o[i, 1] = xo1
        n_o[i, 2] = xo2
        n_d[i, 0] = wi0
        n_d[i, 1] = wi1
        n_d[i, 2] = wi2
        n_thr[i, 0] = f0
        n_thr[i, 1] = f1
        n_thr[i, 2] = f2
        n_pdf[i] = pdf


@nb.njit(**_JIT)
def compact_paths(alive, idx, n_o, n_d, n_thr, n_pdf, idx2, o32, d32, d64, thr, pdf):
    """Copy the surviving paths, in order, into the output buffers; returns their count."""
    j = 0
    for i in range(len(alive)):
        if alive[i]:
            idx2[j] = idx[i]
            for k in range(3):
                o32[j, k] = n_o[i, k]
                d32[j, k] = n_d[i, k]
                d64[j, k] = n_d[i, k]
                thr[j, k] = n_thr[i, k]
            pdf[j] = n_pdf[i]
            j += 1
    return j


@nb.njit(**_JIT)
def compact_shadow(s_dest, s_o, s_d, s_tf, slots, o32, d32, tf):
    """Copy the used shadow slots, in order, into the output buffers; returns their count."""
    j = 0
    for i in range(len(s_dest)):
        if s_dest[i] != DEST_NONE:
            slots[j] = i
            for k in range(3):
                o32[j, k] = s_o[i, k]
                d32[j, k] = s_d[i, k]
            tf[j] = s_tf[i]
            j += 1
    return j


@nb.njit(**_JIT)
def add_shadow(blocked, slots, n_per_path, idx, s_c, s_dest, direct, gi):
    """Add the contributions of unblocked shadow rays to direct or gi (serial: no races)."""
    for j in range(len(slots)):
        if blocked[j]:
            continue
        sl = slots[j]
        s = idx[sl // n_per_path]
        if s_dest[sl] == DEST_DIRECT:
            for k in range(3):
                direct[s, k] += s_c[sl, k]
        else:
            for k in range(3):
                gi[s, k] += s_c[sl, k]


@nb.njit(**_JIT)
def welford_add(pix, x, n, mean, m2):
    """Merge samples x (P, C) of pixels pix (P,) into running count/mean/M2 (in place)."""
    c = x.shape[1]
    for i in range(len(pix)):
        p = pix[i]
        n[p] += 1
        inv = 1.0 / n[p]
        for k in range(c):
            delta = x[i, k] - mean[p, k]
            mean[p, k] += delta * inv
            m2[p, k] += delta * (x[i, k] - mean[p, k])


@nb.njit(**_JIT)
def accumulate_pass(
    pix, gi, direct, hit, alb, nrm, want_aux, lum_w,
    n_g, mean_g, m2_g, n_d, mean_d, m2_d, hit_sum, alb_sum, nrm_sum,
):  # fmt: skip
    """One pass's samples into the per-pixel statistics (in place): Welford mean/M2 of
    (gi rgb, gi luminance) and of direct, and sums of the hit flag, albedo and normal."""
    x = np.empty(4)
    for i in range(len(pix)):
        p = pix[i]
        x[0] = gi[i, 0]
        x[1] = gi[i, 1]
        x[2] = gi[i, 2]
        x[3] = gi[i, 0] * lum_w[0] + gi[i, 1] * lum_w[1] + gi[i, 2] * lum_w[2]
        n_g[p] += 1
        inv = 1.0 / n_g[p]
        for k in range(4):
            delta = x[k] - mean_g[p, k]
            mean_g[p, k] += delta * inv
            m2_g[p, k] += delta * (x[k] - mean_g[p, k])
        n_d[p] += 1
        inv = 1.0 / n_d[p]
        for k in range(3):
            delta = direct[i, k] - mean_d[p, k]
            mean_d[p, k] += delta * inv
            m2_d[p, k] += delta * (direct[i, k] - mean_d[p, k])
        if hit[i]:
            hit_sum[p] += 1.0
        if want_aux:
            for k in range(3):
                alb_sum[p, k] += alb[i, k]
                nrm_sum[p, k] += nrm[i, k]
