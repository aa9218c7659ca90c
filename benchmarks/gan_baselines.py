"""The honest table of learned GI: every learned model next to what needs no network,
on every view of the test path and of held-out views off both paths, with each view's coverage.

Methods (rows):

- ``constant``: one colour, the train pixels' mean GI (icbtool.gan.baselines.ConstantGI);
- ``albedo x k``: k per channel fitted on the train pixels (AlbedoScaledGI);
- ``nearest irradiance``: no learning, the GI / albedo of the 8 nearest train pixels in world space
  times the pixel's albedo (NearestIrradiance);
- ``warp + inpaint``: the previous view of the same evaluation path (what a client holds when its
  cache answered one request earlier) warped to this view, holes inpainted (icbtool.warp);
- ``tracer 1 spp + OIDN``: the path tracer at 1 sample per pixel, denoised (icbtool.trace);
- every generator run given with ``--run NAME=DIR`` (icbtool.gan.Generator);
- every world-space model given with ``--radiance NAME=DIR`` (icbtool.radiance, when present).

The baselines are fitted on the paths given by ``--fit-paths`` (default: the train path alone; a
learned model trained on more, e.g. ``train,cover``, is then compared with baselines fitted on the
same: run again with ``--fit-paths train,cover``). Columns: mean SSIM / MSE (display scale 0-255)
and FLIP per evaluation path, over ALL its views, the median coverage distance (distance from a
view's pixels to the nearest pixel of the fit paths, % of the scene's diagonal), ms per frame.

    ICBTOOL_GL_BACKEND=osmesa .venv/bin/python -m benchmarks.gan_baselines --store STORE \\
        --run J=out/runs/J --tag train

Writes --out/baselines_TAG.json, .csv and .png (truth and every method on the
views with the best and worst coverage).
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "gan"


def _arrays(store, scene, paths: str, names: tuple[str, ...]):
    """(N, 3, H, W) maps ``names`` + gi + (N, 1, H, W) mask of the records of ``paths``."""
    from icbtool.store.dataset import Dataset

    ds = Dataset(store, scene, "train", names, paths={"train": paths})
    xs, gis, masks = [], [], []
    for s in ds:
        xs.append(s.inputs)
        gis.append(s.target)
        masks.append(s.mask)
    if not xs:
        raise SystemExit(f"the store has no records on path(s) {paths!r}")
    x = np.stack(xs)
    out = {n: x[:, 3 * i : 3 * i + 3] for i, n in enumerate(names)}
    return out, np.stack(gis), np.stack(masks), ds.record_ids


def _timed(fn, *a):
    t0 = time.perf_counter()
    r = fn(*a)
    return r, 1e3 * (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--store", default=os.environ.get("ICBTOOL_GAN_STORE"))
    ap.add_argument("--scene", default=str(REPO / "data" / "scenes" / "sponza.toml"))
    ap.add_argument("--fit-paths", default="train", help="paths the baselines are fitted on")
    ap.add_argument("--eval-paths", default="test,walk")
    ap.add_argument("--run", action="append", default=[], help="NAME=RUN_DIR of a generator")
    ap.add_argument("--radiance", action="append", default=[], help="NAME=RUN_DIR (world model)")
    ap.add_argument("--tracer-spp", type=int, nargs="*", default=[1])
    ap.add_argument("--no-tracer", action="store_true")
    ap.add_argument("--exposure", type=float, default=1.0)
    ap.add_argument("--tag", default="train", help="results file suffix")
    add_out_argument(ap, "gan")
    args = ap.parse_args()
    if not args.store:
        ap.error("--store (or ICBTOOL_GAN_STORE) is required")

    import icbtool as icb
    from icbtool import metrics
    from icbtool.gan.baselines import AlbedoScaledGI, ConstantGI, NearestIrradiance
    from icbtool.gan.coverage import coverage_distance
    from icbtool.gan.data import WarpedReferences
    from icbtool.provenance import run_info, write_json
    from icbtool.warp import inpaint_image

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    from icbtool.scene import load_scene

    scene = load_scene(args.scene)
    methods: dict = {}
    ro = icb.store.StoreConfig(readonly=True, create=False, record_hits=False)
    with icb.store.open(args.store, ro) as store:
        tr, gi_tr, m_tr, _ = _arrays(store, scene, args.fit_paths, ("albedo", "position",
                                                                    "normal_world"))  # fmt: skip
        methods["constant"] = ConstantGI.fit(tr["albedo"], gi_tr, m_tr)
        methods["albedo x k"] = AlbedoScaledGI.fit(tr["albedo"], gi_tr, m_tr)
        methods["nearest irradiance"] = NearestIrradiance.fit(
            tr["position"], tr["normal_world"], tr["albedo"], gi_tr, m_tr, scene.bounds
        )
        mt = m_tr[:, 0] > 0.5
        covered = tr["position"].transpose(0, 2, 3, 1)[mt][::4]
        for spec in args.run:
            name, run = spec.split("=", 1)
            methods[name] = icb.gan.Generator.load(run)
        for spec in args.radiance:
            name, run = spec.split("=", 1)
            from icbtool import radiance  # noqa: PLC0415 - optional subpackage

            methods[name] = radiance.load(run)
        if not args.no_tracer:
            from icbtool import trace

            trace.render(scene, store.get(1).camera.resized(16, 16), trace.TraceConfig(spp=1))

        results: dict = {}
        examples: dict = {}
        for path in [p for p in args.eval_paths.split(",") if p]:
            from icbtool.store.dataset import Dataset

            ids = Dataset(store, scene, "test", ("albedo",), paths={"test": path}).record_ids
            if not ids:
                print(f"no records on path {path!r}: skipped")
                continue
            recs = [store.get(r) for r in ids]
            refs = WarpedReferences(store, ids)
            rows: dict = {}
            cov = []
            for i, rec in enumerate(recs):
                geo = rec.mask[..., 0] > 0.5
                cov.append(float(np.median(coverage_distance(covered, rec.position[geo],
                                                             scene.bounds))))  # fmt: skip
                preds, ms = {}, {}
                for name, m in methods.items():
                    preds[name], ms[name] = _timed(m.generate, rec)
                j = refs.reference(i, 1)
                (img, holes), ms_w = _timed(refs.warped, i, j)
                preds["warp + inpaint"], ms_i = _timed(
                    lambda a, h: inpaint_image(a, h) if h.any() else a, img, holes
                )
                ms["warp + inpaint"] = ms_w + ms_i
                if not args.no_tracer:
                    for spp in args.tracer_spp:
                        cfg = trace.TraceConfig(spp=spp, seed=7919 * (i + 1) + spp, denoise=True)
                        r, t = _timed(trace.render, scene, rec.camera, cfg)
                        preds[f"tracer {spp} spp + OIDN"], ms[f"tracer {spp} spp + OIDN"] = r.gi, t
                for name, p in preds.items():
                    row = rows.setdefault(name, {"ssim": [], "mse": [], "flip": [], "ms": []})
                    row["ssim"].append(metrics.ssim(p, rec.gi, args.exposure))
                    row["mse"].append(metrics.mse(p, rec.gi, args.exposure))
                    row["flip"].append(metrics.flip(rec.gi, p, args.exposure))
                    row["ms"].append(ms[name])
                if i % 5 == 0:
                    print(f"{path} {i + 1}/{len(recs)}: " + ", ".join(
                        f"{n} {np.mean(r['ssim']):.3f}" for n, r in rows.items()
                    ))  # fmt: skip
            order = np.argsort(cov)
            examples[path] = [recs[order[0]], recs[order[-1]]]
            results[path] = {
                "views": len(recs),
                "coverage_median_pct": 100 * float(np.median(cov)),
                "coverage_per_view_pct": [100 * c for c in cov],
                "methods": {
                    n: {
                        "ssim": float(np.mean(r["ssim"])),
                        "mse": float(np.mean(r["mse"])),
                        "flip": float(np.mean(r["flip"])),
                        "ms_median": float(np.median(r["ms"])),
                        "ssim_per_view": [float(v) for v in r["ssim"]],
                    }
                    for n, r in rows.items()
                },
            }
        strip = []
        for ex in examples.values():
            for rec in ex:
                tiles = [rec.gi] + [methods[n].generate(rec) for n in methods]
                strip.append(np.concatenate([metrics_display(t, args.exposure) for t in tiles], 1))
    load1 = os.getloadavg()[0]
    res = {
        "fit_paths": args.fit_paths,
        "paths": results,
        "methods": list(next(iter(results.values()))["methods"]),
        "strip_columns": ["truth", *methods],
        "load_1min": [load0, load1],
    }
    write_json(out / f"baselines_{args.tag}.json", res)
    write_json(out / f"baselines_{args.tag}_config.json", {"args": vars(args), "run": run_info()})
    with open(out / f"baselines_{args.tag}.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "method", "views", "ssim", "mse", "flip", "ms_median",
                    "coverage_median_pct"])  # fmt: skip
        for path, r in results.items():
            for n, m in r["methods"].items():
                w.writerow([path, n, r["views"], f"{m['ssim']:.4f}", f"{m['mse']:.1f}",
                            f"{m['flip']:.4f}", f"{m['ms_median']:.1f}",
                            f"{r['coverage_median_pct']:.3f}"])  # fmt: skip
    if strip:
        from icbtool.imageio import write_png

        write_png(out / f"baselines_{args.tag}.png", np.concatenate(strip, 0))
    for path, r in results.items():
        print(f"\n{path}: {r['views']} views, median coverage {r['coverage_median_pct']:.2f} %")
        for n, m in sorted(r["methods"].items(), key=lambda kv: -kv[1]["ssim"]):
            print(f"  {n:28s} SSIM {m['ssim']:.3f}  MSE {m['mse']:7.1f}  FLIP {m['flip']:.3f}  "
                  f"{m['ms_median']:7.1f} ms")  # fmt: skip


def metrics_display(img: np.ndarray, exposure: float) -> np.ndarray:
    from icbtool.imageio import to_display

    return to_display(img, exposure)


if __name__ == "__main__":
    main()
