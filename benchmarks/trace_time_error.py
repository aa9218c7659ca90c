"""Error against time of our path tracer (raw, adaptive, denoised) next to Mitsuba 3.

For the Cornell box and Sponza: RMSE of the linear "full" radiance and FLIP (LDR, on
icbtool.imageio.to_display images) against a high-sample reference, for renders of increasing spp.
Each renderer is measured against its own high-spp reference (ours against ours, Mitsuba against
Mitsuba: they differ slightly in conventions, e.g. shading normals); the RMSE between the two
references is reported as `reference_gap`. Mitsuba cannot split DL/GI, so "full" is compared.

    .venv/bin/python -m benchmarks.trace_time_error [--size 256] [--ref-spp 1024]

Variants of ours: raw (default config: sobol sampler, Embree not robust, as Mitsuba builds its
scenes, 8 extra emission samples on emitter and sky edges), raw_robust (Embree's robust,
watertight traversal), raw_no_edge_samples (``edge_samples=0``), raw_independent (hash sampler),
denoised (GI denoised with OIDN + albedo/normal, as the system uses it: DL comes from the raster),
denoised_fast (the same with OIDN's 'fast' quality), denoised_full (direct + GI denoised together)
and adaptive. The first render (numba JIT or cache load) is a warm-up, not counted; Mitsuba's
kernel cache is warmed by one untimed render per spp. The target check gives, per Mitsuba point (T,
E), the time our curve needs to reach E, divided by T. The Embree floor gives, per Mitsuba point,
the time Embree alone (no shading) needs for the rays of our cheapest raw render that reaches E,
divided by T: above 0.5 no shading code could meet the target there.

The peer is Mitsuba's `llvm_ad_rgb` variant unless `--mitsuba-variant` names another; a variant
that cannot be loaded stops the benchmark with a message (`make bench-deps` installs Mitsuba and
libLLVM), it is never silently replaced by a slower one.

Quiet machine: the 1-minute load average is recorded at the start and the end of the run, and a
run whose load at the start is 1 or more is marked ``"quiet": false`` in its results file
(benchmarks/page.py then labels its numbers as no claim). ``--wait-quiet S`` waits up to S
seconds for the load to drop below 1 before starting (a previous run's load decays in a minute or
two). docs/benchmarks.md's numbers come from one run per scene, e.g.

    .venv/bin/python -m benchmarks.trace_time_error --size 256 --scenes cornell_box \
        --out-name time_error_cornell_box --wait-quiet 120

Besides the fastest runs, the target check of the raw curve is also computed from the per-round
medians (``target_*_paired``: :func:`paired_target_check`), which move less between quiet runs;
``--restat`` adds it to a saved results file without rendering.

Writes --out/<out-name>.{json,png} (default time_error). Mitsuba is a
benchmark peer only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

import icbtool as icb
from benchmarks.common import add_out_argument, bench_scene, run_info, write_json
from benchmarks.trace_throughput import n_rays, record, replay_direct
from icbtool.imageio import to_display
from icbtool.optional import require
from icbtool.trace import TraceConfig
from icbtool.trace.rtc import RtcScene

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"
MAX_DEPTH = 8


def to_mitsuba(scene, cam, spp: int, max_depth: int = MAX_DEPTH):
    """A Mitsuba scene dict for our Scene (two-sided diffuse, area emitters, sun, sky)."""
    mi = require("mitsuba", "the Mitsuba 3 benchmark peer")

    d = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth, "rr_depth": 4}}
    up = cam.up
    d["sensor"] = {
        "type": "perspective",
        "fov": cam.fov_y_deg,
        "fov_axis": "y",
        "to_world": mi.ScalarTransform4f().look_at(
            origin=cam.position.tolist(),
            target=(cam.position + cam.forward).tolist(),
            up=up.tolist(),
        ),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {
            "type": "hdrfilm",
            "width": cam.width,
            "height": cam.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
    }
    for mi_idx, m in enumerate(scene.materials):
        faces = np.flatnonzero(scene.face_material == mi_idx)
        if len(faces) == 0:
            continue
        if m.is_textured:
            refl = {
                "type": "bitmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(m.texture * m.albedo.astype(np.float32))),
                "raw": True,
                "filter_type": "bilinear",
            }
        else:
            refl = {"type": "rgb", "value": m.albedo.tolist()}
        bsdf = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": refl}}
        d[f"mesh{mi_idx}"] = {
            "type": "ply",
            "filename": _write_ply(scene, faces, mi_idx),
            "bsdf": bsdf,
            "face_normals": False,
        }
        if m.is_emissive:
            d[f"mesh{mi_idx}"]["emitter"] = {
                "type": "area",
                "radiance": {"type": "rgb", "value": m.emission.tolist()},
            }
    for i, lt in enumerate(scene.lights_of("directional")):
        d[f"sun{i}"] = {
            "type": "directional",
            "direction": lt.direction.tolist(),
            "irradiance": {"type": "rgb", "value": lt.irradiance.tolist()},
        }
    if scene.sky is not None:
        if scene.sky.kind == "uniform":
            d["sky"] = {
                "type": "constant",
                "radiance": {"type": "rgb", "value": scene.sky.zenith.tolist()},
            }
        else:  # lat-long envmap of the gradient sky; Mitsuba's envmap: +y up, u along phi
            h, w = 128, 256
            th = (np.arange(h) + 0.5) / h * np.pi
            ph = (np.arange(w) + 0.5) / w * 2 * np.pi
            T, P = np.meshgrid(th, ph, indexing="ij")
            dirs = np.stack([np.sin(P) * np.sin(T), np.cos(T), -np.cos(P) * np.sin(T)], -1)
            img = scene.sky.radiance(dirs).astype(np.float32)
            d["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(img)}
    return d


_PLY_DIR = Path("/tmp/icb_trace_bench_ply")


def _write_ply(scene, faces, idx) -> str:
    import trimesh

    _PLY_DIR.mkdir(exist_ok=True)
    f = scene.faces[faces]
    used, inv = np.unique(f, return_inverse=True)
    path = _PLY_DIR / f"{scene.name}_{idx}.ply"
    tm = trimesh.Trimesh(
        scene.vertices[used], inv.reshape(-1, 3), process=False, vertex_normals=scene.normals[used]
    )
    if scene.uvs is not None:
        tm.visual = trimesh.visual.TextureVisuals(uv=scene.uvs[used])
    tm.export(path)
    return str(path)


def mitsuba_render(
    scene, cam, spp: int, seed: int = 0, max_depth: int = MAX_DEPTH
) -> tuple[np.ndarray, float]:
    mi = require("mitsuba", "the Mitsuba 3 benchmark peer")

    sc = mi.load_dict(to_mitsuba(scene, cam, spp, max_depth))
    t0 = time.perf_counter()
    img = np.asarray(mi.render(sc, spp=spp, seed=seed), np.float32)[..., :3]
    return img, time.perf_counter() - t0


def errors(ref: np.ndarray, img: np.ndarray) -> dict:
    flip_evaluator = require("flip_evaluator", "the FLIP metric")

    rmse = float(np.sqrt(np.mean((img - ref) ** 2)))
    a = to_display(ref).astype(np.float32) / 255
    b = to_display(img).astype(np.float32) / 255
    _, flip, _ = flip_evaluator.evaluate(a, b, "LDR")
    return {"rmse": rmse, "flip": float(flip)}


def reference_cache(name: str, size: int, ref_spp: int | str) -> Path:
    """Where this script caches a scene's high-spp references (ours and Mitsuba's)."""
    return REF_CACHE / f"{name}_{size}_{ref_spp}.npz"


def cached_references(name: str, size: int, ref_spp: int | str):
    """The references this script cached for a scene (``ours_full``, ``ours_direct``,
    ``mitsuba``, ``mitsuba_direct``); exits naming the run that makes them when missing."""
    cache = reference_cache(name, size, ref_spp)
    if not cache.is_file():
        sys.exit(f"{cache} is missing: run trace_time_error.py for {name} first")
    return np.load(cache)


def write_results(out: dict, file_name: str, out_dir: Path | None = None) -> None:
    """``out`` with this machine's run info, as ``<out_dir>/<file_name>`` (default: this
    script's ``--out``)."""
    out_dir = Path(out_dir if out_dir is not None else OUT)
    out["run_info"] = run_info()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / file_name, out)
    print(f"wrote {out_dir / file_name}")


def machine_probe() -> dict:
    """Two numbers that tell this host from another, next to run_info's CPU family, model and
    widest SIMD: memory copy bandwidth (numpy, 1 GiB, best of 3) and numpy's sin on 4M doubles
    (best of 3). The same tracer code's time per sample relative to Mitsuba's changed from one
    host to another of the same name (docs/benchmarks.md gives the runs): a vectorising JIT gains
    more than our one-path-at-a-time kernel from a wider or faster host (AVX-512, memory)."""
    a = np.ones(1 << 27)
    b = np.empty_like(a)
    x = np.random.default_rng(0).random(1 << 22)
    copy_s, sin_s = np.inf, np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        np.copyto(b, a)
        copy_s = min(copy_s, time.perf_counter() - t0)
        t0 = time.perf_counter()
        np.sin(x)
        sin_s = min(sin_s, time.perf_counter() - t0)
    return {"copy_gb_per_s": 2 * a.nbytes / copy_s / 1e9, "sin_m_per_s": len(x) / sin_s / 1e6}


def alignment(ours: np.ndarray, theirs: np.ndarray, max_shift: int = 2) -> dict:
    """Pixel alignment of two images of one view: RMSE over integer shifts of ``theirs`` (crop of
    ``max_shift`` px), and the row/column mean profiles' best sub-pixel shift (parabola fit)."""
    h, w = ours.shape[:2]
    m = max_shift
    a = ours[m : h - m, m : w - m]
    grid = {}
    for dy in range(-m, m + 1):
        for dx in range(-m, m + 1):
            b = theirs[m + dy : h - m + dy, m + dx : w - m + dx]
            grid[f"{dy},{dx}"] = float(np.sqrt(np.mean((a - b) ** 2)))
    best = min(grid, key=grid.get)

    def profile_shift(pa: np.ndarray, pb: np.ndarray) -> float:
        pa = pa - pa.mean()
        pb = pb - pb.mean()
        errs = [float(np.mean((pa[m:-m] - np.roll(pb, -s)[m:-m]) ** 2)) for s in (-1, 0, 1)]
        den = errs[0] - 2 * errs[1] + errs[2]
        return 0.0 if den <= 0 else 0.5 * (errs[0] - errs[2]) / den

    lo, lt = ours.mean(-1), theirs.mean(-1)
    return {
        "rmse_by_shift_dy_dx": grid,
        "best_shift_dy_dx": best,
        "row_profile_subpixel_shift": profile_shift(lo.mean(1), lt.mean(1)),
        "column_profile_subpixel_shift": profile_shift(lo.mean(0), lt.mean(0)),
    }


REF_CACHE = Path("/tmp/icb_trace_bench_refs")

#: Our other raw configurations, each a curve of its own, as changes to the default config.
RAW_VARIANTS = {
    "ours_raw_robust": dict(robust=True),
    # without the extra emission samples on emitter/sky edges (TraceConfig.edge_samples)
    "ours_raw_no_edge_samples": dict(edge_samples=0),
    "ours_raw_independent": dict(sampler="independent"),
    "ours_raw_sobol": dict(sampler="sobol"),  # per-pixel points: white noise across pixels
    # four branches after the first vertex (TraceConfig.gi_splits): the same spp of camera
    # rays, about 4x the GI samples
    "ours_raw_gi_splits4": dict(gi_splits=4),
}
#: timed runs longer than this are not repeated
LONG_RUN_S = 5.0
#: Renders shorter than this get SHORT_RUN_FACTOR times the repeats: at 1-2 spp a render takes
#: 50-300 ms, and the VM's stolen time moved single such timings (ours and Mitsuba's alike) by
#: 10-25 % between otherwise identical quiet runs; more tries make the minimum steadier.
SHORT_RUN_S = 0.5
SHORT_RUN_FACTOR = 3


def mitsuba_reference(scene, cam, spp: int, seed: int, max_depth: int) -> np.ndarray:
    """Mean of Mitsuba renders in chunks of <= 128 spp (one huge wavefront is slow and big)."""
    chunks = [min(128, spp - i) for i in range(0, spp, 128)]
    acc = np.zeros((cam.height, cam.width, 3))
    for i, n in enumerate(chunks):
        img, _ = mitsuba_render(scene, cam, n, seed=seed + i, max_depth=max_depth)
        acc += img * n
    return (acc / spp).astype(np.float32)


def ours(scene, cam, cfg: TraceConfig, repeats: int):
    """Our render; its total time is the fastest of ``repeats`` identical (seeded) runs (runs
    longer than LONG_RUN_S are not repeated: load noise matters little there)."""
    best = None
    i = 0
    while i < repeats * (
        SHORT_RUN_FACTOR if best and best.stats.time_s["total"] < SHORT_RUN_S else 1
    ):
        r = icb.trace.render(scene, cam, cfg)
        if best is None or r.stats.time_s["total"] < best.stats.time_s["total"]:
            best = r
        if best.stats.time_s["total"] > LONG_RUN_S:
            break
        i += 1
    return best


def timed(fn, repeats: int):
    """(result, fastest wall time of ``repeats`` calls)."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def time_to_reach(curve: list[dict], err: float, metric: str) -> float | None:
    """Time our curve needs to reach ``err`` (log-log interpolation; None if never reached)."""
    t = np.array([p["time_s"] for p in curve])
    e = np.array([p[metric] for p in curve])
    order = np.argsort(t)
    t, e = t[order], e[order]
    if e[0] <= err:
        return float(t[0])  # reached at our cheapest point (no extrapolation below 1 spp)
    for i in range(1, len(t)):
        if e[i] <= err:
            f = np.log(err / e[i - 1]) / np.log(e[i] / e[i - 1])
            return float(np.exp(np.log(t[i - 1]) + f * (np.log(t[i]) - np.log(t[i - 1]))))
    return None


def floor_ratios(curves: dict, floor: list[dict], metric: str) -> list[float | None]:
    """For each Mitsuba point (T, E): the Embree-only time of our cheapest raw render that
    reaches E, over T. Above 0.5 the target is out of reach at that point for any shading code
    (with our sampling), since Embree alone on those rays takes more than half of T."""
    out = []
    for p in curves["mitsuba"]:
        ok = [f for f, c in zip(floor, curves["ours_raw"]) if c[metric] <= p[metric]]
        out.append(None if not ok else min(f["time_s"] for f in ok) / p["time_s"])
    return out


def target_check(curves: dict, metric: str) -> dict:
    """For each Mitsuba point (T, E): our time to reach E divided by T (target: <= 0.5)."""
    out = {}
    for key, c in curves.items():
        if key == "mitsuba":
            continue
        ratios = []
        for p in curves["mitsuba"]:
            t = time_to_reach(c, p[metric], metric)
            ratios.append(None if t is None else t / p["time_s"])
        valid = [r for r in ratios if r is not None]
        out[key] = {
            "time_ratio_per_mitsuba_point": ratios,
            "worst_ratio": max(valid) if len(valid) == len(ratios) else None,
            "median_ratio": float(np.median(valid)) if valid else None,
            "meets_target_everywhere": bool(len(valid) == len(ratios) and max(valid) <= 0.5),
        }
    return out


def paired_target_check(curves: dict, metric: str) -> dict | None:
    """The target check of ``ours_raw`` from the per-round medians instead of the fastest runs.

    Our time at each spp is the median of the rounds' (ours / Mitsuba) ratios times Mitsuba's
    median time there; Mitsuba's time at each point is its median time. The fastest of a few
    runs moves between quiet runs by more than 10 % at some points (the VM's drift hits the two
    renderers unevenly); the median of back-to-back ratios moves less. None when the curve has
    no per-round times (older results files).
    """
    raw, mi = curves["ours_raw"], curves["mitsuba"]
    if not all("paired_rounds_s" in p for p in raw):
        return None
    ratio = [float(np.median([a / b for a, b in p["paired_rounds_s"]])) for p in raw]
    t_mi = {p["spp"]: float(np.median([b for _, b in p["paired_rounds_s"]])) for p in raw}
    ours = [{**p, "time_s": r * t_mi[p["spp"]]} for p, r in zip(raw, ratio, strict=True)]
    ratios = []
    for p in mi:  # the rounds ran both renderers at each spp
        reach = time_to_reach(ours, p[metric], metric)
        ratios.append(None if reach is None else reach / t_mi[p["spp"]])
    return {
        "time_ratio_per_mitsuba_point": ratios,
        "method": "ours: median per-round ratio x Mitsuba's median time at each spp; "
        "Mitsuba: its median time",
    }


def add_paired_checks(scene_results: dict) -> None:
    """Add ``target_rmse_paired`` and ``target_flip_paired`` (:func:`paired_target_check`) to a
    scene's results, in place."""
    for metric in ("rmse", "flip"):
        check = paired_target_check(scene_results["curves"], metric)
        if check is not None:
            scene_results[f"target_{metric}_paired"] = check


def plot(results: dict, size: int, path: Path, note: str = "") -> None:
    """Error against time per scene (RMSE and FLIP), with Mitsuba's curve and the Embree floor
    of our raw curve; ``note`` (e.g. the load) goes into the titles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["scenes"])
    fig, axes = plt.subplots(2, len(names), figsize=(5.5 * len(names), 7.5), squeeze=False)
    for j, name in enumerate(names):
        sc = results["scenes"][name]
        for i, metric in enumerate(("rmse", "flip")):
            ax = axes[i, j]
            for key, c in sc["curves"].items():
                kw = dict(color="k", lw=2.5, marker="s") if key == "mitsuba" else dict(marker="o")
                ax.loglog([p["time_s"] for p in c], [p[metric] for p in c], label=key, ms=4, **kw)
            floor = sc.get("embree_floor", {}).get("points")
            if floor:  # our raw errors at the time Embree alone needs for the same rays
                raw = sc["curves"]["ours_raw"]
                ax.loglog([f["time_s"] for f in floor], [p[metric] for p in raw], "k:",
                          label="Embree alone, ours_raw's rays")  # fmt: skip
            ax.set_xlabel("time (s)")
            ax.set_ylabel(f"{metric} of full")
            ax.set_title(f"{name} {size}x{size} {note}".strip(), fontsize=9)
        axes[0, j].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


MITSUBA_VARIANT = "llvm_ad_rgb"
#: a run is quiet when the 1-minute load average at its start is below this
QUIET_LOAD = 1.0


def _load_note(load: list[float] | None, quiet: bool | None) -> str:
    if load is None:
        return "(load not recorded)"
    return f"(load {load[0]:.2f} at start: {'quiet' if quiet else 'NOT quiet'})"


def wait_quiet(max_s: float, poll_s: float = 5.0) -> float:
    """Wait until the 1-minute load average is below QUIET_LOAD, at most ``max_s`` seconds;
    returns the seconds waited."""
    t0 = time.perf_counter()
    while os.getloadavg()[0] >= QUIET_LOAD and time.perf_counter() - t0 < max_s:
        time.sleep(min(poll_s, max(max_s - (time.perf_counter() - t0), 0.0)))
    return time.perf_counter() - t0


class PeerMissingError(RuntimeError):
    """The benchmark peer (Mitsuba 3, or the variant asked for) is not installed."""


def load_mitsuba(variant: str):
    """Import Mitsuba 3 and set ``variant``; fail (never switch variant) when it is missing.

    Args:
        variant: a Mitsuba variant name, e.g. ``"llvm_ad_rgb"`` (needs libLLVM) or ``"scalar_rgb"``.

    Returns:
        The ``mitsuba`` module with ``variant`` set.

    Raises:
        PeerMissingError: Mitsuba is not importable, or ``variant`` cannot be set here; the message
            names the variant, the variants Mitsuba offers and how to install the peer.
    """
    try:
        import mitsuba as mi
    except ImportError as e:
        raise PeerMissingError(
            f"the benchmark peer Mitsuba 3 is not installed ({e}); install it with "
            "`make bench-deps` (mitsuba==3.9.1 and libllvm for the llvm variants)"
        ) from e
    available = list(mi.variants())
    if variant not in available:
        raise PeerMissingError(
            f"Mitsuba variant {variant!r} is not in this Mitsuba build (available: "
            f"{', '.join(available)}); choose one with --mitsuba-variant"
        )
    try:
        mi.set_variant(variant)
    except (ImportError, AttributeError, RuntimeError) as e:
        raise PeerMissingError(
            f"Mitsuba variant {variant!r} cannot be loaded here ({type(e).__name__}: {e}). The "
            "llvm variants need libLLVM (install it with `make bench-deps`), the cuda ones an "
            "NVIDIA GPU; or pass "
            "--mitsuba-variant scalar_rgb to compare against the (much slower) scalar variant "
            "explicitly"
        ) from e
    return mi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--spps", default="1,2,4,8,16,32")
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument("--out-name", default="time_error")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per point (min is kept)")
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the saved JSON")
    ap.add_argument(
        "--restat",
        action="store_true",
        help="recompute the saved JSON's derived statistics (the per-round-median target "
        "checks) from its measurements, without rendering",
    )
    ap.add_argument(
        "--mitsuba-variant",
        default=MITSUBA_VARIANT,
        help=f"the Mitsuba variant to compare with (default {MITSUBA_VARIANT}); a variant that "
        "cannot be loaded is an error, never replaced by another",
    )
    ap.add_argument(
        "--wait-quiet",
        type=float,
        default=0.0,
        help="wait up to this many seconds for the 1-minute load average to drop below "
        f"{QUIET_LOAD} before starting (0: start at once); the load at the start is recorded "
        "either way and decides the results file's 'quiet' flag",
    )
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    if args.restat:
        path = OUT / f"{args.out_name}.json"
        saved = json.loads(path.read_text())
        for sc in saved["results"]["scenes"].values():
            add_paired_checks(sc)
        write_json(path, saved)
        print(f"wrote {path}")
        return
    if args.replot:
        saved = json.loads((OUT / f"{args.out_name}.json").read_text())
        plot(
            saved["results"],
            saved["args"]["size"],
            OUT / f"{args.out_name}.png",
            _load_note(saved.get("load_average_start"), saved.get("quiet")),
        )
        print(f"wrote {OUT / args.out_name}.png")
        return
    t_run = time.perf_counter()
    try:
        mi = load_mitsuba(args.mitsuba_variant)
    except PeerMissingError as e:
        sys.exit(f"trace_time_error.py: {e}")
    spps = [int(s) for s in args.spps.split(",")]
    waited = wait_quiet(args.wait_quiet)
    load_start = os.getloadavg()
    quiet = load_start[0] < QUIET_LOAD
    print(
        f"1-minute load at the start {load_start[0]:.2f} (waited {waited:.0f} s): "
        + ("quiet" if quiet else "NOT quiet: the results file is marked quiet=false"),
        flush=True,
    )
    results = {"mitsuba_variant": mi.variant(), "scenes": {}}
    for name in args.scenes.split(","):
        scene = bench_scene(name)
        cam = scene.default_camera.resized(args.size, args.size)
        base = dict(max_depth=MAX_DEPTH, rr_depth=4, spp_per_pass=4)
        # warm-up: the first render pays numba's JIT (or cache load); not counted in the curves
        t0 = time.perf_counter()
        w = icb.trace.render(scene, cam.resized(8, 8), TraceConfig(spp=1, **base))
        warmup_s = time.perf_counter() - t0
        icb.trace.denoise(w.gi, w.albedo, w.normal)  # OIDN loads its weights on the first call
        print(f"{name}: warm-up render (JIT/cache load) {warmup_s:.2f} s", flush=True)
        t0 = time.perf_counter()
        # the reference uses the independent sampler: it must not share a (hypothetical) bias of
        # the default sampler it measures (the stored-reference z-test checks that separately)
        ref_cfg = TraceConfig(spp=args.ref_spp, seed=1000, sampler="independent", **base)
        cache = reference_cache(name, args.size, args.ref_spp)
        if cache.is_file():  # references are deterministic (seeded): reuse them across runs
            z = np.load(cache)
            ref_full, ref_mi, ref_mi_direct = z["ours_full"], z["mitsuba"], z["mitsuba_direct"]
            ref_direct = z["ours_direct"]
            print(f"{name}: references from {cache}", flush=True)
        else:
            ref_ours = icb.trace.render(scene, cam, ref_cfg, progress=True)
            ref_full, ref_direct = ref_ours.full, ref_ours.direct
            print(f"{name}: our reference {time.perf_counter() - t0:.1f} s", flush=True)
            ref_mi = mitsuba_reference(scene, cam, args.ref_spp, 1000, MAX_DEPTH)
            # direct-only image for the alignment check (Mitsuba max_depth 2: emitters + direct)
            ref_mi_direct = mitsuba_reference(scene, cam, args.ref_spp, 3000, 2)
            print(f"{name}: Mitsuba references done", flush=True)
            REF_CACHE.mkdir(parents=True, exist_ok=True)
            np.savez(
                cache,
                ours_full=ref_full,
                ours_direct=ref_direct,
                mitsuba=ref_mi,
                mitsuba_direct=ref_mi_direct,
            )
        gap = float(np.sqrt(np.mean((ref_full - ref_mi) ** 2)))
        # alignment, also on the direct-only images (sharper edges than full); Mitsuba max_depth
        # 2 renders emitters + direct light: our `direct` plus sky/other-emitter direct light
        align = {
            "full": alignment(ref_full, ref_mi),
            "direct_depth2": alignment(ref_direct, ref_mi_direct),
        }
        print(f"{name}: alignment best shift {align['full']['best_shift_dy_dx']}", flush=True)
        keys = (
            "ours_raw",
            *RAW_VARIANTS,
            "ours_denoised",
            "ours_denoised_fast",
            "ours_denoised_full",
            "ours_adaptive",
            "mitsuba",
        )
        curves = {k: [] for k in keys}
        embree_floor = []
        rtc = RtcScene.of(scene, robust=TraceConfig().robust)  # as the default config traces
        for spp in tqdm(spps, desc=name):
            cfg = TraceConfig(spp=spp, seed=spp, **base)
            # ours (default config), Mitsuba and the Embree floor are timed in interleaved rounds
            # (the VM's stolen time drifts over minutes: back-to-back blocks would be unfair)
            r0 = icb.trace.render(scene, cam, cfg)  # untimed: warms the workspace
            rays = record(scene, cam, cfg, capacity=int(r0.stats.total_rays * 1.05) + 1024)
            mitsuba_render(scene, cam, spp, seed=spp + 10_000)  # warm Mitsuba's kernel cache
            r, t_mi, floor, img = None, np.inf, np.inf, None
            rounds = 0
            paired = []  # (ours, Mitsuba) wall times of each round, back to back
            while rounds < args.repeats * (
                SHORT_RUN_FACTOR if r and max(r.stats.time_s["total"], t_mi) < SHORT_RUN_S else 1
            ):
                ri = icb.trace.render(scene, cam, cfg)  # same seed: same image every round
                if r is None or ri.stats.time_s["total"] < r.stats.time_s["total"]:
                    r = ri
                img, dt = mitsuba_render(scene, cam, spp, seed=spp)
                t_mi = min(t_mi, dt)
                paired.append((ri.stats.time_s["total"], dt))
                floor = min(floor, sum(replay_direct(rtc, rays).values()))
                if min(r.stats.time_s["total"], t_mi) > LONG_RUN_S:
                    break
                rounds += 1
            ratio = [a / b for a, b in paired]
            curves["ours_raw"].append(
                {
                    "spp": spp,
                    "time_s": r.stats.time_s["total"],
                    **errors(ref_full, r.full),
                    # per sample, robust to drift: each round's ours / Mitsuba (back to back)
                    "paired_rounds_s": paired,
                    "paired_ratio_quartiles": np.percentile(ratio, [25, 50, 75]).tolist(),
                }
            )
            curves["mitsuba"].append({"spp": spp, "time_s": t_mi, **errors(ref_mi, img)})
            embree_floor.append({"spp": spp, "time_s": floor, "rays": n_rays(rays)})
            # the GI-only denoised image from the same render (the system's use: DL is rastered)
            gi_dn, t_dn = timed(
                lambda r=r: icb.trace.denoise(r.gi_raw, r.albedo, r.normal), args.repeats
            )
            curves["ours_denoised"].append(
                {
                    "spp": spp,
                    "time_s": r.stats.time_s["total"] + t_dn,
                    **errors(ref_full, r.direct + gi_dn),
                }
            )
            # the same with OIDN's 'fast' quality (about half its time)
            gi_dn, t_dn = timed(
                lambda r=r: icb.trace.denoise(r.gi_raw, r.albedo, r.normal, quality="fast"),
                args.repeats,
            )
            curves["ours_denoised_fast"].append(
                {
                    "spp": spp,
                    "time_s": r.stats.time_s["total"] + t_dn,
                    **errors(ref_full, r.direct + gi_dn),
                }
            )
            full_dn, t_dn = timed(
                lambda r=r: icb.trace.denoise(r.full, r.albedo, r.normal), args.repeats
            )
            curves["ours_denoised_full"].append(
                {
                    "spp": spp,
                    "time_s": r.stats.time_s["total"] + t_dn,
                    **errors(ref_full, full_dn),
                }
            )
            for key, change in RAW_VARIANTS.items():  # each timed on its own (min of repeats)
                r = ours(scene, cam, replace(cfg, **change), args.repeats)
                curves[key].append(
                    {"spp": spp, "time_s": r.stats.time_s["total"], **errors(ref_full, r.full)}
                )
            r = ours(
                scene,
                cam,
                replace(cfg, spp=4 * spp, adaptive=True, target_error=0.5 / np.sqrt(spp)),
                args.repeats,
            )
            curves["ours_adaptive"].append(
                {
                    "spp": float(r.spp.mean()),
                    "time_s": r.stats.time_s["total"],
                    **errors(ref_full, r.full),
                }
            )
            tqdm.write(
                f"{name} spp {spp}: "
                + ", ".join(
                    f"{k} {c[-1]['time_s']:.2f}s rmse {c[-1]['rmse']:.4f}"
                    for k, c in curves.items()
                )
            )
        results["scenes"][name] = {
            "size": args.size,
            "ref_spp": args.ref_spp,
            "warmup_render_s": warmup_s,
            "reference_gap_rmse": gap,
            "reference_mean_ours": float(ref_full.mean()),
            "timing": f"min wall time of {args.repeats} runs ({SHORT_RUN_FACTOR * args.repeats} "
            f"where both renders took under {SHORT_RUN_S} s); ours_raw, Mitsuba and the Embree "
            "floor in interleaved rounds (the VM's stolen time varies); ours_raw's points keep "
            "each round's (ours, Mitsuba) times and the quartiles of their ratios",
            "reference_mean_mitsuba": float(ref_mi.mean()),
            "alignment_ours_vs_mitsuba": align,
            "target_rmse": target_check(curves, "rmse"),
            "embree_floor": {
                "what": "Embree alone (direct calls, 2 threads, no shading) on the rays of our "
                "raw render at each spp: no shading code can make that render faster",
                "points": embree_floor,
                "floor_ratio_per_mitsuba_point": floor_ratios(curves, embree_floor, "rmse"),
            },
            "target_flip": target_check(curves, "flip"),
            "load_average_1min_end": os.getloadavg()[0],
            "curves": curves,
        }
        add_paired_checks(results["scenes"][name])
        print(name, "reference gap RMSE", gap, ref_full.mean(), ref_mi.mean())
        for k, v in results["scenes"][name]["target_rmse"].items():
            print(f"  {k}: time ratio to reach Mitsuba's RMSE {v['time_ratio_per_mitsuba_point']}")
    OUT.mkdir(parents=True, exist_ok=True)
    load_end = os.getloadavg()
    write_json(
        OUT / f"{args.out_name}.json",
        {
            "args": vars(args),
            "max_depth": MAX_DEPTH,
            "short_run_s": SHORT_RUN_S,
            "short_run_factor": SHORT_RUN_FACTOR,
            "quiet": bool(quiet),
            "quiet_rule": f"1-minute load average at the start < {QUIET_LOAD}",
            "load_average_start": list(load_start),
            "load_average_end": list(load_end),
            "waited_for_quiet_s": waited,
            "wall_s": time.perf_counter() - t_run,
            "mitsuba_version": mi.__version__,
            "machine_probe": machine_probe(),
            "results": results,
            "run_info": run_info(),
        },
    )
    plot(results, args.size, OUT / f"{args.out_name}.png", _load_note(load_start, quiet))
    print(f"wrote {OUT / args.out_name}.json")


if __name__ == "__main__":
    main()
