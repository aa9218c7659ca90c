"""The server's doors before the handshake: the WebSocket ``Origin`` check and the throttle of
failed logins (docs/network.md).

* **Origin.** A browser sends the origin of the page that opens a WebSocket; any page on the web
  can open one to a server a user's browser reaches (127.0.0.1 included). The server accepts a
  WebSocket whose ``Origin`` is its own (the scheme of the server and the ``Host`` the browser
  asked for: the page ``icbtool serve --web`` serves) or absent (non-browser clients send none);
  anything else, ``null`` included, is refused with HTTP 403 before the handshake.
* **Failed logins.** Per peer address: the first :attr:`LoginThrottle.free` failures in a
  window pass, then every new connection from that address is refused with HTTP 429 until a
  pause that doubles with each further failure (:attr:`LoginThrottle.base_s` up to
  :attr:`LoginThrottle.max_s`); a successful login clears the address. Failures are logged once
  per address as they start and then summed up in one line per :attr:`LoginThrottle.report_s`,
  not one line each.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine's loopback only."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def exposure_warning(host: str, tls: bool) -> str | None:
    """The warning a server listening on ``host`` logs, or None: beyond loopback without TLS,
    the cameras clients ask for are readable on the network and an active man in the middle can
    test token guesses (docs/network.md)."""
    if tls or is_loopback(host):
        return None
    return (
        f"serving on {host} without TLS: anyone on the network sees the cameras clients ask for, "
        "and a man in the middle can test token guesses; give --tls-cert/--tls-key "
        "(docs/network.md)"
    )


def usable_host(host: str) -> str:
    """A host name a client can connect to for a server listening on ``host``: ``host`` itself,
    unless it is a wildcard (``0.0.0.0``, ``::``, empty), then this machine's address on its
    default route (no packet is sent), else its host name."""
    if host not in ("", "0.0.0.0", "::", "[::]"):
        return host
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    probe = "2001:db8::1" if family == socket.AF_INET6 else "192.0.2.1"  # documentation ranges
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect((probe, 9))  # UDP: picks the route's source address, sends nothing
            addr = str(s.getsockname()[0])
        if not ipaddress.ip_address(addr).is_unspecified:
            return f"[{addr}]" if ":" in addr else addr
    except OSError:
        pass
    return socket.gethostname()


def origin_allowed(headers: Any, tls: bool) -> bool:
    """Whether a WebSocket upgrade's ``Origin`` is acceptable (see the module docstring).

    Args:
        headers: the request's headers (``.get(name)``).
        tls: the server speaks TLS (its own origin is then ``https://``).
    """
    origin = headers.get("Origin")
    if origin is None:
        return True
    host = headers.get("Host")
    if not host:
        return False
    scheme = "https" if tls else "http"
    return origin.strip().lower() == f"{scheme}://{host.strip().lower()}"


@dataclass
class _Peer:
    failures: int = 0
    first_s: float = 0.0
    blocked_until_s: float = 0.0
    refused: int = 0


@dataclass
class LoginThrottle:
    """Failed logins per peer address (see the module docstring).

    Attributes:
        free: failures allowed without a pause, per address and window.
        base_s: the first pause, after failure ``free + 1``; doubling with each further one.
        max_s: the longest pause.
        window_s: an address that has not failed for this long starts afresh.
        report_s: the failures are summed up in one log line at most this often.
        clock: the clock (seconds, monotonic): tests give their own.
    """

    free: int = 5
    base_s: float = 0.5
    max_s: float = 60.0
    window_s: float = 600.0
    report_s: float = 60.0
    clock: Callable[[], float] = time.monotonic
    _peers: dict[str, _Peer] = field(default_factory=dict)
    _since_report: dict[str, int] = field(default_factory=dict)
    _refused_since_report: int = 0
    _last_report_s: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.free, int) and self.free >= 0):
            raise ValueError(f"LoginThrottle.free must be an integer >= 0, got {self.free!r}")
        if not 0 < self.base_s <= self.max_s:
            raise ValueError("LoginThrottle: need 0 < base_s <= max_s")

    def _peer(self, addr: str, now: float) -> _Peer:
        p = self._peers.get(addr)
        if p is not None and now - max(p.first_s, p.blocked_until_s) > self.window_s:
            p = None
        if p is None:
            p = self._peers[addr] = _Peer(first_s=now)
        return p

    def admit(self, addr: str) -> float:
        """0 if ``addr`` may try to log in now, else the seconds it must still wait (the
        connection is refused and counted)."""
        now = self.clock()
        p = self._peers.get(addr)
        if p is None or now >= p.blocked_until_s:
            return 0.0
        p.refused += 1
        self._refused_since_report += 1
        self._report(now)
        return p.blocked_until_s - now

    def failed(self, addr: str) -> None:
        """Count a failed login from ``addr`` (wrong token, timeout, a message out of turn)."""
        now = self.clock()
        p = self._peer(addr, now)
        p.failures += 1
        over = p.failures - self.free
        if over > 0:
            p.blocked_until_s = now + min(self.max_s, self.base_s * 2.0 ** (over - 1))
        if addr not in self._since_report and p.failures == 1:
            log.warning("failed login from %s (further ones are summed up)", addr)
        self._since_report[addr] = self._since_report.get(addr, 0) + 1
        self._report(now)

    def succeeded(self, addr: str) -> None:
        """A login from ``addr`` succeeded: forget its failures."""
        self._peers.pop(addr, None)

    def tick(self) -> None:
        """Log the summary line if :attr:`report_s` has passed since the last (call it now and
        then: the server does with its hit-count flushes)."""
        self._report(self.clock())

    def _report(self, now: float) -> None:
        if self._last_report_s is None:
            self._last_report_s = now
            return
        if now - self._last_report_s < self.report_s:
            return
        self.flush(now)

    def flush(self, now: float | None = None) -> None:
        """Log the summary line of the failures since the last one (if any)."""
        now = self.clock() if now is None else now
        if self._since_report or self._refused_since_report:
            worst = sorted(self._since_report.items(), key=lambda kv: -kv[1])[:3]
            log.warning(
                "%d failed logins from %d addresses and %d connections refused while paused in "
                "the last %.0f s (most: %s)",
                sum(self._since_report.values()),
                len(self._since_report),
                self._refused_since_report,
                now - (self._last_report_s or now),
                ", ".join(f"{a}: {n}" for a, n in worst) or "none",
            )
        self._since_report.clear()
        self._refused_since_report = 0
        self._last_report_s = now
        for a in [a for a, p in self._peers.items() if now - p.blocked_until_s > self.window_s]:
            if now - self._peers[a].first_s > self.window_s:
                del self._peers[a]


__all__ = ["LoginThrottle", "exposure_warning", "is_loopback", "origin_allowed", "usable_host"]
