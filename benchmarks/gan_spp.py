"""The cost of the data: train the GAN on GI baked at 4, 16 and 64 spp (noisy targets, no
denoiser) and on the OIDN-denoised 64 spp store, and compare test SSIM against baking time.

Each train set is Sponza's train path at 128x128 baked into its own store
(``STORES/spp<N>``, resumable: ``icbtool bake``); the test path (256 spp, denoised) is copied from
the Figure 7 store so every run is scored on the same truth. Every run uses the Figure 7 settings
(``benchmarks/gan_figure7.py``: configuration J, 64-pixel crops, base 32, HDR scale 0.05 / max 4)
for ``--iterations``. Baking time is the sum of the records' ``render_time_s`` (raster + trace (+
denoise)) measured when they were baked on this machine.

    ICBTOOL_GAN_STORE=STORE .venv/bin/python -m benchmarks.gan_spp --stores out/stores/spp

Writes ``--out/spp.{json,png}`` and ``spp_config.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import add_out_argument
from benchmarks.gan_figure7 import (
    add_training_arguments,
    train_config,
    train_round_robin,
)

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan" / "spp"
SCENE_FILE = REPO / "data" / "scenes" / "sponza.toml"


def bake_store(spp: int, store_dir: Path, test_store: str, scene: str) -> None:
    """Bake the train path at ``spp`` (resumes) and copy the test records in (once)."""
    import icbtool.store as S

    cmd = [sys.executable, "-m", "icbtool", "bake", str(SCENE_FILE), "--path", "train",
           "--store", str(store_dir), "--spp", str(spp),
           "--height", "128", "--width", "128"]  # fmt: skip
    subprocess.run(cmd, check=True)
    ro = S.StoreConfig(readonly=True, record_hits=False)
    with S.open(test_store, ro) as src, S.open(store_dir) as dst:
        have = sum(1 for i in dst if i.meta.tags.get("path") == "test")
        test = [
            i.record_id
            for i in src
            if i.meta.tags.get("path") == "test" and scene in (i.meta.scene_name, i.meta.scene_hash)
        ]
        if have == 0:
            dst.put_many([src.get(r) for r in test])
        elif have != len(test):
            raise SystemExit(f"{store_dir}: holds {have} test records, {test_store} {len(test)}")


def bake_seconds(store_dir: str, scene: str) -> tuple[float, int, list[int]]:
    import icbtool.store as S

    ro = S.StoreConfig(readonly=True, record_hits=False)
    with S.open(store_dir, ro) as st:
        infos = [
            i
            for i in st
            if i.meta.tags.get("path") == "train"
            and scene in (i.meta.scene_name, i.meta.scene_hash)
        ]
        return (
            float(sum(i.meta.render_time_s for i in infos)),
            len(infos),
            sorted({int(i.meta.spp) for i in infos}),
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"),
                    help="the Figure 7 store (denoised 64 spp train path + test path)")  # fmt: skip
    ap.add_argument("--stores", required=True, help="folder for the spp<N> train stores")
    ap.add_argument("--scene", default="sponza")
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    ap.add_argument("--inputs", default="J")
    ap.add_argument("--iterations", type=int, default=1000)
    add_training_arguments(ap)
    ap.set_defaults(preset="paper-cpu")  # its committed results: the first Figure 7 settings
    ap.add_argument("--runs", default=str(REPO / "out" / "gan_spp"))
    add_out_argument(ap, "gan/spp")
    args = ap.parse_args()
    if not args.store:
        raise SystemExit("give --store (or set ICBTOOL_GAN_STORE): the Figure 7 Sponza store")

    from icbtool.provenance import run_info, write_json

    out, runs, stores = Path(args.out), Path(args.runs), Path(args.stores)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sets = {f"{n} spp": stores / f"spp{n}" for n in args.spp}
    for n in args.spp:
        bake_store(n, sets[f"{n} spp"], args.store, args.scene)
    sets["64 spp + OIDN"] = Path(args.store)
    cfg = train_config(args, args.inputs)
    write_json(out / "spp_config.json", {"args": vars(args), "train_config": cfg,
                                         "run": run_info()})  # fmt: skip
    run_dirs = {name: runs / name.replace(" ", "_").replace("+", "") for name in sets}
    jobs = {name: (sdir, cfg, run_dirs[name]) for name, sdir in sets.items()}
    train_round_robin(jobs, args.iterations, args.chunk, args.scene)
    res: dict = {"sets": {}}
    for name, sdir in sets.items():
        ev = json.loads((run_dirs[name] / "evals.json").read_text())
        secs, n, spps = bake_seconds(str(sdir), args.scene)
        res["sets"][name] = {
            "store": str(sdir),
            "train_views": n,
            "spp": spps,
            "bake_s": secs,
            "bake_s_per_view": secs / max(n, 1),
            "iteration": [e["iteration"] for e in ev],
            "ssim": [e["ssim"] for e in ev],
            "mse": [e["mse"] for e in ev],
            "final_ssim": ev[-1]["ssim"],
            "final_mse": ev[-1]["mse"],
        }
        print(f"{name}: bake {secs:.0f} s ({n} views), test SSIM {ev[-1]['ssim']:.4f} "
              f"MSE {ev[-1]['mse']:.0f} at iteration {ev[-1]['iteration']}")  # fmt: skip
    res["wall_s_this_invocation"] = time.perf_counter() - t0
    write_json(out / "spp.json", res)
    plot(res, out / "spp.png")


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, v in res["sets"].items():
        ax[0].plot(v["iteration"], v["ssim"], marker=".", label=name)
        ax[1].scatter(v["bake_s"], v["final_ssim"], s=40)
        ax[1].annotate(name, (v["bake_s"], v["final_ssim"]), fontsize=9,
                       xytext=(4, 4), textcoords="offset points")  # fmt: skip
    ax[0].set(xlabel="iteration", ylabel="test SSIM (display, 0-255)", title="training")
    ax[0].legend()
    ax[1].set(xlabel="baking time of the train set (s, this machine)", xscale="log",
              ylabel="final test SSIM", title="cost of the data")  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
