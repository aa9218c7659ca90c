"""Beyond the paper: a generator that also reads the client's warped GI and its hole mask.

The client of ICB always holds a reference GI map (cached or streamed) warped to its view, with
holes where the reference did not see. This experiment trains the paper's best configuration (J)
twice on the same Sponza store and settings as Figure 7 (``benchmarks/gan_figure7.py``): once as
the paper does (pure generation from the client's buffers) and once with the warped reference GI
and its hole mask as 4 more input channels (``TrainConfig.warped_reference``: references drawn at
random offsets of 1-6 views along the train path; with demodulated targets the reference is
demodulated by the view's albedo too). ``--preset cpu`` (default) trains both with the measured
recipe on the train and coverage views, ``--preset paper-cpu`` as the first runs were. Then along
the whole test path, with the reference ``k`` test views earlier (k = 1, 2, 4; the JSON gives the
median number of path frames between them), it compares (display-scale SSIM / MSE against the
traced truth):

- ``generate``: the paper's pure generator;
- ``warp+inpaint``: the warped reference, holes filled by OpenCV inpainting (what the loop does
  without a generator);
- ``warp+generate``: the warped reference, holes filled by the pure generator's output;
- ``warped generator``: the generator that reads the warped reference and its holes;
- ``warp+warped generator``: the warped reference, holes filled by the warped generator;
- ``gated generator``: a third run, the warped generator with a learned per-pixel gate between
  the warped reference and what it generates (``TrainConfig.reference_gate``; its generated
  image is trained as a whole prediction too, ``weight_generated``, and a quarter of its training
  samples have no reference at all, ``reference_dropout``, as its holes have none).

Scores: SSIM / MSE of the whole frame, and the per-pixel SSIM map averaged over the holes alone
(how well each method fills what the reference did not see).

Resumable (the runs train in chunks); writes ``benchmarks/results/gan/warped/warped.{json,png}``
and ``warped_config.json``::

    ICBTOOL_GAN_STORE=STORE .venv/bin/python -m benchmarks.gan_warped --iterations 2000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument
from benchmarks.gan_figure7 import (
    add_training_arguments,
    train_config,
    train_round_robin,
)

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan" / "warped"
METHODS = (
    "generate",
    "warp+inpaint",
    "warp+generate",
    "warped generator",
    "warp+warped generator",
    "gated generator",
)


def configs(args: argparse.Namespace) -> dict:
    """The two runs' TrainConfig (one chunk; training raises ``iterations``)."""
    base = train_config(args, args.inputs)
    warped = dataclasses.replace(base, warped_reference=True, test_reference_offset=args.offsets[0])
    return {
        "pure": base,
        "warped": warped,
        "gated": dataclasses.replace(
            warped, reference_gate=True, reference_dropout=args.reference_dropout
        ),
    }


def compare(args: argparse.Namespace, runs: Path) -> dict:
    """Every method on every test view for every reference offset."""
    import icbtool.store as S
    from icbtool import metrics
    from icbtool.gan import Generator
    from icbtool.gan.data import WarpedReferences
    from icbtool.store.dataset import Dataset
    from icbtool.warp import inpaint_image

    pure, warped = Generator.load(runs / "pure"), Generator.load(runs / "warped")
    gated = Generator.load(runs / "gated")
    exposure = float(
        json.loads((runs / "pure" / "config.json").read_text())["train_config"]["display_exposure"]
    )
    ro = S.StoreConfig(readonly=True, record_hits=False)
    with S.open(args.store, ro) as store:
        ids = Dataset(store, args.scene, "test", pure.encoding.inputs).record_ids
        recs = [store.get(r) for r in ids]
        refs = WarpedReferences(store, ids)
    gen_pure = [pure.generate(r) for r in recs]
    out: dict = {"offsets": {}, "views": len(recs)}
    examples = {}
    for k in args.offsets:
        rows = {m: {"ssim": [], "mse": [], "ssim_holes": []} for m in METHODS}
        holes_pct, frames = [], []
        for i, rec in enumerate(recs):
            j = refs.reference(i, k)
            frames.append(abs(int(rec.meta.tags["index"]) - int(recs[j].meta.tags["index"])))
            img, holes = refs.warped(i, j)
            geo = rec.mask[..., 0] > 0.5
            holes_pct.append(100.0 * holes[geo].mean() if geo.any() else 0.0)
            maps = {n: getattr(rec, n) for n in warped.encoding.inputs}
            maps.update(warped_gi=img, warp_holes=holes.astype(np.float32))
            wg, gg = warped.generate(maps), gated.generate(maps)
            preds = {
                "generate": gen_pure[i],
                "warp+inpaint": inpaint_image(img, holes) if holes.any() else img,
                "warp+generate": np.where(holes[..., None], gen_pure[i], img),
                "warped generator": wg,
                "warp+warped generator": np.where(holes[..., None], wg, img),
                "gated generator": gg,
            }
            for m, p in preds.items():
                rows[m]["ssim"].append(metrics.ssim(p, rec.gi, exposure))
                rows[m]["mse"].append(metrics.mse(p, rec.gi, exposure))
                if holes.any():  # how well the holes themselves are filled
                    smap = metrics.ssim_map(p, rec.gi, exposure)
                    rows[m]["ssim_holes"].append(float(smap[holes].mean()))
            if k == args.offsets[-1] and (not examples or holes_pct[-1] > examples["holes"]):
                examples = {"i": i, "holes": holes_pct[-1], "truth": rec.gi, **preds}
        out["offsets"][str(k)] = {
            # path frames between a view and its reference (the test path's stride may vary)
            "frames_back": float(np.median(frames)),
            "holes_pct_mean": float(np.mean(holes_pct)),
            "holes_pct_max": float(np.max(holes_pct)),
            **{
                m: {
                    "ssim_mean": float(np.mean(v["ssim"])),
                    "mse_mean": float(np.mean(v["mse"])),
                    # per-pixel SSIM ('same' padding) averaged over the hole pixels of the views
                    # that have holes
                    "ssim_holes_mean": float(np.mean(v["ssim_holes"])),
                    "ssim_per_view": [float(s) for s in v["ssim"]],
                }
                for m, v in rows.items()
            },
        }
        line = ", ".join(f"{m} {np.mean(v['ssim']):.3f}" for m, v in rows.items())
        print(f"reference {k} test views back (holes {np.mean(holes_pct):.2f} %): SSIM {line}")
    out["example"] = {"view": examples["i"], "holes_pct": examples["holes"]}
    plot(out, examples, exposure, Path(args.out))
    return out


def plot(res: dict, ex: dict, exposure: float, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from icbtool.imageio import to_display

    ks = sorted(res["offsets"], key=int)
    fig = plt.figure(figsize=(16, 7))
    ax = fig.add_subplot(2, 1, 1)
    x = [res["offsets"][k]["frames_back"] for k in ks]
    for m in METHODS:
        ax.plot(x, [res["offsets"][k][m]["ssim_mean"] for k in ks], marker="o", label=m)
    ax.set(xlabel="reference age (path frames)", ylabel="test SSIM (display, 0-255)")
    ax.legend()
    ax.set_title("Sponza test path: generator with and without the warped reference")
    names = ["truth", *METHODS]
    for c, n in enumerate(names):
        a = fig.add_subplot(2, len(names), len(names) + c + 1)
        a.imshow(to_display(ex[n], exposure))
        a.set_title(n, fontsize=9)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(out / "warped.png", dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"))
    ap.add_argument("--scene", default="sponza")
    ap.add_argument("--inputs", default="J", help="configuration of both generators")
    ap.add_argument("--iterations", type=int, default=2000)
    add_training_arguments(ap)
    ap.add_argument("--offsets", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument(
        "--reference-dropout",
        type=float,
        default=0.25,
        help="the gated generator's TrainConfig.reference_dropout",
    )
    ap.add_argument("--report-only", action="store_true", help="compare the runs as they are")
    ap.add_argument("--runs", default=str(REPO / "out" / "gan_warped"))
    add_out_argument(ap, "gan/warped")
    args = ap.parse_args()
    if not args.store:
        raise SystemExit("give --store (or set ICBTOOL_GAN_STORE): a baked Sponza store")
    from icbtool.provenance import run_info, write_json

    out, runs = Path(args.out), Path(args.runs)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cfgs = configs(args)
    if not args.report_only:
        jobs = {name: (args.store, cfg, runs / name) for name, cfg in cfgs.items()}
        train_round_robin(jobs, args.iterations, args.chunk, args.scene)
    write_json(out / "warped_config.json", {"args": vars(args), "train_configs": cfgs,
                                            "run": run_info()})  # fmt: skip
    res = compare(args, runs)
    for name in cfgs:
        ev = json.loads((runs / name / "evals.json").read_text())
        res[f"evals_{name}"] = ev
    res["wall_s_this_invocation"] = time.perf_counter() - t0
    write_json(out / "warped.json", res)


if __name__ == "__main__":
    main()
