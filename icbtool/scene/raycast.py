"""Ray queries on a scene: a thin, thread-parallel wrapper around embreex (Embree 4).

It answers geometric questions about one :class:`~icbtool.scene.Scene` (what does a ray hit?)
for the camera walks and placement checks of :mod:`icbtool.scene.walk`, the bakes, tests and
benchmarks. It lives with the scene, below the renderers, so that nothing under ``scene`` or
``camera`` imports ``trace``.

embreex runs each ``scene.run`` call as a serial loop inside ``nogil``, so splitting a batch of rays
over a few Python threads scales almost linearly with the cores.

embreex has no ``tnear``: rays always start at t = 0. :meth:`EmbreeScene.intersect` emulates
``tnear`` by moving the origin along the direction and adding ``tnear`` back to the hit distance.
Callers that start rays on a surface should offset the origin themselves along the geometric
normal (as the tracer's kernels do, see ``_eps`` in :mod:`icbtool.trace.kernels`), which is more
robust than a ``tnear``.

The path tracer does not use this class: its kernels call Embree directly
(:mod:`icbtool.trace.rtc`). It serves the rest of the library (camera walks, placement checks,
tests) and the benchmarks.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.scene.types import Scene

#: Batches smaller than this are never split over threads (the split costs more than it saves).
MIN_RAYS_PER_THREAD = 4096


@dataclass
class Hits:
    """Closest hits of a batch of N rays.

    Attributes:
        t: (N,) float32 ray parameter of the hit (distance if the direction is unit), inf = miss.
        prim: (N,) int32 triangle index into ``scene.faces``, -1 = miss.
        u, v: (N,) float32 barycentrics: ``p = (1 - u - v) * v0 + u * v1 + v * v2``.
        ng: (N, 3) float32 unit geometric normal ``cross(v1 - v0, v2 - v0)`` (face winding, not
            flipped towards the ray); 0 for misses and degenerate triangles.
    """

    t: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    ng: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool, True where the ray hit a triangle."""
        return self.prim >= 0

    def __len__(self) -> int:
        return len(self.prim)


def _as_rays(x: Any, name: str) -> np.ndarray:
    a = np.ascontiguousarray(x, dtype=np.float32)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return a


class EmbreeScene:
    """An Embree BVH over a scene's triangles, queried in thread-parallel batches.

    Args:
        vertices: (V, 3) float world positions.
        faces: (F, 3) int vertex indices.
        robust: Embree's robust mode (watertight, slightly slower; recommended).
        threads: default number of threads per query (>= 1).
    """

    def __init__(self, vertices: Any, faces: Any, robust: bool = True, threads: int = 2) -> None:
        try:
            from embreex import mesh_construction, rtcore_scene
        except ImportError as e:  # pragma: no cover - embreex is a core dependency
            raise ImportError(
                "icbtool.trace needs embreex: pip install embreex (see requirements.lock)"
            ) from e
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.int32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"need vertices (V, 3) and faces (F>0, 3), got {v.shape}, {f.shape}")
        if int(threads) < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.threads = int(threads)
        self.robust = bool(robust)
        self._scene = rtcore_scene.EmbreeScene(robust=self.robust)
        self._mesh = mesh_construction.TriangleMesh(self._scene, v, f)
        tri = v[f].astype(np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        self._face_normals = np.where(ln > 0, n / np.maximum(ln, 1e-300), 0.0).astype(np.float32)
        self.n_triangles = len(f)
        self._pool: ThreadPoolExecutor | None = None

    @classmethod
    def from_scene(cls, scene: Scene, robust: bool = True, threads: int = 2) -> EmbreeScene:
        """The Embree scene of ``scene``'s merged mesh (cached: :mod:`icbtool.scene.derived`)."""
        from icbtool.scene.derived import derived

        es = derived(
            scene,
            f"embree_robust={bool(robust)}",
            lambda: cls(scene.vertices, scene.faces, robust=robust, threads=threads),
        )
        es.threads = max(1, int(threads))
        return es

    # ------------------------------------------------------------------ threading
    def _chunks(self, n: int, threads: int | None) -> list[slice]:
        k = self.threads if threads is None else max(1, int(threads))
        k = max(1, min(k, n // MIN_RAYS_PER_THREAD))
        edges = np.linspace(0, n, k + 1).astype(int)
        return [slice(edges[i], edges[i + 1]) for i in range(k)]

    def _map(self, fn, chunks: list[slice]) -> list:
        if len(chunks) == 1:
            return [fn(chunks[0])]
        if self._pool is None or self._pool._max_workers < len(chunks):
            self._pool = ThreadPoolExecutor(max_workers=len(chunks))
        return list(self._pool.map(fn, chunks))

    # ------------------------------------------------------------------ queries
    def intersect(
        self,
        origins: Any,
        directions: Any,
        tnear: float = 0.0,
        tfar: Any = None,
        threads: int | None = None,
    ) -> Hits:
        """Closest hit of each ray.

        Args:
            origins: (N, 3) ray origins.
            directions: (N, 3) ray directions (need not be unit; ``t`` is in their units).
            tnear: ignore hits closer than this (emulated by moving the origin, see module doc).
            tfar: (N,) or scalar: ignore hits farther than this; None = infinity.
            threads: threads for this call (default: ``self.threads``).

        Returns:
            :class:`Hits` with N entries.
        """
        o = _as_rays(origins, "origins")
        d = _as_rays(directions, "directions")
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and directions {d.shape} differ in shape")
        n = len(o)
        if tnear:
            o = np.ascontiguousarray(o + float(tnear) * d, dtype=np.float32)
        if tfar is None:
            dist = np.full(n, np.inf, np.float32)
        else:
            dist = np.ascontiguousarray(np.broadcast_to(np.asarray(tfar, np.float32), (n,)))
            dist = np.array(dist - float(tnear), np.float32)
        t = np.empty(n, np.float32)
        prim = np.empty(n, np.int32)
        u = np.empty(n, np.float32)
        v = np.empty(n, np.float32)

        def run(s: slice) -> None:
            if s.stop <= s.start:
                return
            dd = np.array(dist[s], np.float32)
            r = self._scene.run(o[s], d[s], dists=dd, query="INTERSECT", output=1)
            p = np.asarray(r["primID"], np.int32)
            miss = p < 0
            tt = np.asarray(r["tfar"], np.float32).copy()
            tt[miss] = np.inf
            t[s], prim[s] = tt, p
            u[s], v[s] = r["u"], r["v"]

        self._map(run, self._chunks(n, threads))
        if tnear:
            t += np.float32(tnear)
        ng = np.zeros((n, 3), np.float32)
        h = prim >= 0
        ng[h] = self._face_normals[prim[h]]
        u[~h] = 0.0
        v[~h] = 0.0
        return Hits(t=t, prim=prim, u=u, v=v, ng=ng)

    def occluded(
        self, origins: Any, directions: Any, tfar: Any, threads: int | None = None
    ) -> np.ndarray:
        """Whether anything lies on each segment ``origin + t * direction``, 0 < t < tfar.

        Args:
            origins: (N, 3) ray origins (offset them off surfaces yourself).
            directions: (N, 3) ray directions.
            tfar: (N,) or scalar maximum ray parameter (np.inf for "to infinity").
            threads: threads for this call (default: ``self.threads``).

        Returns:
            (N,) bool, True = blocked.
        """
        o = _as_rays(origins, "origins")
        d = _as_rays(directions, "directions")
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and directions {d.shape} differ in shape")
        n = len(o)
        dist = np.array(np.broadcast_to(np.asarray(tfar, np.float32), (n,)), np.float32)
        out = np.zeros(n, bool)

        def run(s: slice) -> None:
            if s.stop <= s.start:
                return
            dd = np.array(dist[s], np.float32)
            r = self._scene.run(o[s], d[s], dists=dd, query="OCCLUDED")
            out[s] = np.asarray(r) == 0

        self._map(run, self._chunks(n, threads))
        return out

    # ------------------------------------------------------------------ raw queries (tracer)
    def intersect_raw(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        threads: int | None = None,
        out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest hits without the :class:`Hits` extras (for the tracer's hot loop).

        Args:
            origins, directions: (N, 3) C-contiguous float32 (not copied, not checked).
            threads: threads for this call (default: ``self.threads``).
            out: optional (t, prim, u, v) output arrays of length N to fill (reused buffers).

        Returns:
            t (N,) float32 (undefined for misses), prim (N,) int32 (-1 = miss), u, v (N,) float32.
        """
        n = len(origins)
        if out is None:
            out = (
                np.empty(n, np.float32),
                np.empty(n, np.int32),
                np.empty(n, np.float32),
                np.empty(n, np.float32),
            )
        t, prim, u, v = out

        def run(s: slice) -> None:
            if s.stop <= s.start:
                return
            r = self._scene.run(origins[s], directions[s], query="INTERSECT", output=1)
            prim[s] = r["primID"]
            t[s] = r["tfar"]
            u[s] = r["u"]
            v[s] = r["v"]

        self._map(run, self._chunks(n, threads))
        return t, prim, u, v

    def occluded_raw(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        tfar: np.ndarray,
        threads: int | None = None,
    ) -> np.ndarray:
        """:meth:`occluded` for C-contiguous float32 (N, 3) rays and (N,) float32 ``tfar``
        (``tfar`` is overwritten, nothing is checked or copied). Returns (N,) bool, True = blocked.
        """
        n = len(origins)
        out = np.empty(n, np.bool_)

        def run(s: slice) -> None:
            if s.stop <= s.start:
                return
            r = self._scene.run(origins[s], directions[s], dists=tfar[s], query="OCCLUDED")
            out[s] = np.asarray(r) == 0

        self._map(run, self._chunks(n, threads))
        return out

    def __repr__(self) -> str:
        return (
            f"EmbreeScene({self.n_triangles} triangles, robust={self.robust}, "
            f"threads={self.threads})"
        )
