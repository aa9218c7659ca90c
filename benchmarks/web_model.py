"""The served client model on a real scene, in the browser and in Python.

Given a scene, the store its client-model runs were trained and evaluated on (opened read-only:
only its test-path truth is read) and the runs (GAN and world-space radiance):

1. Candidates. Each run's recorded test SSIM (``evals.json``, what the server reads). A run that
   recorded none (a radiance run trained with ``eval_paths=()``) is, with --evaluate-missing,
   evaluated here exactly as its training would have (``icbtool.radiance.training
   .evaluate_views`` on every test-path record of the store) into a *copy* of the run in a
   temporary folder; the run itself is never written.
2. A server (``web=True``, a fresh temporary store: once the model is here nothing renders)
   offers the one the numbers favour; its log lines (every candidate, the choice) are kept.
3. Headless chromium (SwiftShader: no GPU here): the time from opening the page to the model in
   use (download in chunks, SHA-256, onnxruntime-web session); at each size, frames along the
   test path made with the model: the model's run time in onnxruntime-web (2 WebAssembly
   threads: the page is cross-origin isolated) and the whole frame; the page's GI on
   icbtool.raster's buffers against the Python client's ``ServedModel`` (max abs difference);
   the page's final frames against the Python client's with the same served model (SSIM).
4. The Python client's ``ServedModel.generate`` (onnxruntime, 1 thread) at each size.

Writes --out/web_model.json and web_model.csv (default out/bench/web/model).

    nice -n 10 .venv/bin/python -m benchmarks.web_model --scene data/scenes/sponza.toml \\
        --store out/stores/sponza128 --models RUN[,RUN...] --evaluate-missing
"""

from __future__ import annotations

import argparse
import base64
import csv
import json
import logging
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "web" / "model"
TOKEN = "bench-web-model-0123456789abcdef-0123456789abcdef"
BUFFERS = ("dl", "albedo", "normal_world", "normal_view", "depth", "position", "mask")


def _evaluate_copy(run: Path, store_dir: str, scene: Any, tmp: Path) -> Path:
    """A copy of a radiance run with ``evals.json`` holding its test-path evaluation."""
    from icbtool import store as store_mod
    from icbtool.radiance import RadianceModel
    from icbtool.radiance.data import records_of_path
    from icbtool.radiance.training import evaluate_views, load_views

    cfg = json.loads((run / "config.json").read_text())
    exposure = float(cfg.get("radiance_config", {}).get("display_exposure", 1.0))
    st = store_mod.open(store_dir, store_mod.StoreConfig(readonly=True, create=False))
    try:
        ids = records_of_path(st, "test", scene)
        t0 = time.perf_counter()
        m, _ = evaluate_views(RadianceModel.load(run), load_views(st, ids), exposure)
    finally:
        st.close()
    dst = tmp / run.name
    dst.mkdir(parents=True)
    for f in ("radiance.pt", "config.json"):
        shutil.copy2(run / f, dst / f)
    row = {"iteration": -1, "path": "test", **m, "seconds": time.perf_counter() - t0}
    (dst / "evals.json").write_text(json.dumps([row]))
    print(f"evaluated {run}: test SSIM {m['ssim']:.4f} over {m['views']} views (copy: {dst})")
    return dst


def _page(browser: Any, url: str) -> Any:
    page = browser.new_page(bypass_csp=True)
    page.set_default_timeout(600_000)
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    t0 = time.perf_counter()
    page.goto(url)
    page.wait_for_function("window.icb && window.icb.ready")
    page.evaluate("window.icb.ready")
    page.wait_for_function("window.icb.state.model !== null || window.icb.state.errors.length")
    page.model_s = time.perf_counter() - t0
    page.errors = errors
    return page


def _read_final(page: Any, size: int) -> np.ndarray:
    b = base64.b64decode(page.evaluate("window.icb.read('final')"))
    return np.frombuffer(b, np.float32).reshape(size, size, 4)[..., :3].copy()


def _page_gi(page: Any, wrt: Any, size: int) -> np.ndarray:
    maps = {n: base64.b64encode(np.ascontiguousarray(getattr(wrt, n), np.float32)).decode()
            for n in BUFFERS}  # fmt: skip
    got = page.evaluate(
        """async (a) => {
          const P = window.icbModules.protocol, maps = {};
          for (const [k, v] of Object.entries(a.maps)) {
            maps[k] = new Float32Array(P.unb64(v).buffer);
          }
          const r = await window.icb.state.model.generate(maps, a.n, a.n);
          return P.b64(new Uint8Array(r.gi.buffer));
        }""",
        {"maps": maps, "n": size},
    )
    return np.frombuffer(base64.b64decode(got), np.float32).reshape(size, size, 3)


def main() -> None:
    from playwright.sync_api import sync_playwright

    from icbtool import metrics, raster, system
    from icbtool.net import web
    from icbtool.net.client import NetClientConfig, NetworkSource
    from icbtool.net.client_model import ServedModel
    from icbtool.net.server import Server, ServerConfig
    from icbtool.provenance import run_info, write_json
    from icbtool.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--store", required=True, help="the runs' store (read-only: test truth)")
    ap.add_argument("--models", required=True, help="client-model runs, comma-separated")
    ap.add_argument("--evaluate-missing", action="store_true")
    ap.add_argument("--frames", type=int, default=4, help="frames along the test path per size")
    ap.add_argument("--sizes", default="128,256")
    ap.add_argument("--repeats", type=int, default=5, help="Python generate timings (median)")
    add_out_argument(ap, "web/model")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    web.check_bundle()
    scene = load_scene(args.scene)
    path = scene.paths["test"]
    sizes = [int(s) for s in args.sizes.split(",")]
    times = [float(t) for t in np.linspace(path.times[0], path.times[-1], args.frames)]
    result: dict[str, Any] = {
        "config": vars(args),
        "run_info": run_info(),
        "load_average_1min_start": os.getloadavg()[0],
        "sizes": [],
    }
    logs: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            logs.append(record.getMessage())

    lg = logging.getLogger("icbtool.net.client_model")
    lg.setLevel(logging.INFO)
    lg.addHandler(Keep())
    with tempfile.TemporaryDirectory(prefix="icb-web-model-") as tmp_s, sync_playwright() as pw:
        tmp = Path(tmp_s)
        runs = []
        for r in args.models.split(","):
            run = Path(r)
            if args.evaluate_missing and (run / "radiance.pt").is_file():
                rows = (
                    json.loads((run / "evals.json").read_text())
                    if (run / "evals.json").is_file()
                    else []
                )
                if not any(x.get("path") == "test" for x in rows):
                    run = _evaluate_copy(run, args.store, scene, tmp)
            runs.append(str(run))
        t0 = time.perf_counter()
        srv = Server(scene, tmp / "store", TOKEN, ServerConfig(web=True, models=tuple(runs)),
                     system.CloudConfig(spp=4))  # fmt: skip
        result["offer_s"] = time.perf_counter() - t0  # reading + ONNX export of every run
        result["server_log"] = list(logs)
        result["candidates"] = [c.row() for c in srv.model.candidates]
        info = srv.model.scene_info()
        result["offered"] = {k: info[k] for k in ("kind", "bytes", "chunks", "test_ssim", "inputs")}
        result["offered"]["run"] = str(srv.model.candidate.run)
        print("\n".join(logs))
        srv.start()
        browser = pw.chromium.launch(
            executable_path=web.CHROMIUM, args=list(web.HEADLESS_CHROMIUM_ARGS), headless=True
        )
        result["chromium"] = browser.version
        served = ServedModel(srv.model.data, info, threads=1)
        try:
            with NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=600)) as src:
                src.request_lpm()
                src.wait_level(max(lv["level"] for lv in src.levels))
                src.request_generator()
                assert src.wait_generator(600), "the Python client did not get the model"
                level, lscene = src.best_scene()
                for size in sizes:
                    p = path.with_intrinsics(path.intrinsics.resized(size, size))
                    url = web.page_url(srv.url, TOKEN) + f"&size={size}&test=1"
                    page = _page(browser, url)
                    page.wait_for_function(
                        "(window.icb.client.requestFinerLevels(), window.icb.state.level === "
                        "Math.max(...window.icb.client.levelsOffered))"
                    )
                    row: dict[str, Any] = {"size": size, "page_to_model_s": page.model_s}
                    with raster.Rasterizer(lscene) as rz:
                        wrt = rz.render(p.camera_at(times[len(times) // 2]))
                    want = served.generate(wrt)
                    got = _page_gi(page, wrt, size)
                    row["gi_max_abs_diff"] = float(np.abs(got - want).max())
                    row["gi_max"] = float(np.abs(want).max())
                    stats, finals = [], []
                    for k, t in enumerate(times + times):  # the second walk is reported
                        s = page.evaluate(
                            "(a) => window.icb.client.step({t: a[0], latency: 0.1, seq: a[1]})"
                            ".then(s => ({generate_ms: s.generate_ms, model_ms: s.model_ms,"
                            " raster_ms: s.raster_ms, warp_ms: s.warp_ms, bytes: s.bytes}))",
                            [t, k],
                        )
                        if k >= len(times):
                            stats.append(s)
                            finals.append(_read_final(page, size))
                    for key in ("model_ms", "generate_ms", "raster_ms", "warp_ms"):
                        row[f"page_{key}"] = statistics.median(s[key] for s in stats)
                    row["page_bytes_per_frame"] = max(s["bytes"] for s in stats)
                    ssims = []
                    with system.Client(lscene, src) as client:
                        for k, t in enumerate(times):
                            req = system.GIRequest(p.camera_at(t), time_s=t, seq=k)
                            fr = client.frame(p.camera_at(t), req)
                            ssims.append(float(metrics.ssim(finals[k], fr.final)))
                    row["final_ssim_vs_python"] = ssims
                    ms = []
                    for _ in range(args.repeats):
                        t1 = time.perf_counter()
                        served.generate(wrt)
                        ms.append(1e3 * (time.perf_counter() - t1))
                    row["python_generate_ms_1thread"] = statistics.median(ms)
                    row["page_errors"] = list(page.errors)
                    row["load_average_1min"] = os.getloadavg()[0]
                    result["sizes"].append(row)
                    print(json.dumps(row))
                    page.close()
                result["python_remote_requests"] = src.remote
        finally:
            browser.close()
            srv.stop()
    result["load_average_1min_end"] = os.getloadavg()[0]
    write_json(out / "web_model.json", result)
    with open(out / "web_model.csv", "w", newline="") as f:
        cols = [k for k in result["sizes"][0] if k not in ("final_ssim_vs_python", "page_errors")]
        w = csv.DictWriter(f, cols + ["final_ssim_min"], extrasaction="ignore")
        w.writeheader()
        for r in result["sizes"]:
            w.writerow({**r, "final_ssim_min": min(r["final_ssim_vs_python"])})
    print(f"wrote {out / 'web_model.json'}")


if __name__ == "__main__":
    main()
