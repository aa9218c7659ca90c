"""Finding a stored camera: the in-memory octree index that follows the database, exact and
similar-camera lookups (the similarity test of :mod:`icbtool.store.store`), and the hit
counts. :class:`LookupMixin` is that part of :class:`icbtool.store.Store`."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol

import numpy as np

from icbtool.camera import Camera
from icbtool.store.base import (
    RecordInfo,
)
from icbtool.store.octree import OctreeGeometry, SceneOctree
from icbtool.store.record import (
    CRTBuffer,
)
from icbtool.store.schema import (
    _ROW_COLS,
    camera_key,
)


class _Records(Protocol):
    """What a :class:`Hit` reads its record from (the :class:`~icbtool.store.Store`)."""

    def get(self, record_id: int) -> CRTBuffer: ...

    def info(self, record_id: int) -> RecordInfo: ...


@dataclass(eq=False)
class Hit:
    """A lookup hit: the best similar stored camera.

    Attributes:
        record_id: id of the matched record.
        distance: |p_query - p_record| (scene units).
        dir_score: 1 - dot(d_query, d_record).
        angle_deg: angle between the viewing directions, degrees.
        score: ``distance / alpha_pos + dir_score / alpha_dir`` (what "best" minimises).
        same_intrinsics: whether the record's size and intrinsics equal the query's (within
            tolerance); if not, warp it before use.
        n_candidates: records examined in the visited leaves.
    """

    record_id: int
    distance: float
    dir_score: float
    angle_deg: float
    score: float
    same_intrinsics: bool
    n_candidates: int
    _store: _Records = field(repr=False)

    @cached_property
    def record(self) -> CRTBuffer:
        """The matched CRT-buffer (payload loaded and verified on first access)."""
        return self._store.get(self.record_id)

    @cached_property
    def info(self) -> RecordInfo:
        return self._store.info(self.record_id)

    @property
    def camera(self) -> Camera:
        return self.info.camera


def _intrinsics_check(
    r: Any, q: tuple[int, int, float, float, float, float], policy: str, rtol: float
) -> tuple[bool, bool]:
    """(allowed by the policy, same intrinsics) for a stored camera ``r`` = [h, w, fx, fy, cx, cy]
    and the query ``q`` (same layout)."""
    h, w, fx, fy, cx, cy = r
    qh, qw, qfx, qfy, qcx, qcy = q
    same = (
        h == qh
        and w == qw
        and abs(fx - qfx) <= rtol * qfx
        and abs(fy - qfy) <= rtol * qfy
        and abs(cx - qcx) <= rtol * max(qcx, 1.0)
        and abs(cy - qcy) <= rtol * max(qcy, 1.0)
    )
    if policy == "same":
        return same, same
    if policy == "any":
        return True, same
    s = 1.0 - rtol  # covering: every half-angle tangent at least the query's
    cover = (
        cx / fx >= s * qcx / qfx
        and (w - cx) / fx >= s * (qw - qcx) / qfx
        and cy / fy >= s * qcy / qfy
        and (h - cy) / fy >= s * (qh - qcy) / qfy
    )
    return cover, same


#: A candidate within both thresholds: (distance, 1 - dot, record id, camera row).
_Passing = tuple[float, float, int, tuple[float, ...]]


def _within(dist: Any, dd: Any, a_pos: float, a_dir: float) -> Any:
    """The similarity test (module docstring of :mod:`icbtool.store.store`): ``|p1 - p2| <
    alpha_pos`` and ``1 - dot(d1, d2) < alpha_dir``; on floats, or element-wise on arrays."""
    return (dist < a_pos) & (dd < a_dir)


def _similar_few(leaves: list, m: np.ndarray, a_pos: float, a_dir: float) -> list[_Passing]:
    """The similar records among a few candidates (plain Python)."""
    px, py, pz = m[:3, 3].tolist()
    fx, fy, fz = m[:3, 2].tolist()
    a2 = a_pos * a_pos * (1.0 + 1e-9)  # prefilter only; the exact test is on the sqrt
    out = []
    for leaf in leaves:
        for rid, row in zip(leaf.ids, leaf.rows):
            dx, dy, dz = row[0] - px, row[1] - py, row[2] - pz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > a2:
                continue
            dd = 1.0 - (row[3] * fx + row[4] * fy + row[5] * fz)
            dist = math.sqrt(d2)
            if _within(dist, dd, a_pos, a_dir):
                out.append((dist, dd, rid, row))
    return out


def _similar_many(tree: SceneOctree, m: np.ndarray, a_pos: float, a_dir: float) -> list[_Passing]:
    """The similar records among many candidates (numpy)."""
    data, ids = tree.candidates(m[:3, 3].tolist(), a_pos)
    diff = data[:, 0:3] - m[:3, 3]
    dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    dd = 1.0 - data[:, 3:6] @ m[:3, 2]
    return [
        (float(dist[k]), float(dd[k]), int(ids[k]), tuple(data[k].tolist()))
        for k in np.flatnonzero(_within(dist, dd, a_pos, a_dir)).tolist()
    ]


def _best(
    passing: list[_Passing],
    exclude: set[int],
    q: tuple[int, int, float, float, float, float],
    policy: str,
    rtol: float,
    a_pos: float,
    a_dir: float,
) -> tuple[float, int, float, float, bool] | None:
    """(score, id, distance, 1 - dot, same intrinsics) of the best allowed similar record:
    the smallest ``distance / alpha_pos + (1 - dot) / alpha_dir``, ties to the smaller id."""
    best = None
    for dist, dd, rid, row in passing:
        if rid in exclude:
            continue
        allowed, same = _intrinsics_check(row[6:12], q, policy, rtol)
        if not allowed:
            continue
        sc = dist / a_pos + dd / a_dir
        if best is None or (sc, rid) < (best[0], best[1]):
            best = (sc, rid, dist, dd, same)
    return best


class LookupMixin:
    """The in-memory octree index and the lookups (part of :class:`~icbtool.store.Store`)."""

    def _load_index(self) -> None:
        assert self._conn is not None
        self._trees.clear()
        self._geoms.clear()
        self._ids.clear()
        self._max_id = 0
        for sh, root_min, size, depth in self._conn.execute(
            "SELECT scene_hash, root_min, root_size, depth FROM scenes"
        ):
            self._geoms[sh] = OctreeGeometry(tuple(json.loads(root_min)), size, depth)
        self._data_version = self._conn.execute("PRAGMA data_version").fetchone()[0]
        self._add_rows(self._conn.execute(f"SELECT {_ROW_COLS} FROM records ORDER BY id"))
        self._count, self._bytes = self._conn.execute(
            "SELECT COUNT(*), COALESCE(SUM(nbytes), 0) FROM records"
        ).fetchone()

    def _add_rows(self, rows: Any) -> None:
        for r in rows:
            rid, sh, lh = r[0], r[13], r[14]
            tree = self._trees.get((sh, lh))
            if tree is None:
                geom = self._geoms.get(sh)
                if geom is None:  # a scene registered by another process after our load
                    row = self._conn.execute(
                        "SELECT root_min, root_size, depth FROM scenes WHERE scene_hash=?", (sh,)
                    ).fetchone()
                    geom = self._geoms[sh] = OctreeGeometry(
                        tuple(json.loads(row[0])), row[1], row[2]
                    )
                tree = self._trees[(sh, lh)] = SceneOctree(geom)
            tree.insert(rid, np.array(r[1:13], dtype=np.float64))
            self._ids.add(rid)
            self._max_id = max(self._max_id, rid)

    def refresh(self) -> None:
        """Catch up with commits of other processes (readers call this implicitly on lookup)."""
        assert self._conn is not None
        dv = self._conn.execute("PRAGMA data_version").fetchone()[0]
        if dv == self._data_version:
            return
        self._data_version = dv
        self._add_rows(
            self._conn.execute(
                f"SELECT {_ROW_COLS} FROM records WHERE id > ? ORDER BY id", (self._max_id,)
            )
        )
        self._count, self._bytes = self._conn.execute(
            "SELECT COUNT(*), COALESCE(SUM(nbytes), 0) FROM records"
        ).fetchone()
        if self._count != len(self._ids):  # some were deleted: drop them from the octree
            alive = {r[0] for r in self._conn.execute("SELECT id FROM records")}
            for rid in self._ids - alive:
                for tree in self._trees.values():
                    if tree.remove(rid):
                        break
            self._ids &= alive

    def find_exact(self, camera: Camera, scene_hash: str, light_hash: str) -> int | None:
        """The id of a record with exactly this camera (bit for bit) and hashes, or None."""
        row = (
            self._db()
            .execute(
                "SELECT id FROM records WHERE scene_hash=? AND light_hash=? AND cam_key=? "
                "ORDER BY id LIMIT 1",
                (scene_hash, light_hash, camera_key(camera)),
            )
            .fetchone()
        )
        return None if row is None else int(row[0])

    def find_exact_all(self, camera: Camera, scene_hash: str, light_hash: str) -> list[int]:
        """The ids of every record with exactly this camera (bit for bit) and hashes, ascending."""
        rows = (
            self._db()
            .execute(
                "SELECT id FROM records WHERE scene_hash=? AND light_hash=? AND cam_key=? "
                "ORDER BY id",
                (scene_hash, light_hash, camera_key(camera)),
            )
            .fetchall()
        )
        return [int(r[0]) for r in rows]

    def lookup(
        self,
        camera: Camera,
        scene_hash: str | None = None,
        light_hash: str | None = None,
        *,
        scene: Any = None,
        alpha_pos: float | None = None,
        alpha_dir: float | None = None,
        intrinsics: str | None = None,
        exclude: Any = None,
    ) -> Hit | None:
        """The most similar stored camera (module docstring), or None on a miss.

        Args:
            camera: the query camera.
            scene_hash, light_hash: the scene content and light setup (or give ``scene``).
            scene: an :class:`~icbtool.scene.Scene` supplying both hashes.
            alpha_pos, alpha_dir, intrinsics: override the config's thresholds / policy.
            exclude: record ids never to return (e.g. the query's own record).

        Returns:
            A :class:`Hit` (payload loaded lazily through ``hit.record``), or None.
        """
        if scene is not None:
            scene_hash, light_hash = scene.content_hash, scene.light_hash
        if scene_hash is None or light_hash is None:
            raise ValueError("lookup needs scene_hash and light_hash (or scene=)")
        self._follow_writer()
        cfg = self.config
        a_pos = cfg.alpha_pos if alpha_pos is None else float(alpha_pos)
        a_dir = cfg.alpha_dir if alpha_dir is None else float(alpha_dir)
        if not (a_pos > 0 and a_dir > 0):
            raise ValueError(f"lookup thresholds must be > 0, got {a_pos}, {a_dir}")
        tree = self._trees.get((scene_hash, light_hash))
        if tree is None:
            return None
        policy = intrinsics or cfg.intrinsics
        if policy not in ("same", "covering", "any"):
            raise ValueError(f"intrinsics policy must be same|covering|any, got {policy!r}")
        m = camera.world_from_cam
        leaves = tree.candidate_leaves(m[:3, 3].tolist(), a_pos)
        n_cand = sum(len(leaf.ids) for leaf in leaves)
        if n_cand == 0:
            return None
        if n_cand <= 64:  # the usual case: a few records; plain Python beats numpy's overhead
            passing = _similar_few(leaves, m, a_pos, a_dir)
        else:
            passing = _similar_many(tree, m, a_pos, a_dir)
        q = (camera.height, camera.width, camera.fx, camera.fy, camera.cx, camera.cy)
        excl = set() if exclude is None else {int(e) for e in exclude}
        best = _best(passing, excl, q, policy, cfg.intrinsics_rtol, a_pos, a_dir)
        if best is None:
            return None
        score, rid, dist, dd, same = best
        if cfg.record_hits and not self.readonly:
            n, _ = self._pending_hits.get(rid, (0, 0.0))
            self._pending_hits[rid] = (n + 1, time.time())
        cos = min(1.0, max(-1.0, 1.0 - dd))
        return Hit(rid, dist, dd, math.degrees(math.acos(cos)), score, same, n_cand, self)

    def _follow_writer(self) -> None:
        """A reader catches up with the writer's commits (at most every refresh_interval_s)."""
        if not self.readonly:
            self._db()
            return
        now = time.monotonic()
        if now - self._last_refresh >= self.config.refresh_interval_s:
            self._last_refresh = now
            if self._db().execute("PRAGMA data_version").fetchone()[0] != self._data_version:
                self.refresh()

    def add_hits(self, hits: Mapping[int, tuple[int, float]]) -> None:
        """Count lookups made elsewhere as hits: a read-only connection to this store (which
        cannot write them) hands its counts to the writer, in batches.

        Args:
            hits: ``{record id: (hits, time.time() of the last)}``; ids no longer stored are
                skipped. They go to the database with this connection's own counts (every few
                seconds, before an eviction, which then sees them, and at close).

        Raises:
            ReadOnlyStoreError: this connection is read-only.
        """
        self._writable()
        if not self.config.record_hits:
            return
        for rid, (n, t) in hits.items():
            if rid not in self._ids:
                continue
            m, last = self._pending_hits.get(rid, (0, 0.0))
            self._pending_hits[rid] = (m + int(n), max(last, float(t)))
        if time.monotonic() - self._last_flush > 5.0:
            self._flush_hits()

    def _flush_hits(self) -> None:
        self._last_flush = time.monotonic()
        if not self._pending_hits or self.readonly or self._conn is None:
            return
        items = [(n, t, t, rid) for rid, (n, t) in self._pending_hits.items()]
        self._conn.execute("BEGIN IMMEDIATE")
        self._conn.executemany(
            "UPDATE records SET hits = hits + ?, last_hit = MAX(last_hit, ?, ?) WHERE id=?", items
        )
        self._conn.execute("COMMIT")
        self._pending_hits.clear()
