"""Damage and recovery: verifying payloads, damaged records as misses, orphan files, and
rebuilding the index database from the self-describing payloads (the module docstring of
:mod:`icbtool.store.store`). :class:`RepairMixin` is that part of
:class:`icbtool.store.Store`; :func:`rebuild` works on a closed store."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

from icbtool.store.base import (
    DB_NAME,
    FORMAT_VERSION,
    PAYLOAD_DIR,
    PAYLOAD_SUFFIX,
    QUARANTINE_DIR,
    STORE_KIND,
    CheckReport,
    Damage,
    PayloadError,
    ReadOnlyStoreError,
    RebuildReport,
    StoreConfig,
    StoreFormatError,
)
from icbtool.store.locking import (
    _acquire_lock,
    _release_lock,
)
from icbtool.store.octree import OctreeGeometry
from icbtool.store.record import (
    CRTBuffer,
    decode_payload,
    payload_header,
    record_from_header,
)
from icbtool.store.schema import (
    _INSERT_SQL,
    _checksum,
    _create_schema,
    _fsync_dir,
    _payload_problem,
    _record_values,
)

#: One logger for the store, whichever of its modules logs (names kept as before the split).
log = logging.getLogger("icbtool.store.store")


class RepairMixin:
    """Checks and damaged records (part of :class:`~icbtool.store.Store`)."""

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


def _index_matches(db_path: Path, found: list[tuple], damaged: set[str] = frozenset()) -> bool:
    """Whether the index database at ``db_path`` is healthy and lists exactly the payloads of
    ``found`` (id, file, size, checksum and scene octree), so that a rebuild would only copy it,
    besides rows of the damaged payload files ``damaged`` (relative paths).

    ``found``: the rebuild's ``(id, rel, camera, meta, scene, present, nbytes, digest, geometry)``
    of every intact payload."""
    if not db_path.exists():
        return False
    try:
        con = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=1.0)
    except sqlite3.Error:
        return False
    try:
        meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
        if meta.get("kind") != STORE_KIND or meta.get("format_version") != str(FORMAT_VERSION):
            return False
        if [r[0] for r in con.execute("PRAGMA quick_check").fetchall()] != ["ok"]:
            return False
        rows = set(con.execute("SELECT id, payload, nbytes, checksum FROM records").fetchall())
        scenes = {
            sh: (tuple(json.loads(rmin)), float(size), int(depth))
            for sh, rmin, size, depth in con.execute(
                "SELECT scene_hash, root_min, root_size, depth FROM scenes"
            )
        }
    except (sqlite3.Error, TypeError, ValueError):
        return False
    finally:
        con.close()
    if {r for r in rows if r[1] not in damaged} != {(f[0], f[1], f[6], f[7]) for f in found}:
        return False
    return all(
        scenes.get(f[3].scene_hash) == (tuple(f[8].root_min), f[8].root_size, f[8].depth)
        for f in found
    )


def _drop_rows(db_path: Path, payloads: set[str]) -> None:
    """Delete the rows of the index at ``db_path`` whose payload is one of ``payloads``."""
    if not payloads:
        return
    con = sqlite3.connect(db_path, timeout=10.0)
    try:
        with con:
            con.executemany("DELETE FROM records WHERE payload=?", [(p,) for p in payloads])
    finally:
        con.close()


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
    payloads are moved to ``quarantine/<YYYYmmdd-HHMMSS>/``. No payload is deleted. A healthy index
    that lists exactly the intact payloads (and maybe damaged ones) is kept (``report.rebuilt``
    is False, no ``.damaged`` copy): the rows of damaged payloads leave it, as with ``store check
    --drop-damaged``, their files go to quarantine; running the rebuild again changes nothing
    and leaves no file behind.

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
        scan = _scan_payloads(payload_root, old)
        listed_damaged = set(old) - {f[1] for f in scan.found}
        if _index_matches(db_path, scan.found, listed_damaged):
            # a healthy index: kept (no new file, no .damaged copy); the rows of damaged
            # payloads leave it and the files go to quarantine, as `store check --drop-damaged`
            ids = sorted(f[0] for f in scan.found)
            quarantined = _quarantine(root / QUARANTINE_DIR / stamp, scan.bad_files)
            _drop_rows(db_path, listed_damaged)
            log.info("store %s: its index is healthy; %d damaged record(s) dropped from it",
                     root, len(listed_damaged))  # fmt: skip
            return RebuildReport(
                str(root), ids, scan.damaged, quarantined, scan.orphans, None, len(ids), {},
                rebuilt=False,
            )  # fmt: skip
        tmp = root / f"{DB_NAME}.rebuild-tmp"
        recovered, renumbered, hits_restored = _write_index(tmp, scan.found, old, cfg.fsync)
        old_index = _swap_in(tmp, db_path, stamp)
        quarantined = _quarantine(root / QUARANTINE_DIR / stamp, scan.bad_files)
        if cfg.fsync:
            _fsync_dir(root)
    finally:
        _release_lock(fd)
    damaged, orphans = scan.damaged, scan.orphans
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


@dataclass
class _Scan:
    """What the payload files hold: the intact records (``found``: id, payload path, camera,
    meta, scene entry, buffers, size, checksum, octree geometry), the damaged files and the
    records the old index lists whose file is missing (``damaged``), the damaged files to move
    aside (``bad_files``: path, relative path) and the files that are not payloads."""

    found: list[tuple] = field(default_factory=list)
    damaged: list[Damage] = field(default_factory=list)
    bad_files: list[tuple[Path, str]] = field(default_factory=list)
    orphans: list[str] = field(default_factory=list)


def _scan_payloads(payload_root: Path, old: dict[str, tuple[int, int, float]]) -> _Scan:
    """Read and verify every payload file (its digest, header, every buffer decodes)."""
    scan = _Scan()
    seen_rel: set[str] = set()
    files = (
        sorted(p for p in payload_root.rglob("*") if p.is_file()) if payload_root.is_dir() else []
    )
    for p in files:
        rel = p.relative_to(payload_root).as_posix()
        if rel.startswith("tmp/") or not p.name.endswith(PAYLOAD_SUFFIX):
            scan.orphans.append(str(p))
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
            scan.damaged.append(Damage(old.get(rel, (None,))[0], str(p), problem))
            scan.bad_files.append((p, rel))
            continue
        scan.found.append((rid, rel, cam, meta, scene, present, len(data), _checksum(data), geom))
    for rel, (rid, _h, _t) in sorted(old.items(), key=lambda kv: kv[1][0]):
        if rel not in seen_rel:
            scan.damaged.append(Damage(rid, str(payload_root / rel), "payload file missing"))
    return scan


def _write_index(
    tmp: Path, found: list[tuple], old: dict[str, tuple[int, int, float]], fsync: bool
) -> tuple[list[int], dict[int, int], int]:
    """Build the new index database of the ``found`` records in the file ``tmp``.

    Returns:
        (recovered ids, {old id: new id} of the renumbered, records whose hits were restored).
    """
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
    if fsync:
        tfd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(tfd)
        finally:
            os.close(tfd)
    return recovered, renumbered, hits_restored


def _swap_in(tmp: Path, db_path: Path, stamp: str) -> str | None:
    """Keep the old database aside (never deleted: ``DB.damaged-<stamp>``, with its -wal/-shm),
    then replace it by ``tmp`` atomically. Returns where the old one went (None: there was none).
    """
    root = db_path.parent
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
    return old_index


def _quarantine(qdir: Path, bad_files: list[tuple[Path, str]]) -> list[str]:
    """Move the damaged payload files to ``qdir`` (not payloads/, whose strays a writer
    removes); returns their new paths."""
    quarantined: list[str] = []
    for p, rel in bad_files:
        dest = qdir / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(p, dest)
        quarantined.append(str(dest))
    return quarantined
