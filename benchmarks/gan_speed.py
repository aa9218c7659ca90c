"""The generator's frame time in onnxruntime, per architecture variant and per ONNX node.

The client runs the generator in onnxruntime (docs/design.md section 6); the target is
<= 15 ms at 256 x 256 on one thread. For the ``cpu`` preset's generator before the speed study
and each ablation variant that changes its architecture (benchmarks/gan_ablation.py, one change
at a time; :class:`icbtool.gan.models.GeneratorConfig`), this script exports
the network (random weights: the time does not depend on them; ``--run`` adds trained runs),
times ``session.run`` with 1 intra-op thread at each ``--sizes`` (median and min of ``--repeats``
calls after 3 warm-up calls; the models take turns call by call, so a load that comes and goes
hits them alike), and profiles one session per variant at the largest size (onnxruntime's
profiler: median time per node over the profiled calls), so one sees which layers cost.

    .venv/bin/python -m benchmarks.gan_speed --repeats 30

With ``--store`` it also times one training iteration of the preset before and after the study
(the new network trains more iterations, each cheaper).

Writes --out/speed.json (and speed_config.json). Timings are taken on a shared
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

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"

#: Ablation variants (benchmarks/gan_ablation.py) timed under their own names: the cpu preset
#: before the speed study and each change to it.
ABLATION = (
    "constant lr",
    "4 octaves",
    "1x1 reduction",
    "half-res features",
    "skip without features",
    "1x1 head",
    "top width 8",
    "half-res features + 1x1 head",
    "half-res features + 1x1 head + base 8",
)
#: Further combinations, timed only: name -> TrainConfig fields changed from "constant lr".
EXTRA: dict[str, dict] = {
    "1x1 head + skip without features": {"head_kernel": 1, "skip_features": False},
    "half-res features + 1x1 head + base 12": {
        "position_resolution": "half",
        "head_kernel": 1,
        "base": 12,
    },  # fmt: skip
    "half-res features + 1x1 head + top width 8": {
        "position_resolution": "half",
        "head_kernel": 1,
        "top_width": 8,
    },  # fmt: skip
}


def generator_config(name: str):
    """The GeneratorConfig of an ablation variant or :data:`EXTRA` entry on Sponza's
    configuration J (12 channels, positions in 9..12)."""
    import dataclasses

    from benchmarks.gan_ablation import config

    if name in EXTRA:
        tc = dataclasses.replace(config("constant lr", 3000, 500), **EXTRA[name])
    else:
        tc = config(name, 3000, 500)
    return tc.generator_config(12, (9, 12))


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


def _session(path: Path, profile_prefix: str | None = None):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
    if profile_prefix:
        so.enable_profiling, so.profile_file_prefix = True, profile_prefix
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def time_interleaved(models: dict[str, tuple[Path, int]], side: int, repeats: int) -> dict:
    """ms of one-thread ``session.run`` at ``side`` x ``side`` for every model, the models taking
    turns call by call (a load that comes and goes then hits them alike): {name: {median, min,
    cpu_median, samples}}, after 3 warm-up calls each. ``cpu_median``: the process's CPU time
    per call, which other processes on a shared machine inflate far less than wall time."""
    rng = np.random.default_rng(0)
    sess, xs, ts, cpu = {}, {}, {}, {}
    for name, (path, channels) in models.items():
        sess[name] = _session(path)
        xs[name] = rng.uniform(-1, 1, (1, channels, side, side)).astype(np.float32)
        for _ in range(3):
            sess[name].run(None, {"maps": xs[name]})
        ts[name], cpu[name] = [], []
    for _ in range(repeats):
        for name in models:
            c0, t0 = time.process_time(), time.perf_counter()
            sess[name].run(None, {"maps": xs[name]})
            ts[name].append(1e3 * (time.perf_counter() - t0))
            cpu[name].append(1e3 * (time.process_time() - c0))
    return {
        n: {
            "median": float(np.median(v)),
            "min": float(np.min(v)),
            "cpu_median": float(np.median(cpu[n])),
            "samples": len(v),
        }
        for n, v in ts.items()
    }


def profile_nodes(path: Path, channels: int, side: int, calls: int = 10) -> dict:
    """onnxruntime's per-node profile at ``side``: the 12 costliest nodes (median ms over
    ``calls`` profiled calls after 3 warm-up calls) and the sum over all nodes."""
    sp = _session(path, str(path.with_suffix("")) + "_prof")
    x = np.random.default_rng(0).uniform(-1, 1, (1, channels, side, side)).astype(np.float32)
    for _ in range(3 + calls):
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
    return {
        "side": side,
        "sum_ms": float(sum(m for m, _ in nodes)),
        "top": [{"ms": m, "node": n} for m, n in nodes[:12]],
    }


def iteration_ms(store_dir: str, scene: str, names: list[str], n: int = 100) -> dict:
    """Training cost per iteration of ablation variants on a store: wall and CPU ms of one
    generator update (median conditions: one torch thread, after 5 warm-up updates, mean of
    ``n``), from the training loop's own state (``icbtool.gan.training.TrainingRun``)."""
    import tempfile as tf

    import torch

    import icbtool.store as S
    from benchmarks.gan_ablation import config
    from icbtool.gan.training import TrainingRun

    torch.set_num_threads(1)
    out = {}
    ro = S.StoreConfig(readonly=True, record_hits=False)
    with S.open(store_dir, ro) as st:
        for name in names:
            run = TrainingRun(
                st, config(name, 3000, 500), Path(tf.mkdtemp(prefix="icb-it-")), scene
            )
            for _ in range(5):
                run.iteration()
            load0, c0, t0 = os.getloadavg()[0], time.process_time(), time.perf_counter()
            for _ in range(n):
                run.iteration()
            out[name] = {
                "ms": 1e3 * (time.perf_counter() - t0) / n,
                "cpu_ms": 1e3 * (time.process_time() - c0) / n,
                "iterations_timed": n,
                "load_1min": [load0, os.getloadavg()[0]],
            }
            print(
                f"{name:48s} {out[name]['ms']:.1f} ms ({out[name]['cpu_ms']:.1f} CPU) / iteration"
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--only", nargs="*", default=None, help="variant names (default: all)")
    ap.add_argument("--run", nargs="*", default=[], help="trained runs to time as they are")
    ap.add_argument("--runs-only", action="store_true", help="time the --run runs alone")
    add_out_argument(ap, "gan")
    ap.add_argument("--name", default="speed", help="output file stem")
    ap.add_argument("--store", default=None, help="also time a training iteration on this store")
    ap.add_argument("--scene", default="sponza")
    ap.add_argument(
        "--iteration-variants", nargs="*",
        default=["constant lr", "half-res features + 1x1 head + base 8, 12000 iterations"],
    )  # fmt: skip
    args = ap.parse_args()

    import torch

    from icbtool.gan import Generator
    from icbtool.gan.models import UNetGenerator, init_weights
    from icbtool.provenance import run_info, write_json

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="icb-speed-"))
    res: dict = {"variants": {}, "runs": {}, "load_1min": [os.getloadavg()[0]]}
    models: dict[str, tuple[Path, int]] = {}
    variants = [] if args.runs_only else (args.only or [*ABLATION, *EXTRA])
    for k, name in enumerate(variants):
        cfg = generator_config(name)
        m = UNetGenerator(cfg)
        init_weights(m, torch.Generator().manual_seed(0))
        models[name] = (_export(m, cfg.in_channels, max(args.sizes), tmp / f"v{k}.onnx"), 12)
        res["variants"][name] = {
            "config": asdict(cfg),
            "parameters": sum(t.numel() for t in m.parameters()),
            "ms": {},
        }
    for k, run in enumerate(args.run):
        g = Generator.load(run)
        p = g.export_onnx(tmp / f"run{k}.onnx", max(args.sizes), max(args.sizes))
        models[f"run {run}"] = (p, g.encoding.n_channels)
        res["runs"][str(run)] = {"config": asdict(g.module.config), "ms": {}}
    for side in args.sizes:
        load0 = os.getloadavg()[0]
        ms = time_interleaved(models, side, args.repeats)
        for name, v in ms.items():
            entry = res["runs"][name[4:]] if name.startswith("run ") else res["variants"][name]
            entry["ms"][str(side)] = {**v, "load_1min": [load0, os.getloadavg()[0]]}
    for name, (path, channels) in models.items():
        entry = res["runs"][name[4:]] if name.startswith("run ") else res["variants"][name]
        entry["profile"] = profile_nodes(path, channels, max(args.sizes))
        line = "  ".join(
            f"{s}: {v['median']:.1f} (min {v['min']:.1f}, cpu {v['cpu_median']:.1f}) ms"
            for s, v in entry["ms"].items()
        )
        print(f"{name:48s} {line}")
    if args.store:
        res["iteration"] = iteration_ms(args.store, args.scene, args.iteration_variants)
    res["load_1min"].append(os.getloadavg()[0])
    print(f"1-minute load {res['load_1min'][0]:.2f} -> {res['load_1min'][1]:.2f}")
    out = Path(args.out)
    write_json(out / f"{args.name}.json", res)
    write_json(out / f"{args.name}_config.json", {"args": vars(args), "run": run_info()})


if __name__ == "__main__":
    main()
