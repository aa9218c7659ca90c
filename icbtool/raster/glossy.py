"""The glossy BSDFs the client's raster evaluates, packed as texture-buffer rows per material.

The resolve shader (``shaders/resolve.frag``, ``GLOSSY``) evaluates four of Mitsuba 3's BSDFs
exactly as the tracer does (:mod:`icbtool.trace.bsdfs`): ``plastic``, ``roughplastic``,
``conductor`` and ``roughconductor`` (GGX and Beckmann D, Smith G1 with Beckmann's rational
fit, dielectric Fresnel of the coating with Mitsuba's diffuse/specular split and ``nonlinear``,
conductor Fresnel with eta/k, roughplastic's rough-interface transmittance table). Every other
material keeps the Lambertian stand-in (its ``albedo``/``texture``), as before.

A textured BSDF parameter (a reflectance or alpha given as a :class:`~icbtool.scene.bsdf.Bitmap`
or :class:`~icbtool.scene.bsdf.Checkerboard`) enters as its mean.

Layout (:data:`BSDF_ROWS` RGBA32F texels per material ``m``, from texel ``BSDF_ROWS * m``):

====  ==============================================  ======================================
row   plastic / roughplastic                          conductor / roughconductor
====  ==============================================  ======================================
0     (kind, ggx, alpha, alpha)                       (kind, ggx, alpha_u, alpha_v)
1     (diffuse_reflectance rgb, eta)                  (eta rgb, 0)
2     (specular_reflectance rgb, 1 / eta^2)           (k rgb, 0)
3     (internal diffuse reflectance, nonlinear, 0, 0) (specular_reflectance rgb, 0)
4-19  roughplastic's external transmittance at :data:`~icbtool.trace.bsdfs.ROUGH_TRANSMITTANCE_RES`
      cosines in [0, 1], four per texel
====  ==============================================  ======================================

``kind``: :data:`KIND_LAMBERT` (the stand-in; the other rows are 0), :data:`KIND_PLASTIC`,
:data:`KIND_ROUGHPLASTIC`, :data:`KIND_CONDUCTOR`, :data:`KIND_ROUGHCONDUCTOR`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

KIND_LAMBERT = 0
KIND_PLASTIC = 1
KIND_ROUGHPLASTIC = 2
KIND_CONDUCTOR = 3
KIND_ROUGHCONDUCTOR = 4
#: Texels per material in the packed table.
BSDF_ROWS = 20


def _mean_scalar(x: Any) -> float:
    """A number, or a texture's mean (the mean over its channels of Mitsuba's ``mean``)."""
    from icbtool.scene.bsdf import mean_of

    return float(x) if isinstance(x, (int, float)) else float(np.mean(mean_of(x)))


def kind_of(bsdf: Any) -> int:
    """The raster's kind for a material's ``bsdf`` (None or unsupported: the Lambert stand-in)."""
    from icbtool.scene import bsdf as sb

    if isinstance(bsdf, sb.RoughPlastic):
        return KIND_ROUGHPLASTIC
    if isinstance(bsdf, sb.Plastic):
        return KIND_PLASTIC
    if isinstance(bsdf, sb.RoughConductor):
        return KIND_ROUGHCONDUCTOR
    if isinstance(bsdf, sb.Conductor):
        return KIND_CONDUCTOR
    return KIND_LAMBERT


def has_glossy(materials: Sequence[Any]) -> bool:
    """Whether any material has a BSDF the raster evaluates (otherwise the Lambert-only shader)."""
    return any(kind_of(m.bsdf) != KIND_LAMBERT for m in materials)


def pack_bsdfs(materials: Sequence[Any]) -> np.ndarray:
    """The per-material BSDF table of the resolve shader.

    Args:
        materials: the scene's materials (``icbtool.scene.Material``), in face-material order.

    Returns:
        (BSDF_ROWS * M, 4) float32, the layout of this module's docstring.
    """
    from icbtool.scene import bsdf as sb
    from icbtool.scene.bsdf_tables import (
        ROUGH_TRANSMITTANCE_RES,
        fresnel_diffuse_reflectance,
        rough_tables,
    )

    assert BSDF_ROWS - 4 == ROUGH_TRANSMITTANCE_RES // 4
    out = np.zeros((len(materials), BSDF_ROWS, 4), np.float32)
    for i, m in enumerate(materials):
        b = m.bsdf
        kind = kind_of(b)
        row = out[i]
        row[0, 0] = kind
        if kind in (KIND_PLASTIC, KIND_ROUGHPLASTIC):
            eta = b.eta
            row[1, :3] = sb.mean_of(b.diffuse_reflectance)
            row[1, 3] = eta
            row[2, :3] = sb.mean_of(b.specular_reflectance)
            row[2, 3] = 1.0 / (eta * eta)
            row[3, 1] = float(b.nonlinear)
            if kind == KIND_PLASTIC:
                row[3, 0] = fresnel_diffuse_reflectance(1.0 / eta)
            else:
                ggx = b.distribution == "ggx"
                alpha = max(float(b.alpha), 1e-4)
                ext, internal = rough_tables(ggx, float(b.alpha), eta)
                row[0, 1:] = (float(ggx), alpha, alpha)
                row[3, 0] = internal
                row[4:] = np.asarray(ext, np.float32).reshape(-1, 4)
        elif kind in (KIND_CONDUCTOR, KIND_ROUGHCONDUCTOR):
            row[1, :3] = b.eta
            row[2, :3] = b.k
            row[3, :3] = sb.mean_of(b.specular_reflectance)
            if kind == KIND_ROUGHCONDUCTOR:
                row[0, 1] = float(b.distribution == "ggx")
                row[0, 2] = max(_mean_scalar(b.alpha_u), 1e-4)
                row[0, 3] = max(_mean_scalar(b.alpha_v), 1e-4)
    return out.reshape(-1, 4)
