"""``icbtool demo``: the main job on the built-in default scene (the Cornell box).

1. the client's buffers (DL, albedo, normals, depth, position, mask) at the default camera;
2. the ICB loop along the scene's test path (:mod:`icbtool.pipeline`): raster, cache lookup or
   cloud render at the prefetch camera, warp, combine, inpaint, DL + GI, scored against the truth;
3. with --network, the same loop across processes: an ``icbtool serve`` subprocess on a free
   loopback port and a networked client (:func:`icbtool.net.run_client`) writing into
   OUT/network what step 2 writes, plus the latency split and the bytes received by kind.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from icbtool._optional import require
from icbtool.cli._common import (
    UsageError,
    add_denoise_quality_argument,
    check_out_dir,
    float_in,
    int_at_least,
    load_scene,
    positive_int,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the main job on the default scene (Cornell box)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "scene",
        nargs="?",
        default="cornell_box",
        help="procedural scene name, scene description (.toml) or mesh file (default: cornell_box)",
    )
    p.set_defaults(func=run)
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--path", default="test", help="camera path the client follows")
    p.add_argument("--frames", type=positive_int, default=24, help="client frames along the path")
    p.add_argument("--size", type=positive_int, default=128, help="client image size (square)")
    p.add_argument("--spp", type=positive_int, default=16, help="samples per pixel of the cloud GI")
    p.add_argument(
        "--latency", type=float_in(0.0), default=0.1, help="interaction latency T_IL (s)"
    )
    p.add_argument(
        "--truth-every", type=int_at_least(0), default=6, help="score every N-th frame (0: never)"
    )
    p.add_argument(
        "--truth-spp", type=positive_int, default=128, help="samples per pixel of the truth"
    )
    p.add_argument("--no-prefetch", action="store_true", help="reference at the old camera")
    p.add_argument("--no-denoise", action="store_true", help="serve raw (noisy) GI maps")
    add_denoise_quality_argument(p)
    p.add_argument("--fresh", action="store_true", help="empty the cloud cache first")
    p.add_argument(
        "--network",
        action="store_true",
        help="also run the system across processes: a server subprocess and a client on "
        "loopback (outputs in OUT/network)",
    )
    p.add_argument(
        "--net-latency-ms", type=float_in(0.0), default=50.0, help="emulated RTT of --network"
    )
    p.add_argument(
        "--net-bandwidth-mbit",
        type=float_in(0.0, lo_open=True),
        default=50.0,
        help="emulated bandwidth of --network (Mbit/s)",
    )
    p.add_argument(
        "--generator",
        default=None,
        metavar="RUN",
        help="a trained GAN run (icbtool train): the client generates its GI with it and asks "
        "the cloud only when it cannot (the paper's rule)",
    )


def run(args: argparse.Namespace) -> int:
    import shutil

    from icbtool import imageio, pipeline, raster

    out = check_out_dir(args.out)  # before any work
    if args.generator is not None and not (Path(args.generator) / "generator.pt").is_file():
        raise UsageError(f"--generator {args.generator!r}: no generator.pt in that run directory")
    if not args.no_denoise:
        require("pyoidn", "denoising the demo's GI maps (--no-denoise skips it)")
    if args.fresh and (out / "cache").exists():
        shutil.rmtree(out / "cache")
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    print(f"scene: {scene}")
    cam = scene.default_camera
    if cam is None:
        raise ValueError(f"scene {args.scene!r} has no default camera")
    cam = cam.resized(2 * args.size, 2 * args.size)
    buf = raster.render(scene, cam)
    for name in buf.names:
        arr = getattr(buf, name)
        imageio.write_png(
            out / "buffers" / f"{name}.png",
            imageio.preview(arr, raster.PREVIEW_KIND[name], mask=buf.valid),
        )
    print(f"client buffers at the default camera -> {out / 'buffers'}")
    cfg = pipeline.LoopConfig(
        path=args.path,
        frames=args.frames,
        height=args.size,
        width=args.size,
        spp=args.spp,
        latency_s=args.latency,
        truth_every=args.truth_every,
        truth_spp=args.truth_spp,
        prefetch=not args.no_prefetch,
        denoise=not args.no_denoise,
        denoise_quality=args.denoise_quality,
        generator=args.generator,
    )
    report = pipeline.run_loop(scene, cfg, out_dir=out)
    s = report.summary()
    print(json.dumps(s, indent=2))
    if args.network:
        run_network(args, scene, cfg, out / "network")
    print(
        f"done in {time.perf_counter() - t0:.1f} s; outputs in {out}/ "
        "(frames/*.png, loop.png, summary.json, frames.csv, buffers/*.png)"
    )
    return 0


def run_network(args: argparse.Namespace, scene: object, cfg: object, out: Path) -> None:
    """Step 3: a server subprocess on a free loopback port, a client here, the server stopped
    with SIGTERM (its store kept in OUT/network/cache)."""
    import os
    import secrets
    import signal
    import subprocess
    import sys

    from icbtool import net

    require("websockets", "the networked demo (--network)")
    token = secrets.token_urlsafe(32)  # 256 bits: icbtool serve refuses short tokens
    cmd = [sys.executable, "-m", "icbtool", "serve", args.scene, "--store", str(out / "cache"),
           "--port", "0", "--spp", str(args.spp), "--latency", str(args.latency),
           "--denoise-quality", args.denoise_quality, "--log-level", "WARNING"]  # fmt: skip
    if args.no_denoise:
        cmd.append("--no-denoise")
    if args.no_prefetch:
        cmd.append("--no-prefetch")
    if args.generator is not None:
        cmd += ["--generator", args.generator]
    if args.fresh and (out / "cache").exists():
        import shutil

        shutil.rmtree(out / "cache")
    env = {**os.environ, "ICBTOOL_TOKEN": token}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if "listening on " not in line:
            raise RuntimeError(f"the server did not start: {line!r} (exit {proc.poll()})")
        url = line.split("listening on ", 1)[1].strip()
        print(f"server subprocess {proc.pid} on {url}")
        rep = net.run_client(
            url,
            token,
            cfg,
            net.NetClientConfig(
                shaper=net.ShaperConfig(
                    latency_ms=args.net_latency_ms, bandwidth_mbit=args.net_bandwidth_mbit
                ),
            ),
            out_dir=out,
            truth_scene=scene,
        )
        print(json.dumps(rep.summary(), indent=2))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
    print(f"networked run -> {out}/ (frames/*.png, latency.csv, latency.png, net_summary.json)")
