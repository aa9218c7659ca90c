"""Precomputed terms of Mitsuba 3's coated BSDFs, in numpy (no renderer needed).

``roughplastic``'s rough-interface transmittance table and internal diffuse reflectance, and
``plastic``'s diffuse Fresnel reflectance: the tracer (:mod:`icbtool.trace.bsdfs`) and the
client's raster (:mod:`icbtool.raster.glossy`) evaluate the same BSDFs from the same numbers.
"""

from __future__ import annotations

import functools

import numpy as np

#: Resolution of roughplastic's external transmittance table (Mitsuba's
#: ``MI_ROUGH_TRANSMITTANCE_RES``).
ROUGH_TRANSMITTANCE_RES = 64


def fresnel_diffuse_reflectance(eta: float) -> float:
    """Mitsuba's ``fresnel_diffuse_reflectance`` (Egan-Hilgeman for eta < 1, d'Eon-Irving)."""
    inv = 1.0 / eta
    if eta < 1:
        return 0.0636 * inv + eta * (eta * -1.4399 + 0.7099) + 0.6681
    c = (0.919317, -3.4793, 6.75335, -7.80989, 4.98554, -1.36881)
    x = inv
    return c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * (c[4] + x * c[5]))))


# ---------------------------------------------------------------------------------- roughplastic
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


def _np_fresnel(cos_i: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    out = cos_i >= 0
    eta_it = np.where(out, eta, 1 / eta)
    eta_ti = np.where(out, 1 / eta, eta)
    cts = 1 - eta_ti**2 * (1 - cos_i**2)
    ci = np.abs(cos_i)
    ct = np.sqrt(np.maximum(cts, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a_s = (ci - eta_it * ct) / (ci + eta_it * ct)
        a_p = (ct - eta_it * ci) / (ct + eta_it * ci)
        r = 0.5 * (a_s**2 + a_p**2)
    r = np.where(ci == 0, 1.0, r)
    r = np.where(cts <= 0, 1.0, r)
    cos_t = np.where(cos_i >= 0, -ct, ct)
    return r, cos_t, eta_ti


def _np_g1(ggx: bool, a: float, v: np.ndarray, m: np.ndarray) -> np.ndarray:
    xy = a * a * (v[..., 0] ** 2 + v[..., 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t2 = xy / v[..., 2] ** 2
        if ggx:
            r = 2 / (1 + np.sqrt(1 + t2))
        else:
            aa = 1 / np.sqrt(t2)
            r = np.where(
                aa >= 1.6, 1.0, (3.535 * aa + 2.181 * aa * aa) / (1 + 2.276 * aa + 2.577 * aa * aa)
            )
    r = np.where(xy == 0, 1.0, r)
    # <v, m> written out: numpy's sum over a length-3 last axis is its slowest reduction
    # (most of a scene's table time), and this adds in the same order
    vm = v[..., 0] * m[..., 0] + v[..., 1] * m[..., 1] + v[..., 2] * m[..., 2]
    return np.where(vm * v[..., 2] <= 0, 0.0, r)


@functools.lru_cache(maxsize=512)  # a scene's rough BSDFs share a few (alpha, eta): 0.5 s each
def rough_tables(ggx: bool, alpha: float, eta: float, n: int = 96) -> tuple[np.ndarray, float]:
    """roughplastic's precomputed terms (Mitsuba's ``parameters_changed``): the external
    transmittance 1 - (reflected fraction) of a rough interface at
    :data:`ROUGH_TRANSMITTANCE_RES` cosines in [0, 1], and the internal diffuse reflectance
    ``2 * mean(R(1 / eta) * mu)``. Integrated over microfacet normals (Gauss-Legendre in
    (cos theta_m^2 mapped, phi)) rather than Mitsuba's visible-normal quadrature: the same
    integrals to ~1e-4. Cached by its arguments (the table is read-only)."""
    mu = np.maximum(1e-6, np.linspace(0, 1, ROUGH_TRANSMITTANCE_RES))
    ext = np.clip(_transmitted(ggx, alpha, eta, mu, n), 0, 1)
    ext.setflags(write=False)
    internal = float(np.mean(_reflected(ggx, alpha, 1 / eta, mu, n) * mu) * 2)
    return ext, internal


def _normals(ggx: bool, alpha: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Microfacet normals and their quadrature weights w with sum w g(m) = int D(m) cos(m) g."""
    x, w = _gauss_legendre(n)
    u = 0.5 * (x + 1)
    wu = 0.5 * w
    phi = np.pi * (x + 1)
    wphi = np.pi * w
    # D(m) cos(m) dm = d(CDF(theta)) dphi / (2 pi): sample theta by the CDF's inverse
    if ggx:
        tan2 = alpha * alpha * u / (1 - u)
    else:
        tan2 = -alpha * alpha * np.log(1 - u)
    ct = 1 / np.sqrt(1 + tan2)
    st = np.sqrt(np.maximum(0, 1 - ct * ct))
    m = np.stack(
        [
            st[:, None] * np.cos(phi)[None],
            st[:, None] * np.sin(phi)[None],
            np.repeat(ct[:, None], n, 1),
        ],
        -1,
    ).reshape(-1, 3)
    wt = (wu[:, None] * wphi[None] / (2 * np.pi)).reshape(-1)
    return m, wt


def _reflected(ggx: bool, alpha: float, eta: float, mu: np.ndarray, n: int) -> np.ndarray:
    """Fraction of light from cos ``mu`` reflected by a rough dielectric interface (Mitsuba's
    ``eval_reflectance``: sum over microfacets of F G1 G1-weighted visible projected area)."""
    m, wt = _normals(ggx, alpha, n)
    out = np.empty(len(mu))
    for j, c in enumerate(mu):
        wi = np.array([np.sqrt(1 - c * c), 0.0, c])
        dm = m @ wi
        vis = (
            np.maximum(dm, 0) / c
        )  # visible-normal density / (D cos m) = G1 <wi.m> / (cos_i cos_m)
        g1i = _np_g1(ggx, alpha, np.broadcast_to(wi, m.shape), m)
        wo = 2 * dm[:, None] * m - wi
        f = _np_fresnel(dm, eta)[0]
        g1o = _np_g1(ggx, alpha, wo, m)
        ok = (wo[:, 2] > 0) & (dm > 0)
        val = np.where(ok, f * g1o * g1i * vis / m[:, 2], 0.0)
        out[j] = float((wt * val).sum())
    return out


def _transmitted(ggx: bool, alpha: float, eta: float, mu: np.ndarray, n: int) -> np.ndarray:
    """Fraction of light from cos ``mu`` transmitted through a rough dielectric interface
    (Mitsuba's ``eval_transmittance``)."""
    m, wt = _normals(ggx, alpha, n)
    out = np.empty(len(mu))
    for j, c in enumerate(mu):
        wi = np.array([np.sqrt(1 - c * c), 0.0, c])
        dm = m @ wi
        vis = np.maximum(dm, 0) / c
        g1i = _np_g1(ggx, alpha, np.broadcast_to(wi, m.shape), m)
        f, cos_t, eta_ti = _np_fresnel(dm, eta)
        wo = m * (dm * eta_ti + cos_t)[:, None] - wi * eta_ti[:, None]
        g1o = _np_g1(ggx, alpha, wo, m)
        ok = (wo[:, 2] * wi[2] < 0) & (dm > 0)
        val = np.where(ok, (1 - f) * g1o * g1i * vis / m[:, 2], 0.0)
        out[j] = float((wt * val).sum())
    return out
