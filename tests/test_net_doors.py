"""The server's doors before the handshake (icbtool.net.doors, docs/network.md): the WebSocket
Origin check, the failed-login throttle with its summed-up log lines, the URL and the warning of a
server listening beyond loopback. Loopback only; every wait bounded; no wall-clock assertion (the
throttle's clock is the test's own)."""

from __future__ import annotations

import asyncio
import logging

import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")

from icbtool import scene as sc  # noqa: E402
from icbtool import system  # noqa: E402
from icbtool.net import crypto, protocol  # noqa: E402
from icbtool.net.doors import (  # noqa: E402
    LoginThrottle,
    exposure_warning,
    is_loopback,
    origin_allowed,
    usable_host,
)
from icbtool.net.server import Server, ServerConfig, new_token  # noqa: E402

pytestmark = [pytest.mark.network]

TOKEN = new_token()
CLOUD = system.CloudConfig(spp=1, denoise=False, max_depth=2)
T = 60.0


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


# ---------------------------------------------------------------------------- units
def test_throttle_lets_the_free_failures_pass_then_doubles_the_pause():
    c = Clock()
    th = LoginThrottle(free=2, base_s=1.0, max_s=8.0, clock=c)
    for _ in range(2):
        th.failed("10.0.0.7")
        assert th.admit("10.0.0.7") == 0.0
    pauses = []
    for _ in range(5):
        th.failed("10.0.0.7")
        pauses.append(th.admit("10.0.0.7"))
    assert pauses == [1.0, 2.0, 4.0, 8.0, 8.0]  # doubling, capped at max_s
    assert th.admit("10.0.0.8") == 0.0  # per address
    c.t += 8.0
    assert th.admit("10.0.0.7") == 0.0  # the pause is over
    th.failed("10.0.0.7")
    assert th.admit("10.0.0.7") == 8.0  # still counting: the next pause is the cap
    th.succeeded("10.0.0.7")
    assert th.admit("10.0.0.7") == 0.0  # a good login clears the address


def test_throttle_forgets_an_address_quiet_for_a_window():
    c = Clock()
    th = LoginThrottle(free=1, base_s=1.0, max_s=4.0, window_s=100.0, clock=c)
    th.failed("a")
    th.failed("a")
    assert th.admit("a") == 1.0
    c.t += 200.0
    th.failed("a")  # a fresh start: the first failure is free again
    assert th.admit("a") == 0.0


def test_failed_logins_are_summed_up_not_logged_one_by_one(caplog):
    c = Clock()
    th = LoginThrottle(free=1, base_s=1.0, report_s=60.0, clock=c)
    with caplog.at_level(logging.WARNING, logger="icbtool.net.doors"):
        for i in range(80):
            th.failed(f"10.0.0.{i % 2}")
            th.admit(f"10.0.0.{i % 2}")
            c.t += 0.01
        c.t += 60.0
        th.tick()
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines  # the first failure of each address, then one summary
    assert "80 failed logins from 2 addresses" in lines[-1]


@pytest.mark.parametrize(
    "origin, host, tls, ok",
    [
        (None, "127.0.0.1:8765", False, True),  # non-browser clients send no Origin
        ("http://127.0.0.1:8765", "127.0.0.1:8765", False, True),  # the server's own page
        ("HTTP://LOCALHOST:8765", "localhost:8765", False, True),
        ("https://icb.example:443", "icb.example:443", True, True),
        ("http://evil.example", "127.0.0.1:8765", False, False),
        ("null", "127.0.0.1:8765", False, False),  # a sandboxed or file:// page
        ("http://127.0.0.1:9999", "127.0.0.1:8765", False, False),  # another port: another site
        ("http://127.0.0.1:8765", "127.0.0.1:8765", True, False),  # wrong scheme
        ("http://127.0.0.1:8765", None, False, False),
    ],
)
def test_origin_is_the_servers_own_or_none(origin, host, tls, ok):
    headers = {k: v for k, v in (("Origin", origin), ("Host", host)) if v is not None}
    assert origin_allowed(headers, tls) is ok


def test_a_wildcard_host_gives_a_usable_url_host():
    assert usable_host("127.0.0.1") == "127.0.0.1"
    for wild in ("0.0.0.0", "::", ""):
        h = usable_host(wild)
        assert h and h not in ("0.0.0.0", "::", "[::]")
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.0.2.1")


# ---------------------------------------------------------------------------- a live server
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    scene = sc.PROCEDURAL["cornell_box"]()
    cfg = ServerConfig(login_free_failures=2, login_backoff_max_s=600.0, lpm=False)
    srv = Server(scene, tmp_path_factory.mktemp("store"), TOKEN, cfg, CLOUD).start()
    yield srv
    srv.stop()


async def _login(url: str, token: str, origin: str | None = None) -> str:
    """'ok', 'auth' (refused by the handshake) or 'http NNN' (refused before it)."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    kw = {"origin": origin} if origin else {}
    try:
        async with connect(url, proxy=None, open_timeout=T, max_size=2**24, **kw) as ws:
            hs = crypto.ClientHandshake(token)
            await ws.send(protocol.encode(protocol.Message("hello", hs.hello_fields())))
            welcome = protocol.decode(await asyncio.wait_for(ws.recv(), T))
            channel, auth = hs.finish(welcome.fields)
            await ws.send(protocol.encode(protocol.Message("auth", auth)))
            first = await asyncio.wait_for(ws.recv(), T)
            try:
                protocol.decode(first, channel)
                return "ok"
            except protocol.ProtocolError:
                return protocol.decode(first).fields["code"]
    except InvalidStatus as e:
        return f"http {e.response.status_code}"
    except ConnectionClosed:
        return "closed"


def _run(coro):
    return asyncio.run(asyncio.wait_for(coro, 2 * T))


def test_cross_origin_pages_are_refused_before_the_handshake(server):
    own = f"http://127.0.0.1:{server.port}"
    assert _run(_login(server.url, TOKEN, origin=own)) == "ok"
    assert _run(_login(server.url, TOKEN)) == "ok"
    before = server.stats.origin_refused
    assert _run(_login(server.url, TOKEN, origin="http://evil.example")) == "http 403"
    assert _run(_login(server.url, TOKEN, origin="null")) == "http 403"
    assert server.stats.origin_refused == before + 2


def test_an_address_that_keeps_failing_is_paused_then_a_good_login_clears_it(server):
    wrong = new_token()
    server.throttle.base_s = 300.0  # the pause outlasts the test's connections, however slow
    # the free failures are answered by the handshake; then the address is paused: even the
    # right token is refused before any cryptography (HTTP 429), until the pause ends
    assert [_run(_login(server.url, wrong)) for _ in range(2)] == ["auth", "auth"]
    assert _run(_login(server.url, wrong)) == "auth"  # the failure that starts the pause
    assert _run(_login(server.url, TOKEN)) == "http 429"
    assert server.stats.throttled >= 1
    server.throttle.succeeded("127.0.0.1")  # the pause over (no waiting on a clock in a test)
    assert _run(_login(server.url, TOKEN)) == "ok"
    assert _run(_login(server.url, wrong)) == "auth"  # counting afresh after a good login


def test_serving_beyond_loopback_without_tls_is_warned_of():
    # (no test listens beyond loopback: the rule that decides is checked alone)
    assert "without TLS" in (exposure_warning("0.0.0.0", tls=False) or "")
    assert "without TLS" in (exposure_warning("192.0.2.1", tls=False) or "")
    assert exposure_warning("0.0.0.0", tls=True) is None
    assert exposure_warning("127.0.0.1", tls=False) is None
    assert exposure_warning("localhost", tls=False) is None
