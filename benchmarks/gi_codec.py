"""GI and depth codecs of the ICB protocol (icbtool.net.codec): bytes per frame against error and
time, on real GI maps, to choose the defaults.

Maps: GI path-traced at ``--spp`` and denoised with OIDN as ``CloudConfig`` renders it, plus
the same GI undenoised; depth (view-space z) from a primary Embree ray cast at pixel centres, with
0 where no surface as the CRT-buffers store it, and again with inf, for ``--views``
cameras of the ``test`` path of the built-in Cornell box, and of Sponza when it exists
(``ICBTOOL_SPONZA`` or ../shared/scenes/sponza), at 256 x 256.

Per codec and map kind: bytes per frame (median over the views, and the mean), compression ratio
against raw float32, display-scale SSIM and MSE against the original (icbtool.metrics,
exposure 1; 1.0 / 0.0 for exact codecs), the largest relative error on values in [2^-14, 65504]
and, for GI, relative to the pixel's largest channel (RGBE's bound),
encode / decode time (median of ``--reps`` runs, one thread, on a machine shared with other
jobs: compare codecs, not machines). Depth: bytes, largest relative error on surface pixels,
whether 0 and inf stay exact (depth is also coded with inf where no surface). Ablations of
``f16-zstd`` / ``f32-zstd``: byte shuffle on/off and zstd levels.

Writes --out/gi_codec.{json,csv,png} (+ _config.json).

    ICBTOOL_SPONZA=../shared/scenes/sponza nice -n 10 .venv/bin/python -m benchmarks.gi_codec
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "net"
#: Largest relative error is measured on values in this range (float16's normal range).
NORMAL_RANGE = (2.0**-14, 65504.0)


def sponza_dir() -> Path | None:
    for p in (os.environ.get("ICBTOOL_SPONZA"), REPO.parent / "shared" / "scenes" / "sponza"):
        if p and (Path(p) / "sponza_textured.obj").is_file():
            return Path(p)
    return None


def render_maps(scene, cams, spp: int, seed: int) -> list[dict[str, np.ndarray]]:
    """Per view: denoised and raw GI (one trace, as CloudConfig renders), depth (0 and inf where
    no surface) from a primary Embree ray cast at pixel centres."""
    from icbtool.scene.raycast import EmbreeScene
    from icbtool.trace import TraceConfig, render

    es = EmbreeScene.from_scene(scene)
    out = []
    for k, cam in enumerate(cams):
        t0 = time.perf_counter()
        tr = render(scene, cam, TraceConfig(spp=spp, seed=seed + k, denoise=True))
        o, d, dpd = cam.rays()
        hits = es.intersect(o.reshape(-1, 3), d.reshape(-1, 3))
        z = (hits.t.astype(np.float64) * dpd.reshape(-1)).reshape(cam.height, cam.width)
        hit = hits.hit.reshape(cam.height, cam.width)
        out.append(
            {
                "gi_denoised": np.asarray(tr.gi, np.float32),
                "gi_raw": np.asarray(tr.gi_raw, np.float32),
                "depth": np.where(hit, z, 0.0).astype(np.float32),
                "depth_inf": np.where(hit, z, np.inf).astype(np.float32),
            }
        )
        print(f"  view {k}: rendered in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def _timed(fn, reps: int) -> tuple[float, object]:
    ts, r = [], None
    for _ in range(reps):
        t0 = time.perf_counter()
        r = fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts)), r


def variants():
    """(name, encode(a) -> bytes, decode(b, shape) -> array, for_depth) of every codec and
    ablation."""
    import zstandard

    from icbtool.net import codec

    out = []
    for name, c in codec.CODECS.items():
        out.append(
            (
                name,
                lambda a, n=name: codec.encode(a, n),
                lambda b, s, n=name: codec.decode(b, n, s),
                c.for_depth,
            )
        )

    def plain(dt: str, level: int, shuffle: bool):
        size = np.dtype(dt).itemsize

        def enc(a):
            x = np.where(np.isfinite(a), np.clip(a, -65504, 65504), a) if dt == "<f2" else a
            raw = x.astype(dt).tobytes()
            raw = codec.shuffle(raw, size) if shuffle else raw
            return zstandard.ZstdCompressor(level=level).compress(raw)

        def dec(b, s):
            raw = zstandard.ZstdDecompressor().decompress(b)
            raw = codec.unshuffle(raw, size) if shuffle else raw
            return np.frombuffer(raw, dt).astype(np.float32).reshape(s)

        return enc, dec

    for dt, base in (("<f2", "f16-zstd"), ("<f4", "f32-zstd")):
        for level, shuffle in ((3, False), (1, True), (9, True), (19, True)):
            tag = f"{base}/L{level}" + ("" if shuffle else "/noshuffle")
            enc, dec = plain(dt, level, shuffle)
            out.append((tag, enc, dec, True))
    return out


def measure(maps: list[dict[str, np.ndarray]], scene_name: str, reps: int) -> list[dict]:
    from icbtool import metrics

    rows = []
    for name, enc, dec, for_depth in variants():
        kinds = ["gi_denoised", "gi_raw"] + (["depth", "depth_inf"] if for_depth else [])
        for kind in kinds:
            per_view = []
            for m in maps:
                a = m[kind]
                t_enc, blob = _timed(lambda a=a, enc=enc: enc(a), reps)
                t_dec, b = _timed(lambda blob=blob, a=a, dec=dec: dec(blob, a.shape), reps)
                b = np.asarray(b)
                lo, hi = NORMAL_RANGE
                sel = np.isfinite(a) & (np.abs(a) >= lo) & (np.abs(a) <= hi)
                rel = np.abs(b[sel] - a[sel]) / np.abs(a[sel])
                r = {
                    "bytes": len(blob),
                    "encode_ms": t_enc,
                    "decode_ms": t_dec,
                    "max_rel_error": float(rel.max()) if rel.size else 0.0,
                    "mean_rel_error": float(rel.mean()) if rel.size else 0.0,
                    "exact": bool(a.tobytes() == b.astype(np.float32).tobytes()),
                }
                if kind.startswith("gi"):
                    pix_max = np.maximum(np.abs(a).max(axis=-1, keepdims=True), lo)
                    r["max_pixel_rel_error"] = float((np.abs(b - a) / pix_max)[a >= 0].max())
                    r["ssim"] = 1.0 if r["exact"] else metrics.ssim(a, b)
                    r["mse"] = 0.0 if r["exact"] else metrics.mse(a, b)
                    r["rmse_linear_rel"] = float(
                        np.sqrt(np.mean((b - a) ** 2)) / max(np.sqrt(np.mean(a**2)), 1e-30)
                    )
                else:
                    r["zero_kept"] = bool(np.array_equal(a == 0, b == 0))
                    r["inf_kept"] = bool(np.array_equal(np.isposinf(a), np.isposinf(b)))
                per_view.append(r)
            raw = maps[0][kind].astype(np.float32).nbytes
            row = {
                "scene": scene_name,
                "map": kind,
                "codec": name,
                "shape": list(maps[0][kind].shape),
                "views": len(maps),
                "bytes_median": float(np.median([r["bytes"] for r in per_view])),
                "bytes_mean": float(np.mean([r["bytes"] for r in per_view])),
                "ratio_vs_f32": raw / float(np.mean([r["bytes"] for r in per_view])),
                "encode_ms": float(np.median([r["encode_ms"] for r in per_view])),
                "decode_ms": float(np.median([r["decode_ms"] for r in per_view])),
                "max_rel_error": max(r["max_rel_error"] for r in per_view),
                "mean_rel_error": float(np.mean([r["mean_rel_error"] for r in per_view])),
                "exact": all(r["exact"] for r in per_view),
            }
            if kind.startswith("gi"):
                row["max_pixel_rel_error"] = max(r["max_pixel_rel_error"] for r in per_view)
                row["ssim_min"] = min(r["ssim"] for r in per_view)
                row["ssim_mean"] = float(np.mean([r["ssim"] for r in per_view]))
                row["mse_max"] = max(r["mse"] for r in per_view)
                row["rmse_linear_rel"] = float(np.mean([r["rmse_linear_rel"] for r in per_view]))
            else:
                row["zero_kept"] = all(r["zero_kept"] for r in per_view)
                row["inf_kept"] = all(r["inf_kept"] for r in per_view)
            rows.append(row)
            print(
                f"  {scene_name:11s} {kind:12s} {name:24s} {row['bytes_median'] / 1024:8.1f} KiB "
                f"x{row['ratio_vs_f32']:5.2f} enc {row['encode_ms']:6.2f} ms dec "
                f"{row['decode_ms']:6.2f} ms rel {row['max_rel_error']:.2e}"
                + (f" ssim {row['ssim_min']:.5f}" if "ssim_min" in row else ""),
                flush=True,
            )
    return rows


def choose(rows: list[dict]) -> dict:
    """The default GI codec: among the non-ablation codecs whose displayed GI is visually
    lossless on every view (SSIM >= 0.999 on denoised and raw maps of every scene), the one with
    the fewest bytes (mean over scenes of denoised GI), ties (within 5 %) going to the faster
    decoder. Depth: the smallest codec that keeps 0 and inf exactly with relative error <= 1e-3."""
    from icbtool.net.codec import CODECS

    def total(codec: str, kind: str) -> float:
        return float(np.mean([r["bytes_mean"] for r in rows if r["codec"] == codec
                              and r["map"] == kind]))  # fmt: skip

    ok_gi = [
        c
        for c in CODECS
        if all(r["ssim_min"] >= 0.999 for r in rows if r["codec"] == c and "ssim_min" in r)
    ]
    ok_gi.sort(key=lambda c: total(c, "gi_denoised"))
    best = ok_gi[0]
    for c in ok_gi[1:]:
        if total(c, "gi_denoised") <= 1.05 * total(best, "gi_denoised"):
            dec = lambda c: np.mean([r["decode_ms"] for r in rows if r["codec"] == c])  # noqa: E731
            if dec(c) < dec(best):
                best = c
    ok_d = [
        c
        for c in CODECS
        if CODECS[c].for_depth
        and all(
            r["zero_kept"] and r["inf_kept"] and r["max_rel_error"] <= 1e-3
            for r in rows
            if r["codec"] == c and r["map"].startswith("depth")
        )
    ]
    ok_d.sort(key=lambda c: total(c, "depth"))
    return {
        "gi": best,
        "gi_candidates": ok_gi,
        "depth": ok_d[0],
        "depth_candidates": ok_d,
        "rule": " ".join((choose.__doc__ or "").split()),
    }


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    main = [r for r in rows if "/" not in r["codec"]]
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    codecs = sorted({r["codec"] for r in main})
    colors = dict(zip(codecs, plt.cm.tab10.colors, strict=False))
    ax = axes[0]
    marks = {("cornell_box", "gi_denoised"): "o", ("cornell_box", "gi_raw"): "s",
             ("sponza", "gi_denoised"): "^", ("sponza", "gi_raw"): "D"}  # fmt: skip
    for r in main:
        key = (r["scene"], r["map"])
        if key in marks:
            ax.scatter(r["bytes_mean"] / 1024, 1 - r["ssim_min"] + 1e-7, color=colors[r["codec"]],
                       marker=marks[key], s=45, alpha=0.85)  # fmt: skip
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=colors[c], marker="o", ls="", label=c) for c in codecs]
    handles += [Line2D([], [], color="k", marker=m, ls="", mfc="none", label=f"{s} {k[3:]}")
                for (s, k), m in marks.items() if s in scenes]  # fmt: skip
    ax.legend(handles=handles, fontsize=6, loc="upper right")
    ax.set_yscale("log")
    ax.set_xlabel("KiB per 256x256 GI map")
    ax.set_ylabel("1 - SSIM (display scale, worst view); 1e-7 = exact")
    ax.set_title("GI: size against display error (worst view)")
    for ax, kind, title in ((axes[1], "gi_denoised", "denoised GI"), (axes[2], "depth", "depth")):
        sub = [r for r in rows if r["map"] == kind]
        names = sorted({r["codec"] for r in sub})
        x = np.arange(len(names))
        w = 0.8 / len(scenes)
        for i, s in enumerate(scenes):
            vals = [next((r["bytes_mean"] / 1024 for r in sub if r["codec"] == n and
                          r["scene"] == s), 0) for n in names]  # fmt: skip
            ax.bar(x + i * w, vals, w, label=s)
        ax.set_xticks(x + w * (len(scenes) - 1) / 2, names, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel("KiB per frame (mean)")
        ax.set_title(f"{title}: bytes per frame")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    import icbtool as icb
    from icbtool.provenance import run_info, write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-sponza", action="store_true")
    add_out_argument(ap, "net")
    ap.add_argument("--plot-only", action="store_true", help="redraw the PNG from the JSON")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.plot_only:
        plot(json.loads((out / "gi_codec.json").read_text())["rows"], out / "gi_codec.png")
        return

    scenes = [("cornell_box", lambda: icb.scene.cornell_box(height=args.size, width=args.size))]
    sp = None if args.no_sponza else sponza_dir()
    if sp is not None:
        os.environ["ICBTOOL_SPONZA"] = str(sp)
        scenes.append(("sponza", lambda: icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")))
    else:
        print("Sponza not found (ICBTOOL_SPONZA or ../shared/scenes/sponza): Cornell box only")
    rows, timing = [], {}
    for name, make in scenes:
        t0 = time.perf_counter()
        scene = make()
        path = scene.paths["test"]
        idx = np.linspace(0, len(path) - 1, args.views + 2).round().astype(int)[1:-1]
        cams = [path[int(i)].resized(args.size, args.size) for i in idx]
        print(f"{name}: rendering {len(cams)} views at {args.size}x{args.size}, {args.spp} spp")
        maps = render_maps(scene, cams, args.spp, args.seed)
        timing[name] = time.perf_counter() - t0
        rows += measure(maps, name, args.reps)
    choice = choose(rows)
    print(f"chosen: GI {choice['gi']} (candidates {choice['gi_candidates']}), depth "
          f"{choice['depth']} (candidates {choice['depth_candidates']})")  # fmt: skip
    write_json(out / "gi_codec.json", {"rows": rows, "choice": choice, "render_s": timing})
    write_json(out / "gi_codec_config.json", {"args": vars(args), "run": run_info()})
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "gi_codec.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    plot(rows, out / "gi_codec.png")
    print(f"wrote {out}/gi_codec.{{json,csv,png}}")


if __name__ == "__main__":
    main()
