"""``icbtool serve``: the ICB cloud as a WebSocket server (icbtool.net.Server).

Clients authenticate with --token, receive the scene's mesh levels (never the full-detail
mesh's source), ask for GI maps (answered from the store or path traced, coalesced, encoded) and
the generator (--generator, sent once). SIGINT/SIGTERM stop it cleanly: every committed store
record is kept. Prints ``listening on ws://HOST:PORT`` once it accepts connections.

With --web the same host and port also serve the browser client (icbtool/web, built by
``make web``), and one more line is printed: ``web client: http://HOST:PORT/#token=...``, the URL
that opens the client already authenticated (the token stays in the URL fragment, which the
browser never sends, so no server log holds it).
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from icbtool._optional import require
from icbtool.cli._common import (
    UsageError,
    add_denoise_quality_argument,
    float_in,
    int_at_least,
    load_scene,
    positive_int,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the ICB cloud as a WebSocket server",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", help="procedural scene name, scene description (.toml) or mesh file")
    p.set_defaults(func=run)
    p.add_argument("--store", required=True, help="the cloud's CRT-buffer store directory")
    p.add_argument("--host", default="127.0.0.1", help="interface (default: loopback)")
    p.add_argument("--port", type=int_at_least(0), default=8765, help="port (0: a free one)")
    p.add_argument(
        "--token",
        default=None,
        help="shared secret of the clients (default: $ICBTOOL_TOKEN); required",
    )
    p.add_argument("--generator", default=None, metavar="RUN", help="a trained GAN run to offer")
    p.add_argument(
        "--workers",
        type=positive_int,
        default=1,
        help="cloud render threads: 1 (the only supported value: one thread owns the store and "
        "GL context; the tracer already uses every core)",
    )
    p.add_argument("--spp", type=positive_int, default=16, help="samples per pixel of the GI")
    p.add_argument("--latency", type=float_in(0.0), default=0.1, help="T_IL for the prefetch (s)")
    p.add_argument("--no-prefetch", action="store_true", help="render at the client's camera")
    p.add_argument("--no-denoise", action="store_true", help="serve raw (noisy) GI maps")
    add_denoise_quality_argument(p)
    p.add_argument(
        "--max-pending", type=positive_int, default=4, help="GI requests per client at once"
    )
    p.add_argument("--no-lpm", action="store_true", help="stream the full mesh as one level")
    p.add_argument(
        "--web",
        action="store_true",
        help="also serve the browser client over HTTP on the same host/port and print its URL",
    )
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")


def run(args: argparse.Namespace) -> int:
    from icbtool import net, system

    require("websockets", "icbtool serve")
    token = args.token or os.environ.get("ICBTOOL_TOKEN")
    if not token:
        raise UsageError("--token (or $ICBTOOL_TOKEN) is required")
    if args.workers != 1:
        raise UsageError("--workers: only 1 is supported (see --help)")
    if args.generator is not None and not (
        Path(args.generator).is_file() or (Path(args.generator) / "generator.pt").is_file()
    ):
        raise UsageError(f"--generator {args.generator!r}: no generator.pt there")
    if not args.no_denoise:
        require("pyoidn", "denoising the served GI maps (--no-denoise skips it)")
    if args.web:
        from icbtool.net import web

        try:
            web.check_bundle()
        except web.WebBundleMissing as e:
            raise UsageError(f"--web: {e}") from None
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s: %(message)s")
    scene = load_scene(args.scene)
    server = net.Server(
        scene,
        args.store,
        token,
        net.ServerConfig(
            host=args.host,
            port=args.port,
            max_pending=args.max_pending,
            lpm=not args.no_lpm,
            web=args.web,
        ),
        system.CloudConfig(
            prefetch=not args.no_prefetch,
            latency_s=args.latency,
            spp=args.spp,
            denoise=not args.no_denoise,
            denoise_quality=args.denoise_quality,
        ),
        generator=args.generator,
    )

    def listening(url: str) -> None:
        print(f"listening on {url}", flush=True)
        if args.web:
            from icbtool.net.web import page_url

            print(f"web client: {page_url(url, token)}", flush=True)

    server.on_listening = listening
    server.serve_forever()
    s = server.stats
    print(
        f"stopped: {s.connections} connections, {s.gi_replies} GI replies "
        f"({s.renders} renders, {s.cache_hits} hits, {s.coalesced} coalesced)",
        flush=True,
    )
    return 0
