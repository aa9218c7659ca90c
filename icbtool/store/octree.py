"""The in-memory octree of the CRT-buffer manager (docs/design.md section 3).

A linear octree: the root cube encloses the scene bounds; every leaf sits at one depth ``D`` (chosen
from the scene's scale so that a leaf is about the lookup position threshold wide) and is addressed
by its integer cell coordinates ``(i, j, k)`` in ``[0, 2^D)^3`` (its Morton code is the classic
pointer-free octree address; :func:`morton` gives it). Only occupied leaves exist (a dict), so the
memory is proportional to the records, not to ``8^D``.

Adjacency (the paper's "Adjacent" links) is implicit: the neighbours of leaf ``(i, j, k)`` are the
occupied leaves whose coordinates differ by at most 1 (:meth:`SceneOctree.adjacent`). The lookup
does not stop at the 27-neighbourhood: it visits every leaf that intersects the axis-aligned box
around the ball of radius ``alpha_pos`` (so it is exact for any threshold, also one larger than a
leaf), and switches to scanning the occupied leaves when that box holds more cells than there are
occupied leaves.

Cameras outside the root cube are clamped into the border leaf along each axis. Clamping is
monotone, so the ball-box range of a query contains the clamped leaf of every record within
``alpha_pos``: the lookup stays exact, and far-away cameras only cost time in the border leaves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Columns of a leaf's record table.
COLS = ("px", "py", "pz", "dx", "dy", "dz", "height", "width", "fx", "fy", "cx", "cy")
NCOLS = len(COLS)


def morton(i: int, j: int, k: int) -> int:
    """The Morton (z-order) code of leaf cell ``(i, j, k)`` (interleaved bits, i lowest)."""
    code = 0
    for b in range(21):
        code |= (
            ((i >> b) & 1) << (3 * b)
            | ((j >> b) & 1) << (3 * b + 1)
            | ((k >> b) & 1) << (3 * b + 2)
        )
    return code


@dataclass(frozen=True)
class OctreeGeometry:
    """Where a scene's octree lives.

    Attributes:
        root_min: (3,) corner of the root cube.
        root_size: edge length of the root cube (> 0).
        depth: leaf depth D (the root is depth 0); a leaf is ``root_size / 2^D`` wide.
    """

    root_min: tuple[float, float, float]
    root_size: float
    depth: int

    def __post_init__(self) -> None:
        if not (self.root_size > 0 and math.isfinite(self.root_size)):
            raise ValueError(f"octree root_size must be finite and > 0, got {self.root_size}")
        if not (0 <= self.depth <= 21):
            raise ValueError(f"octree depth must be in [0, 21], got {self.depth}")

    @property
    def cells_per_axis(self) -> int:
        return 1 << self.depth

    @property
    def leaf_size(self) -> float:
        return self.root_size / self.cells_per_axis

    @classmethod
    def for_bounds(
        cls, bounds: np.ndarray, leaf_size: float, max_depth: int = 12, margin: float = 0.01
    ) -> OctreeGeometry:
        """The root cube around ``bounds`` (2, 3), padded by ``margin`` of the extent, with the
        smallest depth whose leaves are at most ``leaf_size`` wide (capped at ``max_depth``)."""
        b = np.asarray(bounds, dtype=np.float64)
        if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
            raise ValueError(f"octree bounds must be finite (2, 3) [min, max], got {b.tolist()}")
        if not (leaf_size > 0):
            raise ValueError(f"octree leaf_size must be > 0, got {leaf_size}")
        extent = float(np.max(b[1] - b[0]))
        size = max(extent * (1.0 + 2.0 * margin), leaf_size)
        centre = 0.5 * (b[0] + b[1])
        depth = int(min(max_depth, max(0, math.ceil(math.log2(size / leaf_size)))))
        return cls(tuple((centre - 0.5 * size).tolist()), size, depth)


class _Leaf:
    __slots__ = ("rows", "ids", "_data", "_ids")

    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []  # (12,) rows as Python floats
        self.ids: list[int] = []
        self._data: np.ndarray | None = None
        self._ids: np.ndarray | None = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if self._data is None:
            self._data = np.array(self.rows, np.float64).reshape(-1, NCOLS)
            self._ids = np.asarray(self.ids, dtype=np.int64)
        return self._data, self._ids  # type: ignore[return-value]


class SceneOctree:
    """The leaves of one (scene, light setup) group.

    Args:
        geometry: the root cube and depth.
    """

    def __init__(self, geometry: OctreeGeometry) -> None:
        self.geometry = geometry
        self._min = np.asarray(geometry.root_min, dtype=np.float64)
        self._min_list = self._min.tolist()
        self._inv = 1.0 / geometry.leaf_size
        self._n = geometry.cells_per_axis
        self.leaves: dict[tuple[int, int, int], _Leaf] = {}
        self._where: dict[int, tuple[int, int, int]] = {}

    def __len__(self) -> int:
        return len(self._where)

    def cell_of(self, p: np.ndarray) -> tuple[int, int, int]:
        """The (clamped) leaf cell of point ``p`` (3,)."""
        c = np.floor((np.asarray(p, np.float64) - self._min) * self._inv)
        c = np.clip(c, 0, self._n - 1).astype(np.int64)
        return int(c[0]), int(c[1]), int(c[2])

    def is_inside(self, p: np.ndarray) -> bool:
        q = (np.asarray(p, np.float64) - self._min) * self._inv
        return bool(np.all(q >= 0) and np.all(q < self._n))

    def insert(self, record_id: int, row: np.ndarray) -> tuple[int, int, int]:
        """Add a record (``row``: (12,) :data:`COLS`); returns its leaf cell."""
        key = self.cell_of(row[:3])
        leaf = self.leaves.get(key)
        if leaf is None:
            leaf = self.leaves[key] = _Leaf()
        leaf.rows.append(tuple(np.asarray(row, dtype=np.float64).tolist()))
        leaf.ids.append(int(record_id))
        leaf._data = None
        self._where[int(record_id)] = key
        return key

    def remove(self, record_id: int) -> bool:
        key = self._where.pop(int(record_id), None)
        if key is None:
            return False
        leaf = self.leaves[key]
        k = leaf.ids.index(int(record_id))
        del leaf.ids[k]
        del leaf.rows[k]
        leaf._data = None
        if not leaf.ids:
            del self.leaves[key]
        return True

    def adjacent(self, key: tuple[int, int, int]) -> list[tuple[int, int, int]]:
        """The occupied leaves sharing a face, edge or corner with leaf ``key``."""
        i, j, k = key
        out = []
        for a in (i - 1, i, i + 1):
            for b in (j - 1, j, j + 1):
                for c in (k - 1, k, k + 1):
                    if (a, b, c) != key and (a, b, c) in self.leaves:
                        out.append((a, b, c))
        return out

    def candidates(self, p: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """Every record in a leaf that intersects the box around the ball (p, radius).

        Returns:
            data: (N, 12) float64 rows (:data:`COLS`).
            ids: (N,) int64 record ids.
        """
        found = [leaf.arrays() for leaf in self.candidate_leaves(p, radius)]
        if not found:
            return np.empty((0, NCOLS)), np.empty(0, np.int64)
        if len(found) == 1:
            return found[0]
        return np.concatenate([f[0] for f in found]), np.concatenate([f[1] for f in found])

    def candidate_leaves(self, p: Any, radius: float) -> list[_Leaf]:
        """The occupied leaves intersecting the axis-aligned box around the ball (p, radius)."""
        inv, mn, n1 = self._inv, self._min_list, self._n - 1
        r = radius * inv
        lo, hi = [], []
        for a, x in enumerate(p.tolist() if isinstance(p, np.ndarray) else p):
            qa = (x - mn[a]) * inv
            lo.append(min(max(math.floor(qa - r), 0), n1))
            hi.append(min(max(math.floor(qa + r), 0), n1))
        count = (hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1)
        leaves = self.leaves
        found = []
        if count > len(leaves):
            for (a, b, c), leaf in leaves.items():
                if lo[0] <= a <= hi[0] and lo[1] <= b <= hi[1] and lo[2] <= c <= hi[2]:
                    found.append(leaf)
        else:
            get = leaves.get
            for a in range(lo[0], hi[0] + 1):
                for b in range(lo[1], hi[1] + 1):
                    for c in range(lo[2], hi[2] + 1):
                        leaf = get((a, b, c))
                        if leaf is not None:
                            found.append(leaf)
        return found

    def occupancy(self) -> dict[str, float]:
        """Leaf statistics: occupied leaves, records per occupied leaf (mean, max)."""
        sizes = [len(leaf.ids) for leaf in self.leaves.values()]
        return {
            "depth": self.geometry.depth,
            "leaf_size": self.geometry.leaf_size,
            "occupied_leaves": len(sizes),
            "records": len(self),
            "mean_per_leaf": float(np.mean(sizes)) if sizes else 0.0,
            "max_per_leaf": int(max(sizes)) if sizes else 0,
        }
