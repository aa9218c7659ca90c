"""The networked ICB system's latency, bytes and throughput on loopback.

1. Latency split per mode (cloud render, cache hit, local generator) and per emulated network
   (RTT / bandwidth, both directions, by the client's shaper): a server in this process (its own
   thread, the cloud on one worker thread), ``icbtool.net.run_client`` along the test path, once
   on an empty store (renders and hits) and once on the filled store (hits), then with the
   generator on offer (shipped once, then every frame generated locally).
2. Bytes per frame per mode, the generator's bytes against the GI stream's, and the frame count
   at which shipping the generator pays off (``generator bytes / GI bytes per frame``).
3. Server throughput and latency percentiles with 1, 8 and 32 concurrent clients (cache hits:
   the serving path, not the path tracer), each client sending its requests one after another.

The generator is the paper's U-Net shape (base 32, configuration I inputs) with untrained
weights: its size and its time are those of a trained one; its images are not (quality is
benchmarks/gan_*). Writes --out/net_latency.json and net_latency.png.

    nice -n 10 .venv/bin/python -m benchmarks.net_latency [--scene cornell_box] [--frames 8]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument, run_info, write_json
from icbtool import pipeline, system
from icbtool.net import NetClientConfig, NetworkSource, Server, ServerConfig, ShaperConfig
from icbtool.net.run import run_client
from icbtool.scene import load_scene

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "net"
TOKEN = "bench-token-" + "0" * 32  # the server refuses tokens under 32 characters
NETWORKS = (
    ShaperConfig(0.0, None),
    ShaperConfig(20.0, 100.0),
    ShaperConfig(100.0, 20.0),
    ShaperConfig(200.0, 10.0),
)


def write_generator(run: Path, base: int = 32) -> Path:
    """An untrained generator of the paper's shape (configuration I inputs)."""
    import torch

    from icbtool.gan.data import InputEncoding
    from icbtool.gan.models import GeneratorConfig, UNetGenerator

    enc = InputEncoding(("albedo", "dl", "normal_world", "depth"), depth_max=8.0)
    cfg = GeneratorConfig(enc.n_channels, base=base)
    torch.manual_seed(0)
    run.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "generator": UNetGenerator(cfg).state_dict(),
            "generator_config": asdict(cfg),
            "encoding": enc.to_dict(),
        },
        run / "generator.pt",
    )
    return run


def latency_runs(scene, args, tmp: Path) -> list[dict]:
    cloud = system.CloudConfig(spp=args.spp, denoise=True, denoise_quality="fast")
    loop = pipeline.LoopConfig(frames=args.frames, height=args.size, width=args.size, truth_every=0)
    gen = write_generator(tmp / "gen")
    rows = []
    for k, shape in enumerate(NETWORKS):
        store = tmp / f"store{k}"
        for phase, generator in (("cold", None), ("warm", None), ("generator", gen)):
            with Server(scene, store, TOKEN, ServerConfig(), cloud, generator=generator) as srv:
                net = NetClientConfig(shaper=shape, use_generator=generator is not None)
                rep = run_client(srv.url, TOKEN, loop, net, progress=False, wait_for_generator=True)
            s = rep.summary()
            rows.append({"network": shape.label(), "phase": phase, **s})
            print(shape.label(), phase, s["frames_by_mode"], s.get("median_request_ms"))
    return rows


def first_frame(scene, args, tmp: Path) -> list[dict]:
    """Time to the first rasterized frame: the coarsest LPM level against the full mesh (the
    LPM's finest level, same encoding), per emulated network. GI comes in parallel either way."""
    from icbtool import raster

    p = scene.paths["test"]
    cam = p.with_intrinsics(p.intrinsics.resized(args.size, args.size)).camera_at(p.times[0])
    cfg = ServerConfig(send_full_mesh=True)
    rows = []
    with Server(scene, tmp / "store_ttff", TOKEN, cfg) as srv:
        top = len(srv.mesh.levels) - 1
        for shape in NETWORKS:
            for what, low in (("lpm_level0", 0), ("full_mesh", top)):
                t0 = time.perf_counter()
                with NetworkSource(srv.url, TOKEN, NetClientConfig(shaper=shape)) as src:
                    src.request_lpm(max_level=top if low else 0, min_level=low)
                    src.wait_level(low)
                    t_mesh = time.perf_counter()
                    mesh = src.scene(low)
                    with raster.Rasterizer(mesh) as rz:
                        rz.render(cam)
                    t_frame = time.perf_counter()
                    got = sum(src.bytes_received.values())
                rows.append(
                    {
                        "network": shape.label(),
                        "mesh": what,
                        "triangles": mesh.n_triangles,
                        "bytes_received": got,
                        "mesh_in_hand_ms": 1e3 * (t_mesh - t0),
                        "first_frame_ms": 1e3 * (t_frame - t0),
                    }
                )
                print("first frame", rows[-1])
        rows.append({"lpm_build_s": srv.mesh.build_s, "levels": srv.mesh.info(cfg.chunk_bytes)})
    return rows


def throughput(scene, args, tmp: Path) -> list[dict]:
    """Cache hits from 1, 8, 32 clients at once."""
    cloud = system.CloudConfig(spp=args.spp, denoise=True, denoise_quality="fast")
    p = scene.paths["test"]
    cams = [
        p.with_intrinsics(p.intrinsics.resized(args.size, args.size)).camera_at(float(t))
        for t in np.linspace(p.times[0], p.times[-1], 4)
    ]
    reqs = [system.GIRequest(c, seq=i, depth_range=(0.3, 10.0)) for i, c in enumerate(cams)]
    out = []
    cfg = ServerConfig(max_pending=4, send_queue=8)
    with Server(scene, tmp / "store_tp", TOKEN, cfg, cloud) as srv:
        with NetworkSource(srv.url, TOKEN) as warm:  # fill the store: every later request hits
            for r in reqs:
                warm.request(r)
        for n in (1, 8, 32):
            lat: list[float] = []
            errors: list[str] = []
            lock = threading.Lock()
            barrier = threading.Barrier(n)

            def client(i: int, lat=lat, errors=errors, barrier=barrier, lock=lock) -> None:
                try:
                    with NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=300)) as src:
                        barrier.wait(120)
                        for j in range(args.requests):
                            t0 = time.perf_counter()
                            src.request(reqs[(i + j) % len(reqs)])
                            with lock:
                                lat.append(1e3 * (time.perf_counter() - t0))
                except Exception as e:  # counted
                    with lock:
                        errors.append(repr(e))

            threads = [threading.Thread(target=client, args=(i,)) for i in range(n)]
            t0 = time.perf_counter()
            for t in threads:
                t.start()
            for t in threads:
                t.join(600)
            wall = time.perf_counter() - t0
            q = np.percentile(lat, [50, 90, 99]) if lat else [float("nan")] * 3
            row = {
                "clients": n,
                "requests": len(lat),
                "errors": len(errors),
                "error_examples": errors[:3],
                "wall_s_with_connects": wall,
                "replies_per_s": len(lat) / wall,
                "p50_ms": float(q[0]),
                "p90_ms": float(q[1]),
                "p99_ms": float(q[2]),
                "mean_ms": statistics.fmean(lat) if lat else float("nan"),
            }
            out.append(row)
            print("throughput", row)
        out.append({"server_stats": asdict(srv.stats)})
    return out


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(21, 4.5))
    stages = ("lookup_ms", "cloud_render_ms", "queue_ms", "encode_ms", "transfer_ms",
              "decode_ms", "generate_ms")  # fmt: skip
    bars, labels = [], []
    for row in res["latency"]:
        for mode in ("cloud_render", "cache_hit", "generator"):
            if (row["phase"], mode) not in (
                ("cold", "cloud_render"),
                ("warm", "cache_hit"),
                ("generator", "generator"),
            ):
                continue
            vals = [row.get(f"median_{s}", {}).get(mode, 0.0) for s in stages]
            if any(vals):
                bars.append(vals)
                labels.append(f"{row['network']}\n{mode}")
    bottom = np.zeros(len(bars))
    for i, s in enumerate(stages):
        v = np.array([b[i] for b in bars])
        ax[0].bar(range(len(bars)), v, bottom=bottom, label=s.removesuffix("_ms"))
        bottom += v
    ax[0].set_xticks(range(len(bars)), labels, rotation=70, fontsize=6)
    ax[0].set_ylabel("median ms per frame")
    ax[0].set_yscale("symlog", linthresh=10)
    ax[0].legend(fontsize=7)
    ax[0].set_title("GI latency split per mode and network")
    b = res["bytes"]
    n = np.arange(0, b["break_even_frames"] * 2 + 10)
    ax[1].plot(n, n * b["gi_reply_bytes_per_frame"] / 1e6, label="GI stream (f16-zstd)")
    ax[1].plot(n, np.full(len(n), b["generator_bytes"] / 1e6), label="generator, sent once")
    ax[1].axvline(b["break_even_frames"], color="k", ls=":", label="break-even")
    ax[1].set_xlabel("remote frames")
    ax[1].set_ylabel("MB received")
    ax[1].legend(fontsize=7)
    ax[1].set_title(f"generator pays off after {b['break_even_frames']:.0f} frames")
    tp = [r for r in res["throughput"] if "clients" in r]
    ax[2].plot([r["clients"] for r in tp], [r["p50_ms"] for r in tp], "o-", label="p50")
    ax[2].plot([r["clients"] for r in tp], [r["p99_ms"] for r in tp], "s--", label="p99")
    ax2 = ax[2].twinx()
    ax2.plot([r["clients"] for r in tp], [r["replies_per_s"] for r in tp], "^-", color="C2")
    ax2.set_ylabel("replies/s (green)")
    ax[2].set_xscale("log", base=2)
    ax[2].set_xlabel("concurrent clients (cache hits, loopback)")
    ax[2].set_ylabel("request -> reply ms")
    ax[2].legend(fontsize=7)
    ax[2].set_title("server throughput")
    ff = [r for r in res["first_frame"]["runs"] if "mesh" in r]
    nets = list(dict.fromkeys(r["network"] for r in ff))
    for j, what in enumerate(("lpm_level0", "full_mesh")):
        v = [next(r["first_frame_ms"] for r in ff if r["network"] == n and r["mesh"] == what)
             for n in nets]  # fmt: skip
        tri = next(r["triangles"] for r in ff if r["mesh"] == what)
        kb = next(r["bytes_received"] for r in ff if r["mesh"] == what) / 1e3
        ax[3].bar(np.arange(len(nets)) + 0.4 * j, v, 0.4, label=f"{what}: {tri} tris, {kb:.0f} kB")
    ax[3].set_xticks(np.arange(len(nets)) + 0.2, nets, fontsize=7)
    ax[3].set_ylabel("ms to the first rasterized frame")
    ax[3].legend(fontsize=7)
    ax[3].set_title(f"first frame: LPM vs full mesh ({Path(res['first_frame']['scene']).stem})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cornell_box")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--requests", type=int, default=8, help="per client in the throughput runs")
    ap.add_argument(
        "--first-frame-scene",
        default=None,
        help="scene of the LPM vs full-mesh first-frame runs (default: Sponza when found, "
        "else --scene)",
    )
    add_out_argument(ap, "net")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    if args.first_frame_scene is None:
        sponza = Path(os.environ.get("ICBTOOL_SPONZA", REPO.parent / "shared/scenes/sponza"))
        if (sponza / "sponza_textured.obj").is_file():
            os.environ["ICBTOOL_SPONZA"] = str(sponza)
            args.first_frame_scene = str(REPO / "data" / "scenes" / "sponza.toml")
        else:
            args.first_frame_scene = args.scene
    scene = load_scene(args.scene)
    OUT.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="icb_net_bench_") as tmp:
        ttff = first_frame(load_scene(args.first_frame_scene), args, Path(tmp))
        lat = latency_runs(scene, args, Path(tmp))
        tp = throughput(scene, args, Path(tmp))
    base = next(r for r in lat if r["network"] == NETWORKS[0].label() and r["phase"] == "cold")
    gen_row = next(r for r in lat if r["phase"] == "generator")
    per_frame = base["gi_reply_bytes_per_remote_frame"]
    res = {
        "config": vars(args),
        "latency": lat,
        "bytes": {
            "gi_reply_bytes_per_frame": per_frame,
            "generator_bytes": gen_row["generator_bytes"],
            "break_even_frames": gen_row["generator_bytes"] / per_frame,
            "lpm_bytes": base["bytes_received"].get("lpm_chunk", 0),
            "scene_info_bytes": base["bytes_received"].get("scene_info", 0),
        },
        "throughput": tp,
        "first_frame": {"scene": args.first_frame_scene, "runs": ttff},
        "wall_s": time.perf_counter() - t0,
        "load_average": os.getloadavg(),
        "run_info": run_info(),
    }
    write_json(OUT / "net_latency.json", res)
    plot(res, OUT / "net_latency.png")
    print(f"wrote {OUT}/net_latency.json and .png in {res['wall_s']:.0f} s")


if __name__ == "__main__":
    main()
