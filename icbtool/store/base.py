"""The store's constants, errors, configuration and reports (shared by its modules; the
public names are re-exported by :mod:`icbtool.store`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from icbtool.camera import Camera
from icbtool.store.record import (
    RecordMeta,
)

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


# ------------------------------------------------------------------------ config and reports
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
        rebuilt: False when the old index was healthy and listed exactly the intact payloads:
            it was left alone (no new database, nothing kept aside).
    """

    path: str
    recovered: list[int]
    damaged: list[Damage]
    quarantined: list[str]
    orphans: list[str]
    old_index: str | None
    hits_restored: int
    renumbered: dict[int, int]
    rebuilt: bool = True

    @property
    def ok(self) -> bool:
        """True when every payload was recovered."""
        return not self.damaged
