"""``icbtool client``: a networked ICB client along a camera path (icbtool.net.run_client).

Connects to an ``icbtool serve`` server, receives the mesh levels (renders from the finest held),
rasterizes its WRT-buffer, asks for GI (or generates it once it holds the server's generator),
warps, combines, blends and writes the frames like ``icbtool demo``, plus the latency split
(latency.csv, latency.png) and the bytes received by kind (net_summary.json). --latency-ms and
--bandwidth-mbit emulate a network on both directions.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from icbtool._optional import require
from icbtool.cli._common import (
    UsageError,
    check_out_dir,
    float_in,
    int_at_least,
    load_scene,
    positive_int,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "client",
        help="run a networked client against an icbtool server",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("url", help="the server, ws://HOST:PORT")
    p.set_defaults(func=run)
    p.add_argument("--token", default=None, help="shared secret (default: $ICBTOOL_TOKEN)")
    p.add_argument("--out", default="out/client", help="output folder (default: out/client)")
    p.add_argument("--path", default="test", help="camera path the client follows")
    p.add_argument("--frames", type=positive_int, default=24, help="client frames along the path")
    p.add_argument("--size", type=positive_int, default=128, help="client image size (square)")
    p.add_argument("--latency", type=float_in(0.0), default=0.1, help="T_IL of the requests (s)")
    p.add_argument(
        "--latency-ms", type=float_in(0.0), default=0.0, help="emulated round-trip time (ms)"
    )
    p.add_argument(
        "--bandwidth-mbit",
        type=float_in(0.0, lo_open=True),
        default=None,
        help="emulated bandwidth per direction (Mbit/s; default unlimited)",
    )
    p.add_argument(
        "--gi-codec", default=None, help="codec asked for the GI maps (default: the library's)"
    )
    p.add_argument("--no-generator", action="store_true", help="never fetch the generator")
    p.add_argument(
        "--truth-scene",
        default=None,
        help="score frames against a trace of this (full) scene: an evaluation only",
    )
    p.add_argument(
        "--truth-every", type=int_at_least(0), default=6, help="with --truth-scene: every N-th"
    )
    p.add_argument("--timeout", type=float_in(0.0, lo_open=True), default=300.0, help="seconds")


def run(args: argparse.Namespace) -> int:
    from icbtool import net, pipeline

    require("websockets", "icbtool client")
    token = args.token or os.environ.get("ICBTOOL_TOKEN")
    if not token:
        raise UsageError("--token (or $ICBTOOL_TOKEN) is required")
    if not args.url.startswith(("ws://", "wss://")):
        raise UsageError(f"url {args.url!r} must start with ws:// or wss://")
    out = check_out_dir(args.out)
    truth = load_scene(args.truth_scene) if args.truth_scene else None
    cfg = pipeline.LoopConfig(
        path=args.path,
        frames=args.frames,
        height=args.size,
        width=args.size,
        latency_s=args.latency,
        truth_every=args.truth_every if truth is not None else 0,
    )
    ncfg = net.NetClientConfig(
        timeout_s=args.timeout,
        **({"gi_codec": args.gi_codec} if args.gi_codec else {}),
        shaper=net.ShaperConfig(latency_ms=args.latency_ms, bandwidth_mbit=args.bandwidth_mbit),
        use_generator=not args.no_generator,
    )
    try:
        rep = net.run_client(args.url, token, cfg, ncfg, out_dir=out, truth_scene=truth)
    except net.NetError as e:  # refused, unreachable, a protocol error: one line, exit 1
        print(f"icbtool client: error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(rep.loop.summary(), indent=2))
    print(json.dumps(rep.summary(), indent=2))
    print(f"outputs in {out}/ (frames/*.png, latency.csv, latency.png, net_summary.json)")
    return 0
