"""Encoded ``gi_reply`` contents of stored records, kept so that a repeated cache hit is not
read, decoded and encoded again (docs/protocol.md, section Scaling out).

An entry is what every reply to one stored record in one pair of codecs carries: the record's
camera (as JSON), the ``parts`` descriptions and the payload (the parts' bytes before sealing;
sealing is per connection). Its key is ``(record id, payload checksum, GI codec, depth codec)``:
a record's payload never changes under its id (a re-render is a new record with a new id and a
new checksum), so an entry can never answer for other data than the record's; entries of
records that left the store (:meth:`ReplyCache.discard`, or never asked for again) are dropped
first by the byte bound, least recently used first.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

#: Key of an entry: (record id, payload checksum, GI codec, depth codec).
ReplyKey = tuple[int, str, str, str]


@dataclass(frozen=True)
class EncodedReply:
    """What a ``gi_reply`` to one stored record in one pair of codecs carries.

    Attributes:
        camera: the record's camera as the protocol's camera object.
        parts: the ``gi_reply.parts`` descriptions (name, codec, shape, dtype, bytes).
        payload: the parts' bytes, one after the other (before sealing).
    """

    camera: dict[str, Any]
    parts: list[dict[str, Any]]
    payload: bytes

    @property
    def nbytes(self) -> int:
        """Bytes the entry holds (its payload; the small JSON parts are not counted)."""
        return len(self.payload)


@dataclass
class ReplyCacheStats:
    """Counters since the cache was made."""

    hits: int = 0
    misses: int = 0
    stored: int = 0
    evicted: int = 0
    discarded: int = 0
    too_large: int = 0


class ReplyCache:
    """A least-recently-used map of :class:`EncodedReply` bounded in bytes; thread-safe.

    Args:
        max_bytes: the bound on the payload bytes held (0: the cache holds nothing). An entry
            larger than a quarter of it is not kept (it would push out many small ones).

    Raises:
        ValueError: ``max_bytes`` is not an integer >= 0.
    """

    def __init__(self, max_bytes: int) -> None:
        if not isinstance(max_bytes, int) or isinstance(max_bytes, bool) or max_bytes < 0:
            raise ValueError(f"ReplyCache.max_bytes must be an integer >= 0, got {max_bytes!r}")
        self.max_bytes = max_bytes
        self.nbytes = 0
        self.stats = ReplyCacheStats()
        self._entries: collections.OrderedDict[ReplyKey, EncodedReply] = collections.OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: object) -> bool:
        return key in self._entries

    def get(self, key: ReplyKey) -> EncodedReply | None:
        """The entry of ``key`` (now the most recently used), or None."""
        with self._lock:
            e = self._entries.get(key)
            if e is None:
                self.stats.misses += 1
                return None
            self._entries.move_to_end(key)
            self.stats.hits += 1
            return e

    def put(self, key: ReplyKey, entry: EncodedReply) -> bool:
        """Keep ``entry`` under ``key``, dropping the least recently used entries beyond the
        bound; False when it is too large to keep."""
        if entry.nbytes > self.max_bytes // 4:
            with self._lock:
                self.stats.too_large += 1
            return False
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self.nbytes -= old.nbytes
            self._entries[key] = entry
            self.nbytes += entry.nbytes
            self.stats.stored += 1
            while self.nbytes > self.max_bytes:
                _, e = self._entries.popitem(last=False)
                self.nbytes -= e.nbytes
                self.stats.evicted += 1
        return True

    def record_ids(self) -> set[int]:
        """The ids of the records with kept replies."""
        with self._lock:
            return {k[0] for k in self._entries}

    def discard(self, record_ids: Iterable[int]) -> int:
        """Drop every entry of these records (they left the store); how many were dropped."""
        ids = {int(i) for i in record_ids}
        if not ids:
            return 0
        with self._lock:
            gone = [k for k in self._entries if k[0] in ids]
            for k in gone:
                self.nbytes -= self._entries.pop(k).nbytes
            self.stats.discarded += len(gone)
        return len(gone)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.nbytes = 0


__all__ = ["EncodedReply", "ReplyCache", "ReplyCacheStats", "ReplyKey"]
