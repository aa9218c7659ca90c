"""The browser client's frame time, first frame and bytes in headless chromium.

No GPU here: chromium renders WebGL2 with SwiftShader (ANGLE's CPU Vulkan), so every browser
number is a SwiftShader number (the JSON records the GL renderer string); a GPU is one to three
orders of magnitude faster at the raster and warp stages.

1. Per stage, at 128^2 and 256^2, along the scene's test path: the WRT-buffer raster (G-buffers +
   DL in one MRT pass), the GI request (and its server / transfer parts), decode of the default
   codec, warp + combine + fill + blend, and the generator (the paper's U-Net shape, base 32,
   configuration I inputs, untrained weights: its time is a trained one's) in onnxruntime-web
   (WebAssembly, threads: the page is cross-origin isolated). The path is walked twice; the
   second walk (cache hits: the serving path, not the path tracer) is reported.
2. First frame (from opening the page to the first finished frame; median of --repeats runs)
   at 0 / 50 / 200 ms emulated round trip (the page delays each direction by half, like
   icbtool.net.shaper), with the LPM's coarsest level (the page renders as soon as level 0 is
   here and asks for the finer levels after its first frame) and with the full mesh (a server
   with lpm=False: the mesh as one level). The store is warm (the first frame's GI is a hit).
3. Bytes received per frame (gi_reply, default codecs) and for the mesh.

Writes --out/web_client.{json,csv,png}.

    nice -n 10 .venv/bin/python -m benchmarks.web_client [--scene cornell_box] [--frames 8]
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import tempfile
from pathlib import Path
from typing import Any

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "web"
TOKEN = "bench-web-" + "0" * 32  # the server refuses tokens under 32 characters
STAGES = ("raster_ms", "request_ms", "server_ms", "transfer_ms", "decode_ms", "warp_ms")


def _page(browser: Any, url: str) -> Any:
    page = browser.new_page(bypass_csp=True)  # Playwright's polling predicates are evaluated
    page.set_default_timeout(600_000)
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function("window.icb && window.icb.ready")
    page.evaluate("window.icb.ready")
    page.errors = errors
    return page


def _walk(page: Any, times: list[float], seq0: int) -> list[dict[str, Any]]:
    out = []
    for k, t in enumerate(times):
        s = page.evaluate(
            "(a) => window.icb.client.step({t: a[0], latency: 0.1, seq: a[1]})"
            ".then(s => { const c = {...s}; delete c.camera; delete c.ref_camera; return c; })",
            [t, seq0 + k],
        )
        out.append(s)
    return out


def _generator_ms(page: Any, size: int, repeats: int) -> dict[str, Any]:
    import base64

    import numpy as np
    import onnxruntime
    import torch

    from icbtool.gan import Generator
    from icbtool.gan.data import InputEncoding
    from icbtool.gan.models import GeneratorConfig, UNetGenerator

    torch.manual_seed(0)
    enc = InputEncoding(inputs=("dl", "normal_world", "depth", "albedo"))  # configuration I
    gen = Generator(UNetGenerator(GeneratorConfig(in_channels=enc.n_channels, base=32)), enc)
    with tempfile.TemporaryDirectory() as d:
        model = gen.export_onnx(Path(d) / "g.onnx", size, size).read_bytes()
    x = np.random.default_rng(0).uniform(-1, 1, (1, enc.n_channels, size, size)).astype(np.float32)
    want = onnxruntime.InferenceSession(model).run(None, {"maps": x})[0]
    res = page.evaluate(
        """async (a) => {
          const M = window.icbModules;
          const g = await M.OnnxGenerator.load(M.protocol.unb64(a.model));
          const x = new Float32Array(M.protocol.unb64(a.x).buffer);
          const ms = [];
          let y = null;
          for (let i = 0; i < a.n; i++) { y = await g.run(x, a.c, a.s, a.s); ms.push(y.ms); }
          const u8 = new Uint8Array(y.data.buffer, y.data.byteOffset, y.data.byteLength);
          return {ms, threads: g.threads, isolated: crossOriginIsolated, y: M.protocol.b64(u8)};
        }""",
        {
            "model": base64.b64encode(model).decode(),
            "x": base64.b64encode(x.tobytes()).decode(),
            "c": enc.n_channels,
            "s": size,
            "n": repeats,
        },
    )
    got = np.frombuffer(base64.b64decode(res["y"]), np.float32).reshape(want.shape)
    return {
        "median_ms": statistics.median(res["ms"][1:] or res["ms"]),
        "first_ms": res["ms"][0],
        "threads": res["threads"],
        "cross_origin_isolated": res["isolated"],
        "model_bytes": len(model),
        "max_abs_diff_vs_onnxruntime": float(np.abs(got - want).max()),
    }


def _read(page: Any, name: str, size: int) -> Any:
    import base64

    import numpy as np

    b = base64.b64decode(page.evaluate("(n) => window.icb.read(n)", name))
    return np.frombuffer(b, np.float32).reshape(size, size, 4)


def _accuracy(page: Any, srv: Any, scene: Any, times: list[float], size: int) -> dict[str, Any]:
    """The browser against icbtool: WRT-buffer vs icbtool.raster on the level held, final frames
    vs the Python client's (same path, server and seqs; SSIM on the display scale)."""
    import numpy as np

    from icbtool import metrics, raster, system
    from icbtool.net import protocol
    from icbtool.net.client import NetClientConfig, NetworkSource

    path = scene.paths["test"]
    p = path.with_intrinsics(path.intrinsics.resized(size, size))
    with NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=600)) as src:
        src.request_lpm()
        src.wait_level(max(lv["level"] for lv in src.levels))
        _, lscene = src.best_scene()
        wrt = []
        with raster.Rasterizer(lscene) as rz:
            for t in times[:: max(1, len(times) // 3)]:
                cam = p.camera_at(t)
                page.evaluate("(c) => window.icb.renderWRT(c)", protocol.camera_to_json(cam))
                al, nr, po, dl = (
                    _read(page, n, size) for n in ("albedo", "normal", "position", "dl")
                )
                ref = rz.render(cam)
                m = ref.mask[..., 0] > 0.5
                both = m & (po[..., 3] > 0)
                z = ref.depth[..., 0][both]
                cos = np.clip((nr[..., :3] * ref.normal_world).sum(-1), -1, 1)[both]
                d = np.abs(dl[..., :3] - ref.dl)[both]
                wrt.append(
                    {
                        "t": t,
                        "mask_agree": float(np.mean((po[..., 3] > 0) == m)),
                        "depth_rel_p99": float(np.percentile(np.abs(po[..., 3][both] - z) / z, 99)),
                        "normal_deg_p99": float(np.percentile(np.degrees(np.arccos(cos)), 99)),
                        "albedo_abs_mean": float(np.abs(al[..., :3] - ref.albedo)[both].mean()),
                        # None where the DL seen is 0 (no light reaches the view)
                        "dl_rel_mean": (
                            float(d.mean() / ref.dl[both].mean())
                            if ref.dl[both].mean() > 0
                            else None
                        ),
                        "dl_p99": float(np.percentile(d, 99)),
                    }
                )
        page.evaluate("() => { window.icb.client.renderer.refs.length = 0; }")
        web_final = []
        for k, t in enumerate(times):
            page.evaluate(
                "(a) => window.icb.client.step({t: a[0], latency: 0.1, seq: a[1]})", [t, k]
            )
            web_final.append(_read(page, "final", size)[..., :3].copy())
        ssim = []
        with system.Client(lscene, src) as client:
            for k, t in enumerate(times):
                t_req = max(t - 0.1, float(path.times[0]))
                v_t, v_r = p.velocity_cam(t_req)
                req = system.GIRequest(p.camera_at(t_req), v_t, v_r, t_req, seq=k)
                fr = client.frame(p.camera_at(t), req)
                ssim.append(metrics.ssim(web_final[k], fr.final))
    return {"size": size, "wrt": wrt, "ssim_final": ssim}


def _first_frame(browser: Any, url: str, rtt: float, wait_all: bool) -> dict[str, Any]:
    page = browser.new_page(bypass_csp=True)
    page.set_default_timeout(600_000)
    page.goto(url + f"&test=1&size=128&rtt={rtt:g}")
    page.wait_for_function("window.icb && window.icb.ready")
    page.evaluate("window.icb.ready")
    if wait_all:
        page.wait_for_function(
            "(window.icb.client.requestFinerLevels(), "
            "window.icb.state.level === Math.max(...window.icb.client.levelsOffered))"
        )
    mesh_ms = page.evaluate("performance.now()")
    t0 = page.evaluate("window.icb.client.path.times[0]")
    page.evaluate("(t) => window.icb.client.step({t, latency: 0.1, seq: 0})", t0)
    r = page.evaluate(
        "({ms: performance.now(), level: window.icb.state.level,"
        " lpm: window.icb.client.session.bytesReceived.lpm_chunk || 0})"
    )
    page.close()
    return {
        "rtt_ms": rtt,
        "mesh_in_hand_ms": mesh_ms,
        "first_frame_ms": r["ms"],
        "level": r["level"],
        "lpm_bytes": r["lpm"],
    }


def main() -> None:
    from playwright.sync_api import sync_playwright

    from icbtool import system
    from icbtool.net import web
    from icbtool.net.server import Server, ServerConfig
    from icbtool.provenance import run_info, write_json
    from icbtool.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="cornell_box")
    ap.add_argument("--frames", type=int, default=8, help="frames per walk of the test path")
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--rtts", default="0,50,200")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3, help="first-frame runs per setting (median)")
    add_out_argument(ap, "web")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    web.check_bundle()
    scene = load_scene(args.scene)
    path = scene.paths["test"]
    times = [
        float(t) for t in __import__("numpy").linspace(path.times[0], path.times[-1], args.frames)
    ]
    cloud = system.CloudConfig(spp=args.spp)
    result: dict[str, Any] = {
        "config": vars(args)
        | {"latency_s": 0.1, "codec": "f16m7-diff-zstd GI, f16-diff-zstd depth"},
        "run_info": run_info(),
        "load_average_1min_start": os.getloadavg()[0],
        "stages": [],
        "first_frame": [],
    }
    rows = []
    with tempfile.TemporaryDirectory(prefix="icb-web-bench-") as store, sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=web.CHROMIUM, args=list(web.HEADLESS_CHROMIUM_ARGS), headless=True
        )
        result["chromium"] = browser.version
        for lpm in (True, False):
            srv = Server(scene, store, TOKEN, ServerConfig(web=True, lpm=lpm), cloud)
            srv.start()
            try:
                url = web.page_url(srv.url, TOKEN)
                if lpm:
                    for size in [int(s) for s in args.sizes.split(",")]:
                        page = _page(browser, url + f"&test=1&size={size}")
                        page.wait_for_function(
                            "(window.icb.client.requestFinerLevels(), window.icb.state.level === "
                            "Math.max(...window.icb.client.levelsOffered))"
                        )
                        cold = _walk(page, times, 0)
                        warm = _walk(page, times, 0)
                        gen = _generator_ms(page, size, 4)
                        if size == min(int(x) for x in args.sizes.split(",")):
                            acc = _accuracy(page, srv, scene, times, size)
                            result["accuracy"] = acc
                            print(f"accuracy {acc}", flush=True)
                        gl = page.evaluate("window.icb.client.renderer.glRenderer")
                        entry = {
                            "size": size,
                            "gl_renderer": gl,
                            "median": {k: statistics.median(s[k] for s in warm) for k in STAGES},
                            "median_cold_request_ms": statistics.median(
                                s["request_ms"] for s in cold
                            ),
                            "generate": gen,
                            "gi_reply_bytes_per_frame": statistics.mean(s["bytes"] for s in warm),
                            "cache_hits_warm": sum(s["cache_hit"] for s in warm),
                            "hole_ratio_mean": statistics.mean(s["hole_ratio"] for s in warm),
                            "mesh_bytes": page.evaluate(
                                "window.icb.client.session.bytesReceived.lpm_chunk || 0"
                            ),
                            "console_errors": page.errors,
                            "load_average_1min": os.getloadavg()[0],
                        }
                        result["stages"].append(entry)
                        for walk, ss in (("cold", cold), ("warm", warm)):
                            for s in ss:
                                rows.append(
                                    {
                                        "size": size,
                                        "walk": walk,
                                        **{
                                            k: s[k]
                                            for k in (
                                                "t",
                                                *STAGES,
                                                "bytes",
                                                "cache_hit",
                                                "hole_ratio",
                                            )
                                        },
                                    }
                                )
                        page.close()
                        print(
                            f"{size}^2: {entry['median']} generate {gen['median_ms']:.0f} ms",
                            flush=True,
                        )
                for rtt in [float(r) for r in args.rtts.split(",")]:
                    reps = [
                        _first_frame(browser, url, rtt, wait_all=False) for _ in range(args.repeats)
                    ]
                    ff = sorted(reps, key=lambda f: f["first_frame_ms"])[len(reps) // 2]  # median
                    ff |= {
                        "first_frame_ms_all": [f["first_frame_ms"] for f in reps],
                        "mesh": "lpm_level0" if lpm else "full_mesh",
                        "load_average_1min": os.getloadavg()[0],
                    }
                    result["first_frame"].append(ff)
                    print(f"first frame {ff}", flush=True)
            finally:
                srv.stop()
        browser.close()
    result["load_average_1min_end"] = os.getloadavg()[0]
    write_json(out / "web_client.json", result)
    with open(out / "web_client.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(result, out / "web_client.png")
    print(f"wrote {out / 'web_client.json'}")


def _plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    stages = ("raster_ms", "decode_ms", "warp_ms")
    for i, e in enumerate(result["stages"]):
        vals = [e["median"][s] for s in stages] + [e["generate"]["median_ms"]]
        ax[0].bar([x + 0.4 * i for x in range(4)], vals, width=0.4, label=f"{e['size']}^2")
    ax[0].set_xticks([x + 0.2 for x in range(4)], ["raster", "decode", "warp", "generate"])
    ax[0].set_ylabel("ms (median, SwiftShader)")
    ax[0].set_yscale("log")
    ax[0].legend()
    ax[0].set_title("browser stage times (headless chromium, SwiftShader)")
    for mesh in ("lpm_level0", "full_mesh"):
        ff = [f for f in result["first_frame"] if f["mesh"] == mesh]
        ax[1].plot(
            [f["rtt_ms"] for f in ff], [f["first_frame_ms"] / 1e3 for f in ff], "o-", label=mesh
        )
    ax[1].set_xlabel("emulated round trip, ms")
    ax[1].set_ylabel("first frame, s")
    ax[1].legend()
    ax[1].set_title("time to first frame (128^2)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
