"""A network shaper for the client's transport: latency and bandwidth, both directions.

Each direction is a FIFO link: a message of ``n`` bytes waits for the link to be free, occupies it
for ``8 n / rate`` seconds (serialisation: a token bucket with a one-message bucket, so no burst
goes faster than the rate), then arrives ``rtt / 2`` later (propagation). Messages keep their
order. The shaper works per message (a WebSocket frame), on top of the real loopback socket, whose
own time adds to it.

Example:
    >>> link = Link(ShaperConfig(latency_ms=100, bandwidth_mbit=20))
    >>> link.arrival(1_000_000, now=0.0)  # 1 MB: 0.4 s on the wire + 50 ms one way
    0.45
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShaperConfig:
    """An emulated network between client and server (applied by the client)."""

    latency_ms: float = 0.0
    """Round-trip time added (each direction gets half), milliseconds."""
    bandwidth_mbit: float | None = None
    """Rate of each direction in Mbit/s (10^6 bit/s); None: unlimited."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.latency_ms) and self.latency_ms >= 0):
            raise ValueError(
                f"ShaperConfig.latency_ms must be finite and >= 0, got {self.latency_ms}"
            )
        if self.bandwidth_mbit is not None and not (
            math.isfinite(self.bandwidth_mbit) and self.bandwidth_mbit > 0
        ):
            raise ValueError(
                f"ShaperConfig.bandwidth_mbit must be > 0 or None, got {self.bandwidth_mbit}"
            )

    @property
    def active(self) -> bool:
        return self.latency_ms > 0 or self.bandwidth_mbit is not None

    def label(self) -> str:
        bw = "inf" if self.bandwidth_mbit is None else f"{self.bandwidth_mbit:g}"
        return f"{self.latency_ms:g}ms/{bw}Mbit"


class Link:
    """One direction of a shaped link: when does a message sent now arrive?"""

    def __init__(self, config: ShaperConfig) -> None:
        self.config = config
        self._free_at = 0.0

    def arrival(self, nbytes: int, now: float) -> float:
        """Arrival time (same clock as ``now``) of ``nbytes`` sent at ``now``; books the link."""
        start = max(now, self._free_at)
        bw = self.config.bandwidth_mbit
        wire = 0.0 if bw is None else 8.0 * nbytes / (bw * 1e6)
        self._free_at = start + wire
        return round(self._free_at + self.config.latency_ms / 2e3, 9)


class DelayLine:
    """Delivers items through a :class:`Link` on an asyncio loop, in order, each at its arrival
    time (a delay queue). ``deliver`` is awaited for each item in turn.

    Args:
        config: the link's shape.
        deliver: ``async (item) -> None``, called when the item arrives.
        maxsize: items waiting at most (``put`` then waits: the line is bounded).
    """

    def __init__(
        self,
        config: ShaperConfig,
        deliver: Callable[[Any], Awaitable[None]],
        maxsize: int = 256,
    ) -> None:
        self.link = Link(config)
        self._deliver = deliver
        self._queue: asyncio.Queue[tuple[float, Any]] = asyncio.Queue(maxsize)
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def put(self, item: Any, nbytes: int) -> None:
        """Send ``item`` of ``nbytes`` into the line now."""
        due = self.link.arrival(nbytes, time.monotonic())
        await self._queue.put((due, item))

    async def _run(self) -> None:
        while True:
            due, item = await self._queue.get()
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            try:
                await self._deliver(item)
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the receiver's problem; the line keeps going
                log.warning("shaped delivery failed: %r", e)

    async def aclose(self) -> None:
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self._task = None


__all__ = ["DelayLine", "Link", "ShaperConfig"]
