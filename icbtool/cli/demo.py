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

from icbtool.cli._common import (
    UsageError,
    add_command,
    add_out_argument,
    add_scene_argument,
    check_out_dir,
    load_scene,
)
from icbtool.cli._options import ConfigOptions, add_config
from icbtool.optional import require


def register(sub: argparse._SubParsersAction) -> None:
    add_command(
        sub,
        "demo",
        help="run the main job on the default scene (Cornell box)",
        description=__doc__,
        options=_options,
    )


def _options(p: argparse.ArgumentParser) -> None:
    from icbtool.net.shaper import ShaperConfig
    from icbtool.pipeline import LoopConfig

    add_scene_argument(p, optional=True)
    add_out_argument(p, default="out/demo")
    p.add_argument("--fresh", action="store_true", help="empty the cloud cache first")
    p.add_argument(
        "--network",
        action="store_true",
        help="also run the system across processes: a server subprocess and a client on "
        "loopback (outputs in OUT/network)",
    )
    loop = add_config(p, LoopConfig)
    shaper = add_config(
        p,
        ShaperConfig,
        prefix="net-",
        defaults={"latency_ms": 50.0, "bandwidth_mbit": 50.0},
        title="the emulated network of --network (ShaperConfig)",
    )
    p.set_defaults(func=run, loop_options=loop, shaper_options=shaper)


def run(args: argparse.Namespace) -> int:
    import shutil

    from icbtool import imageio, pipeline, raster

    cfg = args.loop_options.build(args)  # a bad setting: one line, exit 2, before any work
    shaper = args.shaper_options.build(args)
    out = check_out_dir(args.out)
    if cfg.generator is not None and not (Path(cfg.generator) / "generator.pt").is_file():
        raise UsageError(f"--generator {cfg.generator!r}: no generator.pt in that run directory")
    if cfg.cloud.denoise:
        require("pyoidn", "denoising the demo's GI maps (--no-denoise skips it)")
    if args.fresh and (out / "cache").exists():
        shutil.rmtree(out / "cache")
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    print(f"scene: {scene}")
    cam = scene.default_camera
    if cam is None:
        raise ValueError(f"scene {args.scene!r} has no default camera")
    cam = cam.resized(2 * cfg.height, 2 * cfg.width)
    buf = raster.render(scene, cam)
    for name in buf.names:
        arr = getattr(buf, name)
        imageio.write_png(
            out / "buffers" / f"{name}.png",
            imageio.preview(arr, raster.PREVIEW_KIND[name], mask=buf.valid),
        )
    print(f"client buffers at the default camera -> {out / 'buffers'}")
    report = pipeline.run_loop(scene, cfg, out_dir=out)
    s = report.summary()
    if args.network:
        run_network(args, scene, cfg, shaper, out / "network")
    noise = pipeline.truth_noise_ssim(scene, cfg) if cfg.truth_every else None
    print(
        f"done in {time.perf_counter() - t0:.1f} s; outputs in {out}/ "
        "(frames/*.png, loop.png, summary.json: every number, frames.csv, buffers/*.png)"
    )
    print(verdict(s, noise, cfg.truth_spp))
    return 0


def verdict(summary: dict, truth_noise: float | None, truth_spp: int) -> str:
    """The main job's result for people: a short table of what matters, each with what a good
    value is (the whole summary is in summary.json).

    Args:
        summary: :meth:`icbtool.pipeline.LoopReport.summary`.
        truth_noise: :func:`icbtool.pipeline.truth_noise_ssim` (None: no truth rendered).
        truth_spp: samples per pixel of the truth.

    Returns:
        The table, lines joined by newlines.
    """

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    final = summary.get("mean_ssim_final_vs_truth")
    dl = summary.get("mean_ssim_dl_only_vs_truth")
    holes = summary.get("mean_hole_ratio_combined")
    rows = [
        ("final SSIM vs truth", num(final, ".3f"), "higher is better; 1 = the truth"),
        ("  DL only (no cloud)", num(dl, ".3f"), "the final must beat it: the GI's gain"),
        (
            f"  truth vs truth ({truth_spp} spp)",
            num(truth_noise, ".3f"),
            "the truth's own noise: the best any frame can score",
        ),
        (
            "cache hit rate",
            num(summary.get("cache_hit_rate"), ".0%"),
            "frames answered from the store; higher = fewer cloud renders",
        ),
        (
            "holes after combining",
            num(holes, ".1%"),
            "pixels no reference saw (inpainted); below 5 % is good",
        ),
        (
            "cloud render on a miss",
            num(summary.get("median_cloud_render_on_miss_ms"), ".0f") + " ms",
            "median; the prefetch hides it up to the latency",
        ),
        (
            "client raster + warp",
            num(_add(summary.get("median_raster_ms"), summary.get("median_warp_ms")), ".0f")
            + " ms",
            "median per frame; below 33 ms keeps 30 fps",
        ),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    lines = ["verdict", *(f"  {a:<{w0}}  {b:>{w1}}  {c}" for a, b, c in rows)]
    if final is not None and dl is not None:
        gain = final - dl
        below = None if truth_noise is None else truth_noise - final
        ceiling = "" if below is None else f", {below:.3f} below the truth's own noise"
        word = "helps" if gain > 0 else "does NOT help"
        lines.append(f"  the cloud's GI {word}: SSIM {gain:+.3f} over DL alone{ceiling}")
    return "\n".join(lines)


def _add(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a + b


def run_network(
    args: argparse.Namespace, scene: object, cfg: object, shaper: object, out: Path
) -> None:
    """Step 3: a server subprocess on a free loopback port, a client here, the server stopped
    with SIGTERM (its store kept in OUT/network/cache)."""
    import os
    import signal
    import subprocess
    import sys

    from icbtool import net
    from icbtool.net.server import new_token

    require("websockets", "the networked demo (--network)")
    token = new_token()  # 256 bits: icbtool serve refuses short tokens
    cmd = [sys.executable, "-m", "icbtool", "serve", args.scene, "--store", str(out / "cache"),
           "--port", "0", "--log-level", "WARNING"]  # fmt: skip
    cmd += config_argv(cfg.cloud, args.loop_options, "cloud")  # the same cloud settings
    if cfg.generator is not None:
        cmd += ["--models", cfg.generator]
    if args.fresh and (out / "cache").exists():
        import shutil

        shutil.rmtree(out / "cache")
    env = {**os.environ, "ICBTOOL_TOKEN": token}
    # a process group of its own: a Ctrl-C in the terminal interrupts the demo, which then
    # stops the server (SIGTERM below), instead of both saying so
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True, process_group=0)
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
            net.NetClientConfig(shaper=shaper),
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


def config_argv(config: object, options: ConfigOptions, part: str) -> list[str]:
    """The command-line options that give every field of ``config`` (the nested config
    ``part`` of ``options``' class) its value: the same spellings on every command."""
    argv: list[str] = []
    for f in options.fields:
        if f.path[:-1] != (part,):
            continue
        v = getattr(config, f.path[-1])
        if isinstance(v, bool):
            argv.append(f.option if v else "--no-" + f.option[2:])
        elif v is not None:
            argv += [f.option, ",".join(map(str, v)) if isinstance(v, tuple) else str(v)]
    return argv
