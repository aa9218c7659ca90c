"""Keeping a store within its capacity: which records go first (least recently hit, least hit,
farthest from the focus; damaged ones before any intact one). :class:`EvictionMixin` is that
part of :class:`icbtool.store.Store`."""

from __future__ import annotations

from typing import Any

import numpy as np


class EvictionMixin:
    """Capacity and eviction (part of :class:`~icbtool.store.Store`)."""

    def _over_capacity(self) -> bool:
        c = self.config
        return (c.max_records is not None and self._count > c.max_records) or (
            c.max_bytes is not None and self._bytes > c.max_bytes
        )

    def set_focus(self, position: Any) -> None:
        """The current camera/path position, for ``eviction='farthest'`` ((3,) or None)."""
        self._focus = None if position is None else np.asarray(position, np.float64).reshape(3)

    def evict(
        self,
        max_records: int | None = None,
        max_bytes: int | None = None,
        policy: str | None = None,
        protect: tuple[int, ...] = (),
        deep: bool = False,
    ) -> list[int]:
        """Evict records until within capacity; returns the evicted ids.

        Damaged records go first (:meth:`evict_damaged`, whatever the capacity), then intact ones
        by ``policy`` until within the targets.

        Args:
            max_records, max_bytes: targets (default: the config's capacity times ``evict_to``).
            policy: 'lru' | 'least_hit' | 'farthest' (default: the config's).
            protect: ids never evicted by this call.
            deep: find damaged records by checksum (reads every payload) rather than by file
                existence and size (a stat per record, what an automatic eviction does).
        """
        conn = self._writable()
        damaged = self.evict_damaged(deep=deep, protect=protect)
        cfg = self.config
        if max_records is None and max_bytes is None:
            if cfg.max_records is not None:
                max_records = int(cfg.max_records * cfg.evict_to)
            if cfg.max_bytes is not None:
                max_bytes = int(cfg.max_bytes * cfg.evict_to)
        policy = policy or cfg.eviction
        if policy not in ("lru", "least_hit", "farthest"):
            raise ValueError(f"unknown eviction policy {policy!r} (lru, least_hit, farthest)")
        if policy == "farthest" and self._focus is None:
            raise ValueError("eviction 'farthest' needs store.set_focus(position)")
        n_excess = 0 if max_records is None else max(0, self._count - max_records)
        b_excess = 0 if max_bytes is None else max(0, self._bytes - max_bytes)
        if n_excess == 0 and b_excess == 0:
            return damaged
        self._flush_hits()
        rows = conn.execute("SELECT id, last_hit, hits, px, py, pz, nbytes FROM records").fetchall()
        a = np.array([r[:6] for r in rows], dtype=np.float64).reshape(-1, 6)
        nbytes = np.array([r[6] for r in rows], dtype=np.int64)
        if policy == "lru":
            order = np.lexsort((a[:, 0], a[:, 1]))  # oldest last hit first, then lower id
        elif policy == "least_hit":
            order = np.lexsort((a[:, 0], a[:, 1], a[:, 2]))  # fewest hits, then oldest
        else:
            dist = np.linalg.norm(a[:, 3:6] - self._focus, axis=1)
            order = np.lexsort((a[:, 0], -dist))
        protected = set(protect)
        victims: list[int] = []
        freed_n, freed_b = 0, 0
        for k in order:
            if freed_n >= n_excess and freed_b >= b_excess:
                break
            rid = int(a[k, 0])
            if rid in protected:
                continue
            victims.append(rid)
            freed_n += 1
            freed_b += int(nbytes[k])
        self.delete(victims)
        return damaged + victims
