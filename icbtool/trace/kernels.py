"""numba kernels of the path tracer: whole paths per sample, Embree called from the kernel.

:func:`trace_paths` does all per-sample work: primary rays, closest hits and shadow rays (through
Embree 4's C API, see :mod:`icbtool.trace.rtc` and :func:`call3`), hit attributes, textures,
emission with MIS, next-event estimation (sun, point/spot, emissive triangles, sky or environment
map), cosine BSDF sampling and Russian roulette. It takes one parameter struct,
:data:`TraceParams` (named tuples: Embree, camera, surfaces, lights, sky, sampling) and its
scratch outputs (:data:`Outputs`) and the per-pixel statistics it adds every sample to
(:data:`PixelStats`); its steps are inlined helpers: :func:`_camera_ray`,
:func:`_hit_frame`, the texture footprint, and one sample function per light type
(:func:`_sun_sample`, :func:`_punctual_sample`, :func:`_emitter_point` + :func:`_emitter_sample`,
:func:`_sky_sample` + :func:`_sky_light_weight`) whose shadow ray the loop traces. The driver in
:mod:`icbtool.trace.tracer` runs it on a few Python threads (the kernels release the GIL), each
on whole pixels, so the samples go straight into their pixels' statistics (:func:`_add_sample`)
with no per-sample buffer and no serial merge.

Random numbers are a pure function of (seed, pixel, sample index, dimension), never of the thread
that computes them, so images do not depend on the number of threads. Two samplers:

- ``independent``: a splitmix64 hash per dimension (bit-compatible with the numpy tracer it
  replaced: same seeds give the same random numbers).
- ``sobol``: shuffled, Owen-scrambled 2D Sobol points per pair of dimensions (Burley 2020,
  "Practical Hash-based Owen Scrambling"), padded with independent per-pair scrambles: every
  sample is uniformly distributed (so the estimator stays unbiased) while the samples of one
  pixel are stratified in each pair (pixel area, BSDF direction, point on the light).
- ``zsobol`` (the ``sobol`` sampler with a Z key, ``Sampling.zshift >= 0``): the same Sobol
  points, but the index of a sample is its screen-space key, the pixel's Morton code followed by
  the sample index (:func:`_zkey`), nested-scrambled per pair (:func:`_zsobol2`). A pixel's
  samples stay one aligned block of indices (stratified as with ``sobol``), and so are those of
  every aligned 2^k x 2^k block of pixels: neighbouring pixels' errors become negatively
  correlated (blue noise on screen). The extra edge samples keep per-pixel points.

No ``fastmath``: NaN/Inf checks and IEEE behaviour must hold (stability stress tests). Every
kernel has ``cache=True``: numba writes its cache next to this file, or, when that directory is
read-only, in the user-wide cache (``~/.cache/numba`` or ``$NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from icbtool.trace.layout import RAYHIT_WORDS
from icbtool.trace.shapes import (
    shape_frame,
    shape_pdf,
    shape_sample,
    shapes_intersect,
    shapes_occluded,
)

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)

#: The first 16 hex digits of the SHA-256 of icbtool/trace/shapes.py, whose helpers these
#: kernels inline. numba's cache is keyed on the text of this file alone: a change there must
#: change this line too (a test checks), or cached kernels would keep the old shapes code.
SHAPES_SOURCE = "b7867323bc8227e5"

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
def _sobol_point(i, h):
    """Owen-scrambled 2D Sobol point of index ``i`` (scrambles from the pair seed ``h``).

    x0 = nus(rev(i)) = rev(lk(i)); x1 = nus(sobol1(i)) = rev(lk(rev(sobol1(i)))).
    """
    x0 = _rev32(_lk_perm(i, h >> _U32))
    x1 = _rev32(_lk_perm(_sobol1_rev(i), _mix(h + _GOLD) & _MASK32))
    return np.float64(x0) * _INV32, np.float64(x1) * _INV32


@nb.njit(**_JIT)
def _sobol2(pixseed, sid, pair):
    """Shuffled Owen-scrambled 2D Sobol point of sample ``sid`` in pair ``pair`` of a pixel."""
    h = _pair_seed(pixseed, pair)
    return _sobol_point(_shuffled_index(h, sid), h)


@nb.njit(**_JIT)
def _part1by1(v):
    """Bits of the 16-bit ``v`` spread to the even bit positions (for Morton codes)."""
    v = v & np.uint64(0xFFFF)
    v = (v | (v << _B8)) & np.uint64(0x00FF00FF)
    v = (v | (v << np.uint64(4))) & np.uint64(0x0F0F0F0F)
    v = (v | (v << np.uint64(2))) & np.uint64(0x33333333)
    v = (v | (v << _U1)) & np.uint64(0x55555555)
    return v


@nb.njit(inline="always", **_JIT)
def _zkey(x, y, sid, log2spp, zshift):
    """Screen-space sample key of the Z sampler: (Morton(x, y) << log2spp | sid), aligned to
    the top of 32 bits (``zshift`` = 32 - its width)."""
    m = _part1by1(np.uint64(x)) | (_part1by1(np.uint64(y)) << _U1)
    return (((m << np.uint64(log2spp)) | np.uint64(sid)) << np.uint64(zshift)) & _MASK32


@nb.njit(**_JIT)
def _zsobol2(zseed, zkey, zshift, pair):
    """Z-sampler point of pair ``pair``: the Sobol point whose index is the sample key
    :func:`_zkey` after a nested (Owen) scramble of its bits from the most significant down,
    seeded per pair. A pixel's samples are one aligned block of indices (stratified as
    :func:`_sobol2`'s), and so are the samples of every aligned 2^k x 2^k block of pixels: the
    pixels' errors are negatively correlated, blue noise on screen."""
    h = _pair_seed(zseed, pair)
    i = _nus(zkey, h & _MASK32) >> np.uint64(zshift)
    return _sobol_point(i, h)


@nb.njit(inline="always", **_JIT)
def _ld2(pixseed, sid, pair, zseed, zkey, zshift):
    """Low-discrepancy 2D point of pair ``pair``: :func:`_zsobol2` when the Z sampler is on
    (``zshift`` >= 0), else :func:`_sobol2`."""
    if zshift >= 0:
        return _zsobol2(zseed, zkey, zshift, pair)
    return _sobol2(pixseed, sid, pair)


#: the sobol sampler is used for the first LD_MAX_DEPTH vertices; deeper ones use hashes
LD_MAX_DEPTH = 2


@nb.njit(inline="always", **_JIT)
def _sample_base(seed_mix, pix, sid):
    """Hash base of one (pixel, sample) for the independent sampler (as the numpy tracer's
    ``_Rng``): its dimension d is ``_u01(base, salts[d])``."""
    key = (np.uint64(pix) << _U24) ^ np.uint64(sid)
    return _mix(key * _GOLD + seed_mix)


# ---------------------------------------------------------------------------------- shading
# Helpers take the few arrays they read (or scalars), never the parameter struct: numba increfs
# and decrefs (atomically) every array an inlined helper is given, per call; a struct of ~35
# arrays made the kernel 2-3x slower, a handful of arrays per vertex ~15 %.
@nb.njit(inline="always", **_JIT)
def _envmap(env, rot, scale, dx, dy, dz):
    """Radiance of the lat-long map ``env`` (H, W + 1, 3) float32 (last column = first) along
    the world direction (dx, dy, dz); ``rot``: world_from_map (3, 3). Mitsuba's envmap lookup
    (bilinear, half-texel shifted in u), see :class:`icbtool.scene.Sky`."""
    lx = rot[0, 0] * dx + rot[1, 0] * dy + rot[2, 0] * dz
    ly = rot[0, 1] * dx + rot[1, 1] * dy + rot[2, 1] * dz
    lz = rot[0, 2] * dx + rot[1, 2] * dy + rot[2, 2] * dz
    h = env.shape[0]
    w1 = env.shape[1]
    u = math.atan2(lx, -lz) * (0.5 * _INV_PI) - 0.5 / (w1 - 1)
    u -= math.floor(u)
    v = math.acos(min(max(ly, -1.0), 1.0)) * _INV_PI
    x = u * (w1 - 1)
    y = v * (h - 1)
    xi = min(np.int64(x), w1 - 2)
    yi = min(np.int64(y), h - 2)
    fx = x - xi
    fy = y - yi
    ga = (1 - fy) * (1 - fx)
    gb = (1 - fy) * fx
    gc = fy * (1 - fx)
    gd = fy * fx
    return (
        scale * (ga * env[yi, xi, 0] + gb * env[yi, xi + 1, 0])
        + scale * (gc * env[yi + 1, xi, 0] + gd * env[yi + 1, xi + 1, 0]),
        scale * (ga * env[yi, xi, 1] + gb * env[yi, xi + 1, 1])
        + scale * (gc * env[yi + 1, xi, 1] + gd * env[yi + 1, xi + 1, 1]),
        scale * (ga * env[yi, xi, 2] + gb * env[yi, xi + 1, 2])
        + scale * (gc * env[yi + 1, xi, 2] + gd * env[yi + 1, xi + 1, 2]),
    )


@nb.njit(inline="always", **_JIT)
def _sky(kind, sky, env, rot, scale, dx, dy, dz):
    """Sky radiance along (dx, dy, dz): :func:`_envmap` for an envmap (``kind == SKY_ENVMAP``),
    else :func:`_sky_analytic`."""
    if kind == SKY_ENVMAP:
        return _envmap(env, rot, scale, dx, dy, dz)
    return _sky_analytic(kind, sky, dx, dy, dz)


@nb.njit(inline="always", **_JIT)
def _sky_analytic(kind, sky, dx, dy, dz):
    """Radiance of a uniform or gradient sky along (dx, dy, dz); ``sky`` = [zenith, horizon,
    ground, up] (float32 values)."""
    if kind == SKY_UNIFORM:
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


@nb.njit(inline="always", **_JIT)
def _texel(tex, lut, p):
    """Texel value p: ``lut[tex[p]]`` (uint8 codes into the sRGB levels, 8-bit textures), or
    ``lut[p]`` when ``tex`` is empty (``lut`` then holds the float texels themselves)."""
    if len(tex) > 0:
        return np.float64(lut[np.int64(tex[p])])
    return np.float64(lut[p])


@nb.njit(inline="always", **_JIT)
def _bilerp(tex, lut, p00, p01, p10, p11, ga, gb, gc, gd):
    """One channel of a bilinear lookup: texels p00..p11 with weights ga..gd."""
    return (ga * _texel(tex, lut, p00) + gb * _texel(tex, lut, p01)) + (
        gc * _texel(tex, lut, p10) + gd * _texel(tex, lut, p11)
    )


@nb.njit(inline="always", **_JIT)
def _prefetch_texel(tex, lut, p):
    """Start loading texel p's cache line (its code, or its float value) without waiting."""
    if len(tex) > 0:
        _prefetch(tex, p)
    else:
        _prefetch(lut, p)


@nb.njit(inline="always", **_JIT)
def _texture_albedo(tex, lut, nearest, fp, al):
    """The albedo ``al`` (r, g, b) times the texture at footprint ``fp``: the
    :func:`_bilinear_footprint`, or with ``nearest`` the :func:`_nearest_texel` offset first."""
    p00, p01, p10, p11, ga, gb, gc, gd = fp
    if nearest:
        return (
            al[0] * _texel(tex, lut, p00),
            al[1] * _texel(tex, lut, p00 + 1),
            al[2] * _texel(tex, lut, p00 + 2),
        )
    return (
        al[0] * _bilerp(tex, lut, p00, p01, p10, p11, ga, gb, gc, gd),
        al[1] * _bilerp(tex, lut, p00 + 1, p01 + 1, p10 + 1, p11 + 1, ga, gb, gc, gd),
        al[2] * _bilerp(tex, lut, p00 + 2, p01 + 2, p10 + 2, p11 + 2, ga, gb, gc, gd),
    )


@nb.njit(inline="always", **_JIT)
def _hold_vertex(held, row, fp, al, t0, t1, t2):
    """Keep a textured vertex's texture footprint ``fp``, untextured albedo ``al`` and throughput
    t in its part's ``held`` row while its texels load (:func:`_held_throughput` reads them)."""
    p00, p01, p10, p11, ga, gb, gc, gd = fp
    held[row, 0] = np.float64(p00)  # texel offsets: exact in float64
    held[row, 1] = np.float64(p01)
    held[row, 2] = np.float64(p10)
    held[row, 3] = np.float64(p11)
    held[row, 4] = ga
    held[row, 5] = gb
    held[row, 6] = gc
    held[row, 7] = gd
    held[row, 8] = al[0]
    held[row, 9] = al[1]
    held[row, 10] = al[2]
    held[row, 11] = t0
    held[row, 12] = t1
    held[row, 13] = t2


@nb.njit(inline="always", **_JIT)
def _held_throughput(held, row, tex, lut, nearest):
    """The held vertex's albedo with its texture, throughput f = t * albedo and f / pi (the
    diffuse BSDF): (f0, f1, f2, f / pi)."""
    fp = (
        np.int64(held[row, 0]), np.int64(held[row, 1]), np.int64(held[row, 2]),
        np.int64(held[row, 3]), held[row, 4], held[row, 5], held[row, 6], held[row, 7],
    )  # fmt: skip
    al = _texture_albedo(tex, lut, nearest, fp, (held[row, 8], held[row, 9], held[row, 10]))
    f0 = held[row, 11] * al[0]
    f1 = held[row, 12] * al[1]
    f2 = held[row, 13] * al[2]
    return f0, f1, f2, (f0 * _INV_PI, f1 * _INV_PI, f2 * _INV_PI)


@nb.njit(inline="always", **_JIT)
def _hold_light(held, row, nh, to_direct, l0, l1, l2, g):
    """Keep light sample ``nh`` of a held vertex (its radiance, factor g and destination), to be
    added once the vertex's albedo is known; returns the new count."""
    r = row + 1 + nh
    held[r, 0] = l0
    held[r, 1] = l1
    held[r, 2] = l2
    held[r, 3] = g
    held[r, 4] = 1.0 if to_direct else 0.0
    return nh + 1


@nb.njit(inline="always", **_JIT)
def _towards(x0, x1, x2, y0, y1, y2):
    """Unit direction from point x to point y, and their distance: (w0, w1, w2, dist)."""
    v0 = y0 - x0
    v1 = y1 - x1
    v2 = y2 - x2
    dist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    dd = max(dist, 1e-300)
    return v0 / dd, v1 / dd, v2 / dd, dist


@nb.njit(inline="always", **_JIT)
def _eps(px, py, pz, t, diag):
    mag = max(abs(px), max(abs(py), abs(pz)))
    return 3e-5 * (mag + abs(t)) + 1e-6 * diag


# ---------------------------------------------------------------------------------- embree
@intrinsic
def call3(typingctx, fn, a, b, c):
    """Call the C function at integer address ``fn`` with three pointer arguments (no result).

    The address is a run-time argument, so kernels that use this stay cacheable."""
    sig = types.void(fn, a, b, c)

    def codegen(context, builder, signature, args):
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(x, i8p) for x in args[1:]])
        return context.get_dummy_value()

    return sig, codegen


_F16 = np.uint64(15)
_INVALID = np.uint32(0xFFFFFFFF)
#: The primitive map of a scene without instances (faces are Embree's primIDs).
_NO_MAP = np.zeros(0, np.int64)


@nb.njit(**_JIT)
def _rayhit(prim_map):
    """A 16-byte aligned RTCRayHit: (uint32 words, float32 view, first word, its address,
    ``prim_map``: the scene's primitive map, see :func:`_intersect`)."""
    buf = np.zeros(RAYHIT_WORDS + 4, np.uint32)
    addr = np.uint64(buf.ctypes.data)
    off = (np.uint64(16) - (addr & _F16)) & _F16
    return buf, buf.view(np.float32), np.int64(off >> np.uint64(2)), addr + off, prim_map


@intrinsic
def _stack_words(typingctx):
    """Pointers (uint32*, float32*) to RAYHIT_WORDS 16-byte aligned words on the calling
    function's stack (allocated once, in its entry block): the RTCRayHit record of a kernel
    compiled without numba's reference counting (``_nrt=False``, see :func:`trace_paths`),
    which cannot allocate arrays."""
    sig = types.Tuple((types.CPointer(types.uint32), types.CPointer(types.float32)))()

    def codegen(context, builder, signature, args):
        buf = cgutils.alloca_once(builder, ir.ArrayType(ir.IntType(32), RAYHIT_WORDS))
        buf.align = 16
        pw = builder.bitcast(buf, ir.IntType(32).as_pointer())
        pf = builder.bitcast(buf, ir.FloatType().as_pointer())
        return context.make_tuple(builder, signature.return_type, (pw, pf))

    return sig, codegen


@intrinsic
def _take_block(typingctx, queue):
    """The next block of a shared work queue: ``queue[0] += 1`` as one atomic step (LLVM
    ``atomicrmw add``), returning the old value. Parts that take blocks this way share the
    work by how fast each runs, not by a fixed split (docs/design.md, section 8)."""
    if not (isinstance(queue, types.Array) and queue.dtype == types.int64):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        one = ir.Constant(ir.IntType(64), 1)
        return builder.atomic_rmw("add", ary.data, one, "monotonic")

    return types.int64(queue), codegen


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Ask the CPU to start loading the cache line of ``arr[idx]`` (LLVM ``llvm.prefetch``, read,
    high locality) and go on without waiting: a later load of it then finds it in cache. A
    prefetch never faults, whatever the index."""
    if not (isinstance(arr, types.Array) and isinstance(idx, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        i8p = ir.IntType(8).as_pointer()
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), i8p)
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [ptr, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


@intrinsic
def _address(typingctx, ptr):
    """The address of a pointer, as uint64."""

    def codegen(context, builder, signature, args):
        return builder.ptrtoint(args[0], ir.IntType(64))

    return types.uint64(ptr), codegen


@nb.njit(inline="always", **_JIT)
def _set_ray(ray, ox, oy, oz, dx, dy, dz, tfar):
    w, f, k = ray[0], ray[1], ray[2]
    f[k] = ox
    f[k + 1] = oy
    f[k + 2] = oz
    f[k + 3] = 0.0
    f[k + 4] = dx
    f[k + 5] = dy
    f[k + 6] = dz
    f[k + 7] = 0.0
    f[k + 8] = tfar
    w[k + 9] = _INVALID
    w[k + 10] = 0
    w[k + 11] = 0


@nb.njit(inline="always", **_JIT)
def _intersect(rtc, fn, ray, ox, oy, oz, dx, dy, dz):
    """Closest hit of one float32 ray (in the RTCRayHit ``ray`` of :func:`_rayhit`):
    (t, prim or -1, u, v).

    The prim is the scene's face index. With Embree instancing (:class:`~icbtool.trace.rtc.
    RtcScene` of an instanced scene) the ray's primitive map ``ray[4]`` is not empty: a hit in
    instance i (``instID``) is face ``map[i] + primID`` (instance i's faces are one run of the
    scene's, in its prototype's order), a hit on the top level's triangles (geomID g = the
    number of instances) is face ``map[g + primID]``."""
    w, f, k, addr, pm = ray[0], ray[1], ray[2], ray[3], ray[4]
    _set_ray(ray, ox, oy, oz, dx, dy, dz, np.inf)
    w[k + 17] = _INVALID
    w[k + 18] = _INVALID
    w[k + 19] = _INVALID
    call3(fn, rtc, addr, _U0)
    if w[k + 18] == _INVALID:
        return f[k + 8], -1, np.float32(0.0), np.float32(0.0)
    prim = np.int64(w[k + 17])
    if pm.shape[0] > 0:
        inst = w[k + 19]
        if inst != _INVALID:
            prim += pm[np.int64(inst)]
        else:
            prim = pm[np.int64(w[k + 18]) + prim]
    return f[k + 8], prim, f[k + 15], f[k + 16]


@nb.njit(inline="always", **_JIT)
def _occluded(rtc, fn, ray, ox, oy, oz, dx, dy, dz, tfar):
    """Whether anything lies on the float32 ray segment 0 < t < tfar."""
    f, k, addr = ray[1], ray[2], ray[3]
    _set_ray(ray, ox, oy, oz, dx, dy, dz, tfar)
    call3(fn, rtc, addr, _U0)
    return f[k + 8] == -np.inf


@nb.njit(inline="always", **_JIT)
def _closest(rtc, fn, ray, shp, n_tri, ox, oy, oz, dx, dy, dz):
    """Closest hit of the ray from the float32 origin (ox, oy, oz) along the unit float64
    (dx, dy, dz) among Embree's triangles and the analytic shapes ``shp``: (t float64, prim or
    -1, u, v); shape k's prim is ``n_tri + k``."""
    h_t, prim, h_u, h_v = _intersect(
        rtc, fn, ray, ox, oy, oz, np.float32(dx), np.float32(dy), np.float32(dz)
    )
    th = np.float64(h_t)
    if shp.shape[0] > 0:
        t, k = shapes_intersect(
            shp, np.float64(ox), np.float64(oy), np.float64(oz), dx, dy, dz,
            th if prim >= 0 else np.inf,
        )  # fmt: skip
        if k >= 0:
            return t, n_tri + k, h_u, h_v
    return th, prim, h_u, h_v


@nb.njit(**_JIT)
def rtc_intersect_batch(rtc, fn, o, d, t, prim, u, v, lo, hi):
    """Closest hits of float32 rays lo..hi-1 (o, d (N, 3)) into t, prim (-1 = miss), u, v."""
    rtc_intersect_mapped(rtc, fn, o, d, t, prim, u, v, lo, hi, _NO_MAP)


@nb.njit(**_JIT)
def rtc_intersect_mapped(rtc, fn, o, d, t, prim, u, v, lo, hi, prim_map):
    """:func:`rtc_intersect_batch` with a BVH's primitive map (an instanced scene's
    :attr:`~icbtool.trace.rtc.RtcScene.prim_map`): prim is the scene's face index."""
    ray = _rayhit(prim_map)
    for i in range(lo, hi):
        a, b, c, e = _intersect(rtc, fn, ray, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2])
        t[i] = a
        prim[i] = b
        u[i] = c
        v[i] = e


@nb.njit(**_JIT)
def rtc_occluded_batch(rtc, fn, o, d, tfar, out, lo, hi):
    """Occlusion of float32 ray segments lo..hi-1 (0 < t < tfar) into out (True = blocked)."""
    ray = _rayhit(_NO_MAP)
    for i in range(lo, hi):
        out[i] = _occluded(
            rtc, fn, ray, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tfar[i]
        )


# ---------------------------------------------------------------------------------- sky table
@nb.njit(inline="always", **_JIT)
def _search_right(cdf, row, u):
    """First index k with cdf[row, k] > u (numpy's searchsorted(side='right') on one row of a
    2D CDF; a loop here is ~30 % faster than np.searchsorted in numba)."""
    a = 0
    b = cdf.shape[1]
    while a < b:
        mid = (a + b) // 2
        if cdf[row, mid] <= u:
            a = mid + 1
        else:
            b = mid
    return a


@nb.njit(inline="always", **_JIT)
def _cdf_pick(cdf, row, u):
    """(first index k with cdf[row, k] > u, the remainder of u within that cell in [0, 1))."""
    n = cdf.shape[1]
    k = min(_search_right(cdf, row, u), n - 1)
    lo = cdf[row, k - 1] if k > 0 else 0.0
    width = cdf[row, k] - lo
    r = (u - lo) / width if width > 0 else 0.5
    return k, min(max(r, 0.0), 0.9999999999999999)


@nb.njit(inline="always", **_JIT)
def _sky_sample(frame, marg, cond, pdf, rows, phi0, u1, u2):
    """A direction drawn from a sky table and its density: (dx, dy, dz, pdf).

    marg: (1, nc) row CDF; cond: (nc, nphi) column CDFs; rows are equal in ``c = d . up``
    (``rows == ROWS_COS``) or in the polar angle (``ROWS_THETA``, envmaps; uniform in ``c``
    within a row either way); columns start at azimuth ``phi0``."""
    nc, nphi = pdf.shape
    i, rc = _cdf_pick(marg, 0, u1)
    j, rp = _cdf_pick(cond, i, u2)
    if rows == ROWS_THETA:
        c_hi = math.cos(i * (_PI / nc))
        c_lo = math.cos((i + 1) * (_PI / nc))
        c = c_hi + rc * (c_lo - c_hi)
    else:
        c = -1.0 + (i + rc) * (2.0 / nc)
    phi = phi0 + (j + rp) * (2.0 * _PI / nphi)
    sn = math.sqrt(max(0.0, 1.0 - c * c))
    x = sn * math.cos(phi)
    y = sn * math.sin(phi)
    d0 = x * frame[0, 0] + y * frame[1, 0] + c * frame[2, 0]
    d1 = x * frame[0, 1] + y * frame[1, 1] + c * frame[2, 1]
    d2 = x * frame[0, 2] + y * frame[1, 2] + c * frame[2, 2]
    return d0, d1, d2, pdf[i, j]


@nb.njit(inline="always", **_JIT)
def _sky_pdf(frame, pdf, rows, phi0, dx, dy, dz):
    """Density of :func:`_sky_sample` at the unit direction (dx, dy, dz)."""
    nc, nphi = pdf.shape
    c = dx * frame[2, 0] + dy * frame[2, 1] + dz * frame[2, 2]
    if rows == ROWS_THETA:
        th = math.acos(min(max(c, -1.0), 1.0))
        i = min(max(np.int64(th * (nc / _PI)), 0), nc - 1)
    else:
        i = min(max(np.int64((c + 1.0) * 0.5 * nc), 0), nc - 1)
    j = 0
    if nphi > 1:
        phi = (
            math.atan2(
                dx * frame[1, 0] + dy * frame[1, 1] + dz * frame[1, 2],
                dx * frame[0, 0] + dy * frame[0, 1] + dz * frame[0, 2],
            )
            - phi0
        )
        if phi < 0:
            phi += 2.0 * _PI
        j = min(max(np.int64(phi * (nphi / (2.0 * _PI))), 0), nphi - 1)
    return pdf[i, j]


@nb.njit(**_JIT)
def sky_sample_batch(sk, u, out_d, out_pdf):
    """:func:`_sky_sample` of the :data:`SkyParams` ``sk`` for uniform pairs u (N, 2)."""
    frame, marg, cond, pdf, rows, phi0 = sk.frame, sk.marg, sk.cond, sk.pdf, sk.rows, sk.phi0
    for n in range(len(u)):
        d0, d1, d2, p = _sky_sample(frame, marg, cond, pdf, rows, phi0, u[n, 0], u[n, 1])
        out_d[n, 0] = d0
        out_d[n, 1] = d1
        out_d[n, 2] = d2
        out_pdf[n] = p


@nb.njit(**_JIT)
def sky_pdf_batch(sk, d, out):
    """:func:`_sky_pdf` of the :data:`SkyParams` ``sk`` for unit directions d (N, 3)."""
    frame, pdf, rows, phi0 = sk.frame, sk.pdf, sk.rows, sk.phi0
    for n in range(len(d)):
        out[n] = _sky_pdf(frame, pdf, rows, phi0, d[n, 0], d[n, 1], d[n, 2])


@nb.njit(**_JIT)
def sky_radiance_batch(sk, d, out):
    """:func:`_sky` of the :data:`SkyParams` ``sk`` for unit directions d (N, 3) (tests: the
    kernels' lookup equals Sky.radiance)."""
    kind, rad, env, rot, scale = sk.kind, sk.rad, sk.env, sk.env_rot, sk.env_scale
    for n in range(len(d)):
        a, b, c = _sky(kind, rad, env, rot, scale, d[n, 0], d[n, 1], d[n, 2])
        out[n, 0] = a
        out[n, 1] = b
        out[n, 2] = c


# ---------------------------------------------------------------------------------- parameters
# The parameter struct of trace_paths: named tuples (numba types every field; built by
# icbtool.trace.tracer.Tracer). Arrays are C-contiguous; scalars are int64 or float64.

#: Embree 4: scene handle, addresses of rtcIntersect1 and rtcOccluded1.
#: ``prim_map``: (K,) int64, empty unless the BVH instances prototypes (see :func:`_intersect`).
EmbreeFns = namedtuple("EmbreeFns", ["scene", "fn_intersect", "fn_occluded", "prim_map"])
#: Camera: (fx, fy, cx, cy), world_from_cam rotation (3, 3), centre (3,), image width, jitter
#: (1: box-filter the pixel, 0: its centre), extra emission samples per sample of each pixel
#: (N,) int32 (on the pixels an emitter's or the sky's edge crosses; empty: none anywhere),
#: kind (CAM_*), lens (3,) float64: aperture radius, focus distance, near clip (see
#: :class:`icbtool.camera.Camera`; read unless kind is CAM_PINHOLE).
View = namedtuple("View", ["intr", "r_wc", "pos", "width", "jitter", "edge_extra", "kind", "lens"])
#: Surfaces: per face (F) float32 corners (F, 3, 3), geometric normal (F, 3), corner normals
#: (F, 3, 3), material (F,), corner uvs (F, 3, 2); per material (M) albedo and emission (M, 3)
#: float64, texture offset into the texels (-1: untextured) and (h, w); texels: uint8 codes into
#: tex_lut, or empty with tex_lut the float32 texels (one dtype pair either way: one compiled
#: kernel); nearest (1: nearest texel, 0: bilinear), shading_normals
#: (1: interpolated, 0: flat), scene diagonal; the analytic shapes' table (S, SHAPE_COLS)
#: (:func:`icbtool.trace.shapes.pack_shapes`; S = 0: none). A shape k is primitive F + k of the
#: per-primitive arrays: ``face_mat`` and the Lights' ``face_light_pmf``, ``face_area``,
#: ``face_is_area`` have F + S entries (``tri``, ``face_n``, ``vn``, ``face_uv``: F).
Surfaces = namedtuple(
    "Surfaces",
    [
        "tri", "face_n", "vn", "face_mat", "face_uv", "mat_albedo", "mat_emission",
        "tex_flat", "tex_lut", "tex_off", "tex_hw", "nearest", "shading_normals", "diag",
        "shapes",
    ],
)  # fmt: skip
#: Lights: suns (S, 6) direction, irradiance; punct (Q, 12) position, intensity, axis, cos_in,
#: cos_out, is_spot (see :func:`_spot_falloff`: 2 = Mitsuba's profile, angles in place of the
#: cosines); emissive triangles: pmf (F,), area (F,), part of an AreaLight (F,),
#: emissive faces (E,) and their CDF (1, E).
Lights = namedtuple(
    "Lights", ["suns", "punct", "face_light_pmf", "face_area", "face_is_area", "emit_faces",
               "emit_cdf"],
)  # fmt: skip
#: Sky: kind (SKY_*), [zenith, horizon, ground, up] (4, 3), envmap (H, W + 1, 3) float32 (the
#: first column repeated), world_from_map (3, 3), its scale; importance table (see
#: icbtool.trace.tracer.SkyTable): frame (3, 3), marg (1, nc), cond (nc, nphi), pdf (nc, nphi),
#: rows (ROWS_*), phi0; mis (1: one light sample per vertex, MIS with the BSDF).
SkyParams = namedtuple(
    "SkyParams", ["kind", "rad", "env", "env_rot", "env_scale", "frame", "marg", "cond", "pdf",
                  "rows", "phi0", "mis"],
)  # fmt: skip
#: Sampling: hash seed, per-dimension salts (independent sampler), Sobol pixel seed, sampler
#: (SAMPLER_*), depth limit, Russian roulette depth, want_aux (1: first-hit albedo/normal), log2
#: of the sample slots per pixel and the shift of the Z key (-1: no Z key; see :func:`_zkey`),
#: the number of branches of a path after its first vertex (>= 1) and log2 of their slots.
Sampling = namedtuple(
    "Sampling",
    ["seed_mix", "salts", "pixseed", "sampler", "limit", "rr_depth", "want_aux", "log2spp",
     "zshift", "splits", "log2split"],
)  # fmt: skip
#: Everything trace_paths reads.
TraceParams = namedtuple("TraceParams", ["embree", "cam", "surf", "lights", "sky", "sampling"])
#: One sample's outputs, in a scratch row per part (``part * ROW_STRIDE``; n_parts * ROW_STRIDE
#: rows): direct, gi (R, 3), first hit (R,), first-hit albedo and normal (R, 3) (or (1, 3) when
#: not wanted); and ``held`` (R, 14): a textured vertex waiting for its texels, its footprint,
#: albedo and throughput in the part's first row, its light samples in the rows after it
#: (:func:`_hold_vertex`, :func:`_hold_light`).
Outputs = namedtuple("Outputs", ["direct", "gi", "first_hit", "albedo", "normal", "held"])
#: Rows between two parts' scratch rows: 64, so that no two threads write one cache line even in
#: the one-byte ``first_hit`` (8 rows apart, both threads' flags shared a line: every sample wrote
#: it).
ROW_STRIDE = 64
#: Per-pixel statistics every sample is added to (:func:`_add_sample`): luminance weights (3,);
#: the sample count (N,); Welford mean and M2 of gi rgb + luminance (N, 4), (N, 4) and of direct
#: (N, 3), (N, 3) (one count serves both: every sample adds to both); sums of the hit flag (N,),
#: first-hit albedo and normal (N, 3) (or (1, 3)).
PixelStats = namedtuple(
    "PixelStats",
    ["lum_w", "n", "mean_g", "m2_g", "mean_d", "m2_d", "hit_sum", "alb_sum", "nrm_sum"],
)

#: Camera kinds: a pinhole (every ray from the centre), a perspective camera with a thin lens
#: or a near clip (an origin per sample), an orthographic camera (an origin per image point).
CAM_PINHOLE = 0
CAM_PERSPECTIVE = 1
CAM_ORTHOGRAPHIC = 2
#: The lens sample's dimensions (independent sampler: LENS_DIM, LENS_DIM + 1; dimensions 2 .. 9
#: are free, the first bounce starts at 2 + DIMS_PER_BOUNCE) and Sobol pair (pairs 1 .. 3 are
#: free, the first bounce starts at 4): its own, so the aperture point correlates neither with
#: the pixel jitter (dimensions 0 - 1, pair 0) nor with any vertex's numbers.
LENS_DIM = 2
LENS_PAIR = 1

SKY_NONE = 0
SKY_UNIFORM = 1
SKY_GRADIENT = 2
SKY_ENVMAP = 3
ROWS_COS = 0
ROWS_THETA = 1

#: salt of the independent sampler's hash base of a branch (splits > 1)
_SPLIT_SALT = np.uint64(0xD1B54A32D192ED03)

#: Samples per block; the threads of a pass take every n-th block (balanced, no false sharing).
BLOCK = 256

#: Sobol pairs of the sky light sample (vertices 1 .. LD_MAX_DEPTH): after the other dimensions
SKY_PAIR0 = 1 + 3 * (LD_MAX_DEPTH + 1)
#: Sobol pair of the extra emission samples' pixel positions (point ``sid * k + j`` for extra
#: sample j of sample sid, k extras per sample: all of a pixel's extras are one Sobol prefix)
EDGE_PAIR = SKY_PAIR0 + LD_MAX_DEPTH + 1


# ---------------------------------------------------------------------------------- path steps
@nb.njit(inline="always", **_JIT)
def _camera_ray(cam, sampler, salts, pix_s, sid_s, ps_pix, base_s, zk):
    """Float32 origin and unit world direction (ox, oy, oz, dx, dy, dz) of the camera ray of
    sample ``sid_s`` through pixel ``pix_s`` (jittered or centred; a thin lens's from its own
    lens sample); ``cam``: :data:`View`; ``zk``: (zseed, zkey, zshift) of :func:`_ld2`."""
    if cam.jitter:
        if sampler == SAMPLER_SOBOL:
            jx, jy = _ld2(ps_pix, sid_s, 0, zk[0], zk[1], zk[2])
        else:
            jx = _u01(base_s, salts[0])
            jy = _u01(base_s, salts[1])
    else:
        jx = 0.5
        jy = 0.5
    px = np.float64(pix_s % cam.width) + jx
    py = np.float64(pix_s // cam.width) + jy
    lu1 = 0.5
    lu2 = 0.5
    if cam.kind == CAM_PERSPECTIVE and cam.lens[0] > 0:
        if sampler == SAMPLER_SOBOL:
            lu1, lu2 = _ld2(ps_pix, sid_s, LENS_PAIR, zk[0], zk[1], zk[2])
        else:
            lu1 = _u01(base_s, salts[LENS_DIM])
            lu2 = _u01(base_s, salts[LENS_DIM + 1])
    return _point_ray(cam, px, py, lu1, lu2)


@nb.njit(inline="always", **_JIT)
def _point_ray(cam, px, py, lu1, lu2):
    """Float32 origin and unit world direction of the camera ray through the image point
    (px, py) (pixels, from the top-left corner) from the lens sample (lu1, lu2) (Mitsuba's
    ``sample_ray``; see :class:`icbtool.camera.Camera`): a pinhole's from its centre, else
    from its own origin on the near clip plane."""
    pos = cam.pos
    if cam.kind == CAM_PINHOLE:
        dx, dy, dz = _ray_through(cam.intr, cam.r_wc, px, py)
        return np.float32(pos[0]), np.float32(pos[1]), np.float32(pos[2]), dx, dy, dz
    intr = cam.intr
    r = cam.r_wc
    x = (px - intr[2]) / intr[0]
    y = (py - intr[3]) / intr[1]
    near = cam.lens[2]
    if cam.kind == CAM_ORTHOGRAPHIC:
        ocx, ocy, ocz = x, y, near
        dcx, dcy, dcz = 0.0, 0.0, 1.0
    else:
        ax = 0.0
        ay = 0.0
        rad = cam.lens[0]
        if rad > 0:  # Mitsuba's camera x and y are icbtool's negated: so is its disk point
            ux, uy = _concentric_disk(lu1, lu2)
            ax = -rad * ux
            ay = -rad * uy
        fd = cam.lens[1]  # aim at the pinhole ray's point at depth fd
        dcx = x * fd - ax
        dcy = y * fd - ay
        nrm = math.sqrt(dcx * dcx + dcy * dcy + fd * fd)
        dcx /= nrm
        dcy /= nrm
        dcz = fd / nrm
        t = near / dcz
        ocx = ax + dcx * t
        ocy = ay + dcy * t
        ocz = dcz * t
    ox = pos[0] + r[0, 0] * ocx + r[0, 1] * ocy + r[0, 2] * ocz
    oy = pos[1] + r[1, 0] * ocx + r[1, 1] * ocy + r[1, 2] * ocz
    oz = pos[2] + r[2, 0] * ocx + r[2, 1] * ocy + r[2, 2] * ocz
    dx = r[0, 0] * dcx + r[0, 1] * dcy + r[0, 2] * dcz
    dy = r[1, 0] * dcx + r[1, 1] * dcy + r[1, 2] * dcz
    dz = r[2, 0] * dcx + r[2, 1] * dcy + r[2, 2] * dcz
    return np.float32(ox), np.float32(oy), np.float32(oz), dx, dy, dz


@nb.njit(inline="always", **_JIT)
def _ray_through(intr, r_wc, px, py):
    """Unit world direction of the camera ray through the image point (px, py) (pixels, from the
    top-left corner of the image)."""
    cxp = (px - intr[2]) / intr[0]
    cyp = (py - intr[3]) / intr[1]
    nrm = math.sqrt(cxp * cxp + cyp * cyp + 1.0)
    cxp /= nrm
    cyp /= nrm
    czp = 1.0 / nrm
    dx = r_wc[0, 0] * cxp + r_wc[0, 1] * cyp + r_wc[0, 2] * czp
    dy = r_wc[1, 0] * cxp + r_wc[1, 1] * cyp + r_wc[1, 2] * czp
    dz = r_wc[2, 0] * cxp + r_wc[2, 1] * cyp + r_wc[2, 2] * czp
    return dx, dy, dz


@nb.njit(inline="always", **_JIT)
def _emission_seen(
    fn, face_mat, mat_emission, sky_kind, sky, env, rot, scale, prim, dx, dy, dz, shape_front_seen
):
    """Radiance a camera ray along (dx, dy, dz) gets from what it reaches first, emission only:
    the front of an emissive face ``prim`` (one-sided, as :func:`_hit_frame` decides front; for
    an analytic shape, ``prim`` >= F, ``shape_front_seen`` says it), the sky when it misses
    (``prim < 0``), else 0."""
    if prim < 0:
        if sky_kind == SKY_NONE:
            return 0.0, 0.0, 0.0
        return _sky(sky_kind, sky, env, rot, scale, dx, dy, dz)
    m = face_mat[prim]
    e0 = mat_emission[m, 0]
    e1 = mat_emission[m, 1]
    e2 = mat_emission[m, 2]
    if not (e0 > 0 or e1 > 0 or e2 > 0):
        return 0.0, 0.0, 0.0
    if prim >= fn.shape[0]:  # an analytic shape: front = its (flipped) normal faces the ray
        return (e0, e1, e2) if shape_front_seen else (0.0, 0.0, 0.0)
    g0 = np.float64(fn[prim, 0])
    g1 = np.float64(fn[prim, 1])
    g2 = np.float64(fn[prim, 2])
    if g0 * dx + g1 * dy + g2 * dz < 0 or (g0 == 0 and g1 == 0 and g2 == 0):
        return e0, e1, e2
    return 0.0, 0.0, 0.0


@nb.njit(inline="always", **_JIT)
def _emission_through(rtc, fn_isect, ray, log, cam, px, py, surf, sky_p):
    """Emission seen (:func:`_emission_seen`) along the camera ray of ``cam`` (:data:`View`,
    the lens centre's) through the image point (px, py): one closest hit, logged as a camera
    ray. ``surf`` = (face normals, face materials, material emission), ``sky_p`` = the first
    five fields of :data:`SkyParams`. Triangles only: :func:`_emission_through_all` sees the
    analytic shapes too."""
    ox, oy, oz, dx, dy, dz = _point_ray(cam, px, py, 0.5, 0.5)
    _log_ray(log, 0, ox, oy, oz, dx, dy, dz, np.float32(np.inf))
    dx32, dy32, dz32 = np.float32(dx), np.float32(dy), np.float32(dz)
    _, prim, _, _ = _intersect(rtc, fn_isect, ray, ox, oy, oz, dx32, dy32, dz32)
    fn, face_mat, mat_emission = surf
    sky_kind, sky, env, rot, scale = sky_p
    return _emission_seen(
        fn, face_mat, mat_emission, sky_kind, sky, env, rot, scale, prim, dx, dy, dz, False
    )


@nb.njit(inline="always", **_JIT)
def _emission_through_all(rtc, fn_isect, ray, log, cam, px, py, surf, sky_p, shp):
    """:func:`_emission_through` among the triangles and the analytic shapes ``shp``."""
    ox, oy, oz, dx, dy, dz = _point_ray(cam, px, py, 0.5, 0.5)
    _log_ray(log, 0, ox, oy, oz, dx, dy, dz, np.float32(np.inf))
    fn, face_mat, mat_emission = surf
    n_tri = fn.shape[0]
    th, prim, _, _ = _closest(rtc, fn_isect, ray, shp, n_tri, ox, oy, oz, dx, dy, dz)
    front = False
    if prim >= n_tri:
        front = shape_frame(shp, prim - n_tri, np.float64(ox), np.float64(oy), np.float64(oz),
                            dx, dy, dz, th)[3]  # fmt: skip
    sky_kind, sky, env, rot, scale = sky_p
    return _emission_seen(
        fn, face_mat, mat_emission, sky_kind, sky, env, rot, scale, prim, dx, dy, dz, front
    )


@nb.njit(**_JIT)
def emission_at(p, lum_w, pts, out, lo, hi):
    """Luminance of the emission seen (:func:`_emission_seen`) along the camera rays through
    the image points ``pts[lo:hi]`` ((N, 2) x, y in pixels) into ``out``: the tracer compares a
    pixel's four corners to find the pixels an emitter's or the sky's edge crosses."""
    rtc, fn_isect = p.embree[0], p.embree[1]
    cam = p.cam
    surf = (p.surf.face_n, p.surf.face_mat, p.surf.mat_emission)
    shp = p.surf.shapes
    pw, pf = _stack_words()
    ray = (pw, pf, np.int64(0), _address(pw), p.embree[3])
    no_log = (np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32),
              np.zeros(1, np.float32), np.zeros(1, np.int8), np.zeros(1, np.int64))  # fmt: skip
    for n in range(lo, hi):
        e0, e1, e2 = _emission_through_all(
            rtc, fn_isect, ray, no_log, cam, pts[n, 0], pts[n, 1], surf, p.sky[:5], shp
        )
        out[n] = e0 * lum_w[0] + e1 * lum_w[1] + e2 * lum_w[2]


@nb.njit(inline="always", **_JIT)
def _hit_frame(tri, fn, vn, shading_normals, prim, h_u, h_v, dx, dy, dz):
    """Where a ray hit face ``prim`` at barycentrics (h_u, h_v): (point, barycentrics (w0, b1,
    b2), cos_o (geometric normal . -ray), front, forward-facing geometric normal nf, shading
    normal ns on nf's side), vectors as 3-tuples."""
    b1 = np.float64(h_u)
    b2 = np.float64(h_v)
    w0 = 1.0 - b1 - b2
    x0 = w0 * tri[prim, 0, 0] + b1 * tri[prim, 1, 0] + b2 * tri[prim, 2, 0]
    x1 = w0 * tri[prim, 0, 1] + b1 * tri[prim, 1, 1] + b2 * tri[prim, 2, 1]
    x2 = w0 * tri[prim, 0, 2] + b1 * tri[prim, 1, 2] + b2 * tri[prim, 2, 2]
    g0 = np.float64(fn[prim, 0])
    g1 = np.float64(fn[prim, 1])
    g2 = np.float64(fn[prim, 2])
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
    return (x0, x1, x2), (w0, b1, b2), cos_o, front, (nf0, nf1, nf2), (ns0, ns1, ns2)


@nb.njit(inline="always", **_JIT)
def _tex_coords(face_uv, prim, bary):
    """Texture coordinates (u, v) at barycentrics (w0, b1, b2) of face ``prim``."""
    w0, b1, b2 = bary
    uu = w0 * face_uv[prim, 0, 0] + b1 * face_uv[prim, 1, 0] + b2 * face_uv[prim, 2, 0]
    vv = w0 * face_uv[prim, 0, 1] + b1 * face_uv[prim, 1, 1] + b2 * face_uv[prim, 2, 1]
    return uu, vv


@nb.njit(inline="always", **_JIT)
def _wrap(i, n):
    """``i % n`` (the repeat wrap of a texel index, n > 0): a mask when n is a power of two (most
    textures), where it equals the modulo for negative i too, instead of an integer division."""
    if n & (n - 1) == 0:
        return i & (n - 1)
    return i % n


@nb.njit(inline="always", **_JIT)
def _nearest_texel(off, th, tw, uu, vv):
    """Offset of the nearest texel's red value at (uu, vv) in a texture at ``off`` in the
    texels (th x tw, RGB, repeat)."""
    xi = _wrap(np.int64(math.floor(uu * tw - 0.5 + 0.5)), tw)
    yi = _wrap(np.int64(math.floor((1.0 - vv) * th - 0.5 + 0.5)), th)
    return off + (yi * tw + xi) * 3


@nb.njit(inline="always", **_JIT)
def _bilinear_footprint(off, th, tw, uu, vv):
    """The four texel offsets (red values) and bilinear weights at (uu, vv) in a texture at
    ``off`` (th x tw, RGB, repeat): (p00, p01, p10, p11, ga, gb, gc, gd)."""
    xx = uu * tw - 0.5
    yy = (1.0 - vv) * th - 0.5
    fx0 = math.floor(xx)
    fy0 = math.floor(yy)
    fx = xx - fx0
    fy = yy - fy0
    xa = _wrap(np.int64(fx0), tw)
    ya = _wrap(np.int64(fy0), th)
    xb = xa + 1 if xa + 1 < tw else 0
    yb = ya + 1 if ya + 1 < th else 0
    return (
        off + (ya * tw + xa) * 3,
        off + (ya * tw + xb) * 3,
        off + (yb * tw + xa) * 3,
        off + (yb * tw + xb) * 3,
        (1 - fy) * (1 - fx),
        (1 - fy) * fx,
        fy * (1 - fx),
        fy * fx,
    )


@nb.njit(inline="always", **_JIT)
def _emission_mis_weight(pmf, area, th, cos_o, pdf_prev):
    """Power-heuristic weight of a BSDF-sampled hit on an emitter (face pick pmf, face area,
    distance th, cosine at the emitter cos_o) against the emitter sample."""
    pl = pmf / max(area, 1e-300) * th * th / max(cos_o, 1e-12)
    pb = pdf_prev
    return pb * pb / max(pb * pb + pl * pl, 1e-300) if pl > 0 else 1.0


# Light samples: each light type gives a direction wi, the shadow ray's length and whether the
# sample can contribute (above both normals); trace_paths traces the shadow ray and adds the
# contribution f / pi * radiance * geometry.
@nb.njit(inline="always", **_JIT)
def _sun_sample(d0, d1, d2, nf, ns):
    """A directional light travelling along d: (usable, wi, cos at the shading normal)."""
    wi0 = -d0
    wi1 = -d1
    wi2 = -d2
    c = min(ns[0] * wi0 + ns[1] * wi1 + ns[2] * wi2, 1.0)
    ok = c > 0 and nf[0] * wi0 + nf[1] * wi1 + nf[2] * wi2 > 0
    return ok, wi0, wi1, wi2, c


@nb.njit(inline="always", **_JIT)
def _spot_falloff(punct, j, wi0, wi1, wi2):
    """Falloff of point or spot light j of ``punct`` towards the unit wi (from the shading
    point to the light): 1 for a point light; a spot's profile (column 11: 1 smoothstep in cos
    between the cosines in columns 9 (inner) and 10 (outer); 2 linear in the angle between the
    angles in radians in columns 9 and 10, Mitsuba 3's spot)."""
    if punct[j, 11] == 0:
        return 1.0
    ca = -(wi0 * punct[j, 6] + wi1 * punct[j, 7] + wi2 * punct[j, 8])
    if punct[j, 11] > 1.5:
        a = math.acos(min(max(ca, -1.0), 1.0))
        return min(max((punct[j, 10] - a) / (punct[j, 10] - punct[j, 9]), 0.0), 1.0)
    xf = min(max((ca - punct[j, 10]) / (punct[j, 9] - punct[j, 10]), 0.0), 1.0)
    return xf * xf * (3.0 - 2.0 * xf)


@nb.njit(inline="always", **_JIT)
def _punctual_sample(punct, j, x, nf, ns, eps):
    """Point or spot light j of ``punct`` (Q, 12) from x: (usable, wi, shadow-ray length,
    intensity towards x (spot falloff applied), geometry cos / r^2)."""
    wi0, wi1, wi2, dist = _towards(x[0], x[1], x[2], punct[j, 0], punct[j, 1], punct[j, 2])
    c = min(ns[0] * wi0 + ns[1] * wi1 + ns[2] * wi2, 1.0)
    fall = _spot_falloff(punct, j, wi0, wi1, wi2)
    i0 = punct[j, 3] * fall
    i1 = punct[j, 4] * fall
    i2 = punct[j, 5] * fall
    ok = c > 0 and nf[0] * wi0 + nf[1] * wi1 + nf[2] * wi2 > 0 and dist > 0
    ok = ok and (i0 > 0 or i1 > 0 or i2 > 0)
    tf = np.float32(dist * (1 - 1e-5) - eps)
    g = c / (dist * dist) if ok else 0.0
    return ok, wi0, wi1, wi2, tf, (i0, i1, i2), g


@nb.njit(inline="always", **_JIT)
def _emitter_pick(emit_faces, emit_cdf, ul, ra, reuse):
    """The emitter (a face, or an analytic shape F + k) drawn by power (ul), and the first
    number of its point: ``ra``, or with ``reuse`` ul's remainder within the emitter's CDF cell
    (see :func:`_emitter_point`)."""
    if reuse:
        k, ra = _cdf_pick(emit_cdf, 0, ul)
    else:
        k = min(_search_right(emit_cdf, 0, ul), len(emit_faces) - 1)
    return emit_faces[k], ra


@nb.njit(inline="always", **_JIT)
def _triangle_point(tri, lf, ra, r2):
    """The uniform point (ra, r2) on face lf: (y0, y1, y2)."""
    r1 = math.sqrt(ra)
    ca = r1 * (1 - r2)
    cb = r1 * r2
    y0 = (
        np.float64(tri[lf, 0, 0])
        + ca * (np.float64(tri[lf, 1, 0]) - np.float64(tri[lf, 0, 0]))
        + cb * (np.float64(tri[lf, 2, 0]) - np.float64(tri[lf, 0, 0]))
    )
    y1 = (
        np.float64(tri[lf, 0, 1])
        + ca * (np.float64(tri[lf, 1, 1]) - np.float64(tri[lf, 0, 1]))
        + cb * (np.float64(tri[lf, 2, 1]) - np.float64(tri[lf, 0, 1]))
    )
    y2 = (
        np.float64(tri[lf, 0, 2])
        + ca * (np.float64(tri[lf, 1, 2]) - np.float64(tri[lf, 0, 2]))
        + cb * (np.float64(tri[lf, 2, 2]) - np.float64(tri[lf, 0, 2]))
    )
    return y0, y1, y2


@nb.njit(inline="always", **_JIT)
def _shape_light_sample(shp, k, pmf, diag, x, nf, ns, eps, u1, u2):
    """Analytic emitter shape k (pick pmf) sampled from x as Mitsuba 3 does
    (:func:`icbtool.trace.shapes.shape_sample`): as :func:`_emitter_sample`, (usable, shadow-ray
    direction from the offset origin, its length, geometry times the power-heuristic MIS
    weight against cosine BSDF sampling)."""
    ok, wi0, wi1, wi2, dist, pdf, y, _ = shape_sample(shp, k, x[0], x[1], x[2], u1, u2)
    c = min(ns[0] * wi0 + ns[1] * wi1 + ns[2] * wi2, 1.0)
    if not (ok and c > 0 and nf[0] * wi0 + nf[1] * wi1 + nf[2] * wi2 > 0):
        return False, wi0, wi1, wi2, np.float32(0.0), 0.0
    pl = pmf * pdf
    pb = c * _INV_PI
    g = c * pl / (pl * pl + pb * pb)
    eps_l = _eps(y[0], y[1], y[2], dist, diag)
    s0 = np.float64(np.float32(x[0] + nf[0] * eps))
    s1 = np.float64(np.float32(x[1] + nf[1] * eps))
    s2 = np.float64(np.float32(x[2] + nf[2] * eps))
    sw0, sw1, sw2, sdist = _towards(s0, s1, s2, y[0], y[1], y[2])
    return True, sw0, sw1, sw2, np.float32(max(sdist - eps_l, 0.0)), g


@nb.njit(inline="always", **_JIT)
def _emitter_point(tri, emit_faces, emit_cdf, ul, ra, r2, reuse):
    """An emissive face drawn by power (ul) and a uniform point on it (ra, r2): (face, point).
    With ``reuse``, ``ra`` is ignored and ul's remainder within the face's CDF cell takes its
    place, so that the whole light sample is one 2D point (ul, r2): stratifying that pair
    stratifies the point over all the emitters' area (with one face pick and a separate pair,
    the pick and the point were stratified apart)."""
    lf, ra = _emitter_pick(emit_faces, emit_cdf, ul, ra, reuse)
    return lf, _triangle_point(tri, lf, ra, r2)


@nb.njit(inline="always", **_JIT)
def _emitter_sample(y, nl, pmf, area, diag, x, nf, ns, eps):
    """The point y on an emissive face (normal nl, face pick pmf, area) seen from x: (usable,
    shadow-ray direction, shadow-ray length, geometry times the MIS weight against BSDF
    sampling, power heuristic).

    The shadow ray starts where the kernel starts it, at the offset float32 origin
    ``so = x + eps nf``, and is aimed from there at y (as Mitsuba's ``spawn_ray_to``), ending
    ``eps_l`` short of it. Aimed along x -> y from ``so`` instead, it met the emitter's own plane
    ``eps (nl . nf) / cl`` before y: where the emitter is seen at a grazing angle (small cl: a
    sphere light's rim, a large light seen from its side) the light hid itself, and a
    tessellated sphere light over a floor lost 10-18 % of its light."""
    wi0, wi1, wi2, dist = _towards(x[0], x[1], x[2], y[0], y[1], y[2])
    c = min(ns[0] * wi0 + ns[1] * wi1 + ns[2] * wi2, 1.0)
    cl = -(nl[0] * wi0 + nl[1] * wi1 + nl[2] * wi2)
    if not (c > 0 and cl > 0 and nf[0] * wi0 + nf[1] * wi1 + nf[2] * wi2 > 0 and dist > 0):
        return False, wi0, wi1, wi2, np.float32(0.0), 0.0
    pl = pmf / area * dist * dist / cl
    pb = c * _INV_PI
    # c * w / pl with w = pl^2 / (pl^2 + pb^2), written so that a huge pl (an emitter seen edge-on)
    # gives 0, not inf / inf
    g = c * pl / (pl * pl + pb * pb)
    eps_l = _eps(y[0], y[1], y[2], dist, diag)
    s0 = np.float64(np.float32(x[0] + nf[0] * eps))  # the shadow ray's origin, as the kernel's
    s1 = np.float64(np.float32(x[1] + nf[1] * eps))
    s2 = np.float64(np.float32(x[2] + nf[2] * eps))
    sw0, sw1, sw2, sdist = _towards(s0, s1, s2, y[0], y[1], y[2])
    tf = np.float32(max(sdist - eps_l, 0.0))
    return True, sw0, sw1, sw2, tf, g


@nb.njit(inline="always", **_JIT)
def _sky_light_weight(psk, wi0, wi1, wi2, nf, ns):
    """A sky direction drawn from its table with density psk: (usable, geometry times the MIS
    weight against BSDF sampling, power heuristic)."""
    c = min(ns[0] * wi0 + ns[1] * wi1 + ns[2] * wi2, 1.0)
    if not (psk > 0 and c > 0 and nf[0] * wi0 + nf[1] * wi1 + nf[2] * wi2 > 0):
        return False, 0.0
    pb = c * _INV_PI
    return True, c * (psk / (psk * psk + pb * pb))  # c * w / psk, w = power heuristic


# Taylor coefficients of sin and cos up to x^17 / x^16: on |x| <= pi / 4 the truncation error is
# below 1e-16 (x^19 / 19! < 1.3e-19, x^18 / 18! < 1.0e-17), as accurate as libm's sincos there.
_S3, _S5, _S7, _S9, _S11, _S13, _S15, _S17 = (
    (-1) ** k / math.factorial(2 * k + 1) for k in range(1, 9)
)
_C2, _C4, _C6, _C8, _C10, _C12, _C14, _C16 = (
    (-1) ** k / math.factorial(2 * k) for k in range(1, 9)
)


@nb.njit(inline="always", **_JIT)
def _sincos_quarter(x):
    """(sin x, cos x) for |x| <= pi / 4: two short polynomials instead of a libm call (which took
    6 % of the Cornell box's render time in cosine sampling alone)."""
    z = x * x
    s = _S13 + z * (_S15 + z * _S17)
    s = _S7 + z * (_S9 + z * (_S11 + z * s))
    s = x + x * z * (_S3 + z * (_S5 + z * s))
    c = _C12 + z * (_C14 + z * _C16)
    c = _C6 + z * (_C8 + z * (_C10 + z * c))
    c = 1.0 + z * (_C2 + z * (_C4 + z * c))
    return s, c


@nb.njit(inline="always", **_JIT)
def _concentric_disk(u1, u2):
    """Shirley and Chiu's concentric map of the unit square onto the unit disk: area-preserving
    like the polar map (r = sqrt(u1), phi = 2 pi u2) but with little distortion, so stratified
    (Sobol) points stay well spread on the disk; its angles lie within pi / 4 of an axis."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        s, c = _sincos_quarter((0.25 * _PI) * (b / a))
        return a * c, a * s
    s, c = _sincos_quarter((0.25 * _PI) * (a / b))
    return b * s, b * c  # angle pi / 2 - x: (cos, sin) = (sin x, cos x)


@nb.njit(inline="always", **_JIT)
def _cosine_sample(nf, ns, u1, u2):
    """A cosine-weighted direction about the shading normal (Duff et al. basis; Malley's method
    on :func:`_concentric_disk`), mirrored above the geometric surface, and its density: (wi0,
    wi1, wi2, pdf)."""
    ns0, ns1, ns2 = ns
    nf0, nf1, nf2 = nf
    sign = 1.0 if ns2 >= 0 else -1.0
    a = -1.0 / (sign + ns2)
    b = ns0 * ns1 * a
    ta0 = 1 + sign * ns0 * ns0 * a
    ta1 = sign * b
    ta2 = -sign * ns0
    tb0 = b
    tb1 = sign + ns1 * ns1 * a
    tb2 = -ns1
    rc, rs = _concentric_disk(u1, u2)
    zc = math.sqrt(max(0.0, 1 - (rc * rc + rs * rs)))
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
    return wi0, wi1, wi2, max(ns0 * wi0 + ns1 * wi1 + ns2 * wi2, 1e-12) * _INV_PI


# No reference counting in the megakernel (_nrt=False): it allocates nothing (the ray record is
# on its stack), its arrays are its arguments' (kept alive by the caller), and numba would
# otherwise incref/decref (atomically, on arrays both threads share) every array an inlined
# helper receives: 12 % of the single-thread CPU time on the Cornell box, 7 % on Sponza.
@nb.njit(_nrt=False, **_JIT)
def trace_paths(p, out, acc, counts, log, part, queue, pix, sid, bounds):
    """Trace one whole path per sample (every depth, shadow rays inline) for a share of samples
    and add each sample to its pixel's statistics. With ``Sampling.splits`` = k > 1 the path
    branches after its first vertex's light sample: branch 0 goes on from there, branches 1 ..
    k - 1 restart from the saved first vertex; each carries 1 / k of the throughput and draws
    its numbers from its own slot ``sid * k + branch``.

    Args:
        p: :data:`TraceParams`.
        out: :data:`Outputs` (scratch rows; this part's row is overwritten).
        acc: :data:`PixelStats` (this part's pixels are updated in place).
        counts: (3,) int64 rays traced by this part: primary, bounce, shadow (added to).
        log: ray log (benchmarks): o, d (C, 3), tfar (C,), kind (C,) 0 = camera, 1 = shadow,
            2 = bounce; n (1,) entries used; C <= 1 turns logging off.
        part: this part's scratch row (``part * ROW_STRIDE``); parts running at once differ.
        queue: (1,) int64, the next block to take, shared by every part of the call (zero at
            the start): each part takes blocks from it until none is left, so a part that runs
            faster (its pixels cost less, or the host gives its thread more time) takes more.
        pix, sid: (P,) pixel index (row-major, non-decreasing) and sample index of each sample.
        bounds: (B + 1,) the blocks' first samples and P; every boundary lies between two pixels.

    No pixel's samples span two blocks, so parts update disjoint pixels: several threads can run
    parts at once (the kernel releases the GIL). Per sample, contributions are added in a fixed
    order (emission seen, then each light's shadow-tested sample: suns, point/spot, emitter,
    sky), and samples are added to their pixel in sample order, so images depend neither on the
    number of parts nor on which part took which block.
    """
    # the struct's fields as locals, once (see the note above the shading helpers)
    rtc, fn_isect, fn_occl = p.embree[0], p.embree[1], p.embree[2]
    cam = p.cam
    width, edge_extra = cam.width, cam.edge_extra
    sf = p.surf
    tri, fn, vn, face_mat, face_uv = sf.tri, sf.face_n, sf.vn, sf.face_mat, sf.face_uv
    mat_albedo, mat_emission = sf.mat_albedo, sf.mat_emission
    tex, lut, tex_off, tex_hw = sf.tex_flat, sf.tex_lut, sf.tex_off, sf.tex_hw
    nearest, shading_normals, diag = sf.nearest, sf.shading_normals, sf.diag
    shp = sf.shapes
    n_tri = tri.shape[0]
    suns, punct, face_light_pmf, face_area, face_is_area, emit_faces, emit_cdf = p.lights
    sky_kind, sky, env, rot, scale, frame, marg, cond, spdf, rows, phi0, mis = p.sky
    (seed_mix, salts, pixseed0, sampler, limit, rr_depth, want_aux, log2spp, zshift, splits,
     log2split) = p.sampling  # fmt: skip
    inv_splits = 1.0 / splits
    direct, gi, first_hit, alb_out, nrm_out, held = out
    sky_mis = mis != 0 and sky_kind != SKY_NONE
    any_extra = len(edge_extra) > 0
    n_s = suns.shape[0]
    n_q = punct.shape[0]
    n_e = len(emit_faces)
    # a textured vertex's light samples wait in its part's held rows (one per light at most)
    hold_ok = n_s + n_q + 2 < ROW_STRIDE
    # the RTCRayHit record (as _rayhit's) on this function's stack: no allocation
    pw, pf = _stack_words()
    # pointers index as the arrays of _rayhit do
    ray = (pw, pf, np.int64(0), _address(pw), p.embree[3])
    n_prim = 0
    n_bounce = 0
    n_shadow = 0
    row = part * ROW_STRIDE
    n_blocks = len(bounds) - 1
    while True:
        blk = _take_block(queue)
        if blk >= n_blocks:
            break
        for s in range(bounds[blk], bounds[blk + 1]):
            # this sample's scratch row starts at zero
            direct[row, 0] = direct[row, 1] = direct[row, 2] = 0.0
            gi[row, 0] = gi[row, 1] = gi[row, 2] = 0.0
            first_hit[row] = False
            if want_aux:
                alb_out[row, 0] = alb_out[row, 1] = alb_out[row, 2] = 0.0
                nrm_out[row, 0] = nrm_out[row, 1] = nrm_out[row, 2] = 0.0
            pixel_seed = _mix(pixseed0 ^ (np.uint64(pix[s]) * _GOLD))
            base_s = _sample_base(seed_mix, pix[s], sid[s])
            pix_x = pix[s] % width
            pix_y = pix[s] // width
            zkey = _U0
            if zshift >= 0:
                zkey = _zkey(pix_x, pix_y, sid[s], log2spp, zshift)
            zk = (pixseed0, zkey, zshift)
            ox, oy, oz, dx, dy, dz = _camera_ray(
                cam, sampler, salts, pix[s], sid[s], pixel_seed, base_s, zk
            )
            # ---- extra emission samples on an edge pixel: the emission seen directly is the
            # mean over them and this path's camera ray (each uniform over the pixel: unbiased)
            w_seen = 1.0
            k_extra = edge_extra[pix[s]] if any_extra else 0
            if k_extra > 0:
                w_seen = 1.0 / (k_extra + 1)
                for j in range(k_extra):
                    if sampler == SAMPLER_SOBOL:
                        jx, jy = _sobol2(pixel_seed, sid[s] * k_extra + j, EDGE_PAIR)
                    else:
                        bj = _mix(base_s + np.uint64(j + 1) * _GOLD)
                        jx = _u01(bj, salts[0])
                        jy = _u01(bj, salts[1])
                    px = np.float64(pix_x) + jx
                    py = np.float64(pix_y) + jy
                    le = _emission_through_all(
                        rtc, fn_isect, ray, log, cam, px, py,
                        (fn, face_mat, mat_emission), (sky_kind, sky, env, rot, scale), shp,
                    )  # fmt: skip
                    n_prim += 1
                    direct[row, 0] += le[0] * w_seen
                    direct[row, 1] += le[1] * w_seen
                    direct[row, 2] += le[2] * w_seen
            # ---- the path from the first vertex on: `splits` branches (docs/design.md,
            # section 8); branch 0 finds the first vertex, the others restart from it
            v1 = False
            s_so = (np.float32(0.0), np.float32(0.0), np.float32(0.0))
            s_f = (0.0, 0.0, 0.0)
            s_nf = (0.0, 0.0, 0.0)
            s_ns = (0.0, 0.0, 0.0)
            for branch in range(splits):
                if branch > 0 and not v1:
                    break
                sid_b = sid[s]
                base_b = base_s
                zkey_b = zkey
                zshift_b = zshift
                if splits > 1:  # the branch's own sample slot: sid * splits + branch
                    sid_b = sid[s] * splits + branch
                    base_b = _sample_base(seed_mix ^ _SPLIT_SALT, pix[s], sid_b)
                    if zshift >= 0:
                        zshift_b = zshift - log2split
                        zkey_b = _zkey(pix_x, pix_y, sid_b, log2spp + log2split, zshift_b)
                t0 = 1.0
                t1 = 1.0
                t2 = 1.0
                pdf_prev = 0.0
                from_first = False
                rr_boost = 1.0
                for depth in range(1, limit + 1):
                    if branch == 0 or depth > 1:
                        # the first vertex's light sample is the sample's, the rest the branch's
                        sid_d, base_d, zkey_d, zshift_d = (
                            (sid[s], base_s, zkey, zshift)
                            if depth == 1
                            else (sid_b, base_b, zkey_b, zshift_b)
                        )
                        # ---- closest hit of segment `depth`
                        _log_ray(
                            log, 0 if depth == 1 else 2, ox, oy, oz, dx, dy, dz, np.float32(np.inf)
                        )
                        th, prim, h_u, h_v = _closest(
                            rtc, fn_isect, ray, shp, n_tri, ox, oy, oz, dx, dy, dz
                        )
                        if depth == 1:
                            n_prim += 1
                        else:
                            n_bounce += 1
                        # ---- the sky: direct for a camera ray, else gi (MIS-weighted)
                        if prim < 0:
                            if sky_kind != SKY_NONE:
                                le = _sky(sky_kind, sky, env, rot, scale, dx, dy, dz)
                                if depth == 1:
                                    direct[row, 0] += le[0] * w_seen
                                    direct[row, 1] += le[1] * w_seen
                                    direct[row, 2] += le[2] * w_seen
                                else:
                                    w = 1.0
                                    # MIS weight of the BSDF sample against the sky sample
                                    if sky_mis:
                                        psk = _sky_pdf(frame, spdf, rows, phi0, dx, dy, dz)
                                        w = (
                                            pdf_prev
                                            * pdf_prev
                                            / max(pdf_prev * pdf_prev + psk * psk, 1e-300)
                                        )
                                    gi[row, 0] += le[0] * t0 * w
                                    gi[row, 1] += le[1] * t1 * w
                                    gi[row, 2] += le[2] * t2 * w
                            break
                        if prim >= n_tri:  # an analytic shape (icbtool.trace.shapes)
                            x, bary, cos_o, front, nf, ns = shape_frame(
                                shp, prim - n_tri, np.float64(ox), np.float64(oy),
                                np.float64(oz), dx, dy, dz, th,
                            )  # fmt: skip
                        else:
                            x, bary, cos_o, front, nf, ns = _hit_frame(
                                tri, fn, vn, shading_normals, prim, h_u, h_v, dx, dy, dz
                            )
                        # ---- emission seen (one-sided): direct for a camera ray and for a bounce
                        # off the first hit into an AreaLight (MIS-weighted); else gi (MIS-weighted)
                        m = face_mat[prim]
                        e0 = mat_emission[m, 0]
                        e1 = mat_emission[m, 1]
                        e2 = mat_emission[m, 2]
                        if front and (e0 > 0 or e1 > 0 or e2 > 0):
                            if depth == 1:
                                direct[row, 0] += e0 * w_seen
                                direct[row, 1] += e1 * w_seen
                                direct[row, 2] += e2 * w_seen
                            else:
                                if prim >= n_tri:
                                    pl = face_light_pmf[prim] * shape_pdf(
                                        shp, prim - n_tri, np.float64(ox), np.float64(oy),
                                        np.float64(oz), dx, dy, dz, th, cos_o,
                                    )  # fmt: skip
                                    w = (
                                        pdf_prev
                                        * pdf_prev
                                        / max(pdf_prev * pdf_prev + pl * pl, 1e-300)
                                    )
                                else:
                                    w = _emission_mis_weight(
                                        face_light_pmf[prim], face_area[prim], th, cos_o, pdf_prev
                                    )
                                _add_to(
                                    direct,
                                    gi,
                                    from_first and face_is_area[prim],
                                    row,
                                    e0 * t0 * w,
                                    e1 * t1 * w,
                                    e2 * t2 * w,
                                )
                        al = (mat_albedo[m, 0], mat_albedo[m, 1], mat_albedo[m, 2])
                        # ``pend``: the texels are asked for now (prefetched) and read after the
                        # vertex's shadow rays, which hide the wait for them; its light samples
                        # are held until then (docs/design.md, section 8)
                        pend = False
                        if tex_off[m] >= 0:  # textured (repeat)
                            uu, vv = _tex_coords(face_uv, prim, bary)
                            if nearest:
                                qn = _nearest_texel(tex_off[m], tex_hw[m, 0], tex_hw[m, 1], uu, vv)
                                fp = (qn, qn, qn, qn, 0.0, 0.0, 0.0, 0.0)
                            else:
                                fp = _bilinear_footprint(
                                    tex_off[m], tex_hw[m, 0], tex_hw[m, 1], uu, vv
                                )
                            if (depth == 1 and want_aux) or not hold_ok or depth >= limit:
                                al = _texture_albedo(tex, lut, nearest, fp, al)
                            else:
                                pend = True
                                _prefetch_texel(tex, lut, fp[0])
                                _prefetch_texel(tex, lut, fp[2])
                                _hold_vertex(held, row, fp, al, t0, t1, t2)
                        al0, al1, al2 = al
                        if depth == 1:
                            first_hit[row] = True
                            if want_aux:
                                alb_out[row, 0] = al0
                                alb_out[row, 1] = al1
                                alb_out[row, 2] = al2
                                nrm_out[row, 0] = ns[0]
                                nrm_out[row, 1] = ns[1]
                                nrm_out[row, 2] = ns[2]
                        if depth >= limit:
                            break
                        f0 = t0 * al0  # (while ``pend``, without the texture: zero stays zero)
                        f1 = t1 * al1
                        f2 = t2 * al2
                        if not (f0 > 0 or f1 > 0 or f2 > 0):
                            break
                        nh = 0  # light samples held
                        # ---- next-event estimation from the offset float32 origin `so`
                        eps = _eps(x[0], x[1], x[2], th, diag)
                        so = (
                            np.float32(x[0] + nf[0] * eps),
                            np.float32(x[1] + nf[1] * eps),
                            np.float32(x[2] + nf[2] * eps),
                        )
                        fo = (f0 * _INV_PI, f1 * _INV_PI, f2 * _INV_PI)
                        to_direct_dl = depth == 1
                        dim0 = 2 + depth * DIMS_PER_BOUNCE
                        pair0 = 1 + 3 * depth
                        use_ld = sampler == SAMPLER_SOBOL and depth <= LD_MAX_DEPTH
                        for j in range(n_s):  # directional lights (delta: no MIS)
                            ok, wi0, wi1, wi2, c = _sun_sample(
                                suns[j, 0], suns[j, 1], suns[j, 2], nf, ns
                            )
                            if ok:
                                n_shadow += 1
                                if _visible_all(
                                    rtc, fn_occl, ray, log, shp, so, wi0, wi1, wi2,
                                    np.float32(np.inf),
                                ):  # fmt: skip
                                    nh = _add_or_hold(
                                        direct, gi, held, row, nh, pend, to_direct_dl, fo,
                                        suns[j, 3], suns[j, 4], suns[j, 5], c,
                                    )  # fmt: skip
                        for j in range(n_q):  # point and spot lights (delta)
                            ok, wi0, wi1, wi2, tf, ii, g = _punctual_sample(
                                punct, j, x, nf, ns, eps
                            )
                            if ok:
                                n_shadow += 1
                                if _visible_all(rtc, fn_occl, ray, log, shp, so, wi0, wi1, wi2, tf):
                                    nh = _add_or_hold(
                                        direct, gi, held, row, nh, pend, to_direct_dl, fo,
                                        ii[0], ii[1], ii[2], g,
                                    )  # fmt: skip
                        if n_e > 0:  # emissive triangles: power-sampled, MIS with the BSDF
                            if use_ld:  # one stratified pair: face pick and point (reuse)
                                ul, rb = _ld2(
                                    pixel_seed, sid_d, pair0 + 2, pixseed0, zkey_d, zshift_d
                                )
                                ra = 0.0
                            else:
                                ul = _u01(base_d, salts[dim0 + 2])
                                ra = _u01(base_d, salts[dim0 + 3])
                                rb = _u01(base_d, salts[dim0 + 4])
                            lf, ra = _emitter_pick(emit_faces, emit_cdf, ul, ra, use_ld)
                            if lf >= n_tri:  # an analytic emitter (icbtool.trace.shapes)
                                ok, wi0, wi1, wi2, tf, g = _shape_light_sample(
                                    shp, lf - n_tri, face_light_pmf[lf], diag, x, nf, ns, eps,
                                    ra, rb,
                                )  # fmt: skip
                            else:
                                y = _triangle_point(tri, lf, ra, rb)
                                nl = (fn[lf, 0], fn[lf, 1], fn[lf, 2])
                                ok, wi0, wi1, wi2, tf, g = _emitter_sample(
                                    y, nl, face_light_pmf[lf], face_area[lf], diag, x, nf, ns, eps
                                )
                            if ok:
                                n_shadow += 1
                                if _visible_all(rtc, fn_occl, ray, log, shp, so, wi0, wi1, wi2, tf):
                                    me = face_mat[lf]
                                    nh = _add_or_hold(
                                        direct, gi, held, row, nh, pend,
                                        to_direct_dl and face_is_area[lf], fo,
                                        mat_emission[me, 0], mat_emission[me, 1],
                                        mat_emission[me, 2], g,
                                    )  # fmt: skip
                        if sky_mis:  # the sky, importance-sampled from its table; always gi
                            if use_ld:
                                us1, us2 = _ld2(
                                    pixel_seed, sid_d, SKY_PAIR0 + depth, pixseed0, zkey_d, zshift_d
                                )
                            else:
                                us1 = _u01(base_d, salts[dim0 + 6])
                                us2 = _u01(base_d, salts[dim0 + 7])
                            wi0, wi1, wi2, psk = _sky_sample(
                                frame, marg, cond, spdf, rows, phi0, us1, us2
                            )
                            ok, g = _sky_light_weight(psk, wi0, wi1, wi2, nf, ns)
                            if ok:
                                n_shadow += 1
                                if _visible_all(
                                    rtc, fn_occl, ray, log, shp, so, wi0, wi1, wi2,
                                    np.float32(np.inf),
                                ):  # fmt: skip
                                    le = _sky(sky_kind, sky, env, rot, scale, wi0, wi1, wi2)
                                    nh = _add_or_hold(
                                        direct, gi, held, row, nh, pend, False, fo,
                                        le[0], le[1], le[2], g,
                                    )  # fmt: skip
                        if pend:  # the texels: the albedo, then the held light samples in order
                            f0, f1, f2, fo = _held_throughput(held, row, tex, lut, nearest)
                            if not (f0 > 0 or f1 > 0 or f2 > 0):
                                break  # a black texel (its shadow rays were traced for nothing)
                            for j in range(nh):
                                r = row + 1 + j
                                _add_light(
                                    direct, gi, held[r, 4] != 0.0, row, fo,
                                    held[r, 0], held[r, 1], held[r, 2], held[r, 3],
                                )  # fmt: skip
                        if depth == 1 and splits > 1:  # the first vertex, for the other branches
                            v1 = True
                            s_so = so
                            s_f = (f0, f1, f2)
                            s_nf = nf
                            s_ns = ns
                    else:  # branch > 0 at the first vertex: restart from it
                        so = s_so
                        f0, f1, f2 = s_f
                        nf = s_nf
                        ns = s_ns
                        dim0 = 2 + DIMS_PER_BOUNCE
                        pair0 = 1 + 3
                        use_ld = sampler == SAMPLER_SOBOL
                    # ---- bounce
                    if use_ld:
                        u1, u2 = _ld2(pixel_seed, sid_b, pair0, pixseed0, zkey_b, zshift_b)
                    else:
                        u1 = _u01(base_b, salts[dim0])
                        u2 = _u01(base_b, salts[dim0 + 1])
                    wi0, wi1, wi2, pdf = _cosine_sample(nf, ns, u1, u2)
                    if depth + 1 > rr_depth:  # Russian roulette for the next segment
                        q = min(max(f0, max(f1, f2)) * rr_boost, 0.95)
                        if not (_u01(base_b, salts[dim0 + 5]) < q):
                            break
                        f0 /= q
                        f1 /= q
                        f2 /= q
                    ox, oy, oz = so
                    dx, dy, dz = wi0, wi1, wi2
                    t0, t1, t2 = f0, f1, f2
                    if depth == 1 and splits > 1:  # each branch carries 1 / splits of the path
                        t0 *= inv_splits
                        t1 *= inv_splits
                        t2 *= inv_splits
                        rr_boost = np.float64(splits)  # roulette on the unsplit throughput
                    pdf_prev = pdf
                    from_first = depth == 1
            _add_sample(acc, pix[s], direct, gi, first_hit, alb_out, nrm_out, row, want_aux)
    counts[0] += n_prim
    counts[1] += n_bounce
    counts[2] += n_shadow


@nb.njit(inline="always", **_JIT)
def _add_to(direct, gi, to_direct, s, a, b, c):
    """Add (a, b, c) to sample s of ``direct`` or ``gi`` (no array-valued expression: in a
    loop run by several threads, those cost atomic reference counts on shared arrays)."""
    if to_direct:
        direct[s, 0] += a
        direct[s, 1] += b
        direct[s, 2] += c
    else:
        gi[s, 0] += a
        gi[s, 1] += b
        gi[s, 2] += c


@nb.njit(inline="always", **_JIT)
def _add_light(direct, gi, to_direct, s, fo, l0, l1, l2, g):
    """A light sample's contribution ``fo * (l0, l1, l2) * g`` (``fo``: the vertex's BSDF value
    times the throughput, a 3-tuple; ``g``: the sample's geometry and pdf factor) into sample
    s of ``direct`` or ``gi``, each channel evaluated as (fo * l) * g."""
    _add_to(direct, gi, to_direct, s, fo[0] * l0 * g, fo[1] * l1 * g, fo[2] * l2 * g)


@nb.njit(inline="always", **_JIT)
def _add_or_hold(direct, gi, held, row, nh, pend, to_direct, fo, l0, l1, l2, g):
    """A shadow-tested light sample of a vertex: added now (:func:`_add_light`), or held while
    the vertex waits for its texels (``pend``, :func:`_hold_light`). Returns the held count."""
    if pend:
        return _hold_light(held, row, nh, to_direct, l0, l1, l2, g)
    _add_light(direct, gi, to_direct, row, fo, l0, l1, l2, g)
    return nh


@nb.njit(inline="always", **_JIT)
def _log_ray(log, kind, ox, oy, oz, dx, dy, dz, tf):
    """Append a ray to the benchmark log (o, d, tfar, kind, n) unless it is off (C <= 1) or full."""
    log_o, log_d, log_tf, log_kind, log_n = log
    j = log_n[0]
    if len(log_kind) > 1 and j < len(log_kind):
        log_o[j, 0], log_o[j, 1], log_o[j, 2] = ox, oy, oz
        log_d[j, 0], log_d[j, 1], log_d[j, 2] = dx, dy, dz
        log_tf[j] = tf
        log_kind[j] = kind
        log_n[0] += 1


@nb.njit(inline="always", **_JIT)
def _visible_all(rtc, fn_occl, ray, log, shp, so, dx, dy, dz, tf):
    """:func:`_visible`, the analytic shapes ``shp`` (icbtool.trace.shapes) blocking too."""
    if shp.shape[0] > 0 and shapes_occluded(
        shp, np.float64(so[0]), np.float64(so[1]), np.float64(so[2]), dx, dy, dz, np.float64(tf)
    ):
        _log_ray(log, 1, so[0], so[1], so[2], dx, dy, dz, tf)
        return False
    return _visible(rtc, fn_occl, ray, log, so, dx, dy, dz, tf)


@nb.njit(inline="always", **_JIT)
def _visible(rtc, fn_occl, ray, log, so, dx, dy, dz, tf):
    """Shadow ray from the float32 origin ``so`` (3-tuple) along the unit (dx, dy, dz) up to
    ``tf``: unblocked by the triangles?"""
    ox, oy, oz = so
    _log_ray(log, 1, ox, oy, oz, dx, dy, dz, tf)
    dx32, dy32, dz32 = np.float32(dx), np.float32(dy), np.float32(dz)
    return not _occluded(rtc, fn_occl, ray, ox, oy, oz, dx32, dy32, dz32, tf)


@nb.njit(inline="always", **_JIT)
def _add_sample(acc, p, direct, gi, hit, alb, nrm, row, want_aux):
    """A sample's outputs (scratch ``row``) into pixel ``p``'s statistics: Welford mean/M2 of
    (gi rgb, gi luminance) and of direct, and sums of the hit flag, albedo and normal. A pixel
    whose count is 0 is set, not added to: its other statistics need no zeroing."""
    lum_w, n, mean_g, m2_g, mean_d, m2_d, hit_sum, alb_sum, nrm_sum = acc
    g3 = gi[row, 0] * lum_w[0] + gi[row, 1] * lum_w[1] + gi[row, 2] * lum_w[2]
    if n[p] == 0:  # the pixel's first sample sets its statistics (only ``n`` starts zeroed)
        n[p] = 1
        for k in range(4):
            mean_g[p, k] = gi[row, k] if k < 3 else g3
            m2_g[p, k] = 0.0
        for k in range(3):
            mean_d[p, k] = direct[row, k]
            m2_d[p, k] = 0.0
        hit_sum[p] = 1.0 if hit[row] else 0.0
        if want_aux:
            for k in range(3):
                alb_sum[p, k] = alb[row, k]
                nrm_sum[p, k] = nrm[row, k]
        return
    n[p] += 1
    inv = 1.0 / n[p]
    for k in range(4):
        x = gi[row, k] if k < 3 else g3
        delta = x - mean_g[p, k]
        mean_g[p, k] += delta * inv
        m2_g[p, k] += delta * (x - mean_g[p, k])
    for k in range(3):
        delta = direct[row, k] - mean_d[p, k]
        mean_d[p, k] += delta * inv
        m2_d[p, k] += delta * (direct[row, k] - mean_d[p, k])
    if hit[row]:
        hit_sum[p] += 1.0
    if want_aux:
        for k in range(3):
            alb_sum[p, k] += alb[row, k]
            nrm_sum[p, k] += nrm[row, k]


@nb.njit(**_JIT)
def rel_error_lum(n, mean, m2, hit_sum, rel):
    """Per-pixel relative standard error of the mean of channel 3 (GI luminance) into ``rel``
    (inf where fewer than 2 samples); returns its mean over covered pixels (those whose samples
    mostly hit geometry). The denominator is floored at 1 % of the mean covered luminance."""
    npix = len(n)
    tot = 0.0
    cnt = 0
    for p in range(npix):
        if n[p] > 0 and hit_sum[p] > 0.5 * max(n[p], 1):
            tot += abs(mean[p, 3])
            cnt += 1
    if cnt == 0:
        rel[:] = 0.0
        return 0.0
    floor = max(1e-2 * (tot / cnt), 1e-12)
    acc = 0.0
    for p in range(npix):
        k = n[p]
        if k > 1:
            r = math.sqrt(m2[p, 3] / (k - 1) / k) / max(abs(mean[p, 3]), floor)
        else:
            r = np.inf
        rel[p] = r
        if k > 0 and hit_sum[p] > 0.5 * max(k, 1):
            acc += r
    return acc / cnt


@nb.njit(**_JIT)
def finish(
    n_g, mean_g, m2_g, mean_d, hit_sum, alb_sum, nrm_sum, want_aux,
    gi, direct, var, mask, albedo, normal, lo, hi,
):  # fmt: skip
    """Per-pixel outputs (float32) of pixels lo..hi-1 from the statistics: gi and direct means,
    variance of the gi mean, coverage mask, mean first-hit albedo and unit normal (0 where it
    cancels out)."""
    for p in range(lo, hi):
        k = n_g[p]
        kk = max(k, 1)
        if k == 0:  # no sample (its statistics were never set): zeros
            for c in range(3):
                gi[p, c] = direct[p, c] = var[p, c] = 0.0
                if want_aux:
                    albedo[p, c] = normal[p, c] = 0.0
            mask[p] = 0.0
            continue
        for c in range(3):
            gi[p, c] = mean_g[p, c]
            direct[p, c] = mean_d[p, c]
            var[p, c] = m2_g[p, c] / max(k - 1, 1) / kk if k > 1 else 0.0
        mask[p] = 1.0 if hit_sum[p] / kk > 0.5 else 0.0
        if want_aux:
            a0 = nrm_sum[p, 0] / kk
            a1 = nrm_sum[p, 1] / kk
            a2 = nrm_sum[p, 2] / kk
            ln = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            for c in range(3):
                albedo[p, c] = alb_sum[p, c] / kk
            if ln > 1e-20:
                normal[p, 0] = a0 / ln
                normal[p, 1] = a1 / ln
                normal[p, 2] = a2 / ln
            else:
                normal[p, 0] = 0.0
                normal[p, 1] = 0.0
                normal[p, 2] = 0.0
