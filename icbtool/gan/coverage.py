"""Where the training views have looked: coverage of a scene's surfaces, and a planner that adds
the views that are missing (docs/gan.md, "Coverage").

A generator (or any learned GI) can only be as good as the surfaces its training views showed: a
test view that looks at walls the train path never faced asks it to make those up. Two tools:

- :func:`coverage_distance`: for every query pixel (world position), the distance to the nearest
  training pixel, as a fraction of the scene's bounding-box diagonal. The median over a view is its
  *coverage distance*; tables print it next to every score.
- :func:`plan_coverage`: greedy view selection. Candidate cameras stand on collision-free eye
  positions of the scene (random walks of :func:`icbtool.scene.walk.random_walk`) and look in
  ``yaws`` x ``pitches`` directions; each candidate's world positions are rasterized at a small
  size, and the planner repeatedly takes the candidate that sees the most surface points farther
  than ``radius`` from everything already covered (the existing views' pixels, e.g. a store's train
  path, plus the views chosen so far). It never looks at test cameras: it knows only the scene's
  geometry and what has been rendered, as the cloud's octree does.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from icbtool.camera import Camera, CameraPath
from icbtool.camera.camera import pose_from_forward


def _diagonal(bounds: np.ndarray) -> float:
    lo, hi = np.asarray(bounds, dtype=np.float64)
    d = float(np.linalg.norm(hi - lo))
    if not (math.isfinite(d) and d > 0):
        raise ValueError(f"scene bounds {bounds.tolist()} have no extent")
    return d


def _points(a: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} of {len(p)} points are not finite")
    return p


def coverage_distance(
    covered: np.ndarray, queries: np.ndarray, bounds: np.ndarray, max_covered: int = 400_000
) -> np.ndarray:
    """Distance from each query point to the nearest covered point, over the scene's diagonal.

    Args:
        covered: (N, 3) world positions already seen (e.g. every train pixel's position).
        queries: (M, 3) world positions to score (e.g. a test view's pixels).
        bounds: (2, 3) scene bounds (the diagonal normalises the distances).
        max_covered: covered points above this count are subsampled evenly (a fixed stride,
            deterministic) to bound the KD-tree's size.

    Returns:
        (M,) float64 distances as fractions of the diagonal (0: a training pixel saw exactly this
        point).

    Raises:
        ValueError: no covered points, non-finite points, degenerate bounds.
    """
    from scipy.spatial import cKDTree

    cov = _points(covered, "covered")
    q = _points(queries, "queries")
    if len(cov) == 0:
        raise ValueError("coverage_distance: no covered points")
    if len(cov) > max_covered:
        cov = cov[:: int(math.ceil(len(cov) / max_covered))]
    d, _ = cKDTree(cov).query(q, k=1)
    return d / _diagonal(bounds)


def store_points(
    store: Any, paths: Iterable[str], scene: Any = None, stride: int = 1
) -> np.ndarray:
    """World positions of every covered pixel of a store's records on the given camera paths.

    Args:
        store: an open :class:`icbtool.store.Store`.
        paths: path tags (``record.meta.tags["path"]``), e.g. ``("train",)``.
        scene: restrict to this scene's records (Scene, name or hash; None: all).
        stride: keep every ``stride``-th pixel in both image axes.

    Returns:
        (N, 3) float64 positions (background pixels excluded).
    """
    from icbtool.store.dataset import Dataset

    out = []
    for name in paths:
        ds = Dataset(store, scene, "train", ("position",), paths={"train": name})
        for s in ds:
            pos = s.inputs.transpose(1, 2, 0)[::stride, ::stride]
            m = s.mask[0, ::stride, ::stride] > 0.5
            out.append(pos[m])
    if not out:
        return np.zeros((0, 3))
    return np.concatenate(out).astype(np.float64)


@dataclass(frozen=True)
class CoveragePlan:
    """What :func:`plan_coverage` returns.

    Attributes:
        path: the chosen cameras as a :class:`CameraPath` (1/30 s apart; the times carry no motion).
        gain: (n,) fraction of each chosen view's pixels that were newly covered when it was taken.
        uncovered_before, uncovered_after: fraction of all candidate pixels farther than
            ``radius`` from the covered set before and after the plan.
        candidates: number of candidate cameras scored.
    """

    path: CameraPath
    gain: np.ndarray
    uncovered_before: float
    uncovered_after: float
    candidates: int


def candidate_cameras(
    scene: Any,
    intrinsics: Camera,
    n_positions: int = 60,
    seed: int = 0,
    yaws: int = 8,
    pitches_deg: tuple[float, ...] = (-5.0, 25.0),
    height_range: tuple[float, float] = (1.6, 3.0),
) -> list[Camera]:
    """Collision-free cameras in every direction: ``n_positions`` eye positions from a random walk
    of the scene (every ~4th step, so neighbours are apart) x ``yaws`` headings x ``pitches_deg``.

    Raises:
        ValueError: the scene has no floor to walk on (see :func:`random_walk`).
    """
    from icbtool.scene.walk import random_walk

    if n_positions < 1 or yaws < 1 or not pitches_deg:
        raise ValueError("candidate_cameras: n_positions, yaws and pitches must be >= 1")
    walk = random_walk(
        scene, intrinsics, 4 * n_positions, seed, height_range=height_range, name="candidates"
    )
    up = np.asarray(scene.up, dtype=np.float64)
    # two horizontal axes perpendicular to up
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = a - up * (a @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    cams = []
    for i in range(0, len(walk), 4):
        eye = walk[i].position
        for k in range(yaws):
            phi = 2 * math.pi * k / yaws
            h = math.cos(phi) * e1 + math.sin(phi) * e2
            for p in pitches_deg:
                t = math.radians(p)
                fwd = math.cos(t) * h + math.sin(t) * up
                cams.append(intrinsics.with_pose(pose_from_forward(eye, fwd, up)))
    return cams


def plan_coverage(
    scene: Any,
    n_views: int,
    intrinsics: Camera,
    covered: np.ndarray | None = None,
    radius: float = 0.01,
    probe_size: int = 32,
    n_positions: int = 60,
    seed: int = 0,
    name: str = "cover",
    progress: bool = True,
) -> CoveragePlan:
    """Choose ``n_views`` cameras that see the most surface not yet covered (module doc).

    Args:
        scene: the scene.
        n_views: cameras to choose.
        intrinsics: the size and field of view of the views to bake (their pose is ignored).
        covered: (N, 3) world positions already covered (e.g. :func:`store_points` of the train
            path); None: nothing yet.
        radius: a point is covered when a covered point lies within ``radius`` x the diagonal.
        probe_size: candidates are rasterized at this size (square) to score them.
        n_positions: eye positions of :func:`candidate_cameras`.
        seed: seed of the candidates' random walk.
        name: the returned path's name (the bake tags records with it).
        progress: show a progress bar while scoring candidates.

    Returns:
        :class:`CoveragePlan`.

    Raises:
        ValueError: ``n_views`` < 1 or more than there are candidates, bad ``radius``.
    """
    from scipy.spatial import cKDTree

    from icbtool import raster

    if n_views < 1:
        raise ValueError(f"plan_coverage: n_views must be >= 1, got {n_views}")
    if not (0 < radius < 1):
        raise ValueError(f"plan_coverage: radius must be in (0, 1), got {radius}")
    cands = candidate_cameras(scene, intrinsics, n_positions, seed)
    if n_views > len(cands):
        raise ValueError(f"plan_coverage: {n_views} views asked, only {len(cands)} candidates")
    diag = _diagonal(scene.bounds)
    r = radius * diag
    probe = intrinsics.resized(probe_size, probe_size)
    pts: list[np.ndarray] = []
    it: Any = cands
    if progress:
        from tqdm import tqdm

        it = tqdm(cands, desc="coverage: candidates", unit="view")
    with raster.Rasterizer(scene) as rz:
        for c in it:
            b = rz.render(probe.with_pose(c.world_from_cam), buffers=("position", "mask"))
            m = b.mask[..., 0] > 0.5
            pts.append(b.position[m].astype(np.float64))
    n_px = probe_size * probe_size
    # uncovered[i]: boolean per candidate pixel, True while no covered point is within r
    if covered is not None and len(covered):
        tree = cKDTree(_points(covered, "covered"))
        uncovered = [tree.query(p, k=1, distance_upper_bound=r)[0] > r for p in pts]
    else:
        uncovered = [np.ones(len(p), bool) for p in pts]
    total = sum(len(p) for p in pts)
    before = sum(int(u.sum()) for u in uncovered) / max(total, 1)
    chosen, gain = [], []
    for _ in range(n_views):
        score = np.array([u.sum() for u in uncovered], dtype=np.float64)
        score[chosen] = -1
        best = int(np.argmax(score))
        chosen.append(best)
        gain.append(score[best] / n_px)
        new = pts[best][uncovered[best]]
        if len(new):
            t = cKDTree(new)
            for j, p in enumerate(pts):
                if uncovered[j].any():
                    idx = np.flatnonzero(uncovered[j])
                    d, _ = t.query(p[idx], k=1, distance_upper_bound=r)
                    uncovered[j][idx[d <= r]] = False
    after = sum(int(u.sum()) for u in uncovered) / max(total, 1)
    poses = np.stack([cands[i].world_from_cam for i in chosen])
    path = CameraPath(np.arange(len(chosen)) / 30.0, poses, intrinsics, name=name)
    return CoveragePlan(path, np.asarray(gain), before, after, len(cands))


__all__ = [
    "CoveragePlan",
    "candidate_cameras",
    "coverage_distance",
    "plan_coverage",
    "store_points",
]
