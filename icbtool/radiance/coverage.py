"""Coverage: how far a view's surface points are from the nearest train pixel in world space.

A world-space model knows the irradiance only near surfaces the train views saw; elsewhere it
extrapolates. ``coverage_distances`` measures that per pixel: the distance from each query point
to the nearest of (a seeded subsample of) the train pixels' positions, divided by the scene's
bounding-box diagonal. ``view_coverage`` summarises a view by the median of its surface pixels.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class TrainCoverage:
    """A k-d tree over train pixel positions.

    Args:
        train_positions: (N, 3) world positions of train pixels.
        diagonal: the scene's bounding-box diagonal (distances are divided by it).
        max_points: subsample the train positions to at most this many (seeded).
        seed: seed of the subsample.

    Raises:
        ValueError: no train positions, or a diagonal that is not > 0.
    """

    def __init__(
        self, train_positions: np.ndarray, diagonal: float, max_points: int = 200_000, seed: int = 0
    ) -> None:
        from scipy.spatial import cKDTree

        p = np.asarray(train_positions, np.float64).reshape(-1, 3)
        if len(p) == 0:
            raise ValueError("TrainCoverage: no train positions")
        if not (np.isfinite(diagonal) and diagonal > 0):
            raise ValueError(f"TrainCoverage: diagonal must be > 0, got {diagonal}")
        if len(p) > max_points:
            p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
        self.tree = cKDTree(p)
        self.diagonal = float(diagonal)
        self.points = len(p)

    def distances(self, positions: np.ndarray) -> np.ndarray:
        """(N,) float64 nearest-train-pixel distance of (N, 3) points / diagonal."""
        q = np.asarray(positions, np.float64).reshape(-1, 3)
        if len(q) == 0:
            return np.zeros(0)
        d, _ = self.tree.query(q, k=1)
        return d / self.diagonal


def coverage_distances(
    train_positions: np.ndarray, query: np.ndarray, diagonal: float, **kw: Any
) -> np.ndarray:
    """(N,) nearest-train-pixel distances of query points as a fraction of ``diagonal``."""
    return TrainCoverage(train_positions, diagonal, **kw).distances(query)


def view_coverage(cov: TrainCoverage, positions: np.ndarray) -> float:
    """Median fraction-of-diagonal distance of a view's surface points (nan: no surface)."""
    d = cov.distances(positions)
    return float(np.median(d)) if len(d) else float("nan")


__all__ = ["TrainCoverage", "coverage_distances", "view_coverage"]
