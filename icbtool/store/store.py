"""The persistent octree CRT-buffer manager (docs/design.md section 3).

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
import fcntl
import hashlib
import json
import logging
import math
import os
import sqlite3
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np

from icbtool.camera import Camera
from icbtool.store.octree import OctreeGeometry, SceneOctree, morton
from icbtool.store.record import (
    CRTBuffer,
    RecordMeta,
    decode_payload,
    encode_payload,
    payload_header,
    record_from_header,
)

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
STORE_KIND = "icbtool-crt-store"
DB_NAME = "icbstore.sqlite"
LOCK_NAME = ".writer.lock"
PAYLOAD_DIR = "payloads"
PAYLOAD_SUFFIX = ".icbp"
QUARANTINE_DIR = "quarantine"


# ------------------------------------------------------------------------------------ errors
class StoreError(Exception):
    """Base class of the store's errors."""


class StoreFormatError(StoreError, ValueError):
    """The directory or database is not an icbtool store, is damaged, or has an unknown version."""


class StoreIndexError(StoreFormatError):
    """The store's index database is missing or damaged; :func:`rebuild` recovers it."""


class StoreLockedError(StoreError, RuntimeError):
    """Another process holds the store open for writing."""


class ReadOnlyStoreError(StoreError, PermissionError):
    """A write was attempted on a store opened with ``readonly=True``."""


class RecordNotFoundError(StoreError, KeyError):
    """No record with that id."""

    def __str__(self) -> str:  # KeyError's str() would quote the message
        return str(self.args[0]) if self.args else "record not found"


class PayloadError(StoreError, ValueError):
    """A record's payload file is missing, truncated or fails its checksum."""


# ------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class StoreConfig:
    """How a store matches, sizes and persists records."""

    alpha_pos: float = 0.1
    """Position threshold: a stored camera is similar if ``|p1 - p2| < alpha_pos`` (scene units)."""
    alpha_dir: float = 0.1
    """Direction threshold on ``1 - dot(d1, d2)`` (0.1 = 25.8 deg, 0.01 = 8.1 deg, 0.001 = 2.6)."""
    intrinsics: Literal["same", "covering", "any"] = "same"
    """Intrinsics policy for a match (module docstring): reuse as is, wider reference, or any."""
    intrinsics_rtol: float = 1e-4
    """Relative tolerance on fx, fy, cx, cy for "same" (and on the half-angles for "covering")."""
    leaf_size: float | None = None
    """Largest leaf edge of a new scene's octree (default: 2 * alpha_pos, so a lookup ball touches
    at most 2 leaves per axis); fixed once the scene exists."""
    max_depth: int = 12
    """Deepest octree level (2^12 leaves per axis)."""
    max_records: int | None = None
    """Capacity in records (None: unbounded)."""
    max_bytes: int | None = None
    """Capacity in payload bytes (None: unbounded)."""
    eviction: Literal["lru", "least_hit", "farthest"] = "lru"
    """Which records go first when over capacity: least recently hit (creation counts as a hit),
    fewest hits (then oldest), or farthest from :meth:`Store.set_focus` (the current path)."""
    evict_to: float = 0.9
    """On overflow, evict down to this fraction of the capacity (hysteresis: not a scan per put)."""
    compression_level: int = 1
    """zlib level of the payloads (1 fast .. 9 small); lossless whatever the level."""
    readonly: bool = False
    """Open as a reader: no writes, no lock, follows the writer's commits."""
    create: bool = True
    """Create the store if the directory does not exist or is empty."""
    record_hits: bool = True
    """Count lookup hits (for LRU / least-hit eviction); flushed to the DB every few seconds."""
    refresh_interval_s: float = 0.05
    """Readers: how often (at most) a lookup checks for the writer's new commits."""
    lock_timeout_s: float = 10.0
    """How long a writer waits for another writer to close the store."""
    fsync: bool = True
    """fsync payloads and directories before committing (durability across power loss)."""

    def __post_init__(self) -> None:
        for k in ("alpha_pos", "alpha_dir"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"StoreConfig.{k} must be finite and > 0, got {v!r}")
        if self.alpha_dir > 2:
            raise ValueError(
                f"StoreConfig.alpha_dir is 1 - cos(angle), at most 2; got {self.alpha_dir}"
            )
        if self.intrinsics not in ("same", "covering", "any"):
            raise ValueError(
                f"StoreConfig.intrinsics must be same|covering|any, got {self.intrinsics!r}"
            )
        if self.eviction not in ("lru", "least_hit", "farthest"):
            raise ValueError(
                f"StoreConfig.eviction must be lru|least_hit|farthest, got {self.eviction!r}"
            )
        if not (0 <= self.intrinsics_rtol < 1):
            raise ValueError(
                f"StoreConfig.intrinsics_rtol must be in [0, 1), got {self.intrinsics_rtol}"
            )
        if self.leaf_size is not None and not (
            self.leaf_size > 0 and math.isfinite(self.leaf_size)
        ):
            raise ValueError(f"StoreConfig.leaf_size must be > 0, got {self.leaf_size}")
        if not (0 <= self.max_depth <= 21):
            raise ValueError(f"StoreConfig.max_depth must be in [0, 21], got {self.max_depth}")
        for k in ("max_records", "max_bytes"):
            v = getattr(self, k)
            if v is not None and (int(v) != v or v < 1):
                raise ValueError(f"StoreConfig.{k} must be None or an integer >= 1, got {v!r}")
        if not (0 < self.evict_to <= 1):
            raise ValueError(f"StoreConfig.evict_to must be in (0, 1], got {self.evict_to}")
        if not (0 <= self.compression_level <= 9):
            raise ValueError(
                f"StoreConfig.compression_level must be 0..9, got {self.compression_level}"
            )
        if not (self.refresh_interval_s >= 0):
            raise ValueError(
                f"StoreConfig.refresh_interval_s must be >= 0, got {self.refresh_interval_s}"
            )
        if self.lock_timeout_s < 0:
            raise ValueError(f"StoreConfig.lock_timeout_s must be >= 0, got {self.lock_timeout_s}")


# ------------------------------------------------------------------------------------ results
@dataclass(frozen=True)
class RecordInfo:
    """A record's index entry (no payload).

    Attributes:
        record_id: the id :meth:`Store.put` returned.
        meta: provenance.
        camera: the record's camera.
        buffers: names of the stored maps.
        nbytes: payload file size.
        payload: payload file path.
        checksum: BLAKE2b-256 hex digest of the payload file.
        hits: lookup hits so far (flushed ones, plus this process's).
        last_hit: time of the last hit (creation time if never hit).
    """

    record_id: int
    meta: RecordMeta
    camera: Camera
    buffers: tuple[str, ...]
    nbytes: int
    payload: Path
    checksum: str
    hits: int
    last_hit: float


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
    _store: Store = field(repr=False)

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


@dataclass(frozen=True)
class Damage:
    """One problem found by :meth:`Store.check`."""

    record_id: int | None
    path: str
    problem: str


@dataclass(frozen=True)
class CheckReport:
    """What :meth:`Store.check` found (and did, with ``repair``)."""

    records_checked: int
    damaged: list[Damage]
    orphans: list[str]
    removed_orphans: int
    dropped_records: list[int]
    db_integrity: str

    @property
    def ok(self) -> bool:
        """True when no record is damaged and the database is intact (orphans are harmless)."""
        return not self.damaged and self.db_integrity == "ok"


@dataclass(frozen=True)
class RebuildReport:
    """What :func:`rebuild` did.

    Attributes:
        path: the store directory.
        recovered: ids of the records in the new index (their payloads verified), ascending.
        damaged: payloads that failed verification (moved to ``quarantined``) and records the old
            index listed whose payload file is missing; ``record_id`` is None when neither the
            payload nor the old index could say which record it was.
        quarantined: where the damaged payload files were moved (nothing is deleted).
        orphans: files under ``payloads/`` that are not payloads (half-written ``tmp/`` files,
            other names); left in place (a writer's open removes them, as always).
        old_index: where the previous database was kept, or None if there was none.
        hits_restored: records whose hit counts could be read from the old database.
        renumbered: {old id: new id} for payloads that claimed an id already taken.
    """

    path: str
    recovered: list[int]
    damaged: list[Damage]
    quarantined: list[str]
    orphans: list[str]
    old_index: str | None
    hits_restored: int
    renumbered: dict[int, int]

    @property
    def ok(self) -> bool:
        """True when every payload was recovered."""
        return not self.damaged


# ------------------------------------------------------------------------------------ helpers
_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE scenes (
    scene_hash TEXT PRIMARY KEY, scene_name TEXT NOT NULL, bounds TEXT NOT NULL,
    root_min TEXT NOT NULL, root_size REAL NOT NULL, depth INTEGER NOT NULL);
CREATE TABLE records (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    scene_name TEXT NOT NULL, scene_hash TEXT NOT NULL, light_hash TEXT NOT NULL,
    cam_key TEXT NOT NULL,
    px REAL NOT NULL, py REAL NOT NULL, pz REAL NOT NULL,
    dx REAL NOT NULL, dy REAL NOT NULL, dz REAL NOT NULL,
    height INTEGER NOT NULL, width INTEGER NOT NULL,
    fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
    pose BLOB NOT NULL, leaf INTEGER NOT NULL,
    buffers TEXT NOT NULL, payload TEXT NOT NULL UNIQUE, nbytes INTEGER NOT NULL,
    checksum TEXT NOT NULL,
    spp INTEGER NOT NULL, render_time_s REAL NOT NULL, created REAL NOT NULL,
    tags TEXT NOT NULL, scene_bounds TEXT,
    hits INTEGER NOT NULL DEFAULT 0, last_hit REAL NOT NULL);
CREATE INDEX records_group ON records (scene_hash, light_hash);
CREATE INDEX records_cam ON records (scene_hash, light_hash, cam_key);
"""

_INFO_COLS = (
    "id, scene_name, scene_hash, light_hash, height, width, fx, fy, cx, cy, pose, buffers, "
    "payload, nbytes, checksum, spp, render_time_s, created, tags, scene_bounds, hits, last_hit"
)
_INSERT_COLS = (
    "scene_name, scene_hash, light_hash, cam_key, px, py, pz, dx, dy, dz, height, width, fx, fy, "
    "cx, cy, pose, leaf, buffers, payload, nbytes, checksum, spp, render_time_s, created, tags, "
    "scene_bounds, hits, last_hit"
)
_ROW_COLS = "id, px, py, pz, dx, dy, dz, height, width, fx, fy, cx, cy, scene_hash, light_hash"


def _create_schema(conn: sqlite3.Connection) -> None:
    """Create the tables and the meta rows of an empty store database (one transaction)."""
    conn.execute("BEGIN")
    for stmt in _SCHEMA.strip().split(";"):
        if stmt.strip():
            conn.execute(stmt)
    conn.executemany(
        "INSERT INTO meta VALUES (?, ?)",
        [
            ("kind", STORE_KIND),
            ("format_version", str(FORMAT_VERSION)),
            ("created", str(time.time())),
        ],
    )
    conn.execute("COMMIT")


def _acquire_lock(root: Path, timeout_s: float) -> int:
    """Take the store's writer lock (an exclusive flock); returns the open file descriptor."""
    fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                try:
                    holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
                except OSError:
                    holder = "?"
                os.close(fd)
                raise StoreLockedError(
                    f"store {root} is open for writing by another process (pid {holder}); "
                    f"waited {timeout_s} s. Open it with StoreConfig(readonly=True) to read."
                ) from None
            time.sleep(0.05)
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


def _release_lock(fd: int) -> None:
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)


def _record_values(
    meta: RecordMeta,
    cam: Camera,
    present: tuple[str, ...],
    rel: str,
    nbytes: int,
    digest: str,
    geom: OctreeGeometry,
) -> tuple:
    """The values of a records row, in ``_INSERT_COLS`` order without the trailing hits and
    last_hit."""
    row = _camera_row(cam)
    leaf = SceneOctree(geom).cell_of(row[:3])
    return (
        meta.scene_name,
        meta.scene_hash,
        meta.light_hash,
        camera_key(cam),
        *map(float, row[:6]),
        cam.height,
        cam.width,
        cam.fx,
        cam.fy,
        cam.cx,
        cam.cy,
        np.ascontiguousarray(cam.world_from_cam, np.float64).tobytes(),
        morton(*leaf),
        ",".join(present),
        rel,
        nbytes,
        digest,
        meta.spp,
        float(meta.render_time_s),
        float(meta.created),
        json.dumps(meta.tags),
        None if meta.scene_bounds is None else json.dumps(meta.scene_bounds),
    )


_INSERT_SQL = f"INSERT INTO records (id, {_INSERT_COLS}) VALUES ({', '.join(['?'] * 30)})"


def _payload_problem(path: Path, nbytes: int, digest: str, deep: bool = True) -> str | None:
    """What is wrong with a record's payload file, or None if it is intact.

    ``deep``: read it and compare the checksum (else only its existence and size)."""
    if not deep:
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            return "payload file missing"
        return None if size == nbytes else f"size {size} != recorded {nbytes}"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return "payload file missing"
    if len(data) != nbytes:
        return f"size {len(data)} != recorded {nbytes}"
    if _checksum(data) != digest:
        return "checksum mismatch"
    return None


def camera_key(cam: Camera) -> str:
    """A hex digest identifying a camera exactly (size, intrinsics and pose, bit for bit)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.array([cam.height, cam.width], np.int64).tobytes())
    h.update(np.array([cam.fx, cam.fy, cam.cx, cam.cy], np.float64).tobytes())
    h.update(np.ascontiguousarray(cam.world_from_cam, np.float64).tobytes())
    return h.hexdigest()


def _checksum(data: bytes) -> str:
    return hashlib.blake2b(data, digest_size=32).hexdigest()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _camera_row(cam: Camera) -> np.ndarray:
    m = cam.world_from_cam
    return np.array(
        [
            m[0, 3],
            m[1, 3],
            m[2, 3],
            m[0, 2],
            m[1, 2],
            m[2, 2],
            cam.height,
            cam.width,
            cam.fx,
            cam.fy,
            cam.cx,
            cam.cy,
        ],
        dtype=np.float64,
    )


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


# ------------------------------------------------------------------------------------ the store
class Store:
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

    # -------------------------------------------------------------- opening
    def _open(self) -> None:
        root, cfg = self.root, self.config
        if root.exists() and not root.is_dir():
            raise StoreFormatError(f"store path {root} exists and is not a directory")
        db_exists = self._db_path.exists() and self._db_path.stat().st_size > 0
        if not db_exists:
            if root.exists():
                if _has_payloads(self._payload_root):
                    what = "is empty" if self._db_path.exists() else "is missing"
                    raise StoreIndexError(
                        f"store {root}: its index database {DB_NAME} {what} but payloads/ holds "
                        f"records; rebuild the index from them with "
                        f"`icbtool store check {root} --rebuild` (icbtool.store.rebuild)"
                    )
                leftovers = {
                    p.name
                    for p in root.iterdir()
                    if not p.name.startswith(DB_NAME) and p.name not in (LOCK_NAME, QUARANTINE_DIR)
                } - {PAYLOAD_DIR}
                if leftovers:
                    raise StoreFormatError(
                        f"{root} is not an icbtool store (no {DB_NAME}) and is not empty "
                        f"(found {sorted(leftovers)[:5]}); refusing to create a store there"
                    )
            if self.readonly or not cfg.create:
                raise FileNotFoundError(f"no icbtool store at {root} (missing {DB_NAME})")
            root.mkdir(parents=True, exist_ok=True)
        if not self.readonly:
            self._acquire_lock()
            db_exists = self._db_path.exists() and self._db_path.stat().st_size > 0
        if self.readonly:
            uri = f"file:{self._db_path}?mode=ro"
            self._conn = sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None)
        else:
            self._conn = sqlite3.connect(self._db_path, timeout=30.0, isolation_level=None)
        version = FORMAT_VERSION
        try:
            if db_exists:
                version = self._validate()
            else:
                self._create()
            self._load_index()
        except sqlite3.DatabaseError as e:
            raise StoreIndexError(
                f"store {root}: its index database {self._db_path} is damaged ({e}); left "
                f"untouched. Rebuild it from the payloads with "
                f"`icbtool store check {root} --rebuild` (icbtool.store.rebuild)"
            ) from e
        if db_exists and not self.readonly:
            self._conn.execute("PRAGMA journal_mode=WAL")
        # FULL: a commit is on disk when put returns; NORMAL (fsync=False) in WAL mode still
        # survives a process crash, only not a power loss.
        self._conn.execute(f"PRAGMA synchronous={'FULL' if self.config.fsync else 'NORMAL'}")
        if not self.readonly:
            if version < FORMAT_VERSION:
                self._migrate(version)
            self.orphans_removed_on_open = len(self._remove_orphans(self._find_orphans()))

    def _acquire_lock(self) -> None:
        self._lock_fd = _acquire_lock(self.root, self.config.lock_timeout_s)

    def _migrate(self, version: int) -> None:
        """Rewrite a format-``version`` store's intact payloads in the current format.

        New payload files are written first, then every row is updated in one transaction (with
        the format version), then the old files are removed: a crash leaves either store intact
        plus orphan files. Damaged payloads are left as they are (``check`` reports them).
        """
        conn = self._db()
        updates, old_files, dirs = [], [], set()
        scenes: dict[str, dict[str, Any]] = {}
        n_damaged = 0
        for info in list(self):
            try:
                buf = self.get(info.record_id)
            except PayloadError as e:
                log.warning("store %s: migration leaves %s", self.root, e)
                n_damaged += 1
                continue
            sh = buf.meta.scene_hash
            if sh not in scenes:
                scenes[sh] = self._scene_entry(sh)
            record = {"id": info.record_id, "scene": scenes[sh]}
            rel, nbytes, digest, new_dirs = self._write_payload(buf, record)
            dirs |= new_dirs
            updates.append((rel, nbytes, digest, info.record_id))
            old_files.append(info.payload)
        if self.config.fsync:
            for d in sorted(dirs, key=lambda p: len(p.parts)):
                _fsync_dir(d)
        conn.execute("BEGIN IMMEDIATE")
        try:
            conn.executemany(
                "UPDATE records SET payload=?, nbytes=?, checksum=? WHERE id=?", updates
            )
            conn.execute(
                "UPDATE meta SET value=? WHERE key='format_version'", (str(FORMAT_VERSION),)
            )
            conn.execute("COMMIT")
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        for f in old_files:
            with contextlib.suppress(FileNotFoundError):
                f.unlink()
        self._bytes = conn.execute("SELECT COALESCE(SUM(nbytes), 0) FROM records").fetchone()[0]
        self.migrated_from = version
        log.info(
            "store %s: migrated from format %d to %d (%d records rewritten, %d damaged left)",
            self.root,
            version,
            FORMAT_VERSION,
            len(updates),
            n_damaged,
        )

    @classmethod
    def rebuild(cls, root: str | os.PathLike, config: StoreConfig | None = None) -> RebuildReport:
        """Rebuild a store's index database from its payloads (see :func:`rebuild`)."""
        return rebuild(root, config)

    def _validate(self) -> int:
        """Check the database is an icbtool store of a known version; returns the version."""
        assert self._conn is not None
        try:
            rows = dict(self._conn.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError as e:
            hint = (
                f"; if it is an icbtool store, rebuild its index from the payloads with "
                f"`icbtool store check {self.root} --rebuild`"
                if _has_payloads(self._payload_root)
                else ""
            )
            raise StoreIndexError(
                f"{self._db_path} is not an icbtool store database or is damaged ({e}); left "
                f"untouched{hint}"
            ) from e
        if rows.get("kind") != STORE_KIND:
            raise StoreFormatError(
                f"{self._db_path} is an SQLite database but not an icbtool store "
                f"(meta kind {rows.get('kind')!r}); left untouched"
            )
        try:
            version = int(rows.get("format_version", "-1"))
        except ValueError:
            version = -1
        if version < 1 or version > FORMAT_VERSION:
            raise StoreFormatError(
                f"{self._db_path}: store format version {rows.get('format_version')!r} is not "
                f"supported (this icbtool reads versions 1..{FORMAT_VERSION}; a newer icbtool "
                f"wrote it?)"
            )
        problems = [r[0] for r in self._conn.execute("PRAGMA quick_check(5)").fetchall()]
        if problems != ["ok"]:
            raise sqlite3.DatabaseError("; ".join(problems))
        return version

    def _create(self) -> None:
        assert self._conn is not None
        self._conn.execute("PRAGMA journal_mode=WAL")
        _create_schema(self._conn)
        (self._payload_root / "tmp").mkdir(parents=True, exist_ok=True)
        if self.config.fsync:
            _fsync_dir(self._payload_root)
            _fsync_dir(self.root)

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

    # -------------------------------------------------------------- scenes
    def register_scene(
        self,
        scene: Any = None,
        *,
        scene_hash: str | None = None,
        bounds: Any = None,
        name: str = "",
    ) -> OctreeGeometry:
        """Fix the octree of a scene (from a :class:`~icbtool.scene.Scene` or hash + bounds).

        The geometry of a scene never changes once registered (records keep their leaves). A scene
        first seen through :meth:`put` is registered from ``meta.scene_bounds`` or, without them,
        from the record's masked positions and camera centre.
        """
        if scene is not None:
            scene_hash, bounds, name = scene.content_hash, scene.bounds, scene.name
        if scene_hash is None or bounds is None:
            raise ValueError("register_scene needs a scene, or scene_hash and bounds")
        if scene_hash in self._geoms:
            return self._geoms[scene_hash]
        conn = self._writable()
        leaf = self.config.leaf_size or 2.0 * self.config.alpha_pos
        geom = OctreeGeometry.for_bounds(
            np.asarray(bounds, np.float64), leaf, self.config.max_depth
        )
        conn.execute(
            "INSERT OR IGNORE INTO scenes VALUES (?, ?, ?, ?, ?, ?)",
            (
                scene_hash,
                name,
                json.dumps(np.asarray(bounds, np.float64).tolist()),
                json.dumps(list(geom.root_min)),
                geom.root_size,
                geom.depth,
            ),
        )
        row = conn.execute(
            "SELECT root_min, root_size, depth FROM scenes WHERE scene_hash=?", (scene_hash,)
        ).fetchone()
        geom = OctreeGeometry(tuple(json.loads(row[0])), row[1], row[2])
        self._geoms[scene_hash] = geom
        return geom

    def geometry(self, scene_hash: str) -> OctreeGeometry:
        """The octree geometry (root cube, depth) of a registered scene.

        Raises:
            KeyError: if the scene is not registered.
        """
        if scene_hash not in self._geoms:
            raise KeyError(f"scene {scene_hash!r} is not registered in store {self.root}")
        return self._geoms[scene_hash]

    def _bounds_for(self, buf: CRTBuffer) -> np.ndarray:
        if buf.meta.scene_bounds is not None:
            return np.asarray(buf.meta.scene_bounds, np.float64)
        pts = [buf.camera.position[None]]
        if buf.position is not None:
            m = (
                buf.mask[..., 0] > 0
                if buf.mask is not None
                else np.ones(buf.position.shape[:2], bool)
            )
            pts.append(buf.position[m].astype(np.float64))
        p = np.concatenate(pts)
        p = p[np.all(np.isfinite(p), axis=1)]  # the camera centre is always finite
        return np.stack([p.min(0), p.max(0)])

    # -------------------------------------------------------------- writing
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

    def _scene_entry(self, scene_hash: str) -> dict[str, Any]:
        """A registered scene's row, as written into its records' payload headers."""
        name, bounds, root_min, size, depth = (
            self._db()
            .execute(
                "SELECT scene_name, bounds, root_min, root_size, depth FROM scenes "
                "WHERE scene_hash=?",
                (scene_hash,),
            )
            .fetchone()
        )
        return {
            "name": name,
            "bounds": json.loads(bounds),
            "root_min": json.loads(root_min),
            "root_size": size,
            "depth": depth,
        }

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

    def _over_capacity(self) -> bool:
        c = self.config
        return (c.max_records is not None and self._count > c.max_records) or (
            c.max_bytes is not None and self._bytes > c.max_bytes
        )

    def set_focus(self, position: Any) -> None:
        """The current camera/path position, for ``eviction='farthest'`` ((3,) or None)."""
        self._focus = None if position is None else np.asarray(position, np.float64).reshape(3)

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

    def damaged_ids(self, deep: bool = True) -> dict[int, str]:
        """The damaged records: {id: problem}.

        Args:
            deep: read every payload and compare its checksum; else only check that each payload
                file exists with its recorded size (one stat per record). Records whose payload
                failed a :meth:`get` in this process are re-verified with a checksum either way.
        """
        rows = self._db().execute("SELECT id, payload, nbytes, checksum FROM records").fetchall()
        out: dict[int, str] = {}
        for rid, rel, nbytes, digest in rows:
            problem = _payload_problem(
                self._payload_root / rel, nbytes, digest, deep or rid in self._damaged
            )
            if problem is not None:
                out[rid] = problem
        return out

    def evict_damaged(self, deep: bool = True, protect: tuple[int, ...] = ()) -> list[int]:
        """Delete the damaged records (see :meth:`damaged_ids`); returns their ids.

        A record whose payload verifies is never deleted here. Each one is logged (WARNING).
        """
        self._writable()
        bad = {k: v for k, v in self.damaged_ids(deep).items() if k not in set(protect)}
        for rid, problem in sorted(bad.items()):
            log.warning("store %s: evicting damaged record %d (%s)", self.root, rid, problem)
        self.delete(sorted(bad))
        return sorted(bad)

    def verify(self, record_id: int) -> str | None:
        """What is wrong with a record's payload (missing, size, checksum), or None if intact."""
        info = self.info(record_id)
        return _payload_problem(info.payload, info.nbytes, info.checksum)

    def get_intact(self, record_id: int) -> CRTBuffer | None:
        """:meth:`get`, but a damaged record is a miss: logged (WARNING) and None returned.

        Raises:
            RecordNotFoundError: no such id (that is a caller's mistake, not damage).
        """
        try:
            return self.get(record_id)
        except PayloadError as e:
            log.warning("store %s: %s; treating it as a miss", self.root, e)
            return None

    def replace_damaged(self, record_id: int, buf: CRTBuffer) -> int:
        """Store ``buf`` (a re-render of a damaged record) and delete the damaged record.

        The new record is committed first; the old one is deleted only if its payload still
        fails verification (an intact record is never deleted). Returns the new record's id.
        """
        new_id = self.put(buf)
        if record_id in self._ids and record_id != new_id:
            problem = self.verify(record_id)
            if problem is not None:
                log.warning(
                    "store %s: record %d (%s) replaced by record %d",
                    self.root,
                    record_id,
                    problem,
                    new_id,
                )
                self.delete([record_id])
        return new_id

    # -------------------------------------------------------------- reading
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

    # -------------------------------------------------------------- lookup
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
        conn = self._db()
        if self.readonly:
            now = time.monotonic()
            if now - self._last_refresh >= self.config.refresh_interval_s:
                self._last_refresh = now
                if conn.execute("PRAGMA data_version").fetchone()[0] != self._data_version:
                    self.refresh()
        cfg = self.config
        a_pos = cfg.alpha_pos if alpha_pos is None else float(alpha_pos)
        a_dir = cfg.alpha_dir if alpha_dir is None else float(alpha_dir)
        if not (a_pos > 0 and a_dir > 0):
            raise ValueError(f"lookup thresholds must be > 0, got {a_pos}, {a_dir}")
        tree = self._trees.get((scene_hash, light_hash))
        if tree is None:
            return None
        m = camera.world_from_cam
        pw = m[:3, 3].tolist()
        fw = m[:3, 2].tolist()
        policy = intrinsics or cfg.intrinsics
        if policy not in ("same", "covering", "any"):
            raise ValueError(f"intrinsics policy must be same|covering|any, got {policy!r}")
        q = (camera.height, camera.width, camera.fx, camera.fy, camera.cx, camera.cy)
        excl = None if exclude is None else {int(e) for e in exclude}
        leaves = tree.candidate_leaves(pw, a_pos)
        n_cand = sum(len(leaf.ids) for leaf in leaves)
        if n_cand == 0:
            return None
        # (distance, 1 - dot, id, row) of the records within both thresholds
        passing: list[tuple[float, float, int, tuple[float, ...]]] = []
        if n_cand <= 64:  # the usual case: a few records; plain Python beats numpy's overhead
            px, py, pz = pw
            fx_, fy_, fz_ = fw
            a2 = a_pos * a_pos * (1.0 + 1e-9)  # prefilter only; the exact test is on the sqrt
            for leaf in leaves:
                for rid, row in zip(leaf.ids, leaf.rows):
                    dx, dy, dz = row[0] - px, row[1] - py, row[2] - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 > a2:
                        continue
                    dd = 1.0 - (row[3] * fx_ + row[4] * fy_ + row[5] * fz_)
                    dist = math.sqrt(d2)
                    if dist < a_pos and dd < a_dir:
                        passing.append((dist, dd, rid, row))
        else:
            data, ids = tree.candidates(pw, a_pos)
            diff = data[:, 0:3] - m[:3, 3]
            dist_a = np.sqrt(np.einsum("ij,ij->i", diff, diff))
            dd_a = 1.0 - data[:, 3:6] @ m[:3, 2]
            for k in np.flatnonzero((dist_a < a_pos) & (dd_a < a_dir)).tolist():
                passing.append(
                    (float(dist_a[k]), float(dd_a[k]), int(ids[k]), tuple(data[k].tolist()))
                )
        best: tuple[float, int, float, float, bool] | None = None  # score, id, dist, dd, same
        for dist, dd, rid, row in passing:
            if excl is not None and rid in excl:
                continue
            allowed, same = _intrinsics_check(row[6:12], q, policy, cfg.intrinsics_rtol)
            if not allowed:
                continue
            sc = dist / a_pos + dd / a_dir
            if best is None or (sc, rid) < (best[0], best[1]):
                best = (sc, rid, dist, dd, same)
        if best is None:
            return None
        score, rid, dist, dd, same = best
        if cfg.record_hits and not self.readonly:
            n, _ = self._pending_hits.get(rid, (0, 0.0))
            self._pending_hits[rid] = (n + 1, time.time())
        cos = min(1.0, max(-1.0, 1.0 - dd))
        return Hit(rid, dist, dd, math.degrees(math.acos(cos)), score, same, n_cand, self)

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

    # -------------------------------------------------------------- maintenance
    def _find_orphans(self) -> list[Path]:
        if not self._payload_root.exists():
            return []
        known = {r[0] for r in self._db().execute("SELECT payload FROM records")}
        out = []
        for p in self._payload_root.rglob("*"):
            if not p.is_file():
                continue
            rel = p.relative_to(self._payload_root).as_posix()
            if rel not in known:
                out.append(p)
        return sorted(out)

    def _remove_orphans(self, paths: list[Path]) -> list[Path]:
        removed = []
        for p in paths:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p)
        return removed

    def check(self, repair: bool = False, drop_damaged: bool = False) -> CheckReport:
        """Verify every payload (exists, size, checksum, decodes) and the database.

        Args:
            repair: remove orphan payload files (left by a crash between payload and row).
            drop_damaged: also delete the rows of damaged records (their data is lost anyway).

        Returns:
            A :class:`CheckReport`; ``report.ok`` is False when anything is damaged.
        """
        conn = self._db()
        if (repair or drop_damaged) and self.readonly:
            raise ReadOnlyStoreError(f"store {self.root}: check --repair needs a writable store")
        integrity = conn.execute("PRAGMA integrity_check").fetchone()[0]
        damaged: list[Damage] = []
        rows = conn.execute(
            "SELECT id, payload, nbytes, checksum FROM records ORDER BY id"
        ).fetchall()
        for rid, rel, nbytes, digest in rows:
            path = self._payload_root / rel
            problem = _payload_problem(path, nbytes, digest)
            if problem is None:
                try:
                    decode_payload(path.read_bytes(), str(path))
                except ValueError as e:
                    problem = f"undecodable: {e}"
            if problem is not None:
                damaged.append(Damage(rid, str(path), problem))
        orphans = [] if self.readonly else self._find_orphans()
        removed = len(self._remove_orphans(orphans)) if repair else 0
        dropped: list[int] = []
        if drop_damaged and damaged:
            dropped = [d.record_id for d in damaged if d.record_id is not None]
            self.delete(dropped)
        return CheckReport(
            len(rows), damaged, [str(p) for p in orphans], removed, dropped, integrity
        )

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


def _has_payloads(payload_root: Path) -> bool:
    """Whether a store's payload folder holds at least one payload file."""
    if not payload_root.is_dir():
        return False
    return any(
        p.is_file() and p.parent.name != "tmp" for p in payload_root.rglob("*" + PAYLOAD_SUFFIX)
    )


def _salvage_old_index(db_path: Path) -> dict[str, tuple[int, int, float]]:
    """{payload path: (id, hits, last_hit)} of whatever rows a damaged database still yields."""
    out: dict[str, tuple[int, int, float]] = {}
    if not db_path.exists():
        return out
    try:
        con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=1.0)
    except sqlite3.Error:
        return out
    try:
        for rid, rel, hits, last_hit in con.execute(
            "SELECT id, payload, hits, last_hit FROM records"
        ):
            if isinstance(rel, str) and isinstance(rid, int):
                out[rel] = (rid, int(hits or 0), float(last_hit or 0.0))
    except (sqlite3.Error, TypeError, ValueError):
        pass  # a damaged database gives what it can
    finally:
        con.close()
    return out


def _unused_name(path: Path) -> Path:
    k, out = 1, path
    while out.exists() or Path(f"{out}-wal").exists():
        k += 1
        out = path.with_name(f"{path.name}.{k}")
    return out


def rebuild(root: str | os.PathLike, config: StoreConfig | None = None) -> RebuildReport:
    """Rebuild the index database of the store at ``root`` from its self-describing payloads.

    Every payload file is read and verified (its own digest, its header, every buffer decodes).
    The intact ones become the records of a new database, built in a temporary file and swapped
    in with ``os.replace`` (their ids, metadata, cameras and scene octrees come from the payload
    headers; hit counts from the old database where it can still be read). The old database
    (and its -wal/-shm files) is kept as ``icbstore.sqlite.damaged-<YYYYmmdd-HHMMSS>``; damaged
    payloads are moved to ``quarantine/<YYYYmmdd-HHMMSS>/``. Nothing is deleted.

    Takes the writer lock (waits ``config.lock_timeout_s``, as :func:`open`).

    Args:
        root: the store directory.
        config: only ``lock_timeout_s`` and ``fsync`` are used.

    Returns:
        A :class:`RebuildReport`.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        StoreFormatError: ``root`` holds neither a store database nor payloads.
        StoreLockedError: another process has the store open for writing.
    """
    cfg = config or StoreConfig()
    root = Path(root)
    db_path, payload_root = root / DB_NAME, root / PAYLOAD_DIR
    if not root.is_dir():
        raise FileNotFoundError(f"no icbtool store at {root} (not a directory)")
    if not db_path.exists() and not payload_root.is_dir():
        raise StoreFormatError(
            f"{root} is not an icbtool store (neither {DB_NAME} nor {PAYLOAD_DIR}/); "
            "nothing to rebuild"
        )
    stamp = time.strftime("%Y%m%d-%H%M%S")
    fd = _acquire_lock(root, cfg.lock_timeout_s)
    try:
        old = _salvage_old_index(db_path)
        damaged: list[Damage] = []
        bad_files: list[tuple[Path, str]] = []
        orphans: list[str] = []
        found: list[tuple[int, str, Any, Any, dict, tuple, int, str]] = []
        seen_rel: set[str] = set()
        files = (
            sorted(p for p in payload_root.rglob("*") if p.is_file())
            if (payload_root.is_dir())
            else []
        )
        for p in files:
            rel = p.relative_to(payload_root).as_posix()
            if rel.startswith("tmp/") or not p.name.endswith(PAYLOAD_SUFFIX):
                orphans.append(str(p))
                continue
            seen_rel.add(rel)
            try:
                data = p.read_bytes()
                header = payload_header(data, str(p))
                cam, meta = record_from_header(header, str(p))
                decode_payload(data, str(p), verify=False)
                rec = header["record"]
                rid, scene = int(rec["id"]), rec["scene"]
                geom = OctreeGeometry(
                    tuple(map(float, scene["root_min"])),
                    float(scene["root_size"]),
                    int(scene["depth"]),
                )
                present = tuple(e[0] for e in header["buffers"])
            except (OSError, ValueError, KeyError, TypeError) as e:
                problem = str(e)
                if problem.startswith(str(p) + ": "):
                    problem = problem[len(str(p)) + 2 :]
                damaged.append(Damage(old.get(rel, (None,))[0], str(p), problem))
                bad_files.append((p, rel))
                continue
            found.append((rid, rel, cam, meta, scene, present, len(data), _checksum(data), geom))
        for rel, (rid, _h, _t) in sorted(old.items(), key=lambda kv: kv[1][0]):
            if rel not in seen_rel:
                damaged.append(Damage(rid, str(payload_root / rel), "payload file missing"))

        # the new database, in a temporary file
        tmp = root / f"{DB_NAME}.rebuild-tmp"
        for suffix in ("", "-wal", "-shm", "-journal"):
            with contextlib.suppress(FileNotFoundError):
                Path(f"{tmp}{suffix}").unlink()
        conn = sqlite3.connect(tmp, isolation_level=None)
        recovered: list[int] = []
        renumbered: dict[int, int] = {}
        hits_restored = 0
        try:
            _create_schema(conn)
            conn.execute("BEGIN")
            taken: set[int] = set()
            next_free = max([f[0] for f in found] + [r[0] for r in old.values()] + [0]) + 1
            scene_geoms: dict[str, OctreeGeometry] = {}  # the first (lowest id) payload's wins
            for rid, rel, cam, meta, scene, present, nbytes, digest, geom in sorted(
                found, key=lambda f: (f[0], f[3].created, f[1])
            ):
                if meta.scene_hash not in scene_geoms:
                    scene_geoms[meta.scene_hash] = geom
                    conn.execute(
                        "INSERT INTO scenes VALUES (?, ?, ?, ?, ?, ?)",
                        (
                            meta.scene_hash,
                            str(scene.get("name", meta.scene_name)),
                            json.dumps(scene.get("bounds")),
                            json.dumps(list(geom.root_min)),
                            geom.root_size,
                            geom.depth,
                        ),
                    )
                geom = scene_geoms[meta.scene_hash]
                if rid in taken or rid < 1:
                    renumbered[rid] = next_free
                    rid, next_free = next_free, next_free + 1
                taken.add(rid)
                hits, last_hit = 0, float(meta.created)
                prev = old.get(rel)
                if prev is not None and prev[0] == rid:
                    hits, last_hit = prev[1], max(prev[2], last_hit)
                    hits_restored += 1
                values = _record_values(meta, cam, present, rel, nbytes, digest, geom)
                conn.execute(_INSERT_SQL, (rid, *values, hits, last_hit))
                recovered.append(rid)
            # ids are never reused: continue after the largest id any index or payload knew
            conn.execute(
                "UPDATE sqlite_sequence SET seq=MAX(seq, ?) WHERE name='records'", (next_free - 1,)
            )
            conn.execute(
                "INSERT INTO sqlite_sequence (name, seq) SELECT 'records', ? WHERE NOT EXISTS "
                "(SELECT 1 FROM sqlite_sequence WHERE name='records')",
                (next_free - 1,),
            )
            conn.execute("COMMIT")
            conn.execute("PRAGMA journal_mode=WAL")
        finally:
            conn.close()
        if cfg.fsync:
            tfd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(tfd)
            finally:
                os.close(tfd)

        # keep the old database aside (never deleted), then swap the new one in atomically
        old_index: str | None = None
        if db_path.exists():
            aside = _unused_name(root / f"{DB_NAME}.damaged-{stamp}")
            os.link(db_path, aside)
            old_index = str(aside)
        for suffix in ("-wal", "-shm", "-journal"):
            side = Path(f"{db_path}{suffix}")
            if side.exists():  # must not be applied to the new database
                base = Path(old_index) if old_index else root / f"{DB_NAME}.damaged-{stamp}"
                os.replace(side, Path(f"{base}{suffix}"))
        os.replace(tmp, db_path)

        # damaged payloads go to the quarantine (not payloads/, whose strays a writer removes)
        quarantined: list[str] = []
        if bad_files:
            qdir = root / QUARANTINE_DIR / stamp
            for p, rel in bad_files:
                dest = qdir / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(p, dest)
                quarantined.append(str(dest))
        if cfg.fsync:
            _fsync_dir(root)
    finally:
        _release_lock(fd)
    report = RebuildReport(
        str(root),
        sorted(recovered),
        damaged,
        quarantined,
        orphans,
        old_index,
        hits_restored,
        renumbered,
    )
    log.info(
        "store %s: index rebuilt: %d records recovered, %d damaged, %d orphans; old index %s",
        root,
        len(recovered),
        len(damaged),
        len(orphans),
        old_index,
    )
    return report


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
