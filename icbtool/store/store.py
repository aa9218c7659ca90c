"""The persistent octree CRT-buffer manager (docs/design.md section 3).

The :class:`Store` is split by concern: opening and the schema (:mod:`icbtool.store.schema`),
the writer lock (:mod:`icbtool.store.locking`), the scenes' octrees (:mod:`icbtool.store.scenes`),
lookups (:mod:`icbtool.store.lookup`), checks and rebuilds (:mod:`icbtool.store.repair`),
eviction (:mod:`icbtool.store.eviction`); this module keeps the records (put, get, delete) and
the public API.

On disk, a store is a directory::

    DIR/icbstore.sqlite     index + metadata (SQLite, WAL mode, synchronous=FULL)
    DIR/payloads/ab/<uuid>.icbp   one compressed payload per record (see icbtool.store.record)
    DIR/payloads/tmp/       payloads being written
    DIR/.writer.lock        flock held by the one writer process

Durability: :meth:`Store.put` writes the payload to ``payloads/tmp``, fsyncs it, renames it into
place, fsyncs the directory, and only then inserts and commits the DB row. A crash (even SIGKILL)
can therefore leave an *orphan payload* (a file no row references), never a row without its payload.
Orphans are removed when a writer opens the store and by ``check(repair=True)``. Deletion (eviction)
goes the other way round: rows first (committed), then files.

Damage and recovery (format 2): every payload is self-describing (record id, metadata, camera,
scene octree geometry in its header) and carries its own BLAKE2b digest (see
:mod:`icbtool.store.record`), so the index is a cache of the payloads:

* a damaged index database (truncated, overwritten, deleted) makes :func:`open` raise
  :class:`StoreIndexError`, which says to run ``icbtool store check DIR --rebuild``;
  :func:`rebuild` builds a new index from the payloads in a temporary file and swaps it in with
  ``os.replace``. The old database is kept aside as ``icbstore.sqlite.damaged-<time>`` and damaged
  payloads are moved to ``DIR/quarantine/<time>/``: nothing is deleted, no intact record is lost
  (hit counts are taken from the old database where it can still be read);
* a damaged record (payload missing, truncated or failing its checksum) met by a reader is a miss:
  :meth:`Store.get_intact` logs a WARNING naming the record and returns None, and the caller
  re-renders and calls :meth:`Store.replace_damaged`; :meth:`Store.evict` removes damaged records
  before any intact one. Nothing deletes a record whose payload verifies.

A format-1 store (payloads without metadata) is migrated when a writer opens it: each intact
payload is rewritten in format 2 (new file, then one committed transaction, then the old files go).

Concurrency: one writer (an exclusive ``flock`` on ``.writer.lock``; a second writer waits up to
``lock_timeout_s`` then gets :class:`StoreLockedError`) and any number of readers
(``StoreConfig(readonly=True)``). A reader's in-memory octree follows the writer's commits: every
lookup checks SQLite's ``PRAGMA data_version`` and loads new rows (or reloads after deletions).

Lookup (pre-rendering by lookup, docs/design.md section 3): a stored camera is *similar* when
``|p1 - p2| < alpha_pos`` and ``1 - dot(d1, d2) < alpha_dir`` (d = unit viewing directions),
both for the same scene content hash and light-setup hash, and its intrinsics pass the
``intrinsics`` policy:

* ``"same"``: same resolution and fx, fy, cx, cy within ``intrinsics_rtol`` (direct reuse);
* ``"covering"``: the stored frustum contains the query's at equal orientation (tan of every
  half-angle at least as large: a wider prefetch camera; usable after warping);
* ``"any"``: no intrinsics test (the caller warps whatever comes back).

Among similar cameras the best is the one with the smallest combined score
``distance / alpha_pos + (1 - dot) / alpha_dir`` (each term in [0, 1) inside the thresholds; ties
go to the smaller record id).
"""

from __future__ import annotations

import builtins
import contextlib
import json
import logging
import os
import sqlite3
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.camera import Camera
from icbtool.store.base import (  # noqa: F401
    DB_NAME,
    FORMAT_VERSION,
    LOCK_NAME,
    PAYLOAD_DIR,
    PAYLOAD_SUFFIX,
    QUARANTINE_DIR,
    STORE_KIND,
    CheckReport,
    Damage,
    PayloadError,
    ReadOnlyStoreError,
    RebuildReport,
    RecordInfo,
    RecordNotFoundError,
    StoreConfig,
    StoreError,
    StoreFormatError,
    StoreIndexError,
    StoreLockedError,
)
from icbtool.store.eviction import EvictionMixin
from icbtool.store.locking import (  # noqa: F401
    _acquire_lock,
    _release_lock,
)
from icbtool.store.lookup import (  # noqa: F401
    Hit,
    LookupMixin,
    _intrinsics_check,
)
from icbtool.store.octree import OctreeGeometry, SceneOctree
from icbtool.store.record import (
    CRTBuffer,
    RecordMeta,
    decode_payload,
    encode_payload,
)
from icbtool.store.repair import (  # noqa: F401
    RepairMixin,
    _index_matches,
    _salvage_old_index,
    _unused_name,
    rebuild,
)
from icbtool.store.scenes import ScenesMixin
from icbtool.store.schema import (  # noqa: F401
    _INFO_COLS,
    _INSERT_COLS,
    _INSERT_SQL,
    _ROW_COLS,
    _SCHEMA,
    SchemaMixin,
    _camera_row,
    _checksum,
    _create_schema,
    _fsync_dir,
    _has_payloads,
    _payload_problem,
    _record_values,
    camera_key,
)

#: One logger for the store, whichever of its modules logs (names kept as before the split).
log = logging.getLogger("icbtool.store.store")


class Store(SchemaMixin, ScenesMixin, LookupMixin, RepairMixin, EvictionMixin):
    """An open CRT-buffer store. Create with :func:`open` (a context manager)."""

    def __init__(self, root: str | os.PathLike, config: StoreConfig | None = None) -> None:
        self.root = Path(root)
        self.config = config or StoreConfig()
        self.readonly = self.config.readonly
        self._db_path = self.root / DB_NAME
        self._payload_root = self.root / PAYLOAD_DIR
        self._lock_fd: int | None = None
        self._conn: sqlite3.Connection | None = None
        self._trees: dict[tuple[str, str], SceneOctree] = {}
        self._geoms: dict[str, OctreeGeometry] = {}
        self._ids: set[int] = set()
        self._max_id = 0
        self._count = 0
        self._bytes = 0
        self._data_version = -1
        self._pending_hits: dict[int, tuple[int, float]] = {}
        self._last_flush = time.monotonic()
        self._last_refresh = 0.0
        self._focus: np.ndarray | None = None
        self._damaged: set[int] = set()
        self.orphans_removed_on_open = 0
        self.migrated_from: int | None = None
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    # -------------------------------------------------------------- closing
    def close(self) -> None:
        """Flush hit counts and release the database and the writer lock (idempotent)."""
        if self._conn is not None:
            with contextlib.suppress(sqlite3.Error):
                self._flush_hits()
            self._conn.close()
            self._conn = None
        if self._lock_fd is not None:
            _release_lock(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreError(f"store {self.root} is closed")
        return self._conn

    def _writable(self) -> sqlite3.Connection:
        if self.readonly:
            raise ReadOnlyStoreError(f"store {self.root} was opened read-only")
        return self._db()

    @classmethod
    def rebuild(cls, root: str | os.PathLike, config: StoreConfig | None = None) -> RebuildReport:
        """Rebuild a store's index database from its payloads (see :func:`rebuild`)."""
        return rebuild(root, config)

    # -------------------------------------------------------------- records
    def put(self, buf: CRTBuffer) -> int:
        """Store a CRT-buffer durably; returns its record id.

        The payload is durable on disk before the row is committed; when ``put`` returns, the
        record survives a crash. May evict other records (capacity, see :class:`StoreConfig`).

        Raises:
            ReadOnlyStoreError: if opened read-only.
            ValueError: if ``buf`` is not a CRTBuffer or eviction 'farthest' has no focus.
        """
        return self.put_many([buf])[0]

    def put_many(self, bufs: list[CRTBuffer]) -> list[int]:
        """Store several CRT-buffers in one transaction (bulk import); returns their ids.

        All payloads are made durable first, then every row is committed at once: after a crash
        either all of them are in the store or none (orphan payloads are cleaned on open).
        """
        conn = self._writable()
        bufs = list(bufs)
        for b in bufs:
            if not isinstance(b, CRTBuffer):
                raise ValueError(f"put() needs a CRTBuffer, got {type(b).__name__}")
        if not bufs:
            return []
        cfg = self.config
        capped = cfg.max_records is not None or cfg.max_bytes is not None
        if capped and cfg.eviction == "farthest" and self._focus is None:
            raise ValueError("eviction='farthest' needs a focus: call store.set_focus(position)")
        for b in bufs:
            if b.meta.scene_hash not in self._geoms:
                self.register_scene(
                    scene_hash=b.meta.scene_hash,
                    bounds=self._bounds_for(b),
                    name=b.meta.scene_name,
                )
        # ids are assigned here (the writer lock makes this process the only one inserting) so
        # that each payload can name its own record: the index can be rebuilt from them.
        first_id = self._next_id()
        scenes = {sh: self._scene_entry(sh) for sh in {b.meta.scene_hash for b in bufs}}
        staged = []
        dirs: set[Path] = set()
        for k, buf in enumerate(bufs):
            record = {"id": first_id + k, "scene": scenes[buf.meta.scene_hash]}
            rel, nbytes, digest, new_dirs = self._write_payload(buf, record)
            dirs |= new_dirs
            staged.append((buf, rel, nbytes, digest))
        if cfg.fsync:
            for d in sorted(dirs, key=lambda p: len(p.parts)):
                _fsync_dir(d)
        rows = []
        for k, (buf, rel, nbytes, digest) in enumerate(staged):
            meta, cam = buf.meta, buf.camera
            values = _record_values(
                meta, cam, buf.present, rel, nbytes, digest, self._geoms[meta.scene_hash]
            )
            rows.append((first_id + k, *values, 0, float(meta.created)))
        ids = []
        conn.execute("BEGIN IMMEDIATE")
        try:
            for r in rows:
                conn.execute(_INSERT_SQL, r)
                ids.append(r[0])
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        for rid, (buf, _rel, nbytes, _d) in zip(ids, staged):
            meta = buf.meta
            key = (meta.scene_hash, meta.light_hash)
            tree = self._trees.get(key)
            if tree is None:
                tree = self._trees[key] = SceneOctree(self._geoms[meta.scene_hash])
            tree.insert(rid, _camera_row(buf.camera))
            self._ids.add(rid)
            self._max_id = max(self._max_id, rid)
            self._count += 1
            self._bytes += nbytes
        if self._over_capacity():
            self.evict(protect=tuple(ids))
        elif time.monotonic() - self._last_flush > 5.0:
            self._flush_hits()
        return ids

    def _next_id(self) -> int:
        """The id the next inserted record gets (ids are never reused, as AUTOINCREMENT)."""
        conn = self._db()
        (seq,) = conn.execute(
            "SELECT COALESCE(MAX(seq), 0) FROM sqlite_sequence WHERE name='records'"
        ).fetchone()
        (top,) = conn.execute("SELECT COALESCE(MAX(id), 0) FROM records").fetchone()
        return max(int(seq), int(top), self._max_id) + 1

    def _write_payload(
        self, buf: CRTBuffer, record: dict[str, Any]
    ) -> tuple[str, int, str, set[Path]]:
        """Write a payload durably under a new name; (relative path, size, checksum, new dirs)."""
        cfg = self.config
        tmp_dir = self._payload_root / "tmp"
        tmp_dir.mkdir(parents=True, exist_ok=True)
        dirs: set[Path] = set()
        data = encode_payload(buf, cfg.compression_level, record)
        name = uuid.uuid4().hex
        rel = f"{name[:2]}/{name}{PAYLOAD_SUFFIX}"
        final = self._payload_root / rel
        tmp = tmp_dir / f"{name}.tmp"
        with builtins.open(tmp, "wb") as f:
            f.write(data)
            if cfg.fsync:
                f.flush()
                os.fsync(f.fileno())
        if not final.parent.exists():
            final.parent.mkdir(parents=True, exist_ok=True)
            dirs.add(self._payload_root)
        os.replace(tmp, final)
        dirs.add(final.parent)
        return rel, len(data), _checksum(data), dirs

    def delete(self, ids: Any) -> int:
        """Delete records by id (rows first, then payload files). Returns how many were deleted."""
        conn = self._writable()
        ids = [int(i) for i in ids]
        if not ids:
            return 0
        rows = []
        for k in range(0, len(ids), 500):
            chunk = ids[k : k + 500]
            q = ",".join("?" * len(chunk))
            rows += conn.execute(
                f"SELECT id, payload, nbytes FROM records WHERE id IN ({q})", chunk
            ).fetchall()
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.executemany("DELETE FROM records WHERE id=?", [(r[0],) for r in rows])
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        self._data_version = conn.execute("PRAGMA data_version").fetchone()[0]
        for rid, rel, nbytes in rows:
            with contextlib.suppress(FileNotFoundError):
                (self._payload_root / rel).unlink()
            for tree in self._trees.values():
                if tree.remove(rid):
                    break
            self._ids.discard(rid)
            self._damaged.discard(rid)
            self._pending_hits.pop(rid, None)
            self._count -= 1
            self._bytes -= nbytes
        return len(rows)

    def _row(self, record_id: int) -> tuple:
        row = (
            self._db()
            .execute(
                f"SELECT {_INFO_COLS} FROM records WHERE id=?",
                (int(record_id),),
            )
            .fetchone()
        )
        if row is None:
            raise RecordNotFoundError(f"store {self.root} has no record {record_id}")
        return row

    def _info_from_row(self, r: tuple) -> RecordInfo:
        (
            rid,
            sname,
            sh,
            lh,
            h,
            w,
            fx,
            fy,
            cx,
            cy,
            pose,
            bufs,
            rel,
            nbytes,
            digest,
            spp,
            rt,
            created,
            tags,
            sb,
            hits,
            last_hit,
        ) = r
        cam = Camera(h, w, fx, fy, cx, cy, np.frombuffer(pose, np.float64).reshape(4, 4))
        meta = RecordMeta(
            sname,
            sh,
            lh,
            spp,
            rt,
            created,
            json.loads(tags),
            None if sb is None else json.loads(sb),
        )
        pend = self._pending_hits.get(rid)
        if pend is not None:
            hits, last_hit = hits + pend[0], max(last_hit, pend[1])
        return RecordInfo(
            rid,
            meta,
            cam,
            tuple(b for b in bufs.split(",") if b),
            nbytes,
            self._payload_root / rel,
            digest,
            hits,
            last_hit,
        )

    def info(self, record_id: int) -> RecordInfo:
        """A record's index entry (no payload read)."""
        return self._info_from_row(self._row(record_id))

    def get(self, record_id: int) -> CRTBuffer:
        """Load a record, verifying its payload checksum.

        Raises:
            RecordNotFoundError: no such id.
            PayloadError: the payload file is missing, truncated or damaged (names record, file).
        """
        info = self.info(record_id)
        path = info.payload
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            self._damaged.add(record_id)
            raise PayloadError(
                f"record {record_id}: payload file {path} is missing (run `icbtool store check`)"
            ) from None
        if len(data) != info.nbytes or _checksum(data) != info.checksum:
            self._damaged.add(record_id)
            raise PayloadError(
                f"record {record_id}: payload file {path} is damaged ("
                + (
                    f"size {len(data)} != {info.nbytes}"
                    if len(data) != info.nbytes
                    else "checksum mismatch"
                )
                + "; run `icbtool store check`)"
            )
        try:
            maps = decode_payload(data, f"record {record_id} ({path})", verify=False)
        except ValueError as e:
            self._damaged.add(record_id)
            raise PayloadError(f"record {record_id}: payload file {path} is damaged ({e})") from e
        return CRTBuffer(camera=info.camera, meta=info.meta, **maps)

    def __len__(self) -> int:
        if self.readonly and self._conn is not None:
            self.refresh()
        return self._count

    def __contains__(self, record_id: object) -> bool:
        return record_id in self._ids

    def __iter__(self) -> Iterator[RecordInfo]:
        """Every record's :class:`RecordInfo`, in id order."""
        rows = self._db().execute(f"SELECT {_INFO_COLS} FROM records ORDER BY id").fetchall()
        for r in rows:
            yield self._info_from_row(r)

    def ids(self) -> list[int]:
        """All record ids, ascending."""
        return sorted(self._ids)

    @property
    def total_bytes(self) -> int:
        """Sum of the payload file sizes."""
        return int(self._bytes)

    def stats(self) -> dict[str, Any]:
        """Records, bytes, per scene / light setup, octree occupancy."""
        conn = self._db()
        if self.readonly:
            self.refresh()
        groups = []
        for sname, sh, lh, n, b, hits in conn.execute(
            "SELECT scene_name, scene_hash, light_hash, COUNT(*), SUM(nbytes), SUM(hits) "
            "FROM records GROUP BY scene_hash, light_hash ORDER BY scene_name"
        ):
            tree = self._trees.get((sh, lh))
            groups.append(
                {
                    "scene_name": sname,
                    "scene_hash": sh,
                    "light_hash": lh,
                    "records": n,
                    "bytes": b,
                    "hits": hits,
                    "octree": tree.occupancy() if tree is not None else None,
                }
            )
        return {
            "path": str(self.root),
            "format_version": FORMAT_VERSION,
            "records": self._count,
            "bytes": self._bytes,
            "bytes_per_record": self._bytes / self._count if self._count else 0.0,
            "capacity": {
                "max_records": self.config.max_records,
                "max_bytes": self.config.max_bytes,
                "eviction": self.config.eviction,
            },
            "groups": groups,
        }


def open(root: str | os.PathLike, config: StoreConfig | None = None) -> Store:  # noqa: A001
    """Open (or create) the store in directory ``root``; use as a context manager.

    Raises:
        StoreFormatError: ``root`` is not a store (and not empty), or its database is of an
            unknown format version. Nothing is overwritten.
        StoreIndexError: its index database is damaged or missing while payloads are there
            (the message says to run ``icbtool store check DIR --rebuild``, see :func:`rebuild`).
        StoreLockedError: another process has it open for writing (after ``lock_timeout_s``).
        FileNotFoundError: no store there and ``readonly`` or ``create=False``.
    """
    return Store(root, config)
