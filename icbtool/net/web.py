"""The browser client's files over HTTP, on the WebSocket server's own host and port.

``icbtool serve --web`` hands :func:`http_handler` to ``websockets``' ``process_request`` hook:
a plain HTTP ``GET`` (no ``Upgrade: websocket``) for one of the page's files is answered here;
a WebSocket upgrade goes on to the protocol (docs/protocol.md). The page (``icbtool/web/``:
``index.html``, ``style.css`` and ``bundle/``, built by ``make web`` from ``icbtool/web/src``
with esbuild) ships inside the package. :func:`page_url` is the one URL to open: the token
travels in the URL fragment (``#token=...``), which browsers never send to the server, so it is
in no HTTP request and no server log.

Responses carry ``Cross-Origin-Opener-Policy: same-origin`` and
``Cross-Origin-Embedder-Policy: require-corp`` (the page is cross-origin isolated, so
onnxruntime-web may use WebAssembly threads), a restrictive Content-Security-Policy (scripts
and connections only from this origin) and ``Cache-Control: no-store``.
"""

from __future__ import annotations

import urllib.parse
from collections.abc import Callable
from http import HTTPStatus
from pathlib import Path
from typing import Any

#: The page's folder inside the package.
WEB_ROOT = Path(__file__).resolve().parent.parent / "web"

#: The files served, by URL path, with their content types. Nothing else is served.
FILES: dict[str, tuple[str, str]] = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/index.html": ("index.html", "text/html; charset=utf-8"),
    "/style.css": ("style.css", "text/css; charset=utf-8"),
    "/bundle/app.js": ("bundle/app.js", "text/javascript; charset=utf-8"),
    "/bundle/app.js.LEGAL.txt": ("bundle/app.js.LEGAL.txt", "text/plain; charset=utf-8"),
    "/bundle/ort-wasm-simd-threaded.mjs": (
        "bundle/ort-wasm-simd-threaded.mjs",
        "text/javascript; charset=utf-8",
    ),
    "/bundle/ort-wasm-simd-threaded.wasm": (
        "bundle/ort-wasm-simd-threaded.wasm",
        "application/wasm",
    ),
}

#: Headers of every answer.
SECURITY_HEADERS: dict[str, str] = {
    "Cache-Control": "no-store",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Cross-Origin-Embedder-Policy": "require-corp",
    "Cross-Origin-Resource-Policy": "same-origin",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; connect-src 'self'; "
        "img-src 'self' blob: data:; style-src 'self'; worker-src 'self' blob:; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
}


#: Debian's chromium, headless with software WebGL2 (SwiftShader): how the tests and
#: benchmarks.web_client open the page on a machine without a GPU (docs/protocol.md is
#: spoken over loopback only; a fresh --user-data-dir is added by the caller).
CHROMIUM = "/usr/bin/chromium"
HEADLESS_CHROMIUM_ARGS: tuple[str, ...] = (
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
)


class WebBundleMissing(FileNotFoundError):
    """The page's JavaScript bundle was not built (``make web``)."""


def check_bundle(root: Path = WEB_ROOT) -> None:
    """Raise :class:`WebBundleMissing` (naming the fix) if the page cannot be served.

    Raises:
        WebBundleMissing: ``root/bundle/app.js`` is absent.
    """
    if not (root / "bundle" / "app.js").is_file():
        raise WebBundleMissing(
            f"the web client's bundle {root / 'bundle' / 'app.js'} is not built: run `make web` "
            "(npm ci + esbuild; `make install` does it) in the icbtool repository"
        )


def page_url(ws_url: str, token: str) -> str:
    """The URL that opens the client already authenticated: ``http://HOST:PORT/#token=...``.

    Args:
        ws_url: the server's ``ws://HOST:PORT`` (:attr:`icbtool.net.Server.url`).
        token: the shared secret; it goes into the fragment only (never sent over HTTP).
    """
    u = urllib.parse.urlsplit(ws_url)
    scheme = {"ws": "http", "wss": "https"}.get(u.scheme)
    if scheme is None:
        raise ValueError(f"page_url: {ws_url!r} is not a ws:// or wss:// URL")
    frag = urllib.parse.urlencode({"token": token}, quote_via=urllib.parse.quote)
    return f"{scheme}://{u.netloc}/#{frag}"


def http_handler(root: Path = WEB_ROOT) -> Callable[[Any, Any], Any]:
    """A ``process_request`` hook for ``websockets.asyncio.server.serve``.

    Returns:
        ``hook(connection, request)``: None for a WebSocket upgrade (the protocol goes on), else
        a ``websockets`` Response: the file (200), 404 for any other path, 503 naming the fix
        when a bundle file is missing (``websockets`` itself answers only GET requests).

    Raises:
        WebBundleMissing: see :func:`check_bundle` (checked once, here).
    """
    from icbtool.optional import require

    Headers = require("websockets.datastructures", "icbtool serve --web").Headers
    Response = require("websockets.http11", "icbtool serve --web").Response

    check_bundle(root)
    cache: dict[str, bytes] = {}

    def answer(status: HTTPStatus, body: bytes, ctype: str) -> Any:
        h = Headers(SECURITY_HEADERS)
        h["Content-Type"] = ctype
        h["Content-Length"] = str(len(body))
        return Response(status.value, status.phrase, h, body)

    def hook(connection: Any, request: Any) -> Any:
        if "upgrade" in request.headers.get("Connection", "").lower():
            return None  # the WebSocket protocol
        path = urllib.parse.urlsplit(request.path).path
        entry = FILES.get(path)
        if entry is None:
            return answer(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain; charset=utf-8")
        name, ctype = entry
        if name not in cache:
            f = root / name
            if not f.is_file():
                msg = f"{name} is missing: run `make web` to build the web client\n"
                return answer(HTTPStatus.SERVICE_UNAVAILABLE, msg.encode(), "text/plain")
            cache[name] = f.read_bytes()
        return answer(HTTPStatus.OK, cache[name], ctype)

    return hook


__all__ = [
    "CHROMIUM",
    "FILES",
    "HEADLESS_CHROMIUM_ARGS",
    "SECURITY_HEADERS",
    "WEB_ROOT",
    "WebBundleMissing",
    "check_bundle",
    "http_handler",
    "page_url",
]
