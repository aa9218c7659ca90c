"""The generator's frame time in onnxruntime, per architecture variant and per ONNX node.

The client runs the generator in onnxruntime (docs/design.md section 6); issue 17 asks for
<= 15 ms at 256 x 256 on one thread. For the ``cpu`` preset's generator and each variant that
changes one architecture field (:class:`icbtool.gan.models.GeneratorConfig`), this script exports
the network (random weights: the time does not depend on them; ``--run`` adds trained runs),
times ``session.run`` with 1 intra-op thread (median of ``--repeats`` after 3 warm-up calls) at
each ``--sizes``, and profiles one session per variant at the largest size (onnxruntime's
profiler: median time per node over the profiled calls), so one sees which layers cost.

    .venv/bin/python benchmarks/gan_speed.py --repeats 30

Writes benchmarks/results/gan/speed.json (and speed_config.json). Timings are taken on a shared
machine: the 1-minute load before and after each variant is recorded next to its numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"

#: The cpu preset's generator before this study: configuration J (12 channels, position in
#: 9..12), 6 octaves at full resolution, full-resolution skip with a 3 x 3 head, base 16.
BEFORE = dict(
    in_channels=12,
    base=16,
    full_res_skip=True,
    fourier_channels=(9, 12),
    fourier_octaves=6,
)

#: name -> GeneratorConfig fields changed from ``BEFORE``
VARIANTS: dict[str, dict] = {
    "before (6 octaves, full-res features, 3x3 head)": {},
    "4 octaves": {"fourier_octaves": 4},
    "1x1 reduction to 16": {"reduce": 16},
    "features at half resolution": {"fourier_resolution": "half", "skip_features": False},
    "skip without features": {"skip_features": False},
    "1x1 head": {"head_kernel": 1},
    "top width 8": {"top_width": 8},
    "1x1 head + skip without features": {"head_kernel": 1, "skip_features": False},
    "half-res features + 1x1 head": {
        "fourier_resolution": "half",
        "skip_features": False,
        "head_kernel": 1,
    },  # fmt: skip
    "half-res features + 1x1 head + top 8": {
        "fourier_resolution": "half",
        "skip_features": False,
        "head_kernel": 1,
        "top_width": 8,
    },  # fmt: skip
}


def _export(module, channels: int, side: int, path: Path) -> Path:
    import warnings

    import torch

    x = torch.zeros(1, channels, side, side)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module.eval(), (x,), str(path), dynamo=False, input_names=["maps"],
            output_names=["gi_encoded"], opset_version=17,
            dynamic_axes={"maps": {2: "h", 3: "w"}, "gi_encoded": {2: "h", 3: "w"}},
        )  # fmt: skip
    return path


def time_onnx(path: Path, channels: int, sides: list[int], repeats: int) -> dict:
    """Median ms of one-thread ``session.run`` per side, and the per-node profile at the
    largest side (node -> median ms)."""
    import onnxruntime as ort

    def session(profile_prefix: str | None = None):
        so = ort.SessionOptions()
        so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
        if profile_prefix:
            so.enable_profiling, so.profile_file_prefix = True, profile_prefix
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])

    rng = np.random.default_rng(0)
    out: dict = {"ms": {}, "load_1min": [os.getloadavg()[0]]}
    s = session()
    for side in sides:
        x = rng.uniform(-1, 1, (1, channels, side, side)).astype(np.float32)
        for _ in range(3):
            s.run(None, {"maps": x})
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            s.run(None, {"maps": x})
            ts.append(1e3 * (time.perf_counter() - t0))
        out["ms"][str(side)] = {"median": float(np.median(ts)), "min": float(np.min(ts))}
    side = max(sides)
    sp = session(str(path.with_suffix("")) + "_prof")
    x = rng.uniform(-1, 1, (1, channels, side, side)).astype(np.float32)
    for _ in range(3 + 10):
        sp.run(None, {"maps": x})
    events = json.loads(Path(sp.end_profiling()).read_text())
    per: dict = defaultdict(list)
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            per[(e["name"][: -len("_kernel_time")], e["args"].get("op_name"))].append(e["dur"])
    nodes = sorted(
        ((float(np.median(v[3:])) / 1e3, f"{op} {name}") for (name, op), v in per.items()),
        reverse=True,
    )
    out["profile_side"] = side
    out["profile_sum_ms"] = float(sum(m for m, _ in nodes))
    out["profile_top"] = [{"ms": m, "node": n} for m, n in nodes[:12]]
    out["load_1min"].append(os.getloadavg()[0])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (default: all)")
    ap.add_argument("--run", nargs="*", default=[], help="trained runs to time as they are")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--name", default="speed", help="output file stem")
    args = ap.parse_args()

    import torch

    from icbtool.gan import Generator
    from icbtool.gan.models import GeneratorConfig, UNetGenerator, init_weights
    from icbtool.provenance import run_info, write_json

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="icb-speed-"))
    res: dict = {"variants": {}, "runs": {}}
    names = args.only or list(VARIANTS)
    for k, name in enumerate(names):
        cfg = GeneratorConfig(**{**BEFORE, **VARIANTS[name]})
        m = UNetGenerator(cfg)
        init_weights(m, torch.Generator().manual_seed(0))
        p = _export(m, cfg.in_channels, max(args.sizes), tmp / f"v{k}.onnx")
        r = time_onnx(p, cfg.in_channels, args.sizes, args.repeats)
        r["config"] = asdict(cfg)
        r["parameters"] = sum(t.numel() for t in m.parameters())
        res["variants"][name] = r
        ms = "  ".join(f"{s}: {v['median']:.2f} ms" for s, v in r["ms"].items())
        print(f"{name:48s} {ms}  (load {r['load_1min'][0]:.2f}-{r['load_1min'][1]:.2f})")
    for run in args.run:
        g = Generator.load(run)
        p = g.export_onnx(tmp / f"run{len(res['runs'])}.onnx", max(args.sizes), max(args.sizes))
        r = time_onnx(p, g.encoding.n_channels, args.sizes, args.repeats)
        r["config"] = asdict(g.module.config)
        res["runs"][str(run)] = r
        ms = "  ".join(f"{s}: {v['median']:.2f} ms" for s, v in r["ms"].items())
        print(f"{run:48s} {ms}  (load {r['load_1min'][0]:.2f}-{r['load_1min'][1]:.2f})")
    out = Path(args.out)
    write_json(out / f"{args.name}.json", res)
    write_json(out / f"{args.name}_config.json", {"args": vars(args), "run": run_info()})


if __name__ == "__main__":
    main()
