"""``icbtool serve``: the ICB cloud as a WebSocket server (icbtool.net.Server).

Clients authenticate with a token: --token / $ICBTOOL_TOKEN (at least 32 characters unless
--allow-weak-token), or none given: a fresh 256-bit token is generated and printed once. They
receive the scene's mesh levels (never the full-detail
mesh's source), ask for GI maps (answered from the store or path traced, coalesced, encoded) and
the generator (--generator, sent once). SIGINT/SIGTERM stop it cleanly: every committed store
record is kept. Prints ``listening on ws://HOST:PORT`` once it accepts connections.
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
        help="shared secret of the clients (default: $ICBTOOL_TOKEN, else a new 256-bit token "
        "printed once)",
    )
    p.add_argument(
        "--allow-weak-token",
        action="store_true",
        help="accept a token under 32 characters (it can be guessed offline from one recorded "
        "handshake: docs/protocol.md, Threat model)",
    )
    p.add_argument(
        "--tls-cert", default=None, help="PEM certificate: serve wss:// (with --tls-key)"
    )
    p.add_argument("--tls-key", default=None, help="PEM private key of --tls-cert")
    p.add_argument("--generator", default=None, metavar="RUN", help="a trained GAN run to offer")
    p.add_argument(
        "--workers",
        type=int_at_least(0),
        default=0,
        help="render workers: 0 renders in this process; N starts a local Dask cluster of N "
        "worker processes on 127.0.0.1 (needs the 'cloud' extra)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="render on an existing Dask cluster (e.g. tcp://10.0.0.5:8786) instead",
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
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")


def run(args: argparse.Namespace) -> int:
    from icbtool import net, system
    from icbtool.net.server import MIN_TOKEN_CHARS, new_token

    require("websockets", "icbtool serve")
    token = args.token or os.environ.get("ICBTOOL_TOKEN")
    generated = not token
    if generated:
        token = new_token()
    elif len(token) < MIN_TOKEN_CHARS and not args.allow_weak_token:
        raise UsageError(
            f"--token: {len(token)} characters is too short to resist offline guessing (at least "
            f"{MIN_TOKEN_CHARS}); leave it out to get a 256-bit one, or pass "
            "--allow-weak-token"
        )
    if (args.tls_cert is None) != (args.tls_key is None):
        raise UsageError("--tls-cert and --tls-key go together")
    for flag, f in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
        if f is not None and not Path(f).is_file():
            raise UsageError(f"{flag} {f!r}: no such file")
    if args.workers or args.scheduler:
        require("distributed", "render workers on Dask (--workers N / --scheduler)")
    if args.generator is not None and not (
        Path(args.generator).is_file() or (Path(args.generator) / "generator.pt").is_file()
    ):
        raise UsageError(f"--generator {args.generator!r}: no generator.pt there")
    if not args.no_denoise:
        require("pyoidn", "denoising the served GI maps (--no-denoise skips it)")
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
            workers=args.workers,
            scheduler=args.scheduler,
            tls_cert=args.tls_cert,
            tls_key=args.tls_key,
            allow_weak_token=args.allow_weak_token,
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
    if generated:  # printed once, never logged
        print(f"token: {token}", flush=True)
    server.on_listening = lambda url: print(f"listening on {url}", flush=True)
    server.serve_forever()
    s = server.stats
    print(
        f"stopped: {s.connections} connections, {s.gi_replies} GI replies "
        f"({s.renders} renders, {s.cache_hits} hits, {s.coalesced} coalesced)",
        flush=True,
    )
    return 0
