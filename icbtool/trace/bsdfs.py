"""Mitsuba 3's BSDFs as numba functions: evaluation, sampling and density, in a local frame.

The general kernel (:mod:`icbtool.trace.general`) shades every vertex with these. Directions
are 3-tuples in the vertex's local shading frame (z = the shading normal on the side the surface
faces, as Mitsuba's ``Frame3f``); ``wi`` points towards where the path came from, ``wo`` towards
the next vertex or the light (Mitsuba's naming in radiance mode). Evaluation returns the BSDF
times ``|cos(wo)|`` (Mitsuba's ``eval``), sampling returns that divided by the density
(Mitsuba's sample weight); delta lobes (smooth conductor, smooth plastic's coating, dielectrics)
are only sampled, never evaluated.

Each BSDF is written after its Mitsuba 3 plugin (``src/bsdfs/*.cpp``) and
``include/mitsuba/render/{microfacet,fresnel}.h``: the same Fresnel terms (dielectric,
conductor, Egan-Hilgeman / d'Eon-Irving diffuse Fresnel), Smith G1 (Beckmann's rational fit,
GGX exact), ``plastic``'s and ``roughplastic``'s internal scattering (``nonlinear``) and lobe
probabilities, ``dielectric``'s radiance scaling by 1 / eta^2 on refraction, ``thindielectric``'s
series of inter-reflections, ``blendbsdf``'s mixture density. Microfacet normals are drawn from
the distribution of normals visible from wi, with Mitsuba's density: for Beckmann by Mitsuba's
own numerical inversion, for GGX by Heitz 2018's hemisphere projection (Mitsuba uses Heitz
2014's slope mapping: the same distribution), so images agree in expectation, not sample for
sample.

``normalmap`` and ``bumpmap`` nodes (at a material's root or as a ``twosided`` side) tilt the
local frame as Mitsuba 3.9 does (:func:`map_frame`, Estevez et al.'s shadowing term); the
kernel hands :func:`bsdf_eval` and :func:`bsdf_sample` the vertex's dp/du, dp/dv and geometric
normal in the local frame for them.

The scene's BSDFs are one node table (:class:`BsdfTable`, built by :func:`pack`): a material's
root node, nodes' types, constants, texture ids and children; ``twosided``, ``blendbsdf``,
``mask`` and the maps nest leaves (``mask`` is resolved by the kernel: a stochastic pass-through).
"""

from __future__ import annotations

import math
from collections import namedtuple
from dataclasses import dataclass
from typing import Any

import numba as nb
import numpy as np

from icbtool.scene import bsdf as sb
from icbtool.scene.bsdf_tables import (
    ROUGH_TRANSMITTANCE_RES,
    fresnel_diffuse_reflectance,
    rough_tables,
)

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)
_INV_PI = 1.0 / math.pi
_PI = math.pi

# node types
LAMBERT2 = 0  #: icbtool's two-sided Lambertian material (a Material without a bsdf)
DIFFUSE = 1
PLASTIC = 2
ROUGHPLASTIC = 3
CONDUCTOR = 4
ROUGHCONDUCTOR = 5
DIELECTRIC = 6
THINDIELECTRIC = 7
ROUGHDIELECTRIC = 8
TWOSIDED = 9
BLEND = 10
MASK = 11
NORMALMAP = 12
BUMPMAP = 13

TEX_BITMAP = 0
TEX_CHECKER = 1


#: The node table the kernel reads: types (N,), float parameters (N, 12), children / table rows
#: (N, 4), constant values (N, 4, 3) and their texture ids (N, 4) (-1: constant); textures: kind
#: (T,), parameters (T, 12) (to_uv 2x3, color0, color1), (offset, h, w, nearest (-1: the render's
#: filter), the start of its level table in ``texel_lut``) (T, 5), texels as uint8 codes into
#: ``texel_lut`` (or empty, ``texel_lut`` then the linear float32 texels:
#: :mod:`icbtool.trace.texels`); roughplastic transmittance tables (R, 64).
BsdfParams = namedtuple(
    "BsdfParams",
    ["nt", "nf", "ni", "nv", "ntex", "tk", "tf", "ti", "texels", "ttab", "texel_lut"],
)


# ---------------------------------------------------------------------------------- textures
@nb.njit(inline="always", **_JIT)
def _texel3(texels, lut, lb, p):
    """Texel p's RGB: ``lut[lb + code]`` (uint8 codes into a level table starting at ``lb``),
    or ``lut[p]`` when there are no codes (``lut`` then holds the float texels)."""
    if len(texels) > 0:
        return (
            np.float64(lut[lb + np.int64(texels[p])]),
            np.float64(lut[lb + np.int64(texels[p + 1])]),
            np.float64(lut[lb + np.int64(texels[p + 2])]),
        )
    return np.float64(lut[p]), np.float64(lut[p + 1]), np.float64(lut[p + 2])


@nb.njit(inline="always", **_JIT)
def _tex_uv(tf, t, uu, vv):
    """Mitsuba's uv of texture ``t`` (its ``to_uv`` applied) at the scene uv (v = 1 - vv)."""
    vm = 1.0 - vv
    return tf[t, 0] * uu + tf[t, 1] * vm + tf[t, 2], tf[t, 3] * uu + tf[t, 4] * vm + tf[t, 5]


@nb.njit(inline="always", **_JIT)
def _cell(ti, t, u, v):
    """The bilinear cell of bitmap ``t`` at uv (u, v), repeated: the flat texel offsets of its
    corners (x0 y0, x1 y0, x0 y1, x1 y1) and the weights (fx, fy) of x1 and y1."""
    off = ti[t, 0]
    th = ti[t, 1]
    tw = ti[t, 2]
    xx = u * tw - 0.5
    yy = v * th - 0.5
    fx0 = math.floor(xx)
    fy0 = math.floor(yy)
    xa = np.int64(fx0) % tw
    ya = np.int64(fy0) % th
    xb = xa + 1 if xa + 1 < tw else 0
    yb = ya + 1 if ya + 1 < th else 0
    corners = (
        off + (ya * tw + xa) * 3,
        off + (ya * tw + xb) * 3,
        off + (yb * tw + xa) * 3,
        off + (yb * tw + xb) * 3,
    )
    return corners, xx - fx0, yy - fy0


@nb.njit(**_JIT)
def tex_eval(tk, tf, ti, texels, lut, t, uu, vv, nearest_default):
    """Texture ``t`` at the scene uv (uu, vv) (v up; Mitsuba's v = 1 - vv): (r, g, b)."""
    u, v = _tex_uv(tf, t, uu, vv)
    if tk[t] == TEX_CHECKER:
        mx = (u - math.floor(u)) > 0.5
        my = (v - math.floor(v)) > 0.5
        if mx == my:
            return tf[t, 6], tf[t, 7], tf[t, 8]
        return tf[t, 9], tf[t, 10], tf[t, 11]
    lb = ti[t, 4]
    nearest = ti[t, 3] if ti[t, 3] >= 0 else nearest_default
    if nearest:
        th = ti[t, 1]
        tw = ti[t, 2]
        xi = np.int64(math.floor(u * tw)) % tw
        yi = np.int64(math.floor(v * th)) % th
        return _texel3(texels, lut, lb, ti[t, 0] + (yi * tw + xi) * 3)
    (pa, pb, pc, pd), fx, fy = _cell(ti, t, u, v)
    a = _texel3(texels, lut, lb, pa)
    b = _texel3(texels, lut, lb, pb)
    c = _texel3(texels, lut, lb, pc)
    d = _texel3(texels, lut, lb, pd)
    ga = (1 - fy) * (1 - fx)
    gb = (1 - fy) * fx
    gc = fy * (1 - fx)
    gd = fy * fx
    return (
        ga * a[0] + gb * b[0] + gc * c[0] + gd * d[0],
        ga * a[1] + gb * b[1] + gc * c[1] + gd * d[1],
        ga * a[2] + gb * b[2] + gc * c[2] + gd * d[2],
    )


@nb.njit(**_JIT)
def value(B, node, slot, uu, vv, nearest):
    """Constant or textured value ``slot`` of ``node`` at (uu, vv): (r, g, b)."""
    t = B.ntex[node, slot]
    c0 = B.nv[node, slot, 0]
    c1 = B.nv[node, slot, 1]
    c2 = B.nv[node, slot, 2]
    if t < 0:
        return c0, c1, c2
    r, g, b = tex_eval(B.tk, B.tf, B.ti, B.texels, B.texel_lut, t, uu, vv, nearest)
    return c0 * r, c1 * g, c2 * b


@nb.njit(**_JIT)
def value1(B, node, slot, uu, vv, nearest):
    """A scalar parameter (alpha, weight, opacity): a texture's luminance, a constant's first
    channel (as Mitsuba's ``eval_1``)."""
    if B.ntex[node, slot] < 0:
        return B.nv[node, slot, 0]
    r, g, b = value(B, node, slot, uu, vv, nearest)
    return 0.212671 * r + 0.715160 * g + 0.072169 * b


@nb.njit(inline="always", **_JIT)
def _lum(texels, lut, lb, p):
    r, g, b = _texel3(texels, lut, lb, p)
    return 0.212671 * r + 0.715160 * g + 0.072169 * b


@nb.njit(**_JIT)
def tex_grad1(tk, tf, ti, texels, lut, t, uu, vv):
    """Mitsuba's ``eval_1_grad`` of bitmap ``t`` at the scene uv (uu, vv): the gradient
    (d/du, d/dv) of its bilinear interpolant's luminance in Mitsuba's uv (v = 1 - vv), through
    ``to_uv`` (as Mitsuba: the transform's transpose, then the resolution); (0, 0) for a
    nearest-filtered bitmap or a checkerboard."""
    if tk[t] != TEX_BITMAP or ti[t, 3] == 1:
        return 0.0, 0.0
    u, v = _tex_uv(tf, t, uu, vv)
    lb = ti[t, 4]
    (p00, p10, p01, p11), w1x, w1y = _cell(ti, t, u, v)
    f00 = _lum(texels, lut, lb, p00)
    f10 = _lum(texels, lut, lb, p10)
    f01 = _lum(texels, lut, lb, p01)
    f11 = _lum(texels, lut, lb, p11)
    dfx = (1.0 - w1y) * (f10 - f00) + w1y * (f11 - f01)
    dfy = (1.0 - w1x) * (f01 - f00) + w1x * (f11 - f10)
    tw = ti[t, 2]
    th = ti[t, 1]
    return tw * (tf[t, 0] * dfx + tf[t, 3] * dfy), th * (tf[t, 1] * dfx + tf[t, 4] * dfy)


# ---------------------------------------------------------------------------------- fresnel
@nb.njit(**_JIT)
def fresnel(cos_i, eta):
    """Mitsuba's ``fresnel``: (F, cos_t (signed), eta_it, eta_ti) of a dielectric interface
    with relative IOR ``eta`` = int / ext, ``cos_i`` negative from inside."""
    outside = cos_i >= 0
    rcp_eta = 1.0 / eta
    eta_it = eta if outside else rcp_eta
    eta_ti = rcp_eta if outside else eta
    cos_t_sqr = 1.0 - eta_ti * eta_ti * (1.0 - cos_i * cos_i)
    ci = abs(cos_i)
    ct = math.sqrt(max(cos_t_sqr, 0.0))
    if eta == 1.0:
        r = 0.0
    elif ci == 0.0:
        r = 1.0
    else:
        a_s = (ci - eta_it * ct) / (ci + eta_it * ct)
        a_p = (ct - eta_it * ci) / (ct + eta_it * ci)
        r = 0.5 * (a_s * a_s + a_p * a_p)
    if cos_t_sqr <= 0:
        r = 1.0
    cos_t = -ct if cos_i >= 0 else ct
    return r, cos_t, eta_it, eta_ti


@nb.njit(**_JIT)
def fresnel_conductor(cos_i, eta_r, eta_i):
    """Mitsuba's ``fresnel_conductor`` (unpolarised, complex IOR eta_r + i eta_i)."""
    c2 = cos_i * cos_i
    s2 = 1.0 - c2
    s4 = s2 * s2
    temp1 = eta_r * eta_r - eta_i * eta_i - s2
    a2pb2 = math.sqrt(max(temp1 * temp1 + 4.0 * eta_i * eta_i * eta_r * eta_r, 0.0))
    a = math.sqrt(max(0.5 * (a2pb2 + temp1), 0.0))
    term1 = a2pb2 + c2
    term2 = 2.0 * cos_i * a
    r_s = (term1 - term2) / (term1 + term2)
    term3 = a2pb2 * c2 + s4
    term4 = term2 * s2
    r_p = r_s * (term3 - term4) / (term3 + term4)
    return 0.5 * (r_s + r_p)


# ---------------------------------------------------------------------------------- microfacets
@nb.njit(**_JIT)
def mf_d(ggx, au, av, mx, my, mz):
    """Microfacet distribution D(m) (Mitsuba's ``MicrofacetDistribution::eval``)."""
    if mz <= 0:
        return 0.0
    c2 = mz * mz
    xa = mx / au
    ya = my / av
    if ggx:
        t = xa * xa + ya * ya + c2
        r = 1.0 / (_PI * au * av * t * t)
    else:
        r = math.exp(-(xa * xa + ya * ya) / c2) / (_PI * au * av * c2 * c2)
    return r if r * mz > 1e-20 else 0.0


@nb.njit(**_JIT)
def mf_g1(ggx, au, av, vx, vy, vz, mx, my, mz):
    """Smith's G1 (Mitsuba's ``smith_g1``: Beckmann's rational fit, GGX exact)."""
    if (vx * mx + vy * my + vz * mz) * vz <= 0:
        return 0.0
    xy = (au * vx) ** 2 + (av * vy) ** 2
    if xy == 0:
        return 1.0
    t2 = xy / (vz * vz)
    if ggx:
        return 2.0 / (1.0 + math.sqrt(1.0 + t2))
    a = 1.0 / math.sqrt(t2)
    if a >= 1.6:
        return 1.0
    return (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)


_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)


@nb.njit(**_JIT)
def erfinv(x):
    """Inverse error function on (-1, 1): Giles' (2010) approximation refined by three Newton
    steps (on erf, or on log(erfc) near +-1): double precision; +-inf at +-1."""
    if x <= -1.0 or x >= 1.0:
        return math.copysign(math.inf, x)
    a = abs(x)
    w = -math.log((1.0 - a) * (1.0 + a))
    if w < 5.0:
        w -= 2.5
        p = 2.81022636e-08
        for c in (3.43273939e-07, -3.5233877e-06, -4.39150654e-06, 0.00021858087,
                  -0.00125372503, -0.00417768164, 0.246640727, 1.50140941):  # fmt: skip
            p = c + p * w
    else:
        w = math.sqrt(w) - 3.0
        p = -0.000200214257
        for c in (0.000100950558, 0.00134934322, -0.00367342844, 0.00573950773,
                  -0.0076224613, 0.00943887047, 1.00167406, 2.83297682):  # fmt: skip
            p = c + p * w
    y = p * a
    for _ in range(3):
        d = 2.0 * _INV_SQRT_PI * math.exp(-y * y)
        if a < 0.5:
            y -= (math.erf(y) - a) / d
        else:  # on log(erfc): no cancellation near 1, nearly linear in the tail
            c = math.erfc(y)
            y += (math.log(c) - math.log1p(-a)) * c / d
    return math.copysign(y, x)


@nb.njit(**_JIT)
def _beckmann_slopes_11(cos_i, u1, u2):
    """Slopes of a Beckmann (alpha 1) normal visible from the direction with cosine cos_i (> 0):
    the CDF inverted numerically in the erf domain as Mitsuba does (an analytic start and three
    Newton steps, Jakob 2014)."""
    tan_i = math.sqrt(max(1.0 - cos_i * cos_i, 0.0)) / cos_i
    cot_i = 1.0 / tan_i
    top = math.erf(cot_i)
    u1 = min(max(u1, 1e-6), 1.0 - 1e-6)
    u2 = min(max(u2, 1e-6), 1.0 - 1e-6)
    x = top - (top + 1.0) * math.erf(math.sqrt(-math.log(u1)))
    target = u1 * (1.0 + top + _INV_SQRT_PI * tan_i * math.exp(-cot_i * cot_i))
    for _ in range(3):
        slope = erfinv(x)
        x -= (1.0 + x + _INV_SQRT_PI * tan_i * math.exp(-slope * slope) - target) / (
            1.0 - slope * tan_i
        )
    return erfinv(x), erfinv(2.0 * u2 - 1.0)


@nb.njit(**_JIT)
def mf_sample(ggx, au, av, wx, wy, wz, u1, u2):
    """A microfacet normal visible from the direction w (upper hemisphere) and its density
    (Mitsuba's ``sample_visible``): GGX by Heitz 2018's hemisphere projection, Beckmann by
    Mitsuba's stretch, 1D slope inversion, rotation and unstretch. (mx, my, mz, pdf)."""
    vx = au * wx
    vy = av * wy
    vz = wz
    ln = math.sqrt(vx * vx + vy * vy + vz * vz)
    vx /= ln
    vy /= ln
    vz /= ln
    lensq = vx * vx + vy * vy
    if ggx:
        if lensq > 0:
            il = 1.0 / math.sqrt(lensq)
            t1x, t1y, t1z = -vy * il, vx * il, 0.0
        else:
            t1x, t1y, t1z = 1.0, 0.0, 0.0
        t2x = vy * t1z - vz * t1y
        t2y = vz * t1x - vx * t1z
        t2z = vx * t1y - vy * t1x
        r = math.sqrt(u1)
        phi = 2.0 * _PI * u2
        p1 = r * math.cos(phi)
        p2 = r * math.sin(phi)
        s = 0.5 * (1.0 + vz)
        p2 = (1.0 - s) * math.sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2
        p3 = math.sqrt(max(0.0, 1.0 - p1 * p1 - p2 * p2))
        nx = p1 * t1x + p2 * t2x + p3 * vx
        ny = p1 * t1y + p2 * t2y + p3 * vy
        nz = p1 * t1z + p2 * t2z + p3 * vz
        mx = au * nx
        my = av * ny
        mz = max(nz, 1e-9)
    else:
        if lensq > 0:
            il = 1.0 / math.sqrt(lensq)
            cp, sp = vx * il, vy * il
        else:
            cp, sp = 1.0, 0.0
        sx, sy = _beckmann_slopes_11(vz, u1, u2)
        mx = -(cp * sx - sp * sy) * au
        my = -(sp * sx + cp * sy) * av
        mz = 1.0
    ln = math.sqrt(mx * mx + my * my + mz * mz)
    mx /= ln
    my /= ln
    mz /= ln
    return mx, my, mz, mf_pdf(ggx, au, av, wx, wy, wz, mx, my, mz)


@nb.njit(**_JIT)
def mf_pdf(ggx, au, av, wx, wy, wz, mx, my, mz):
    """Density of :func:`mf_sample`'s normal m for the direction w (upper hemisphere): the
    visible-normal density D(m) G1(w, m) |w.m| / cos(w)."""
    if wz <= 0:
        return 0.0
    d = mf_d(ggx, au, av, mx, my, mz)
    return d * mf_g1(ggx, au, av, wx, wy, wz, mx, my, mz) * abs(wx * mx + wy * my + wz * mz) / wz


@nb.njit(inline="always", **_JIT)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@nb.njit(inline="always", **_JIT)
def _half(a, b, k):
    """The unit normal along a + k b (the reflection half-vector for k = 1, the refraction one
    for k = eta), on the upper side: (ok, m)."""
    mx = a[0] + b[0] * k
    my = a[1] + b[1] * k
    mz = a[2] + b[2] * k
    ln = math.sqrt(mx * mx + my * my + mz * mz)
    if ln == 0:
        return False, (0.0, 0.0, 1.0)
    if mz < 0:
        ln = -ln
    return True, (mx / ln, my / ln, mz / ln)


@nb.njit(inline="always", **_JIT)
def _reflect(w, m):
    """w mirrored about the normal m."""
    d = 2.0 * (w[0] * m[0] + w[1] * m[1] + w[2] * m[2])
    return d * m[0] - w[0], d * m[1] - w[1], d * m[2] - w[2]


@nb.njit(inline="always", **_JIT)
def _dg(ggx, au, av, wi, wo, m):
    """D(m) G1(wi, m) G1(wo, m): the microfacet terms every rough BSDF shares."""
    d = mf_d(ggx, au, av, m[0], m[1], m[2])
    gi = mf_g1(ggx, au, av, wi[0], wi[1], wi[2], m[0], m[1], m[2])
    go = mf_g1(ggx, au, av, wo[0], wo[1], wo[2], m[0], m[1], m[2])
    return d, gi * go


# ---------------------------------------------------------------------------------- lobes
@nb.njit(inline="always", **_JIT)
def _cos_hemi(u1, u2):
    r = math.sqrt(u1)
    phi = 2.0 * _PI * u2
    return r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - u1))


@nb.njit(**_JIT)
def _rough_t(B, node, c):
    """roughplastic's external transmittance at cos c (Mitsuba's ``lerp_gather``)."""
    row = B.ni[node, 2]
    n = B.ttab.shape[1]
    x = min(max(c, 0.0), 1.0) * (n - 1)
    i = min(np.int64(x), n - 2)
    f = x - i
    return (1.0 - f) * B.ttab[row, i] + f * B.ttab[row, i + 1]


@nb.njit(**_JIT)
def _alpha_uv(B, node, uu, vv, nearest):
    au = max(value1(B, node, 2, uu, vv, nearest), 1e-4)
    av = max(value1(B, node, 3, uu, vv, nearest), 1e-4)
    return au, av


@nb.njit(**_JIT)
def leaf_eval(B, node, uu, vv, nearest, wi, wo):
    """BSDF value times |cos(wo)| and density of sampling wo, of a non-nested node:
    (f0, f1, f2, pdf). Delta lobes give 0."""
    typ = B.nt[node]
    ci = wi[2]
    co = wo[2]
    if typ == LAMBERT2 or typ == DIFFUSE:
        if typ == DIFFUSE and not (ci > 0 and co > 0):
            return 0.0, 0.0, 0.0, 0.0
        if ci * co <= 0:
            return 0.0, 0.0, 0.0, 0.0
        r = value(B, node, 0, uu, vv, nearest)
        c = abs(co) * _INV_PI
        return r[0] * c, r[1] * c, r[2] * c, c
    if typ == PLASTIC:
        if not (ci > 0 and co > 0):
            return 0.0, 0.0, 0.0, 0.0
        eta = B.nf[node, 0]
        f_i = fresnel(ci, eta)[0]
        f_o = fresnel(co, eta)[0]
        d = value(B, node, 0, uu, vv, nearest)
        k = B.nf[node, 1] * (1.0 - f_i) * (1.0 - f_o) * co * _INV_PI
        fdr = B.nf[node, 2]
        nonlin = B.nf[node, 4] != 0
        sw = B.nf[node, 3]
        ps = f_i * sw
        pd = (1.0 - f_i) * (1.0 - sw)
        pd = pd / (ps + pd)
        out0 = d[0] / (1.0 - (d[0] * fdr if nonlin else fdr)) * k
        out1 = d[1] / (1.0 - (d[1] * fdr if nonlin else fdr)) * k
        out2 = d[2] / (1.0 - (d[2] * fdr if nonlin else fdr)) * k
        return out0, out1, out2, co * _INV_PI * pd
    if typ == ROUGHPLASTIC:
        if not (ci > 0 and co > 0):
            return 0.0, 0.0, 0.0, 0.0
        eta = B.nf[node, 0]
        ggx = B.nf[node, 5] != 0
        a = max(B.nf[node, 7], 1e-4)
        _, h = _half(wi, wo, 1.0)
        D, G = _dg(ggx, a, a, wi, wo, h)
        F = fresnel(_dot(wi, h), eta)[0]
        spec = F * D * G / (4.0 * ci)
        s = value(B, node, 1, uu, vv, nearest)
        t_i = _rough_t(B, node, ci)
        t_o = _rough_t(B, node, co)
        d = value(B, node, 0, uu, vv, nearest)
        fint = B.nf[node, 6]
        nonlin = B.nf[node, 4] != 0
        k = _INV_PI * B.nf[node, 1] * co * t_i * t_o
        out0 = spec * s[0] + d[0] / (1.0 - (d[0] * fint if nonlin else fint)) * k
        out1 = spec * s[1] + d[1] / (1.0 - (d[1] * fint if nonlin else fint)) * k
        out2 = spec * s[2] + d[2] / (1.0 - (d[2] * fint if nonlin else fint)) * k
        sw = B.nf[node, 3]
        ps = (1.0 - t_i) * sw
        pd = t_i * (1.0 - sw)
        ps = ps / (ps + pd)
        pd = 1.0 - ps
        pm = mf_pdf(ggx, a, a, wi[0], wi[1], wi[2], h[0], h[1], h[2])
        pdf = ps * pm / (4.0 * _dot(wo, h)) + pd * co * _INV_PI
        return out0, out1, out2, pdf
    if typ == ROUGHCONDUCTOR:
        if not (ci > 0 and co > 0):
            return 0.0, 0.0, 0.0, 0.0
        ggx = B.nf[node, 6] != 0
        au, av = _alpha_uv(B, node, uu, vv, nearest)
        _, h = _half(wi, wo, 1.0)
        D, G = _dg(ggx, au, av, wi, wo, h)
        if D == 0:
            return 0.0, 0.0, 0.0, 0.0
        base = D * G / (4.0 * ci)
        cih = _dot(wi, h)
        coh = _dot(wo, h)
        s = value(B, node, 1, uu, vv, nearest)
        f0 = fresnel_conductor(cih, B.nf[node, 0], B.nf[node, 3])
        f1 = fresnel_conductor(cih, B.nf[node, 1], B.nf[node, 4])
        f2 = fresnel_conductor(cih, B.nf[node, 2], B.nf[node, 5])
        pdf = 0.0
        if cih > 0 and coh > 0:
            pdf = mf_pdf(ggx, au, av, wi[0], wi[1], wi[2], h[0], h[1], h[2]) / (4.0 * coh)
        return base * f0 * s[0], base * f1 * s[1], base * f2 * s[2], pdf
    if typ == ROUGHDIELECTRIC:
        return _rough_dielectric_eval(B, node, uu, vv, nearest, wi, wo)
    return 0.0, 0.0, 0.0, 0.0  # delta BSDFs


@nb.njit(**_JIT)
def _rough_dielectric_eval(B, node, uu, vv, nearest, wi, wo):
    ci = wi[2]
    co = wo[2]
    if ci == 0:
        return 0.0, 0.0, 0.0, 0.0
    ggx = B.nf[node, 6] != 0
    au, av = _alpha_uv(B, node, uu, vv, nearest)
    eta0 = B.nf[node, 0]
    refl = ci * co > 0
    eta = eta0 if ci > 0 else 1.0 / eta0
    inv_eta = 1.0 / eta
    ok, m = _half(wi, wo, 1.0 if refl else eta)
    if not ok:
        return 0.0, 0.0, 0.0, 0.0
    D, G = _dg(ggx, au, av, wi, wo, m)
    cim = _dot(wi, m)
    com = _dot(wo, m)
    F = fresnel(cim, eta0)[0]
    # density (Mitsuba's roughdielectric::pdf)
    pdf = 0.0
    if cim * ci > 0 and com * co > 0:
        if refl:
            dwh = 1.0 / (4.0 * com)
        else:
            den = cim + eta * com
            dwh = eta * eta * com / (den * den)
        sgi = 1.0 if ci >= 0 else -1.0
        pm = mf_pdf(ggx, au, av, wi[0] * sgi, wi[1] * sgi, wi[2] * sgi, m[0], m[1], m[2])
        pdf = abs(pm * (F if refl else 1.0 - F) * dwh)
    if refl:
        v = F * D * G / (4.0 * abs(ci))
        r = value(B, node, 0, uu, vv, nearest)
        return v * r[0], v * r[1], v * r[2], pdf
    den = cim + eta * com
    v = abs(inv_eta * inv_eta * (1.0 - F) * D * G * eta * eta * cim * com / (ci * den * den))
    t = value(B, node, 1, uu, vv, nearest)
    return v * t[0], v * t[1], v * t[2], pdf


@nb.njit(**_JIT)
def leaf_sample(B, node, uu, vv, nearest, wi, u0, u1, u2):
    """Sample a direction from a non-nested node: (ok, wo, weight (f |cos| / pdf) rgb, pdf,
    delta)."""
    typ = B.nt[node]
    ci = wi[2]
    zero = (0.0, 0.0, 0.0)
    if typ == LAMBERT2 or typ == DIFFUSE:
        if typ == DIFFUSE and ci <= 0:
            return False, zero, zero, 0.0, False
        x, y, z = _cos_hemi(u1, u2)
        if ci < 0:
            z = -z
        if z == 0:
            return False, zero, zero, 0.0, False
        r = value(B, node, 0, uu, vv, nearest)
        return True, (x, y, z), r, abs(z) * _INV_PI, False
    if typ == CONDUCTOR:
        if ci <= 0:
            return False, zero, zero, 0.0, False
        s = value(B, node, 1, uu, vv, nearest)
        f0 = fresnel_conductor(ci, B.nf[node, 0], B.nf[node, 3])
        f1 = fresnel_conductor(ci, B.nf[node, 1], B.nf[node, 4])
        f2 = fresnel_conductor(ci, B.nf[node, 2], B.nf[node, 5])
        return True, (-wi[0], -wi[1], ci), (f0 * s[0], f1 * s[1], f2 * s[2]), 1.0, True
    if typ == PLASTIC:
        if ci <= 0:
            return False, zero, zero, 0.0, False
        f_i = fresnel(ci, B.nf[node, 0])[0]
        sw = B.nf[node, 3]
        ps = f_i * sw
        pd = (1.0 - f_i) * (1.0 - sw)
        ps = ps / (ps + pd)
        if u0 < ps:
            s = value(B, node, 1, uu, vv, nearest)
            k = f_i / ps
            return True, (-wi[0], -wi[1], ci), (s[0] * k, s[1] * k, s[2] * k), ps, True
        wo = _cos_hemi(u1, u2)
        f0, f1, f2, pdf = leaf_eval(B, node, uu, vv, nearest, wi, wo)
        if not pdf > 0:
            return False, zero, zero, 0.0, False
        return True, wo, (f0 / pdf, f1 / pdf, f2 / pdf), pdf, False
    if typ == ROUGHPLASTIC:
        if ci <= 0:
            return False, zero, zero, 0.0, False
        t_i = _rough_t(B, node, ci)
        sw = B.nf[node, 3]
        ps = (1.0 - t_i) * sw
        pd = t_i * (1.0 - sw)
        ps = ps / (ps + pd)
        if u0 < ps:
            a = max(B.nf[node, 7], 1e-4)
            mx, my, mz, _ = mf_sample(B.nf[node, 5] != 0, a, a, wi[0], wi[1], wi[2], u1, u2)
            wo = _reflect(wi, (mx, my, mz))
        else:
            wo = _cos_hemi(u1, u2)
        return _weighted(B, node, uu, vv, nearest, wi, wo)
    if typ == ROUGHCONDUCTOR:
        if ci <= 0:
            return False, zero, zero, 0.0, False
        au, av = _alpha_uv(B, node, uu, vv, nearest)
        mx, my, mz, _ = mf_sample(B.nf[node, 6] != 0, au, av, wi[0], wi[1], wi[2], u1, u2)
        wo = _reflect(wi, (mx, my, mz))
        return _weighted(B, node, uu, vv, nearest, wi, wo)
    if typ == DIELECTRIC:
        if ci == 0:
            return False, zero, zero, 0.0, False
        r_i, cos_t, eta_it, eta_ti = fresnel(ci, B.nf[node, 0])
        if u0 <= r_i:
            s = value(B, node, 0, uu, vv, nearest)
            return True, (-wi[0], -wi[1], ci), s, r_i, True
        t = value(B, node, 1, uu, vv, nearest)
        k = eta_ti * eta_ti
        wo = (-eta_ti * wi[0], -eta_ti * wi[1], cos_t)
        return True, wo, (t[0] * k, t[1] * k, t[2] * k), 1.0 - r_i, True
    if typ == THINDIELECTRIC:
        r = fresnel(abs(ci), B.nf[node, 0])[0]
        t = 1.0 - r
        if r < 1:
            r += t * t * r / (1.0 - r * r)
        t = 1.0 - r
        if u0 <= r:
            s = value(B, node, 0, uu, vv, nearest)
            return True, (-wi[0], -wi[1], ci), s, r, True
        s = value(B, node, 1, uu, vv, nearest)
        return True, (-wi[0], -wi[1], -wi[2]), s, t, True
    if typ == ROUGHDIELECTRIC:
        if ci == 0:
            return False, zero, zero, 0.0, False
        eta0 = B.nf[node, 0]
        au, av = _alpha_uv(B, node, uu, vv, nearest)
        sgi = 1.0 if ci >= 0 else -1.0
        mx, my, mz, _ = mf_sample(
            B.nf[node, 6] != 0, au, av, wi[0] * sgi, wi[1] * sgi, wi[2] * sgi, u1, u2
        )
        cim = wi[0] * mx + wi[1] * my + wi[2] * mz
        F, cos_t, eta_it, eta_ti = fresnel(cim, eta0)
        if u0 <= F:
            wo = _reflect(wi, (mx, my, mz))
        else:
            k = cim * eta_ti + cos_t
            wo = (mx * k - wi[0] * eta_ti, my * k - wi[1] * eta_ti, mz * k - wi[2] * eta_ti)
        return _weighted(B, node, uu, vv, nearest, wi, wo)
    return False, zero, zero, 0.0, False


@nb.njit(inline="always", **_JIT)
def _weighted(B, node, uu, vv, nearest, wi, wo):
    """A sampled direction's weight eval / pdf (the sample's own density)."""
    f0, f1, f2, pdf = leaf_eval(B, node, uu, vv, nearest, wi, wo)
    if not (pdf > 0) or not (f0 > 0 or f1 > 0 or f2 > 0):
        return False, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, False
    return True, wo, (f0 / pdf, f1 / pdf, f2 / pdf), pdf, False


# ---------------------------------------------------------------------------------- nesting
@nb.njit(inline="always", **_JIT)
def _side(B, node, wi_z):
    """A twosided node resolved for the side of wi: (leaf node, flip z)."""
    if B.nt[node] == TWOSIDED:
        if wi_z < 0:
            return B.ni[node, 1], True
        return B.ni[node, 0], False
    return node, False


@nb.njit(**_JIT)
def node_eval(B, node, uu, vv, nearest, wi, wo):
    """:func:`leaf_eval` through a ``twosided`` wrapper."""
    leaf, flip = _side(B, node, wi[2])
    if flip:
        return leaf_eval(B, leaf, uu, vv, nearest, (wi[0], wi[1], -wi[2]), (wo[0], wo[1], -wo[2]))
    return leaf_eval(B, leaf, uu, vv, nearest, wi, wo)


@nb.njit(**_JIT)
def node_sample(B, node, uu, vv, nearest, wi, u0, u1, u2):
    """:func:`leaf_sample` through a ``twosided`` wrapper."""
    leaf, flip = _side(B, node, wi[2])
    if flip:
        ok, wo, w, pdf, delta = leaf_sample(
            B, leaf, uu, vv, nearest, (wi[0], wi[1], -wi[2]), u0, u1, u2
        )
        return ok, (wo[0], wo[1], -wo[2]), w, pdf, delta
    return leaf_sample(B, leaf, uu, vv, nearest, wi, u0, u1, u2)


@nb.njit(**_JIT)
def _blend_eval(B, node, uu, vv, nearest, wi, wo):
    """A blend of two nodes or a (twosided) leaf: (f0, f1, f2, pdf)."""
    if B.nt[node] == BLEND:
        w = min(max(value1(B, node, 0, uu, vv, nearest), 0.0), 1.0)
        a = node_eval(B, B.ni[node, 0], uu, vv, nearest, wi, wo)
        b = node_eval(B, B.ni[node, 1], uu, vv, nearest, wi, wo)
        return (
            (1 - w) * a[0] + w * b[0],
            (1 - w) * a[1] + w * b[1],
            (1 - w) * a[2] + w * b[2],
            (1 - w) * a[3] + w * b[3],
        )
    return node_eval(B, node, uu, vv, nearest, wi, wo)


@nb.njit(**_JIT)
def _blend_sample(B, node, uu, vv, nearest, wi, u0, u1, u2):
    """Sample a blend of two nodes or a (twosided) leaf: a blend picks a node by its weight and
    weights the direction by the mixture (Mitsuba's ``blendbsdf::sample``)."""
    if B.nt[node] != BLEND:
        return node_sample(B, node, uu, vv, nearest, wi, u0, u1, u2)
    w = min(max(value1(B, node, 0, uu, vv, nearest), 0.0), 1.0)
    pick1 = u0 <= w
    if pick1:
        u0 = u0 / w
        c, o = B.ni[node, 1], B.ni[node, 0]
        wc = w
    else:
        u0 = (u0 - w) / (1.0 - w)
        c, o = B.ni[node, 0], B.ni[node, 1]
        wc = 1.0 - w
    ok, wo, r, pdf, delta = node_sample(B, c, uu, vv, nearest, wi, u0, u1, u2)
    if ok and not delta:
        e = node_eval(B, o, uu, vv, nearest, wi, wo)
        pw = (1.0 - wc) * e[3] + wc * pdf
        if pw > 0:
            r = (
                ((1.0 - wc) * e[0] + wc * r[0] * pdf) / pw,
                ((1.0 - wc) * e[1] + wc * r[1] * pdf) / pw,
                ((1.0 - wc) * e[2] + wc * r[2] * pdf) / pw,
            )
            pdf = pw
        else:
            ok = False
    return ok, wo, r, pdf, delta


# ---------------------------------------------------------------------------------- maps
#: The local geometry of a vertex without a normal or bump map (see :func:`map_frame`).
NO_GEO = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
_IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@nb.njit(inline="always", **_JIT)
def is_map(B, node):
    """Whether ``node`` is a ``normalmap`` or ``bumpmap``."""
    return B.nt[node] == NORMALMAP or B.nt[node] == BUMPMAP


@nb.njit(**_JIT)
def has_map(B, root):
    """Whether a (mask-resolved) root node tilts its frame: a map at the root or as a
    ``twosided`` side (:func:`map_frame` needs the vertex's local geometry then)."""
    if is_map(B, root):
        return True
    if B.nt[root] == TWOSIDED:
        return is_map(B, B.ni[root, 0]) or is_map(B, B.ni[root, 1])
    return False


@nb.njit(**_JIT)
def leaf_of(B, root):
    """The front leaf (or blend) of a (mask-resolved) root node: through maps and twosided."""
    node = root
    if is_map(B, node):
        node = B.ni[node, 0]
    if B.nt[node] == TWOSIDED:
        node = B.ni[node, 0]
    if is_map(B, node):
        node = B.ni[node, 0]
    return node


@nb.njit(inline="always", **_JIT)
def _to_frame(fr, v):
    return _dot(fr[0], v), _dot(fr[1], v), _dot(fr[2], v)


@nb.njit(inline="always", **_JIT)
def _from_frame(fr, v):
    s, t, n = fr
    return (
        s[0] * v[0] + t[0] * v[1] + n[0] * v[2],
        s[1] * v[0] + t[1] * v[1] + n[1] * v[2],
        s[2] * v[0] + t[2] * v[1] + n[2] * v[2],
    )


@nb.njit(**_JIT)
def map_frame(B, node, uu, vv, nearest, geo, wi):
    """The shading frame a ``normalmap``/``bumpmap`` node tilts to, in the local (unperturbed)
    shading frame, for the incident direction wi: (ok, (s, t, n)) as Mitsuba 3.9's ``frame()``.

    ``geo`` is the vertex's geometry in the local frame: (dp/du, dp/dv, geometric normal) and
    dp/du in world space (Mitsuba builds a bump map's tangent by projecting the world-space
    dp/du against the local normal; only an anisotropic nested BSDF sees that choice). A normal
    map's normal is ``2 * rgb - 1``; a bump map's is ``dp_du' x dp_dv'`` with the height
    gradient as their normal components, turned to the geometric normal's side. With
    ``flip_invalid_normals`` a normal that wi lies below has its tangent part mirrored.
    """
    if B.nt[node] == NORMALMAP:
        c = value(B, node, 0, uu, vv, nearest)
        nx = 2.0 * c[0] - 1.0
        ny = 2.0 * c[1] - 1.0
        nz = 2.0 * c[2] - 1.0
    else:
        t = B.ntex[node, 0]
        gu, gv = tex_grad1(B.tk, B.tf, B.ti, B.texels, B.texel_lut, t, uu, vv)
        k = B.nf[node, 0]
        du, dv, ng, _ = geo
        ax, ay, az = du[0], du[1], k * gu
        bx, by, bz = dv[0], dv[1], k * gv
        nx = ay * bz - az * by
        ny = az * bx - ax * bz
        nz = ax * by - ay * bx
        if ng[0] * nx + ng[1] * ny + ng[2] * nz < 0:
            nx, ny, nz = -nx, -ny, -nz
    ok_n, (nx, ny, nz) = _unit(nx, ny, nz)
    if B.nf[node, 1] != 0 and wi[2] * (wi[0] * nx + wi[1] * ny + wi[2] * nz) <= 0:
        nx, ny = -nx, -ny
    if B.nt[node] == NORMALMAP:
        sx, sy, sz = 1.0 - nx * nx, -ny * nx, -nz * nx
    else:
        d = geo[3]
        p = nx * d[0] + ny * d[1] + nz * d[2]
        sx, sy, sz = d[0] - nx * p, d[1] - ny * p, d[2] - nz * p
    ok_s, s = _unit(sx, sy, sz)
    if not (ok_n and ok_s):
        return False, _IDENTITY
    sx, sy, sz = s
    return True, (s, (ny * sz - nz * sy, nz * sx - nx * sz, nx * sy - ny * sx), (nx, ny, nz))


@nb.njit(inline="always", **_JIT)
def _unit(x, y, z):
    """(ok, the vector scaled to length 1); not ok for a zero or non-finite length."""
    ln = math.sqrt(x * x + y * y + z * z)
    if not (ln > 0 and ln < math.inf):
        return False, (0.0, 0.0, 1.0)
    return True, (x / ln, y / ln, z / ln)


@nb.njit(inline="always", **_JIT)
def _tan2(z):
    return max(1.0 - z * z, 0.0) / (z * z)


@nb.njit(inline="always", **_JIT)
def shadow_terminator(n_z, w_z):
    """Estevez et al.'s shadowing of a perturbed normal with cosine ``n_z`` for a direction with
    cosine ``w_z`` (both in the unperturbed frame): Mitsuba's ``eval_shadow_terminator``."""
    a2 = min(0.125 * _tan2(n_z), 1.0)
    return 2.0 / (1.0 + math.sqrt(1.0 + a2 * _tan2(w_z)))


@nb.njit(inline="always", **_JIT)
def _enter_sample(B, node, uu, vv, nearest, geo, wi):
    """A map node's sampling step: (ok, node below, wi in its frame, the frame); any other node
    passes through with the identity frame."""
    if not is_map(B, node):
        return True, node, wi, _IDENTITY
    ok, fr = map_frame(B, node, uu, vv, nearest, geo, wi)
    return ok, B.ni[node, 0], _to_frame(fr, wi), fr


@nb.njit(inline="always", **_JIT)
def _enter_eval(B, node, uu, vv, nearest, geo, wi, wo):
    """A map node's evaluation step: (ok, node below, wi, wo in its frame, shadowing factor);
    any other node passes through. wo must lie on the same side of both frames (Mitsuba)."""
    ok, below, wi_p, fr = _enter_sample(B, node, uu, vv, nearest, geo, wi)
    if not is_map(B, node):
        return True, node, wi, wo, 1.0
    wo_p = _to_frame(fr, wo)
    if not ok or not wo[2] * wo_p[2] > 0:
        return False, node, wi, wo, 0.0
    k = shadow_terminator(fr[2][2], wo[2]) if B.nf[node, 2] != 0 else 1.0
    return True, below, wi_p, wo_p, k


@nb.njit(inline="always", **_JIT)
def _leave_sample(B, node, fr, ok, wo, r):
    """A map node's sampling step back: wo out of the map's frame, checked to lie on the same
    side of both frames, the weight shadowed (Mitsuba's ``bumpmap``/``normalmap::sample``)."""
    wo_u = _from_frame(fr, wo)
    if not ok or not wo[2] * wo_u[2] > 0:
        return False, wo_u, (0.0, 0.0, 0.0)
    if B.nf[node, 2] != 0:
        k = shadow_terminator(fr[2][2], wo_u[2])
        r = (r[0] * k, r[1] * k, r[2] * k)
    return True, wo_u, r


# ---------------------------------------------------------------------------------- roots
@nb.njit(**_JIT)
def bsdf_eval(B, root, uu, vv, nearest, wi, wo, geo):
    """Value times |cos(wo)| and density of a material's (mask-resolved) root node: an optional
    map, twosided (each side with an optional map), a blend of two nodes, or a leaf:
    (f0, f1, f2, pdf). ``geo``: the vertex's local geometry (:func:`map_frame`; :data:`NO_GEO`
    where the root has no map)."""
    ok, node, wi, wo, k1 = _enter_eval(B, root, uu, vv, nearest, geo, wi, wo)
    if not ok:
        return 0.0, 0.0, 0.0, 0.0
    node, flip = _side(B, node, wi[2])
    if flip:
        wi = (wi[0], wi[1], -wi[2])
        wo = (wo[0], wo[1], -wo[2])
    ok, node, wi, wo, k2 = _enter_eval(B, node, uu, vv, nearest, geo, wi, wo)
    if not ok:
        return 0.0, 0.0, 0.0, 0.0
    f0, f1, f2, pdf = _blend_eval(B, node, uu, vv, nearest, wi, wo)
    k = k1 * k2
    return f0 * k, f1 * k, f2 * k, pdf


@nb.njit(**_JIT)
def bsdf_sample(B, root, uu, vv, nearest, wi, u0, u1, u2, geo):
    """Sample a material's (mask-resolved) root node (see :func:`bsdf_eval`): (ok, wo,
    weight rgb, pdf, delta)."""
    zero = (0.0, 0.0, 0.0)
    ok, node, wi, fr1 = _enter_sample(B, root, uu, vv, nearest, geo, wi)
    if not ok:
        return False, zero, zero, 0.0, False
    node, flip = _side(B, node, wi[2])
    if flip:
        wi = (wi[0], wi[1], -wi[2])
    ok, leaf, wi, fr2 = _enter_sample(B, node, uu, vv, nearest, geo, wi)
    if not ok:
        return False, zero, zero, 0.0, False
    ok, wo, r, pdf, delta = _blend_sample(B, leaf, uu, vv, nearest, wi, u0, u1, u2)
    if is_map(B, node):
        ok, wo, r = _leave_sample(B, node, fr2, ok, wo, r)
    if flip:
        wo = (wo[0], wo[1], -wo[2])
    if is_map(B, root):
        ok, wo, r = _leave_sample(B, root, fr1, ok, wo, r)
    return ok, wo, r, pdf, delta


@nb.njit(**_JIT)
def is_smooth(B, root):
    """Whether a root node has only delta lobes (next-event estimation is skipped)."""
    node = root
    if B.nt[node] == MASK:
        node = B.ni[node, 0]
    t = B.nt[leaf_of(B, node)]
    return t == CONDUCTOR or t == DIELECTRIC or t == THINDIELECTRIC


@nb.njit(**_JIT)
def eval_batch(B, roots, uv, wi, wo, out):
    """:func:`bsdf_eval` for arrays (tests): roots (N,), uv (N, 2), wi, wo (N, 3) -> out (N, 4)."""
    for n in range(len(roots)):
        r = bsdf_eval(
            B, roots[n], uv[n, 0], uv[n, 1], 0,
            (wi[n, 0], wi[n, 1], wi[n, 2]), (wo[n, 0], wo[n, 1], wo[n, 2]), NO_GEO,
        )  # fmt: skip
        out[n, 0], out[n, 1], out[n, 2], out[n, 3] = r


@nb.njit(**_JIT)
def sample_batch(B, roots, uv, wi, u, out_wo, out_w, out_pdf, out_flags):
    """:func:`bsdf_sample` for arrays (tests): u (N, 3) -> wo (N, 3), weight (N, 3), pdf (N,),
    flags (N,) (1: ok, 2: delta)."""
    for n in range(len(roots)):
        ok, wo, w, pdf, delta = bsdf_sample(
            B, roots[n], uv[n, 0], uv[n, 1], 0, (wi[n, 0], wi[n, 1], wi[n, 2]),
            u[n, 0], u[n, 1], u[n, 2], NO_GEO,
        )  # fmt: skip
        out_wo[n, 0], out_wo[n, 1], out_wo[n, 2] = wo
        out_w[n, 0], out_w[n, 1], out_w[n, 2] = w
        out_pdf[n] = pdf
        out_flags[n] = (1 if ok else 0) + (2 if delta else 0)


# ---------------------------------------------------------------------------------- packing
@dataclass
class BsdfTable:
    """The scene's BSDF nodes (see :data:`BsdfParams`) and each material's root node."""

    params: Any
    mat_root: np.ndarray  # (M,) int64
    kinds: list[str]  # plugin names present (messages)


class _Packer:
    def __init__(self, maps: bool = True) -> None:
        self.nt: list[int] = []
        self.nf: list[np.ndarray] = []
        self.ni: list[list[int]] = []
        self.nv: list[np.ndarray] = []
        self.ntex: list[list[int]] = []
        self.tk: list[int] = []
        self.tf: list[np.ndarray] = []
        self.ti: list[list[int]] = []
        self.texels: list[np.ndarray] = []
        self.n_texels = 0
        self.texel_off: dict[int, int] = {}  # id of a bitmap's data -> its offset (shared)
        self.ttab: list[np.ndarray] = []
        self.tex_ids: dict[int, int] = {}
        self.kinds: set[str] = set()
        self.maps = maps

    def node(self, typ: int) -> int:
        self.nt.append(typ)
        self.nf.append(np.zeros(12))
        self.ni.append([-1, -1, -1, -1])
        self.nv.append(np.ones((4, 3)))
        self.ntex.append([-1, -1, -1, -1])
        return len(self.nt) - 1

    def texture(self, t: sb.Texture, nearest: int = -1) -> int:
        if id(t) in self.tex_ids:
            return self.tex_ids[id(t)]
        f = np.zeros(12)
        f[:6] = np.asarray(t.to_uv)[:2].ravel()
        i = [0, 1, 1, nearest, 0]
        if isinstance(t, sb.Checkerboard):
            self.tk.append(TEX_CHECKER)
            f[6:9] = t.color0
            f[9:12] = t.color1
        else:
            self.tk.append(TEX_BITMAP)
            d = np.ascontiguousarray(t.data, np.float32)
            if id(t.data) not in self.texel_off:  # bitmaps of one image share its texels
                self.texel_off[id(t.data)] = self.n_texels
                self.texels.append(d.ravel())
                self.n_texels += d.size
            # the level table (column 4) is filled in by params(), once texels are coded
            i = [self.texel_off[id(t.data)], d.shape[0], d.shape[1], nearest, 0]
            if t.filter_type == "nearest":
                i[3] = 1
        self.tf.append(f)
        self.ti.append(i)
        self.tex_ids[id(t)] = len(self.tk) - 1
        return self.tex_ids[id(t)]

    def slot(self, n: int, k: int, v: Any) -> None:
        if isinstance(v, sb.Bitmap | sb.Checkerboard):
            self.ntex[n][k] = self.texture(v)
            self.nv[n][k] = 1.0
        else:
            self.nv[n][k] = np.resize(np.asarray(v, np.float64), 3)

    def lambert(self, albedo: np.ndarray, texture: np.ndarray | None) -> int:
        n = self.node(LAMBERT2)
        self.nv[n][0] = albedo
        if texture is not None:
            self.ntex[n][0] = self.texture(sb.Bitmap(texture))
        return n

    def bsdf(self, b: sb.BSDF) -> int:
        self.kinds.add(sb.plugin_name(b))
        if isinstance(b, sb.NormalMap | sb.BumpMap):
            return self.mapped(b)
        if isinstance(b, sb.Mask):
            n = self.node(MASK)
            self.slot(n, 0, b.opacity)
            self.ni[n][0] = self.bsdf(b.bsdf)
            if self.nt[self.ni[n][0]] == MASK:
                raise ValueError("mask: a mask nested in a mask is not supported")
            return n
        if isinstance(b, sb.TwoSided):
            inner = [b.front, b.back if b.back is not None else b.front]
            if any(isinstance(x, sb.Mask) for x in inner):  # opacity does not depend on side
                if b.back is not None:
                    raise ValueError("twosided: a mask with a different back BSDF")
                m = inner[0]
                return self.bsdf(sb.Mask(sb.TwoSided(m.bsdf), m.opacity))
            n = self.node(TWOSIDED)
            kids = [self.bsdf(x) for x in inner]
            if any(self.has_map(k) and self.nt[self.ni[k][0]] == TWOSIDED for k in kids):
                raise ValueError("twosided: a twosided inside a map inside it is not supported")
            self.ni[n][0], self.ni[n][1] = kids
            return n
        if isinstance(b, sb.BlendBSDF):
            n = self.node(BLEND)
            self.slot(n, 0, b.weight)
            for k, x in enumerate((b.bsdf0, b.bsdf1)):
                c = self.bsdf(x)
                t = self.nt[c]
                if t in (BLEND, MASK) or (
                    t == TWOSIDED and self.nt[self.ni[c][0]] in (BLEND, MASK)
                ):
                    raise ValueError("blendbsdf: nested blendbsdf or mask is not supported")
                if self.has_map(c):
                    raise ValueError(
                        "blendbsdf: a normalmap or bumpmap inside a blendbsdf is not supported "
                        "(put the map around the blendbsdf)"
                    )
                self.ni[n][k] = c
            return n
        if isinstance(b, sb.Diffuse):
            n = self.node(DIFFUSE)
            self.slot(n, 0, b.reflectance)
            return n
        if isinstance(b, sb.RoughPlastic | sb.Plastic):
            rough = isinstance(b, sb.RoughPlastic)
            n = self.node(ROUGHPLASTIC if rough else PLASTIC)
            eta = b.eta
            self.slot(n, 0, b.diffuse_reflectance)
            self.slot(n, 1, b.specular_reflectance)
            d_mean = float(np.mean(sb.mean_of(b.diffuse_reflectance)))
            s_mean = float(np.mean(sb.mean_of(b.specular_reflectance)))
            f = self.nf[n]
            f[0] = eta
            f[1] = 1.0 / (eta * eta)
            f[2] = fresnel_diffuse_reflectance(1.0 / eta)
            f[3] = s_mean / (d_mean + s_mean)
            f[4] = float(b.nonlinear)
            if rough:
                ggx = b.distribution == "ggx"
                f[5] = float(ggx)
                f[7] = float(b.alpha)
                ext, internal = rough_tables(ggx, float(b.alpha), eta)
                f[6] = internal
                self.ni[n][2] = len(self.ttab)
                self.ttab.append(ext)
            return n
        if isinstance(b, sb.Conductor):
            rough = isinstance(b, sb.RoughConductor)
            n = self.node(ROUGHCONDUCTOR if rough else CONDUCTOR)
            self.nf[n][0:3] = b.eta
            self.nf[n][3:6] = b.k
            self.slot(n, 1, b.specular_reflectance)
            if rough:
                self.nf[n][6] = float(b.distribution == "ggx")
                self.slot(n, 2, b.alpha_u)
                self.slot(n, 3, b.alpha_v)
            return n
        if isinstance(b, sb.Dielectric):
            typ = (
                ROUGHDIELECTRIC if isinstance(b, sb.RoughDielectric)
                else THINDIELECTRIC if isinstance(b, sb.ThinDielectric) else DIELECTRIC
            )  # fmt: skip
            n = self.node(typ)
            self.nf[n][0] = b.eta
            self.slot(n, 0, b.specular_reflectance)
            self.slot(n, 1, b.specular_transmittance)
            if isinstance(b, sb.RoughDielectric):
                self.nf[n][6] = float(b.distribution == "ggx")
                self.slot(n, 2, b.alpha_u)
                self.slot(n, 3, b.alpha_v)
            return n
        raise TypeError(f"not a BSDF: {type(b).__name__}")

    def has_map(self, n: int) -> bool:
        """Whether node ``n`` is a map or a twosided with a map side."""
        if self.nt[n] in (NORMALMAP, BUMPMAP):
            return True
        return self.nt[n] == TWOSIDED and any(
            self.nt[self.ni[n][k]] in (NORMALMAP, BUMPMAP) for k in (0, 1)
        )

    def mapped(self, b: sb.NormalMap | sb.BumpMap) -> int:
        """A ``normalmap``/``bumpmap`` node over its nested BSDF (or that BSDF alone when the
        scene has no uvs to look the map up at)."""
        kind = sb.plugin_name(b)
        c = self.bsdf(b.bsdf)
        if self.nt[c] == MASK:
            raise ValueError(f"{kind}: a mask inside a {kind} is not supported (put it outside)")
        if self.has_map(c):
            raise ValueError(f"{kind}: one normalmap or bumpmap per material is supported")
        if not self.maps:
            return c
        n = self.node(NORMALMAP if isinstance(b, sb.NormalMap) else BUMPMAP)
        if isinstance(b, sb.NormalMap):
            self.slot(n, 0, b.normalmap)
        else:
            self.ntex[n][0] = self.texture(b.texture)
            self.nf[n][0] = b.scale
        self.nf[n][1] = float(b.flip_invalid_normals)
        self.nf[n][2] = float(b.use_shadowing_function)
        self.ni[n][0] = c
        return n

    def params(self) -> Any:
        N = max(len(self.nt), 1)
        T = max(len(self.tk), 1)

        def arr(x: list, shape: tuple, dtype: Any) -> np.ndarray:
            return (
                np.ascontiguousarray(np.array(x, dtype).reshape(shape))
                if x
                else np.zeros(shape, dtype)
            )

        from icbtool.trace import texels as tx

        # colour images code into the sRGB levels, raw ones (bump, normal maps) into code / 255
        codes, lut, base = tx.encode_texel_sets(self.texels, [tx.srgb_levels(), tx.linear_levels()])
        chunk_at = {off: j for j, off in enumerate(self.texel_off.values())}
        for k, row in zip(self.tk, self.ti):
            if k == TEX_BITMAP:
                row[4] = int(base[chunk_at[row[0]]])
        return BsdfParams(
            arr(self.nt, (N,), np.int64),
            arr(self.nf, (N, 12), np.float64),
            arr(self.ni, (N, 4), np.int64),
            arr(self.nv, (N, 4, 3), np.float64),
            arr(self.ntex, (N, 4), np.int64),
            arr(self.tk, (T,), np.int64),
            arr(self.tf, (T, 12), np.float64),
            arr(self.ti, (T, 5), np.int64),
            codes,
            arr(self.ttab, (max(len(self.ttab), 1), ROUGH_TRANSMITTANCE_RES), np.float64),
            lut,
        )


def pack(materials: Any, maps: bool = True) -> BsdfTable:
    """The node table of a scene's materials: a declared ``bsdf``, or icbtool's two-sided
    Lambert (albedo times its texture) for a material without one.

    Args:
        materials: the scene's materials.
        maps: keep ``normalmap``/``bumpmap`` nodes (False: their nested BSDFs stand alone, for
            a scene without uvs to look the maps up at).

    Raises:
        ValueError: a nesting the kernel cannot evaluate (a mask in a blend, a blend in a
            blend, a map in a blend or in a map), naming it.
    """
    p = _Packer(maps)
    roots = []
    for m in materials:
        if getattr(m, "bsdf", None) is None:
            roots.append(p.lambert(np.asarray(m.albedo, np.float64), m.texture))
        else:
            try:
                roots.append(p.bsdf(m.bsdf))
            except ValueError as e:
                raise ValueError(f"material '{m.name}': {e}") from None
    return BsdfTable(p.params(), np.asarray(roots, np.int64), sorted(p.kinds))
