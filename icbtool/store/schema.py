"""The store's on-disk format: the SQLite schema and its rows, payload checks, opening a
store (create, validate, migrate format 1 to 2). :class:`SchemaMixin` is the opening part of
:class:`icbtool.store.Store`."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sqlite3
import time
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.camera import Camera
from icbtool.store.base import (
    DB_NAME,
    FORMAT_VERSION,
    LOCK_NAME,
    PAYLOAD_DIR,
    PAYLOAD_SUFFIX,
    QUARANTINE_DIR,
    STORE_KIND,
    PayloadError,
    StoreFormatError,
    StoreIndexError,
)
from icbtool.store.locking import (
    _acquire_lock,
)
from icbtool.store.octree import OctreeGeometry, SceneOctree, morton
from icbtool.store.record import (
    RecordMeta,
)

#: One logger for the store, whichever of its modules logs (names kept as before the split).
log = logging.getLogger("icbtool.store.store")


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


def _connect_readonly(db_path: Path) -> sqlite3.Connection:
    """A read-only connection to the index at ``db_path``, also where the user may only read.

    The index is in WAL mode, whose readers need the ``-shm`` file beside it: SQLite creates it
    when missing (a writer removes it on closing), which a folder the user may only read (or a
    read-only file system) refuses ("unable to open database file"). There, with no writer that
    could be writing, the file is opened ``immutable``: no ``-shm``, no locks."""
    shm = Path(f"{db_path}-shm")
    wal = Path(f"{db_path}-wal")
    if shm.exists() or os.access(db_path.parent, os.W_OK):
        uri = f"file:{db_path}?mode=ro"
    elif wal.exists() and wal.stat().st_size > 0:  # a writer's commits not yet in the file
        raise StoreIndexError(
            f"store {db_path.parent}: may only be read, and its index has commits in "
            f"{wal.name} without {shm.name}; open it once where it can be written (its "
            "owner), which folds them in"
        )
    else:
        uri = f"file:{db_path}?mode=ro&immutable=1"
    return sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None)


def _has_payloads(payload_root: Path) -> bool:
    """Whether a store's payload folder holds at least one payload file."""
    if not payload_root.is_dir():
        return False
    return any(
        p.is_file() and p.parent.name != "tmp" for p in payload_root.rglob("*" + PAYLOAD_SUFFIX)
    )


class SchemaMixin:
    """Opening a store: create or validate its database, take the writer lock, migrate an old
    format (part of :class:`~icbtool.store.Store`, which holds the state these methods use)."""

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
            self._conn = _connect_readonly(self._db_path)
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
