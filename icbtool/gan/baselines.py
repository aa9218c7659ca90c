"""The baselines every learned-GI table carries, and the equal-quality rule (docs/gan.md,
"Honest tables").

A learned GI model earns its place only if it beats what needs no network:

- :class:`ConstantGI`: one colour, the mean GI of the train pixels (per channel);
- :class:`AlbedoScaledGI`: ``GI = k * albedo`` with ``k`` per channel fitted by least squares on
  the train pixels (the simplest formula: a constant irradiance);
- :class:`NearestIrradiance`: no learning at all, the indirect irradiance ``GI / albedo`` of the
  ``k`` nearest train pixels in world space (position, with the normal as a tie-breaker) averaged
  and multiplied by the pixel's albedo.

All three are fitted on (N, 3, H, W) train arrays and predict (H, W, 3) linear GI maps from a
record's (H, W, C) buffers, so a table treats them like any generator.

:func:`equal_quality` finds the cost at which a measured (cost, quality) curve reaches a quality,
interpolating in log cost between measured points, and says so when it cannot: a curve whose
cheapest point is already better has no equal point (``"above"``), one that never gets there has
none either (``"below"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

#: Albedo below this counts as this when demodulating (as the generator's encoding does).
ALBEDO_FLOOR = 0.02


def _surface(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    return np.asarray(mask).reshape(shape) > 0.5


def _train_pixels(
    albedo: np.ndarray, gi: np.ndarray, mask: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) albedo and GI of the surface pixels of (N, 3, H, W) train arrays."""
    a, g = np.asarray(albedo, np.float64), np.asarray(gi, np.float64)
    if a.shape != g.shape or a.ndim != 4 or a.shape[1] != 3:
        raise ValueError(f"albedo {a.shape} and gi {g.shape} must both be (N, 3, H, W)")
    m = _surface(mask, (a.shape[0], 1, *a.shape[2:]))[:, 0]
    if not m.any():
        raise ValueError("no surface pixels to fit on")
    a = a.transpose(0, 2, 3, 1)[m]
    g = g.transpose(0, 2, 3, 1)[m]
    if not (np.isfinite(a).all() and np.isfinite(g).all()):
        raise ValueError("train albedo / GI hold NaN or Inf")
    return a, g


def _get(buffers: Any, name: str) -> np.ndarray:
    v = buffers[name] if isinstance(buffers, dict) else getattr(buffers, name, None)
    if v is None:
        raise ValueError(f"the buffers have no {name!r} map")
    return np.asarray(v, np.float32)


@dataclass(frozen=True)
class ConstantGI:
    """One colour everywhere on surfaces (0 on the background)."""

    colour: np.ndarray

    @classmethod
    def fit(cls, albedo: np.ndarray, gi: np.ndarray, mask: np.ndarray | None = None) -> ConstantGI:
        _, g = _train_pixels(albedo, gi, mask)
        return cls(g.mean(axis=0).astype(np.float32))

    def generate(self, buffers: Any) -> np.ndarray:
        albedo = _get(buffers, "albedo")
        m = _surface(_mask(buffers, albedo), albedo.shape[:2])
        return (m[..., None] * self.colour).astype(np.float32)


@dataclass(frozen=True)
class AlbedoScaledGI:
    """``GI = k * albedo``, ``k`` (3,) per channel."""

    k: np.ndarray

    @classmethod
    def fit(
        cls, albedo: np.ndarray, gi: np.ndarray, mask: np.ndarray | None = None
    ) -> AlbedoScaledGI:
        """Least squares per channel: ``k = sum(a g) / sum(a a)`` over the surface pixels."""
        a, g = _train_pixels(albedo, gi, mask)
        den = (a * a).sum(axis=0)
        if np.any(den <= 0):
            raise ValueError("the train albedo is zero in some channel: k is undefined")
        return cls(((a * g).sum(axis=0) / den).astype(np.float32))

    def generate(self, buffers: Any) -> np.ndarray:
        albedo = _get(buffers, "albedo")
        m = _surface(_mask(buffers, albedo), albedo.shape[:2])
        return (m[..., None] * albedo * self.k).astype(np.float32)


def _mask(buffers: Any, like: np.ndarray) -> np.ndarray | None:
    m = buffers.get("mask") if isinstance(buffers, dict) else getattr(buffers, "mask", None)
    return None if m is None else np.asarray(m)


class NearestIrradiance:
    """World-space nearest-neighbour irradiance (module doc): a baseline with no learning.

    Args:
        positions: (P, 3) world positions of train pixels.
        normals: (P, 3) their world normals.
        irradiance: (P, 3) ``GI / max(albedo, ALBEDO_FLOOR)``.
        bounds: (2, 3) scene bounds; the normal enters the search as ``normal * normal_weight *
            diagonal`` so two sides of a thin wall do not mix.
        k: neighbours averaged.
        normal_weight: see ``bounds``.
    """

    def __init__(
        self,
        positions: np.ndarray,
        normals: np.ndarray,
        irradiance: np.ndarray,
        bounds: np.ndarray,
        k: int = 8,
        normal_weight: float = 0.02,
    ) -> None:
        from scipy.spatial import cKDTree

        p = np.asarray(positions, np.float64).reshape(-1, 3)
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        e = np.asarray(irradiance, np.float32).reshape(-1, 3)
        if not (len(p) == len(n) == len(e)) or len(p) < k:
            raise ValueError(
                f"NearestIrradiance: {len(p)} positions, {len(n)} normals, {len(e)} irradiances "
                f"(need equal counts >= k={k})"
            )
        ok = np.isfinite(p).all(1) & np.isfinite(n).all(1) & np.isfinite(e).all(1)
        if not ok.all():
            raise ValueError(f"NearestIrradiance: {int((~ok).sum())} train pixels are not finite")
        lo, hi = np.asarray(bounds, np.float64)
        self.scale = float(normal_weight * np.linalg.norm(hi - lo))
        self.k = int(k)
        self.tree = cKDTree(np.concatenate([p, n * self.scale], axis=1))
        self.irradiance = e

    @classmethod
    def fit(
        cls,
        position: np.ndarray,
        normal: np.ndarray,
        albedo: np.ndarray,
        gi: np.ndarray,
        mask: np.ndarray | None,
        bounds: np.ndarray,
        k: int = 8,
        max_pixels: int = 600_000,
    ) -> NearestIrradiance:
        """From (N, 3, H, W) train arrays; more than ``max_pixels`` surface pixels are thinned by
        a fixed stride (deterministic)."""
        m = _surface(mask, (position.shape[0], 1, *position.shape[2:]))[:, 0]

        def px(a: np.ndarray) -> np.ndarray:
            return np.asarray(a).transpose(0, 2, 3, 1)[m]

        p, n, a, g = px(position), px(normal), px(albedo), px(gi)
        step = max(1, math.ceil(len(p) / max_pixels))
        e = g / np.maximum(a, ALBEDO_FLOOR)
        return cls(p[::step], n[::step], e[::step], bounds, k)

    def generate(self, buffers: Any) -> np.ndarray:
        albedo = _get(buffers, "albedo")
        pos, nrm = _get(buffers, "position"), _get(buffers, "normal_world")
        h, w = albedo.shape[:2]
        m = _surface(_mask(buffers, albedo), (h, w))
        q = np.concatenate([pos[m], nrm[m] * self.scale], axis=1).astype(np.float64)
        out = np.zeros((h, w, 3), np.float32)
        if len(q):
            _, idx = self.tree.query(q, k=self.k)
            idx = idx.reshape(len(q), -1)
            out[m] = self.irradiance[idx].mean(axis=1) * albedo[m]
        return out


@dataclass(frozen=True)
class EqualQuality:
    """Where a (cost, quality) curve reaches a quality.

    Attributes:
        cost: the interpolated cost (None when there is no equal point).
        status: "interpolated" (between two measured points, linear in log cost), "measured" (a
            measured point has exactly that quality), "above" (the curve's cheapest measured
            point is already better: no equal point was measured), "below" (the curve never gets
            there).
        cheapest: the curve's cheapest (cost, quality).
    """

    cost: float | None
    status: Literal["interpolated", "measured", "above", "below"]
    cheapest: tuple[float, float]


def equal_quality(costs: Any, qualities: Any, target: float) -> EqualQuality:
    """The cost at which the curve first reaches ``target`` quality (module doc).

    The curve is made monotone first: the quality reachable at a cost is the best of every
    measured point that costs no more (a slower setting that scores lower is never chosen).

    Args:
        costs: (K,) positive costs (e.g. ms per frame).
        qualities: (K,) qualities (higher is better, e.g. SSIM).
        target: the quality to reach.

    Raises:
        ValueError: empty or mismatched arrays, non-positive or non-finite costs.
    """
    c = np.asarray(costs, np.float64).reshape(-1)
    q = np.asarray(qualities, np.float64).reshape(-1)
    if len(c) == 0 or len(c) != len(q):
        raise ValueError(f"equal_quality: {len(c)} costs and {len(q)} qualities")
    if not (np.isfinite(c).all() and np.isfinite(q).all()) or (c <= 0).any():
        raise ValueError("equal_quality: costs must be finite and > 0, qualities finite")
    o = np.argsort(c, kind="stable")
    c, q = c[o], np.maximum.accumulate(q[o])
    cheapest = (float(c[0]), float(q[0]))
    if q[0] > target:
        return EqualQuality(None, "above", cheapest)
    if q[-1] < target:
        return EqualQuality(None, "below", cheapest)
    i = int(np.argmax(q >= target))
    if q[i] == target:
        return EqualQuality(float(c[i]), "measured", cheapest)
    f = (target - q[i - 1]) / (q[i] - q[i - 1])
    cost = math.exp(math.log(c[i - 1]) + f * (math.log(c[i]) - math.log(c[i - 1])))
    return EqualQuality(cost, "interpolated", cheapest)


__all__ = [
    "ALBEDO_FLOOR",
    "AlbedoScaledGI",
    "ConstantGI",
    "EqualQuality",
    "NearestIrradiance",
    "equal_quality",
]
