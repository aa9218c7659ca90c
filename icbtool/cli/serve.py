"""``icbtool serve``: the ICB cloud as a WebSocket server (icbtool.net.Server).

Clients authenticate with a token: --token / $ICBTOOL_TOKEN (at least 32 characters unless
--allow-weak-token; an empty one is an error), or none given: a fresh 256-bit token is
generated and printed once. They
receive the scene's mesh levels (never the full-detail
mesh's source), ask for GI maps (answered from the store or path traced, coalesced, encoded) and
the client model (--models RUN[,RUN...]: GAN and world-space radiance runs; the one whose
recorded test SSIM is best, within 0.001 the smallest, is offered as ONNX and the choice logged
with every candidate's numbers). SIGINT/SIGTERM stop it cleanly: every committed store
record is kept (exit code 0 after SIGTERM; 130 after SIGINT, as every command's Ctrl-C).
Prints ``listening on ws://HOST:PORT`` once it accepts connections.

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

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_scene_argument,
    check_out_dir,
    load_scene,
    store_holds_no_record,
)
from icbtool.cli._options import add_config
from icbtool.optional import require


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "serve",
        help="run the ICB cloud as a WebSocket server",
        description=__doc__,
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.net import ServerConfig
    from icbtool.system import CloudConfig

    add_scene_argument(p)
    p.add_argument(
        "--store", required=True, metavar="DIR", help="the cloud's CRT-buffer store directory"
    )
    p.add_argument(
        "--token",
        default=None,
        help="shared secret of the clients (default: $ICBTOOL_TOKEN, else a new 256-bit token "
        "printed once)",
    )
    p.add_argument(
        "--log-level",
        default="INFO",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        type=str.upper,
        help="logging level",
    )
    server = add_config(p, ServerConfig, defaults={"port": 8765})
    cloud = add_config(p, CloudConfig)
    p.set_defaults(func=run, server_options=server, cloud_options=cloud)


def run(args: argparse.Namespace) -> int:
    from icbtool import net
    from icbtool.net.server import MIN_TOKEN_CHARS, new_token

    require("websockets", "icbtool serve")
    server_cfg = args.server_options.build(args)  # a bad setting: one line, exit 2, no work
    cloud_cfg = args.cloud_options.build(args)
    if args.token is not None and not args.token:
        raise UsageError(
            "--token: empty; give the clients' shared secret, or leave --token out to get a "
            "256-bit one"
        )
    env_token = os.environ.get("ICBTOOL_TOKEN")
    if args.token is None and env_token is not None and not env_token:
        raise UsageError(
            "$ICBTOOL_TOKEN: set but empty; unset it to get a 256-bit token, or set it to the "
            "clients' shared secret"
        )
    token = args.token if args.token is not None else env_token
    generated = token is None
    if token is None:
        token = new_token()
    elif len(token) < MIN_TOKEN_CHARS and not server_cfg.allow_weak_token:
        raise UsageError(
            f"--token: {len(token)} characters is too short to resist offline guessing (at least "
            f"{MIN_TOKEN_CHARS}); leave it out to get a 256-bit one, or pass "
            "--allow-weak-token"
        )
    if (server_cfg.tls_cert is None) != (server_cfg.tls_key is None):
        raise UsageError("--tls-cert and --tls-key go together")
    for flag, f in (("--tls-cert", server_cfg.tls_cert), ("--tls-key", server_cfg.tls_key)):
        if f is not None and not Path(f).is_file():
            raise UsageError(f"{flag} {f!r}: no such file")
    if server_cfg.workers or server_cfg.scheduler:
        require("distributed", "render workers on Dask (--workers N / --scheduler)")
    for run in server_cfg.models:
        d = Path(run).parent if Path(run).is_file() else Path(run)
        if not ((d / "generator.pt").is_file() or (d / "radiance.pt").is_file()):
            raise UsageError(
                f"--models: {run!r} holds no generator.pt (GAN run) or radiance.pt (radiance run)"
            )
    if cloud_cfg.denoise:
        require("pyoidn", "denoising the served GI maps (--no-denoise skips it)")
    if server_cfg.web:
        from icbtool.net import web

        try:
            web.check_bundle()
        except web.WebBundleMissing as e:
            raise UsageError(f"--web: {e}") from None
    # the server writes its renders into the store: one it may only read is refused now
    check_out_dir(args.store, "--store", holds_nothing=store_holds_no_record)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s: %(message)s")
    scene = load_scene(args.scene)
    server = net.Server(scene, args.store, token, server_cfg, cloud_cfg)

    def listening(url: str) -> None:
        print(f"listening on {url}", flush=True)
        if server_cfg.web:
            from icbtool.net.web import page_url

            print(f"web client: {page_url(url, token)}", flush=True)

    if generated:  # printed once, never logged
        print(f"token: {token}", flush=True)
    server.on_listening = listening
    server.serve_forever()
    s = server.stats
    print(
        f"stopped: {s.connections} connections, {s.gi_replies} GI replies "
        f"({s.renders} renders, {s.cache_hits} hits, {s.coalesced} coalesced)",
        flush=True,
    )
    if server.stopped_by == "SIGINT":  # Ctrl-C: exit 130 like every command
        raise KeyboardInterrupt
    return 0
