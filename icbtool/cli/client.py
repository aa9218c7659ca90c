"""``icbtool client``: a networked ICB client along a camera path (icbtool.net.run_client).

Connects to an ``icbtool serve`` server, receives the mesh levels (renders from the finest held),
rasterizes its WRT-buffer, asks for GI (or generates it once it holds the server's generator),
warps, combines, blends and writes the frames like ``icbtool demo``, plus the latency split
(latency.csv, latency.png) and the bytes received by kind (net_summary.json). --net-latency-ms and
--net-bandwidth-mbit emulate a network on both directions. A ``wss://`` server whose certificate
is not in the system's trust store (e.g. self-signed): --tls-ca FILE names the PEM to trust.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_out_argument,
    check_out_dir,
    load_scene,
    scene_spec,
)
from icbtool.cli._options import Spelling, add_config
from icbtool.optional import require


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "client",
        help="run a networked client against an icbtool server",
        description=__doc__,
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.net import NetClientConfig
    from icbtool.pipeline import LoopConfig

    p.add_argument("url", help="the server, ws://HOST:PORT (wss:// with TLS)")
    p.add_argument("--token", default=None, help="shared secret (default: $ICBTOOL_TOKEN)")
    add_out_argument(p, default="out/client")
    p.add_argument(
        "--truth-scene",
        default=None,
        type=scene_spec,
        metavar="SCENE",
        help="score frames against a trace of this (full) scene: an evaluation only "
        "(default: no scoring)",
    )
    loop = add_config(
        p,
        LoopConfig,
        only=("path", "frames", "height", "width", "cloud.latency_s", "cloud.seed", "truth_every"),
        title="the client's path (LoopConfig; the server has the cloud's other settings)",
    )
    net = add_config(
        p,
        NetClientConfig,
        defaults={"timeout_s": 300.0},
        spell={  # the emulated network: the same spelling as `icbtool demo --network`
            "shaper.latency_ms": Spelling(option="--net-latency-ms"),
            "shaper.bandwidth_mbit": Spelling(option="--net-bandwidth-mbit"),
            # TLS options share their prefix with `icbtool serve --tls-cert/--tls-key`
            "ca_file": Spelling(option="--tls-ca", metavar="FILE"),
        },
    )
    p.set_defaults(func=run, loop_options=loop, net_options=net)


def run(args: argparse.Namespace) -> int:
    from icbtool import net

    require("websockets", "icbtool client")
    token = args.token or os.environ.get("ICBTOOL_TOKEN")
    if not token:
        raise UsageError("--token (or $ICBTOOL_TOKEN) is required")
    if not args.url.startswith(("ws://", "wss://")):
        raise UsageError(f"url {args.url!r} must start with ws:// or wss://")
    cfg = args.loop_options.build(args)
    ncfg = args.net_options.build(args)
    if ncfg.ca_file is not None:
        if not args.url.startswith("wss://"):
            raise UsageError(f"--tls-ca applies to wss:// servers, not {args.url!r}")
        if not os.path.isfile(ncfg.ca_file):
            raise UsageError(f"--tls-ca {ncfg.ca_file!r}: no such file")
    out = check_out_dir(args.out)
    truth = load_scene(args.truth_scene) if args.truth_scene else None
    if truth is None:
        cfg = dataclasses.replace(cfg, truth_every=0)
    try:
        rep = net.run_client(args.url, token, cfg, ncfg, out_dir=out, truth_scene=truth)
    except net.NetError as e:  # refused, unreachable, a protocol error: one line, exit 1
        print(f"icbtool client: error: {e}", file=sys.stderr)
        return 1
    print(json.dumps(rep.loop.summary(), indent=2))
    print(json.dumps(rep.summary(), indent=2))
    print(f"outputs in {out}/ (frames/*.png, latency.csv, latency.png, net_summary.json)")
    return 0
