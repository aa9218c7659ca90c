"""Write the numbers of docs/benchmarks.md from the committed results files.

Every benchmark number in docs/benchmarks.md sits between marker comments,
``<!-- bench:NAME -->`` and ``<!-- /bench:NAME -->``, and is written here from the JSON files the
benchmark scripts leave in benchmarks/results/ (nothing is typed by hand). ``--check`` rewrites
nothing and exits with 1 when the page differs from what the results files give
(tests/test_benchmarks_page.py runs it, so a stale number fails CI).

    python -m benchmarks.page          # rewrite the bench blocks of docs/benchmarks.md
    python -m benchmarks.page --check  # fail if docs/benchmarks.md is stale
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
PAGE = REPO / "docs" / "benchmarks.md"

MARKER = re.compile(r"<!-- bench:([a-z0-9_-]+) -->\n(.*?)<!-- /bench:\1 -->", re.DOTALL)


class PageBlockError(ValueError):
    """docs/benchmarks.md's bench markers do not match the blocks this script writes."""


def short_runs(d: dict) -> str:
    """' (N for renders under S s)' where a time-error run repeated its short renders more."""
    f, t = d.get("short_run_factor"), d.get("short_run_s")
    return "" if not f else f" ({f * d['args']['repeats']} for renders under {t:g} s)"


def load(rel: str, results: Path) -> Any:
    """The parsed JSON file ``results/rel``; a missing file names itself."""
    path = results / rel
    if not path.is_file():
        raise FileNotFoundError(f"results file {path} is missing: run the benchmark that writes it")
    return json.loads(path.read_text())


def f0(x: float) -> str:
    return f"{x:.0f}"


def f2(x: float) -> str:
    return f"{x:.2f}"


def span(values: list[float], fmt: Callable[[float], str] = f0) -> str:
    """``"lo-hi"`` of the formatted values, or one value when they format alike."""
    lo, hi = fmt(min(values)), fmt(max(values))
    return lo if lo == hi else f"{lo}-{hi}"


def bold(text: str, on: bool) -> str:
    return f"**{text}**" if on else text


def _numbers(v: Any) -> Iterator[float]:
    """The 1-minute values in a load-average entry: a number, a (1, 5, 15 min) triple, or
    lists/dicts of those (None where a run did not record one)."""
    if isinstance(v, int | float):
        yield float(v)
    elif isinstance(v, list) and len(v) == 3 and all(isinstance(x, int | float) for x in v):
        yield float(v[0])
    elif isinstance(v, list):
        for x in v:
            yield from _numbers(x)
    elif isinstance(v, dict):
        for x in v.values():
            yield from _numbers(x)


def walk_load_averages(obj: Any) -> Iterator[float]:
    """Every 1-minute load average recorded anywhere in a results file."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v) if "load_average" in k else walk_load_averages(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from walk_load_averages(v)


# ---------------------------------------------------------------------------------------------
# blocks: each returns the text between its markers


def block_intro(results: Path) -> str:
    loads, cpus = [], set()
    for path in sorted(results.rglob("*.json")):
        d = json.loads(path.read_text())
        loads.extend(walk_load_averages(d))
        info = d.get("run_info") if isinstance(d, dict) else None
        if info:
            cpus.add(info["cpu_count"])
    cores = "/".join(str(c) for c in sorted(cpus))
    load_span = span(loads, lambda x: f"{x:.1f}")
    return (
        "Modules in `benchmarks/`; each writes its numbers (JSON), plots, the resolved "
        "config and the\nmachine/library versions to its `--out`; the committed ones are in "
        "`benchmarks/results/<topic>/`. Timings "
        f"below are from this {cores}-core,\nGPU-less machine while other jobs were running "
        f"(1-minute load average {load_span} over\nthe runs); each benchmark interleaves "
        "icbtool and its peer in one run so both see the same load.\n"
    )


def block_raster(results: Path) -> str:
    d = load("raster/results.json", results)
    ba = load("raster/before_after.json", results)["final"]
    rows = {(r["backend"], r["scene"], r["size"], r["mode"]): r for r in d["results"]}
    met = {
        t["backend"]: t["met"]
        for t in d["target_sponza_512_raster_le_open3d"]
        if t["mode"] == "cached"
    }
    cfg = d["configs"]["osmesa"]["cached"]

    def cell(scene: str, size: int, mode: str = "cached") -> list[str]:
        os_, egl = rows["osmesa", scene, size, mode], rows["egl", scene, size, mode]
        target = scene == "sponza" and size == 512 and mode == "cached"
        return [
            bold(f0(os_["raster_ms_median"]), target and met["osmesa"]),
            bold(f0(egl["raster_ms_median"]), target and met["egl"]),
            span([os_["open3d_ms_median"], egl["open3d_ms_median"]]),
        ]

    tris = rows["osmesa", "sponza", 512, "cached"]["triangles"]
    a = cfg["area_samples"]
    lines = [
        f"**Client raster** (`benchmarks.raster_bench --frames {d['frames']}`): ms per frame "
        "for the full buffer",
        "set (DL with shadows, albedo, world and view normals, depth, position, mask), median of "
        f"{d['frames']} frames",
        "after 2 warm-up frames (the first frames build shaders and shadow maps: not in the",
        "median).",
        "The peer is what a user could do instead with Open3D's `RaycastingScene` (Embree, both "
        "cores):",
        "primary rays plus one shadow ray per hit. Shadow maps cached across frames (static "
        "lights).",
        "",
        "| scene, size | icbtool OSMesa | icbtool EGL | Open3D rays (same runs) |",
        "|---|---|---|---|",
        f"| Sponza ({tris / 1000:.0f}k tris) 512x512 | " + " | ".join(cell("sponza", 512)) + " |",
        "| Sponza 256x256 | " + " | ".join(cell("sponza", 256)) + " |",
        f"| Cornell box 512x512 ({a}x{a} soft area-light shadows) | "
        + " | ".join(cell("cornell_box", 512))
        + " (one hard shadow ray) |",
        "",
    ]
    pairs = [
        (r["after_ms"], r["open3d_ms_after_runs"])
        for r in ba["rows"]
        if r["scene"] == "sponza" and r["size"] == 512 and r["mode"] == "cached"
    ]
    ratios = [a / b for ours, o3d in pairs for a, b in zip(ours, o3d, strict=True)]
    every = [rows[b, "sponza", 512, "shadows_every_frame"] for b in ("osmesa", "egl")]
    all_met = all(met.get(b, False) for b in ("osmesa", "egl"))
    lines += [
        "Target (Sponza, 512x512, full set no slower than Open3D): "
        + ("met" if all_met and max(ratios) <= 1 else "not met")
        + f", {span(ratios, f2)}x of Open3D's time",
        f"over {len(ratios)} paired runs (`before_after.json`). Re-rendering the "
        f"{cfg['shadow_map_size']}^2 sun shadow map every frame",
        f"costs {span([r['raster_ms_median'] for r in every])} ms, which "
        + (
            "still loses to"
            if min(r["raster_ms_median"] for r in every) > max(r["open3d_ms_median"] for r in every)
            else "is close to"
        )
        + f" Open3D ({span([r['open3d_ms_median'] for r in every])} ms).",
        "",
    ]
    return "\n".join(lines)


def block_trace_throughput(results: Path) -> str:
    d = load("trace/throughput.json", results)
    old = load("trace/throughput_first_numpy_version.json", results)
    by = {r["scene"]: r for r in d["results"]}
    first = {r["scene"]: r["tracer_Mrays_per_s"] for r in old["results"]}
    c = d["config"]
    label = {"cornell_box": "Cornell box", "sponza": "Sponza"}
    lines = [
        "**Cloud path tracer** (`benchmarks.trace_throughput`, `benchmarks.trace_profile`, "
        "`benchmarks.trace_time_error`): one numba kernel traces whole paths and calls Embree 4",
        "directly (no Python per depth), on both cores. The throughput benchmark records the "
        "tracer's own",
        "rays and replays them through Embree alone.",
        "",
        f"| {d['args']['size']}x{d['args']['size']}, {c['spp']} spp, max depth {c['max_depth']} "
        "| tracer (all rays, with shading) | Embree alone, same rays: all (direct calls / embreex "
        "`scene.run`) | Embree alone by kind: primary / bounce / shadow |",
        "|---|---|---|---|",
    ]
    for s in ("cornell_box", "sponza"):
        r = by[s]
        k = r["direct_embree_replay_by_kind_Mrays_per_s"]
        lines.append(
            f"| {label[s]} | {r['tracer_Mrays_per_s']:.1f} Mrays/s (first numpy version: "
            f"{first[s]:.1f}) | {r['direct_embree_replay_Mrays_per_s']:.1f} / "
            f"{r['embreex_replay_Mrays_per_s']:.1f} Mrays/s | {k['primary']:.1f} / "
            f"{k['bounce']:.1f} / {k['shadow']:.1f} Mrays/s |"
        )
    share = [f"{100 * by[s]['embree_share_of_tracer_time']:.0f} % ({label[s]})" for s in by]
    after = ", ".join(f"{by[s]['load_average_1min']:.1f}" for s in by)
    start = d.get("load_average_start")
    load_txt = (
        f"1-minute load {start[0]:.1f} at the start, {after} after each scene"
        if start
        else f"1-minute load {after} after each scene (not recorded at the start)"
    )
    lines += [
        "",
        f"Embree's share of the tracer's time: {', '.join(share)}; the rest is shading "
        f"({load_txt}).",
        "The first numpy version's numbers are from its own run "
        "(`throughput_first_numpy_version.json`).",
        "",
    ]
    return "\n".join(lines)


PROFILE_STAGES = {
    "embree_intersect_primary": "Embree, camera rays",
    "embree_intersect_bounce": "Embree, bounce rays",
    "embree_occluded": "Embree, shadow rays",
    "ray_generation": "ray generation",
    "hit_frame": "hit point, normals",
    "textures": "textures",
    "light_sampling": "light sampling (no shadow ray)",
    "bsdf_sampling": "BSDF sampling",
    "sampler": "Sobol numbers",
    "accumulate_python": "accumulation + Python driver",
    "unattributed": "unattributed (megakernel glue)",
}


def block_trace_profile(results: Path) -> str:
    d = load("trace/profile.json", results)
    rows = d["results"]
    label = {"cornell_box": "Cornell box", "sponza": "Sponza"}
    names = [label.get(r["scene"], r["scene"]) for r in rows]
    size = rows[0]["size"]
    lines = [
        f"Where the time goes (`benchmarks.trace_profile`, {size[1]}x{size[0]}, "
        f"{rows[0]['spp']} spp, one thread, CPU seconds; 1-minute load "
        f"{d['load_average_start'][0]:.1f} at the start: CPU time, not wall time, is what a "
        "loaded machine leaves comparable). Stages are the kernel's own helpers and Embree "
        "calls replayed on the render's recorded rays and hits (the script's docstring says "
        "how each is obtained).",
        "",
        "| stage | " + " | ".join(names) + " |",
        "|---" * (len(rows) + 1) + "|",
    ]
    for k, what in PROFILE_STAGES.items():
        cells = [
            f"{r['stages_cpu_s'][k]:.3f} s ({100 * r['stage_shares_of_render'][k]:.0f} %)"
            for r in rows
        ]
        lines.append(f"| {what} | " + " | ".join(cells) + " |")
    lines.append(
        "| **render** | " + " | ".join(f"**{r['render_cpu_s']:.3f} s**" for r in rows) + " |"
    )
    peer = [r["mitsuba_llvm_ad_rgb"] for r in rows]
    if all("render_cpu_s" in m for m in peer):
        lines.append(
            "| Mitsuba `llvm_ad_rgb`, same spp (CPU s of all its threads) | "
            + " | ".join(f"{m['render_cpu_s']:.3f} s" for m in peer)
            + " |"
        )
    pk = [r["embree_packet8_over_one_ray"] for r in rows]
    emb = [
        sum(r["stages_cpu_s"][k] for k in PROFILE_STAGES if k.startswith("embree"))
        / r["render_cpu_s"]
        for r in rows
    ]
    lines += [
        "",
        "Embree's one-ray calls take "
        + ", ".join(f"{100 * e:.0f} % ({n})" for e, n in zip(emb, names, strict=True))
        + " of the render. Embree's 8-ray packets (`rtcIntersect8` / `rtcOccluded8`) on the same "
        "rays, 8 consecutive rays a packet, take "
        + "; ".join(
            f"{n}: {span([p[k] for k in p], f2)}x the one-ray time" for n, p in zip(names, pk)
        )
        + ", so packets of the kernel's own ray order would save little.",
    ]
    by_sampler = [r.get("render_cpu_s_by_sampler") for r in rows]
    if all(by_sampler):
        lines.append(
            "Whole renders with the independent sampler (one hash per number) instead of Sobol "
            "take "
            + "; ".join(
                f"{n}: {b['independent']:.3f} s against {b['sobol']:.3f} s"
                for n, b in zip(names, by_sampler, strict=True)
            )
            + " (the replayed 'Sobol numbers' stage draws them at every vertex, the kernel at "
            "the first two only: an upper bound)."
        )
    firsts = [r.get("embree_first_vertex_shadow_rays") for r in rows]
    if all(firsts):
        lines += [
            "The shadow rays of the paths' first vertices alone, in sample order (neighbouring "
            "pixels, as a wavefront would batch them), take "
            + "; ".join(
                f"{n}: {f['packet8_over_one_ray']:.2f}x ({f['rays']} rays; one by one "
                f"{1e3 * f['one_ray_s']:.0f} ms, {100 * f['one_ray_s'] / r['render_cpu_s']:.1f} % "
                "of the render)"
                for n, f, r in zip(names, firsts, rows, strict=True)
            )
            + " in packets of 8.",
        ]
    ns = [r.get("embree_ns_per_ray") for r in rows]
    if all(n and "mitsuba_bounce" in n for n in ns):
        lines += [
            "",
            "The ray queries alone, ns per ray on one thread (the render's own rays; ours as one "
            "ray / packets of 8 / packets of 16; robust: our scene flag, watertight; not robust: "
            "as Mitsuba builds its scene; Mitsuba: its "
            "`ray_intersect_preliminary` / `ray_test` on the same rays, packets of its JIT's "
            "width, kernel launch included):",
            "",
            "| rays | "
            + " | ".join(f"{n}, robust | {n}, not robust | {n}, Mitsuba's Embree" for n in names)
            + " |",
            "|---" * (3 * len(rows) + 1) + "|",
        ]
        for kind in ("primary", "bounce", "shadow"):
            cells = []
            for v in ns:
                for t in ("robust", "not_robust"):
                    cells.append(" / ".join(f"{v[f'{t}_{q}_{kind}']:.0f}" for q in PROFILE_QUERIES))
                cells.append(f"**{v[f'mitsuba_{kind}']:.0f}**")
            lines.append(f"| {kind} | " + " | ".join(cells) + " |")
        parts = []
        for n, v, r in zip(names, ns, rows, strict=True):
            peer = r["mitsuba_llvm_ad_rgb"].get("render_cpu_s")
            if peer is None:
                continue
            kinds = ("primary", "bounce", "shadow")
            best = 1e-9 * sum(r["rays"][k] * v[f"not_robust_packet16_{k}"] for k in kinds)
            now = sum(r["stages_cpu_s"][k] for k in PROFILE_STAGES if not k.startswith("embree"))
            parts.append(
                f"{n}: {best:.3f} s, {100 * best / peer:.0f} % of Mitsuba's whole render "
                f"({peer:.3f} s), which would leave {peer - best:.3f} s for everything else "
                f"against our {now:.3f} s of shading and bookkeeping today"
            )
        if parts:
            lines += [
                "",
                "Per sample, the best of these query forms (every ray in a packet of 16, the "
                "scene not robust) would still cost, for Embree alone: " + "; ".join(parts) + ".",
            ]
    lines += _simd_bound(results, label)
    lines.append("")
    return "\n".join(lines)


def _simd_bound(results: Path, label: dict[str, str]) -> list[str]:
    """The wavefront / SIMD bound paragraph (benchmarks/trace_simd_bound.py), when it was run,
    with the time the missed FLIP points of the time-against-error runs would need saved."""
    if not (results / "trace" / "simd_bound.json").is_file():
        return []
    d = load("trace/simd_bound.json", results)
    parts = []
    for r in d["results"]:
        by = r["soa_by_batch"]
        best = by[str(r["best_batch"])]["ns_per_vertex"]
        worst = max(by, key=lambda b: by[b]["ns_per_vertex"]["gather"])
        parts.append(
            f"{label.get(r['scene'], r['scene'])}: {r['scalar_ns_per_vertex']:.0f} ns per vertex "
            f"in the kernel's helpers against {best['total']:.0f} ns in batches of "
            f"{r['best_batch']} ({r['speedup_soa']:.2f}x; the math alone "
            f"{r['speedup_soa_without_gather']:.1f}x, the gather {best['gather']:.0f} ns, "
            f"{by[worst]['ns_per_vertex']['gather']:.0f} ns in batches of {worst}, whose 45 "
            f"columns overflow the 32 KiB L1 cache), so at most "
            f"{100 * r['render_saving_bound']:.0f} % off the render (these stages are "
            f"{100 * r['shading_share_of_render']:.0f} % of it)"
        )
    need = []
    for name, (_, _, sc) in time_error_runs(results).items():
        spps = [p["spp"] for p in sc["curves"]["mitsuba"]]
        cut = [1 - 0.5 / r for _, r in missed_points(spps, target_ratios(sc, "target_flip"))]
        if cut:
            need.append(
                f"the {TIME_ERROR_SCENES[name]}'s missed FLIP points need "
                f"{span([100 * c for c in cut])} % less time at equal error"
            )
    return [
        "",
        "What a wavefront with SIMD shading could save (`benchmarks.trace_simd_bound`, 1-minute "
        f"load {d['load_average_start'][0]:.1f} at the start): the per-vertex math (hit frame, "
        "light samples, cosine bounce) on the same render's hits, as the megakernel runs it one "
        "vertex at a time and as a wavefront's stages would over a batch of paths (a gather into "
        "columns, then branch-free loops that LLVM turns into 4-wide AVX2 code, checked equal to "
        "1e-9): " + "; ".join(parts) + ". That is before the wavefront hands each batch to Embree "
        "and its path state from stage to stage, which costs stores and loads like the gather's"
        + (f"; {'; '.join(need)} (time against error, below)." if need else "."),
    ]


#: the Embree queries of trace_profile.py's ``embree_ns_per_ray``
PROFILE_QUERIES = ("one_ray", "packet8", "packet16")


def _first_met(ratios: list[float | None], spps: list[int]) -> int | None:
    """The smallest Mitsuba spp from which every ratio is <= 0.5."""
    for i in range(len(ratios)):
        if all(r is not None and r <= 0.5 for r in ratios[i:]):
            return spps[i]
    return None


TIME_ERROR_SCENES = {"cornell_box": "Cornell box", "sponza": "Sponza"}
#: the commands that write the per-scene time/error files (each under ~10 min on this machine)
TIME_ERROR_COMMANDS = {
    "cornell_box": "-m benchmarks.trace_time_error --size 256 --scenes cornell_box "
    "--ref-spp 1024 --spps 1,2,4,8,16,32,64 --repeats 5 --out-name time_error_cornell_box "
    "--wait-quiet 120",
    "sponza": "-m benchmarks.trace_time_error --size 256 --scenes sponza --ref-spp 512 "
    "--spps 1,2,4,8,16,32 --repeats 5 --out-name time_error_sponza --wait-quiet 120",
}


def time_error_runs(results: Path) -> dict[str, tuple[str, dict, dict]]:
    """Per scene: (results file, its JSON, the scene's entry): ``trace/time_error_<scene>.json``
    (one run per scene) where present, else the scene in ``trace/time_error.json``."""
    out = {}
    for name in TIME_ERROR_SCENES:
        for rel in (f"trace/time_error_{name}.json", "trace/time_error.json"):
            if (results / rel).is_file():
                d = load(rel, results)
                if name in d["results"]["scenes"]:
                    out[name] = (rel, d, d["results"]["scenes"][name])
                    break
    return out


def missed_points(spps: list[int], ratios: list[float | None]) -> list[tuple[int, float]]:
    """(Mitsuba spp, ratio) where the time-to-error target (ratio <= 0.5 from Mitsuba's 2 spp up,
    the tracer's speed goal) is missed."""
    return [
        (s, r) for s, r in zip(spps, ratios, strict=True) if s >= 2 and r is not None and r > 0.5
    ]


def target_ratios(sc: dict, key: str, curve: str = "ours_raw") -> list[float | None]:
    """A time-error scene's target ratios per Mitsuba point: ``sc[key][curve]``, or for the
    per-round-median checks (``target_*_paired``, made for ours_raw alone) ``sc[key]``."""
    check = sc[key] if key.endswith("_paired") else sc[key][curve]
    return check["time_ratio_per_mitsuba_point"]


def round_medians(points: list[dict]) -> list[float]:
    """The median per-round (ours / Mitsuba) time ratio of each point of the ours_raw curve."""
    return [p["paired_ratio_quartiles"][1] for p in points]


def _run_to_run(results: Path, name: str, label: str, sc: dict) -> list[str]:
    """How far the ratios moved between this run and an earlier quiet run of the same scene
    (``trace/time_error_<scene>_previous.json``, where kept): the fastest-run statistic against
    the per-round medians."""
    rel = f"trace/time_error_{name}_previous.json"
    if not (results / rel).is_file():
        return []
    d0 = load(rel, results)
    s0 = d0["results"]["scenes"][name]
    if not (is_quiet(d0) and "target_flip_paired" in s0 and "target_flip_paired" in sc):
        return []
    spps = [p["spp"] for p in sc["curves"]["mitsuba"]]

    def moved(key: str) -> tuple[float, int]:
        a, b = target_ratios(s0, key), target_ratios(sc, key)
        diffs = [abs(x - y) for x, y in zip(a, b, strict=True)]
        i = int(np.argmax(diffs))
        return diffs[i], spps[i]

    med0, med1 = (round_medians(s["curves"]["ours_raw"]) for s in (s0, sc))
    per_round = max(abs(x - y) for x, y in zip(med0, med1, strict=True))
    parts = []
    for key, what in (
        ("target_flip", "FLIP, fastest runs"),
        ("target_flip_paired", "FLIP, per-round medians"),
        ("target_rmse", "RMSE, fastest runs"),
        ("target_rmse_paired", "RMSE, per-round medians"),
    ):
        dv, at = moved(key)
        parts.append(f"{what} {dv:.2f} (at {at} spp)")
    return [
        f"{label}, run to run: against an earlier quiet run (`{rel}`, 1-minute load "
        f"{d0['load_average_start'][0]:.2f}, an earlier build whose images here are the same), "
        "the target ratios moved by at most: " + "; ".join(parts) + f"; the per-sample "
        f"per-round medians by at most {per_round:.2f}. A ratio within about that of 0.5 is "
        "not settled by one run.",
        "",
    ]


def is_quiet(d: dict) -> bool:
    """Whether a results file says its run was on a quiet machine (1-minute load < 1 at the
    start, recorded by the benchmark); files without the flag are not."""
    return d.get("quiet") is True and (d.get("load_average_start") or [9.9])[0] < 1.0


def _error_by_brightness(results: Path) -> list[str]:
    """Where our RMSE lead over Mitsuba comes from (trace_error_by_brightness.py), if run."""
    rel = "trace/error_by_brightness.json"
    if not (results / rel).is_file():
        return []
    d = load(rel, results)
    parts = []
    for name, sc in d["scenes"].items():
        ours, theirs = sc["ours"], sc["mitsuba"]
        bright = [i for i, r in enumerate(ours) if r["display_brightness"][0] >= 0.7]
        rest = [i for i in range(len(ours)) if i not in bright and ours[i]["pixels"] >= 1000]
        n_px = sum(r["pixels"] for r in ours)
        n_bright = sum(ours[i]["pixels"] for i in bright)
        share = sum(theirs[i]["share_of_squared_error"] for i in bright)
        sq = [(ours[i]["rms_error"] ** 2 * ours[i]["pixels"], theirs[i]["rms_error"] ** 2 *
               theirs[i]["pixels"]) for i in bright]  # fmt: skip
        bright_rms = (sum(a for a, _ in sq) / max(sum(b for _, b in sq), 1e-300)) ** 0.5
        rms = [ours[i]["rms_error"] / theirs[i]["rms_error"] for i in rest]
        flip = [ours[i]["flip_mean"] / theirs[i]["flip_mean"] for i in rest]
        parts.append(
            f"{TIME_ERROR_SCENES[name]}: the {n_bright} pixels of display brightness >= 0.7 "
            f"({100 * n_bright / n_px:.1f} % of the image) hold {100 * share:.0f} % of Mitsuba's "
            f"squared error, and our RMS error there is {bright_rms:.2f} of its; in the darker "
            f"bins of 1000 pixels or more our RMS error is "
            f"{span(rms, f2)} of Mitsuba's and our mean FLIP {span(flip, f2)} of its"
        )
    return [
        f"Where the RMSE lead comes from (`benchmarks.trace_error_by_brightness`, "
        f"{d['args']['spp']} spp, each renderer against its own reference, pixels binned by the "
        "reference's display brightness): " + "; ".join(parts) + ". On the Cornell box the lead "
        "is mostly at the light and its edges (the extra emission samples on the light's "
        "outline, `TraceConfig.edge_samples`, and the Sobol sampler's stratified pixel area), "
        "where FLIP's display mapping clips: hence its small FLIP lead.",
        "",
    ]


def _error_split(results: Path) -> list[str]:
    """Which half of the image (GI or direct light) carries the error (trace_error_split.py)."""
    rel = "trace/error_split.json"
    if not (results / rel).is_file():
        return []
    d = load(rel, results)
    parts = []
    for name, rows in d["scenes"].items():
        each = [
            f"{r['spp']} spp: FLIP {r['whole render']['flip']:.3f}, with the GI's noise alone "
            f"{r['GI noise only']['flip']:.3f}, with the direct light's alone "
            f"{r['direct noise only']['flip']:.3f}"
            for r in rows
        ]
        parts.append(f"{TIME_ERROR_SCENES[name]}: " + "; ".join(each))
    return [
        "Which half carries the error (`benchmarks.trace_error_split`, mean of "
        f"{d['args']['seeds']} seeds; one half of our render swapped for the reference's): "
        + "; ".join(parts)
        + ". FLIP is the GI's noise: better light sampling at the first hit cannot move it.",
        "",
    ]


def _gi_variance(results: Path) -> list[str]:
    """Where the GI's noise lies, and what rr_depth / gi_splits buy (trace_gi_variance.py)."""
    rel = "trace/gi_variance.json"
    if not (results / rel).is_file():
        return []
    d = load(rel, results)
    parts = []
    for name, sc in d["scenes"].items():
        div = sc["gi_variance_divided_by_splits"]
        eff = "; ".join(
            f"{r['config'].split(' (')[0]} {r['gi_efficiency_rel']:.2f} / "
            f"{r['display_efficiency_rel']:.2f}"
            for r in sc["rows"][1:]
        )
        parts.append(
            f"{TIME_ERROR_SCENES[name]}: at most {100 * sc['shared_share_at_most']:.0f} % of "
            "the GI's variance is in the camera ray and first hit (it falls "
            f"{div['2']:.1f}x with `gi_splits=2`, {div['4']:.1f}x with 4), and Russian roulette "
            f"from depth 4 adds {100 * sc['roulette_added_gi_variance']:.0f} % to it (against "
            "none up to the maximum depth); at equal CPU time (1 / (variance x time), default = "
            f"1; GI / full image after the display transform): {eff}"
        )
    a = d["args"]
    return [
        "Where the GI's noise lies, and what the path knobs buy at equal time "
        f"(`benchmarks.trace_gi_variance`, {a['size']}x{a['size']}, 1 spp, {a['seeds']} "
        f"seeds, variance per pixel across seeds, 1-minute load {d['load_average_start'][0]:.2f} "
        "at the start; plot `benchmarks/results/trace/gi_variance.png`): "
        + "; ".join(parts)
        + ". The GI's noise is the bounce and what "
        "follows it, from the same estimator as Mitsuba's (cosine-sampled bounce, a light "
        "sample at each vertex, roulette from depth 4). The defaults keep that estimator and "
        "its noise per sample, as the comparison above assumes; `rr_depth` and `gi_splits` "
        "trade noise for time as these ratios show.",
        "",
    ]


def block_trace_time_error(results: Path) -> str:
    runs = time_error_runs(results)
    lines = [
        "Time against error (RMSE and FLIP of the full image against each renderer's own "
        "high-spp reference)",
        "next to Mitsuba 3 (same scene, camera and max depth; plots: "
        "`benchmarks/results/trace/time_error*.png`).",
        "Our time to reach Mitsuba's error, divided by Mitsuba's time (target <= 0.5; bold = met "
        'on a quiet run); "Embree',
        'floor" is the time Embree alone needs for the rays of our cheapest render that reaches '
        "Mitsuba's",
        "RMSE, over Mitsuba's time: above 0.5, no shading code could meet the target there with "
        "our sampling.",
        "Only runs on a quiet machine (1-minute load < 1 at the start, recorded in the results "
        "file) make claims;",
        "a run without that is labelled and its ratios are not bold.",
        "Ratios against Mitsuba also depend on the host: the tracer of 2026-11-25 took 1.86x "
        "Mitsuba's time per sample on the Cornell box (8 spp) in that day's quiet run and about "
        "1.0-1.1x on the host of 2026-11-26 (both 'AMD EPYC', 2 cores), where Mitsuba needed 3.3x "
        "its earlier CPU time and we 1.5x; each run names its host below.",
        "The RMSE ratio at Mitsuba's 2 spp is our 1-spp time (its RMSE is already below "
        "Mitsuba's 2-spp RMSE) over Mitsuba's 2-spp time; between quiet runs on one host, "
        "Mitsuba's fastest 2-spp render has moved enough for that point to pass in one run and "
        "fail in the next.",
        "",
    ]
    for name, (rel, d, sc) in runs.items():
        quiet = is_quiet(d)
        cur = sc["curves"]
        spps = [p["spp"] for p in cur["mitsuba"]]
        ld = d.get("load_average_start")
        load_txt = (
            f"1-minute load {ld[0]:.2f} at the start"
            if ld
            else f"load at the start not recorded (at the end: {sc['load_average_1min_end']:.1f})"
        )
        label = TIME_ERROR_SCENES[name]
        # the host: ratios against Mitsuba's vectorising JIT depend on it (trace_time_error.py's
        # machine_probe docstring)
        ri, probe = d.get("run_info", {}), d.get("machine_probe")
        host = ""
        if "cpu_simd" in ri and probe:
            host = (
                f" Host: {ri.get('cpu', '?')} (family {ri.get('cpu_family', '?')}, model "
                f"{ri.get('cpu_model', '?')}, {ri['cpu_simd']}), {ri.get('cpu_count', '?')} "
                f"cores, memory copy {probe['copy_gb_per_s']:.0f} GB/s."
            )
        lines += [
            f"**{label}** (`{rel}`: {d['args']['size']}^2, reference {sc['ref_spp']} spp, minimum "
            f"of {d['args']['repeats']} runs{short_runs(d)}, "
            f"Mitsuba `{d['results']['mitsuba_variant']}`, "
            f"{load_txt}: " + ("quiet)." if quiet else "**not a quiet run: no claim**).") + host,
            "",
        ]

        def row(what: str, ratios: list[float | None], mark: bool = True, quiet=quiet) -> str:
            cells = [
                "n/a" if r is None else bold(f2(r), quiet and mark and r <= 0.5) for r in ratios
            ]
            return f"| {what} | " + " | ".join(cells) + " |"

        def ratios(key: str, curve: str = "ours_raw", sc=sc) -> list[float | None]:
            return target_ratios(sc, key, curve)

        def paired_target_row(what: str, key: str, sc=sc) -> list[str]:
            """The target check from the per-round medians, where the file has it."""
            return [row(what, ratios(key))] if key in sc else []

        def optional(what: str, key: str, curve: str, sc=sc) -> list[str]:
            """The row of a curve that older results files may lack (it did not exist yet)."""
            return [row(what, ratios(key, curve))] if curve in sc[key] else []

        def paired_row(points: list[dict]) -> list[str]:
            """Median (quartiles) of the per-round time ratios, where the file has them."""
            if not all("paired_ratio_quartiles" in p for p in points):
                return []
            cells = [
                "{1:.2f} ({0:.2f}-{2:.2f}, {3} rounds)".format(
                    *p["paired_ratio_quartiles"], len(p["paired_rounds_s"])
                )
                for p in points
            ]
            what = "per sample, each round's ratio (renders back to back): median (quartiles)"
            return [f"| {what} | " + " | ".join(cells) + " |"]

        def paired_summary(points: list[dict], spps: list[int]) -> str:
            """The per-round medians in words (comparing fastest runs alone can favour either
            renderer by the VM's drift between them)."""
            if not all("paired_ratio_quartiles" in p for p in points):
                return ""
            med = round_medians(points)
            slow = [s for s, m in zip(spps, med, strict=True) if m > 1]
            return f"; round by round, the median ratio is {span(med, f2)}" + (
                f" (above 1 at {', '.join(map(str, slow))} spp)" if slow else ""
            )

        mi_t = [p["time_s"] for p in cur["mitsuba"]]
        per_sample = [o["time_s"] / m["time_s"] for o, m in zip(cur["ours_raw"], cur["mitsuba"])]
        err_ratio = [o["rmse"] / m["rmse"] for o, m in zip(cur["ours_raw"], cur["mitsuba"])]
        head = " | ".join(f"{s} ({t:.3g} s)" for s, t in zip(spps, mi_t, strict=True))
        lines += [
            f"| Mitsuba spp (its time) | {head} |",
            "|---" * (len(spps) + 1) + "|",
            row("per sample: our time / Mitsuba's, same spp", per_sample, mark=False),
            *paired_row(cur["ours_raw"]),
            row("RMSE per sample: ours / Mitsuba's, same spp", err_ratio, mark=False),
            row(
                "RMSE, ours raw (default: "
                + ("Z-Sobol" if "ours_raw_sobol" in sc["target_rmse"] else "Sobol")
                + ", Embree not robust)",
                ratios("target_rmse"),
            ),
            *optional("RMSE, ours raw, `robust=True`", "target_rmse", "ours_raw_robust"),
            *optional(
                "RMSE, ours raw, `edge_samples=0`", "target_rmse", "ours_raw_no_edge_samples"
            ),
            *optional("RMSE, ours raw, `gi_splits=4`", "target_rmse", "ours_raw_gi_splits4"),
            row("RMSE, ours with denoised GI (OIDN)", ratios("target_rmse", "ours_denoised")),
            *optional("RMSE, denoised GI, OIDN 'fast'", "target_rmse", "ours_denoised_fast"),
            *paired_target_row("RMSE, ours raw, from the per-round medians", "target_rmse_paired"),
            row("RMSE, Embree floor", sc["embree_floor"]["floor_ratio_per_mitsuba_point"], False),
            row("FLIP, ours raw", ratios("target_flip")),
            *paired_target_row("FLIP, ours raw, from the per-round medians", "target_flip_paired"),
            *optional(
                "FLIP, ours raw, `sampler='sobol'` (per-pixel points)",
                "target_flip",
                "ours_raw_sobol",
            ),  # fmt: skip
            *optional("FLIP, ours raw, `gi_splits=4`", "target_flip", "ours_raw_gi_splits4"),
            row("FLIP, ours with denoised GI (OIDN)", ratios("target_flip", "ours_denoised")),
            *optional("FLIP, denoised GI, OIDN 'fast'", "target_flip", "ours_denoised_fast"),
            "",
        ]
        if not quiet:
            continue
        slower = [s for s, r in zip(spps, per_sample, strict=True) if r > 1]

        def met(key: str, curve: str = "ours_raw", spps: list[int] = spps, ratios=ratios) -> str:
            first = _first_met(ratios(key, curve), spps)
            if first is not None:
                return f"met from Mitsuba's {first} spp up"
            some = [s for s, r in zip(spps, ratios(key, curve)) if r is not None and r <= 0.5]
            return f"met at {', '.join(map(str, some))} spp only" if some else "not met"

        def speedup_needed(spps: list[int], ratios=ratios) -> str:
            """How much faster at equal error our raw render would have to be at each missed
            point (Mitsuba spp >= 2: the speed goal): ratio / 0.5."""
            parts = []
            for key, name in (("target_rmse", "RMSE"), ("target_flip", "FLIP")):
                miss = [f"{r / 0.5:.2f}x at {s}" for s, r in missed_points(spps, ratios(key))]
                if miss:
                    parts.append(f"{name} {', '.join(miss)} spp")
            if not parts:
                return ""
            return (
                " To meet the target at the missed points (Mitsuba spp >= 2), our raw render "
                "would have to be, at equal error: " + "; ".join(parts) + " faster."
            )

        split = "ours_raw_gi_splits4"
        lines += [
            f"{label}, quiet run: the RMSE target is {met('target_rmse')}, the FLIP target (raw) "
            f"{met('target_flip')}"
            + (
                f"; with `gi_splits=4` the RMSE target is {met('target_rmse', split)}, the FLIP "
                f"target {met('target_flip', split)}"
                if split in sc["target_flip"]
                else ""
            )
            + ". Per sample",
            f"we take {span(per_sample, f2)} of Mitsuba's time"
            + (
                f" (slower than Mitsuba at {', '.join(map(str, slower))} spp)"
                if slower
                else " (faster at every spp)"
            )
            + f", with {span(err_ratio, f2)} of its RMSE"
            + paired_summary(cur["ours_raw"], spps)
            + "."
            + (
                f" From the per-round medians (ours: the median round ratio times Mitsuba's "
                f"median time; Mitsuba: its median time), the RMSE target is "
                f"{met('target_rmse_paired')}, the FLIP target {met('target_flip_paired')}."
                if "target_flip_paired" in sc
                else ""
            )
            + speedup_needed(spps, ratios),
            "",
        ]
        lines += _run_to_run(results, name, label, sc)
    lines += _error_by_brightness(results)
    lines += _error_split(results)
    lines += _gi_variance(results)
    lines += [
        "Commands (each about 10 min or less on this 2-core machine; `--wait-quiet` waits for "
        "the load to settle):",
        "",
        *[f"    .venv/bin/python {TIME_ERROR_COMMANDS[n]}" for n in TIME_ERROR_SCENES],
        "",
        first_use(results),
        "",
    ]
    return "\n".join(lines)


def first_use(results: Path) -> str:
    """What the tracer's first use costs (``benchmarks.trace_compile``)."""
    d = load("trace/compile.json", results)
    t = d["trials"]
    compile_s = span([x["compile_s"] for x in t])
    load_s = span([x["cache_load_s"] for x in t], f2)
    return (
        "First use on a new machine (or after a change to `icbtool/trace/kernels.py`) compiles "
        f"the tracer's kernels: the first render took {compile_s} s in a clean process with an "
        f"empty numba cache, the same render {load_s} s in the next process, which loads them "
        "from the cache "
        f"(`benchmarks.trace_compile`, `trace/compile.json`, 1-minute load "
        f"{d['load_average_start'][0]:.2f} at the start)."
    )


def block_denoise(results: Path) -> str:
    d = load("trace/denoise_quality.json", results)
    rows = {(r["scene"], r["quality"]): r for r in d["rows"]}
    scenes = ["cornell_box", "sponza"]

    def ms(q: str, key: str = "denoise_ms") -> str:
        return span([rows[s, q][key] for s in scenes])

    def e(s: str, q: str, nd: int = 4) -> str:
        return f"{rows[s, q]['rmse']:.{nd}f}"

    same = all(rows[s, "balanced"]["rmse"] == rows[s, "high"]["rmse"] for s in scenes)
    cb = (
        f"Cornell {e('cornell_box', 'high')} with either"
        if e("cornell_box", "high") == e("cornell_box", "fast")
        else f"Cornell {e('cornell_box', 'high')} vs {e('cornell_box', 'fast')}"
    )
    a = d["args"]
    execute = ""
    if all("execute_ms" in rows[s, q] for s in scenes for q in ("high", "fast")):
        execute = (
            f" OIDN's time is its network, not the call around it: a filter committed once on "
            f"fixed buffers, `execute` alone timed, takes 'high' {ms('high', 'execute_ms')} ms, "
            f"'fast' {ms('fast', 'execute_ms')} ms (the same images); on one thread 'high' "
            f"{ms('high', 'execute_ms_1_thread')} ms, 'fast' "
            f"{ms('fast', 'execute_ms_1_thread')} ms."
        )
    return (
        f"Denoising (`benchmarks.denoise_quality`, {a['size']}x{a['size']}, {a['spp']} spp "
        f"GI, OIDN with albedo + normal,\nbest of {a['repeats']}): 'high' {ms('high')} ms, "
        f"'fast' {ms('fast')} ms; RMSE of direct + denoised GI: {cb}\n"
        f"(raw {e('cornell_box', 'none (raw)')}), Sponza {e('sponza', 'high')} vs "
        f"{e('sponza', 'fast')} (raw {e('sponza', 'none (raw)', 3)}); 'balanced' gives "
        + ("the same images as 'high'" if same else "images that differ from 'high'")
        + "."
        + execute
        + "\n"
    )


def block_store(results: Path) -> str:
    d = load("store/store_bench.json", results)
    lines = [
        "**Cache** (`benchmarks.store_bench`): similar-camera lookup (exact, same answers as a "
        "brute",
        f"force scan on {d['lookup'][0]['queries']:,} queries per size).",
        "",
        "| records | octree lookup median (p95) | brute-force numpy scan median |",
        "|---|---|---|",
    ]
    for r in d["lookup"]:
        assert r["agreement_with_brute_force"] == 1.0, "the lookup disagrees with brute force"
        exp = len(str(r["records"])) - 1
        lines.append(
            f"| 10^{exp} | {f0(r['octree_us_median'])} us ({f0(r['octree_us_p95'])}) | "
            f"{r['brute_force_us_median']:,.0f} us |"
        )
    ins = d["insert"]
    rec = ins[0]
    lines += [
        "",
        f"Insert: about {span([r['records_per_s'] for r in ins])} records/s for "
        f"{rec['size']}x{rec['size']} records with all 8 maps (compression dominates; fsync",
        f"or not); {rec['bytes_per_record'] / 1000:.0f} KB per record "
        f"({rec['compression_ratio']:.1f}x smaller than raw float32, GI bit-exact).",
        "An older run on a quiet machine (no results file kept) gave 38 us for the 10^5 lookup.",
        "",
    ]
    return "\n".join(lines)


def block_warp(results: Path) -> str:
    d = load("warp/warp_bench.json", results)
    c, r = d["config"], d["results"]
    names = {
        "kornia_warp_frame_depth": "kornia `warp_frame_depth`, no mask",
        "icbtool_warp_backward_numpy_numba": "icbtool `warp.backward` (fused numba kernel, masks "
        "included)",
        "icbtool_warp_backward_torch": "icbtool torch path (differentiable, masks included)",
    }
    lines = [
        f"**Warping** (`benchmarks.warp_bench --runs {c['runs']} --repeats {c['repeats']}`, "
        f"{c['size']}x{c['size']}, {c['threads']} threads): backward warp",
        "with all hole masks, next to kornia's `warp_frame_depth` without a mask, calls "
        "interleaved; median",
        f"and min over all {c['runs'] * c['repeats']} timed runs, the first (warm-up) call apart, "
        "per-run times in `warp_bench.json`.",
        "",
        "| | median ms | min ms | first call ms | over kornia: ratio of medians (per repeat) "
        "| ratio of mins (per repeat) |",
        "|---|---|---|---|---|---|",
    ]
    for k, label in names.items():
        x = r[k]
        lines.append(
            f"| {label} | {f0(x['median_ms'])} | {f0(x['min_ms'])} | {f0(x['first_call_ms'])} | "
            f"{f2(x['ratio_of_medians'])} ({span(x['ratio_of_medians_per_repeat'], f2)}) | "
            f"{f2(x['ratio_of_mins'])} ({span(x['ratio_of_mins_per_repeat'], f2)}) |"
        )
    nb = r["icbtool_warp_backward_numpy_numba"]
    met = max(nb["ratio_of_medians_per_repeat"] + nb["ratio_of_mins_per_repeat"]) <= 1
    lines += [
        "",
        "Target (ours with masks no slower than kornia without): "
        + ("met" if met else "not met")
        + f", {f2(nb['ratio_of_medians'])}x kornia's time by medians,",
        f"{f2(nb['ratio_of_mins'])}x by mins (min-of-runs).",
        "",
    ]
    return "\n".join(lines)


def block_prefetch(results: Path) -> str:
    d = load("prefetch/prefetch_experiment.json", results)
    c, s = d["config"], d["summary"]
    conds = ["a_no_prefetch", "b_paper_prefetch", "c_prefetch_resolution_rule", "d_combined"]
    w, g = c["walk"], c["gi_rot"]

    def pct(x: float) -> str:
        v = 100 * x
        return f"{v:.1f}" if v >= 10 else f"{v:.2f}"

    def cells(scene: str, rot: float) -> tuple[str, dict]:
        sw = s[scene]["gi_walking" if rot == g else "dl_sweeps"][f"speed={w},rot={rot}"]
        vals = [pct(sw[k]["hole_ratio_mean"]) for k in conds]
        if rot == g:
            vals[-1] = f"**{vals[-1]}**"
        return " / ".join(vals), sw

    rows, checks = [], []
    for rot in [0.0, *c["rot_speeds"]]:
        label = (
            "straight" if rot == 0 else f"yaw {rot:g} rad/s" + (", warped GI" if rot == g else "")
        )
        parts = []
        for scene in ("cornell_box", "sponza"):
            text, sw = cells(scene, rot)
            parts.append(text)
            if sw["a_no_prefetch"]["hole_ratio_mean"] > 0.05:
                checks.append(sw["d_combined"]["hole_ratio_mean"] < 0.01)
        rows.append(f"| {label} | {parts[0]} | {parts[1]} |")

    def ssim(scene: str) -> str:
        sw = s[scene]["gi_walking"][f"speed={w},rot={g}"]
        return " / ".join(f"{sw[k]['ssim_gi_inpainted']:.3f}" for k in conds)

    lines = [
        f"**Prefetch** (`benchmarks.prefetch_experiment --frames {c['frames']} --gi-frames "
        f"{c['gi_frames']}`, T_IL = {1e3 * c['latency']:.0f} ms, client",
        f"{c['size']}x{c['size']} along each scene's test path, {d['speed_scale'].split(' in')[0]}"
        "): holes (% of geometry pixels) after warping",
        "the reference to the client's current camera, for (a) no prefetch, (b) the paper's "
        "prefetch camera",
        "at the client's resolution, (c) prefetch with our resolution rule, (d) (c) combined with "
        "the",
        "previous reference.",
        "",
        f"| walking {w} m/s | Cornell (a / b / c / d) | Sponza (a / b / c / d) |",
        "|---|---|---|",
        *rows,
        "",
        "Target (holes < 1 % with prefetch and combining where plain warping leaves > 5 %): "
        + ("met on both" if checks and all(checks) else "not met on all")
        + " scenes.",
        f"GI SSIM after inpainting (yaw {g:g}): Cornell {ssim('cornell_box')}, Sponza",
        f"{ssim('sponza')}: the paper's same-resolution reference (b) is magnified when warped;",
        "the resolution rule (c) recovers it.",
        "",
    ]
    return "\n".join(lines)


def block_loop(results: Path) -> str:
    s = load("loop/summary.json", results)
    cfg = load("loop/config.json", results)
    run = load("loop/loop_demo.json", results)
    lc = cfg.get("loop", cfg)
    lc = {**lc, **lc.get("cloud", {})}  # the cloud's settings are nested since LoopConfig.cloud
    scene = {"cornell_box": "Cornell box"}.get(s["scene"], s["scene"])
    den = "denoised" if lc["denoise"] else "raw"
    return (
        f"**The ICB loop** (`make demo`, numbers from `benchmarks.loop_demo`: {scene}, "
        f"{s['frames']} client frames at\n{lc['height']}x{lc['width']} along the {lc['path']} "
        f"path, T_IL = {1e3 * lc['latency_s']:.0f} ms, cloud GI at {lc['spp']} spp {den}): cache "
        f"hit rate {100 * s['cache_hit_rate']:.0f} %, holes after combining "
        f"{100 * s['mean_hole_ratio_combined']:.2f} %,\nSSIM of the final frame against a "
        f"{lc['truth_spp']}-spp path-traced truth {s['mean_ssim_final_vs_truth']:.2f} (DL alone: "
        f"{s['mean_ssim_dl_only_vs_truth']:.2f}), {run['wall_s']:.0f} s for the whole command "
        "after the install\n(kernels compiled and cached; 1-minute load average "
        f"{run['load_average_1_5_15min_before'][0]:.1f} at the start). Per stage, median ms "
        f"(first call apart): raster {f0(s['median_raster_ms'])} ({f0(s['first_raster_ms'])}), "
        f"warp {f0(s['median_warp_ms'])} ({f0(s['first_warp_ms'])}), cloud render on a miss "
        f"{f0(s['median_cloud_render_on_miss_ms'])} ({f0(s['first_cloud_render_on_miss_ms'])}).\n"
    )


def block_emitters(results: Path) -> str:
    d = load("emitters/emitter_split.json", results)
    c = d["config"]
    pct = ", ".join(f"{100 * b:+.2f}" for b in d["gi_bias_per_channel"])
    met = "met" if d["within_target"] else "NOT met"
    return (
        "**Emissive geometry as light** (`benchmarks.emitter_split`): the classic Cornell "
        "box written as a glTF\nin millimetres with an emissive ceiling quad, "
        f"{c['size']}x{c['size']}; icbtool's GI (full - direct, {c['spp']} spp, the quad\n"
        "promoted to an area light) against "
        f"Mitsuba {d['mitsuba_version']} (`{d['mitsuba_variant']}`, {c['mi_spp']} spp) indirect "
        "radiance (max_depth -1 minus max_depth 2): mean bias\n"
        f"{100 * d['gi_bias_whole_image']:+.2f} % over the image, per channel {pct} % (target "
        f"{100 * d['target_abs_bias']:.0f} %: {met}); full image "
        f"{100 * max(abs(b) for b in d['full_bias_per_channel']):.2f} % at most.\n"
    )


def _said(lines: list[str], width: int = 70) -> str:
    """What icbtool said when it loaded a scene, shortened for a table cell."""
    short = []
    for text in lines:
        head, _, rest = text.partition(": ")
        text = rest if rest and ".xml:" in head else text
        short.append(text if len(text) <= width else text[: width - 3] + "...")
    return "; ".join(short).replace("|", "/") or "nothing"


def block_mitsuba_xml(results: Path) -> str:
    d = load("mitsuba_xml/compare.json", results)
    c = d["config"]
    rows, over = [], 0
    for r in d["scenes"].values():
        ours, floor = r["icbtool_vs_mitsuba"], r["mitsuba_seed_to_seed"]
        bias = ", ".join(f"{100 * b:+.2f}" for b in ours["bias_per_channel"])
        fbias = ", ".join(f"{100 * b:+.2f}" for b in floor["bias_per_channel"])
        bound = max(0.05, 2 * floor["blurred_rel_rmse"])
        bias_ok = max(abs(b) for b in ours["bias_per_channel"]) < 0.02
        rmse_ok = ours["blurred_rel_rmse"] < bound
        rmse = f"{100 * ours['blurred_rel_rmse']:.2f}"
        over += not (bias_ok and rmse_ok)
        rows.append(
            f"| `{Path(r['file']).name}` ({r['triangles']} tris, depth {r['max_depth']}) "
            f"| {_said(r.get('icbtool_said', []))} "
            f"| {bold(bias, not bias_ok)} "
            f"| {bold(rmse, not rmse_ok)} | {fbias} | "
            f"{100 * floor['blurred_rel_rmse']:.2f} |"
        )
    switched = sum(r.get("approximated_bsdfs_switched_to_diffuse", 0) for r in d["scenes"].values())
    loads = [x for k in ("load_average_start", "load_average_end") for x in _numbers(d.get(k))]
    size = f"films {c['width']} px wide" if c.get("width") else "the films' own sizes"
    refused = d.get("mitsuba_refused", {})
    head = (
        "**Mitsuba 3 scene files** (`benchmarks.mitsuba_xml_compare`): public Mitsuba scene files "
        "(here: Mitsuba's own\ndocumentation scenes, mitsuba-data's `docs/scenes`) loaded by "
        "`icb.scene.load` (the file's camera and depth) and traced,\nagainst Mitsuba "
        f"{d['mitsuba_version']} (`{d['mitsuba_variant']}`) rendering the same file: the BSDFs "
        "icbtool traces exactly are\nMitsuba's own on both sides; one it approximates becomes "
        f"the diffuse icbtool renders ({switched} switched); both {c['spp']} spp,\n{size}; "
        f"blurred relative RMSE: Gaussian sigma {c['blur']:g} px; 1-minute load "
        f'{span(loads, f2)}. "icbtool said":\nits warnings when it loaded the file (what it '
        "skipped or approximated). Bold: outside the peer tests' bound\n(|bias| < 2 % and RMSE "
        f"< max(5 %, 2x Mitsuba's own)): {over} of {len(rows)}. Every image side by side "
        "(icbtool | Mitsuba):\n`results/mitsuba_xml/sheet.png`."
        + "".join(f" Mitsuba refused `{Path(f).name}` ({why})." for f, why in refused.items())
        + " `bsdf_blendbsdf.xml` blends a smooth gold mirror with rough plastic: Mitsuba "
        "3.7-3.9's blend of a delta\nand a non-delta lobe is biased, icbtool's is not "
        '(docs/mitsuba.md, "Blends with a delta lobe"). The glass\nscenes are dominated by '
        "caustics (paths from the floor through the glass to the sky's bright spots), where\n"
        "icbtool's noise is still above Mitsuba's at equal spp.\n\n"
    )
    return (
        head + "| scene | icbtool said | bias ours vs Mitsuba (%, RGB) | blurred rel. RMSE (%) | "
        "Mitsuba seed vs seed bias (%) | its RMSE (%) |\n|---|---|---|---|---|---|\n"
        + "\n".join(rows)
        + "\n"
    )


def block_interiors(results: Path) -> str:
    d = load("interiors/interiors.json", results)
    c = d["config"]
    rows, loads = [], list(walk_load_averages(d["scenes"]))
    for key, r in d["scenes"].items():
        runs, ra, lo = r["runs"], r["ratios"], r["icbtool_load"]
        icb = [p["icbtool"] for p in runs]
        mi = [p["mitsuba"] for p in runs]
        gaps = f", {len(r['dropped_shapes'])} shapes dropped" if r["dropped_shapes"] else ""
        if r.get("replaced_textures"):
            gaps += f", {len(r['replaced_textures'])} missing textures made constant"
        rows.append(
            f"| {key} ({lo['triangles'] / 1e3:.0f}k tris, {lo['texels'] / 1e6:.1f}M texels over "
            f"its materials{gaps}) "
            f"| {span([x['wall_s'] for x in icb])} | {span([x['wall_s'] for x in mi])} "
            f"| {ra['whole_run_time']:.2f}x | {span([x['peak_rss_mb'] for x in icb])} "
            f"| {span([x['peak_rss_mb'] for x in mi])} | {ra['peak_memory']:.2f}x "
            f"| {lo['load_s']:.1f} / {r['mitsuba_load']['load_s']:.1f} |"
        )
    return (
        "**Interiors against Mitsuba 3** (`benchmarks.interiors`): icbtool's whole `trace` "
        "(load, BVH, packing, render,\noutputs) and Mitsuba "
        f"{d.get('mitsuba_version', '?')} (`{c['variant']}`: import, load, render) in child "
        "processes, back to back, on\nthe same prepared file (the BSDFs icbtool traces exactly "
        "kept on both sides; shapes whose mesh files a scene\nlacks or Mitsuba cannot read "
        "dropped, textures whose images it lacks a constant 0.5 grey, on both sides),\n"
        f"{c['width']}x{c['height']}, {c['spp']} spp, max depth "
        f"{c['max_depth']}, {c['repeats']} pair(s); peak memory: each child's VmHWM; 1-minute "
        f"load {min(loads):.1f}-{max(loads):.1f}\n(2 shared cores: compare the ratios, not the "
        "times).\n\n"
        "| scene | icbtool (s) | Mitsuba (s) | time ratio | icbtool peak (MB) | Mitsuba peak "
        "(MB) | memory ratio | load alone (s), icbtool / Mitsuba |\n"
        "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n"
    )


def _baseline_line(results: Path, tag: str = "train", paths: tuple[str, ...] = ("test",)) -> str:
    """One line: the trivial baselines on the current store's ``paths`` (gan/baselines_TAG.json:
    fitted on the train path, or on train + cover with ``tag="cover"``), appended to every GAN
    table (every table carries its baselines: docs/gan.md, "Honest tables")."""
    d = load(f"gan/baselines_{tag}.json", results)
    fitted = "the train path" if tag == "train" else "the train path + the coverage views"
    names = ("constant", "albedo x k", "nearest irradiance", "warp + inpaint",
             "tracer 1 spp + OIDN")  # fmt: skip
    parts = []
    for p in paths:
        t = d["paths"][p]
        m = t["methods"]
        cells = ", ".join(f"{n} {m[n]['ssim']:.3f}" for n in names if n in m)
        parts.append(f"on the {p} path ({t['views']} views, every one scored): SSIM {cells}")
    return (  # after a blank line: a line right under a table would be one of its rows
        "\nBaselines of the current Sponza store (`benchmarks.gan_baselines`, same scene, train "
        f"path and bake settings; fitted on {fitted}) " + "; ".join(parts) + ".\n"
    )


def block_gan_baselines(results: Path) -> str:
    order = ("constant", "albedo x k", "nearest irradiance", "warp + inpaint",
             "tracer 1 spp + OIDN")  # fmt: skip
    out = []
    for tag, what in (
        ("train", "fitted / trained on the train path alone"),
        ("cover", "fitted / trained on the train path + the 40 coverage views"),
    ):
        rel = f"gan/baselines_{tag}.json"
        if not (results / rel).is_file():
            continue
        d = load(rel, results)
        paths = list(d["paths"])
        methods = list(order) + [n for n in d["methods"] if n not in order]
        pp = d["paths"]
        head = " | ".join(
            f"{p} ({pp[p]['views']} views, coverage {pp[p]['coverage_median_pct']:.2f} %)"
            for p in paths
        )
        rows = []
        for n in methods:
            cells = []
            for p in paths:
                r = d["paths"][p]["methods"].get(n)
                cells.append(
                    "-" if r is None else f"{r['ssim']:.3f} / {r['mse']:.0f} / {r['flip']:.3f}"
                )
            ms = [
                d["paths"][p]["methods"][n]["ms_median"]
                for p in paths
                if n in d["paths"][p]["methods"]
            ]
            rows.append(f"| {n} | " + " | ".join(cells) + f" | {np.median(ms):.0f} |")
        load_txt = f"{d['load_1min'][0]:.1f}-{d['load_1min'][1]:.1f}"
        out.append(
            f"{what.capitalize()} (`--tag {tag}`; SSIM / MSE (0-255) / FLIP, means over every "
            f"view; coverage: median distance from a view's pixels to the nearest fitted pixel, % "
            f"of the scene's diagonal; ms per 128x128 frame on this CPU, 1-minute load "
            f"{load_txt}):\n\n| method | {head} | ms |\n|---|"
            + "---|" * (len(paths) + 1)
            + "\n"
            + "\n".join(rows)
            + "\n"
        )
    return (
        "**Learned GI against what needs no network** (`benchmarks.gan_baselines`, Sponza "
        "128x128; truth: 256-spp denoised traces (walk: 128 spp); test: the project's test "
        "path; walk: held-out views of a seeded random walk of the atrium in every direction):"
        "\n\n" + "\n".join(out)
    )


def block_gan_ablation(results: Path) -> str:
    d = load("gan/ablation.json", results)
    v = d["variants"]
    paths = [p for p in ("test", "walk") if any(p in x for x in v.values())]
    sp = load("gan/speed.json", results) if (results / "gan/speed.json").is_file() else None
    side = "256"

    def ms(n: str) -> str:
        x = sp["variants"].get(n.split(",")[0]) if sp else None  # seeds, iterations: same net
        return f"{x['ms'][side]['min']:.1f}" if x and side in x["ms"] else "-"

    rows = "\n".join(
        f"| {n} | {x['change']} | {x['iteration']} | "
        + " | ".join(f"{x[p]['ssim']:.3f} / {x[p]['mse']:.0f}" if p in x else "-" for p in paths)
        + f" | {x['seconds'] / 60:.0f} |"
        + (f" {ms(n)} |" if sp else "")
        for n, x in v.items()
    )
    ms_head, ms_sep, ms_txt = "", "", ""
    if sp:
        lo, hi = sp["load_1min"]
        ms_head, ms_sep = f" ms at {side}^2 |", "---|"
        ms_txt = (
            f" Last column: the generator's ms per {side}x{side} frame in onnxruntime on one "
            "thread, the least of "
            f"{next(iter(sp['variants'].values()))['ms'][side]['samples']} calls (random "
            "weights; `benchmarks.gan_speed`, the variants taking turns call by call, "
            f"1-minute load {lo:.1f} -> {hi:.1f}; medians and CPU times in `gan/speed.json`); "
            "- where the network is one timed above or was not timed."
        )
    return (
        "**What limits the generator** (`benchmarks.gan_ablation`: the `cpu` preset's recipe "
        "and one change at a time; SSIM / MSE over every view; minutes of training on this "
        f"loaded 2-core machine, 1-minute load {d['load_1min'][0]:.1f} at the end).{ms_txt}\n\n"
        "| variant | change | iterations | " + " | ".join(paths) + " | minutes |" + ms_head + "\n"
        "|---|---|---|"
        + "---|" * len(paths)
        + "---|"
        + ms_sep
        + "\n"
        + rows
        + "\n\n"
        + _baseline_line(results, "cover", tuple(paths))
    )


def block_gan_coverage(results: Path) -> str:
    d = load("gan/coverage.json", results)
    mc = d["median_coverage"]
    b = d["bake"]
    cells = "; ".join(
        f"{p}: {100 * c['train']:.2f} % with the train path alone, {100 * c['train+cover']:.2f} % "
        "with the coverage views"
        for p, c in mc.items()
    )
    return (
        "**Coverage** (`benchmarks.gan_coverage`): the planner scored "
        f"{d['candidates']} candidate cameras in {d['plan_seconds']:.0f} s; "
        f"{100 * d['uncovered_before']:.0f} % of their surface was farther than "
        f"{100 * d['radius']:.0f} % of the diagonal from every train pixel. The first "
        f"{d['views']} views of its plan were baked ({b['spp']} spp, denoised, "
        f"{b['seconds'] / 60:.0f} min at load {b['load_1min'][0]:.0f}). Median distance from an "
        f"evaluation view's pixels to the nearest training pixel: {cells}.\n"
    )


def block_envmap(results: Path) -> str:
    d = load("envmap/mitsuba.json", results)
    bias = ", ".join(f"{100 * b:+.3f}" for b in d["mean_bias_per_channel"])
    return (
        "**Environment map** (`benchmarks.envmap_mitsuba`): boxes on a floor lit only by a "
        "generated sky EXR\n(a small sun of peak radiance 2000, a dome, a dark ground; "
        "rotated 40 degrees about y), "
        f"{d['size']}x{d['size']}; icbtool's full radiance\n({d['ours_spp']} spp, the map "
        "importance-sampled with MIS) against Mitsuba's `envmap` + `path` "
        f"(`{d['mitsuba_variant']}`, 2 x {d['mitsuba_spp'][0]} spp)\nfrom the same file and "
        f"`to_world`: mean bias per channel {bias} % (target 1 %), blurred (5x5) relative RMSE "
        f"{100 * d['blurred_rel_rmse_ours_vs_mitsuba']:.2f} %\n(Mitsuba seed to seed "
        f"{100 * d['blurred_rel_rmse_mitsuba_seed_to_seed']:.2f} %); images side by side in "
        "`results/envmap/mitsuba.png`.\n"
    )


def block_mitsuba_materials(results: Path) -> str:
    d = load("mitsuba_materials/mitsuba_materials.json", results)
    a = d["args"]
    rows = []
    for r in d["rows"]:
        last = r["runs"][-1]
        bias = ", ".join(f"{100 * b:+.2f}" for b in last["bias_per_channel"])
        rmse = " / ".join(f"{100 * x['rel_rmse_icbtool']:.2f}" for x in r["runs"])
        own = " / ".join(f"{100 * x['rel_rmse_mitsuba']:.2f}" for x in r["runs"])
        fl = last.get("flip_icbtool"), last.get("flip_mitsuba")
        flip = "-" if None in fl else f"{fl[0]:.3f} / {fl[1]:.3f}"
        general = any("need the general" in k for k in last["kernel_note"])
        kernel = "general" if general else "Lambert"
        t_eq = r["time_s_icbtool_to_mitsuba_rmse"]
        teq = "not reached" if t_eq is None else f"{t_eq:.2f}"
        rows.append(
            f"| {r['scene']} | {kernel} | {bias} | {rmse} | {own} | {flip} | "
            f"{last['time_s_icbtool']:.2f} / {r['time_s_mitsuba']:.2f} | {teq} |"
        )
    spps = " / ".join(str(x["spp"]) for x in d["rows"][0]["runs"])
    loads = [x["load"] for r in d["rows"] for x in r["runs"]]
    return (
        "**Mitsuba 3's BSDFs** (`benchmarks.mitsuba_materials`): material-preview scenes (a "
        "sphere of one BSDF on a checkerboard\nfloor, constant environment and a small area "
        f"light), {a['size']}x{a['size']}, depth 16; reference: Mitsuba 3 (`scalar_rgb`) at "
        f"{a['ref_spp']} spp;\nboth renderers at {spps} spp with another seed. Bias: icbtool's "
        "image mean vs the reference's, per channel (at the\nhighest spp). Blurred (sigma 1.5 px) "
        "relative RMSE against the reference: icbtool, and Mitsuba's own at equal spp (its\n"
        "seed-to-seed difference: the noise floor). FLIP (icbtool / Mitsuba) and wall time "
        "(icbtool / Mitsuba, seconds) at the\nhighest spp; time to equal RMSE: the seconds "
        "icbtool needs to reach Mitsuba's RMSE at the highest spp (log-log fit\nof its RMSE over "
        f"time; 'not reached' when its error does not fall). Load average {span(loads, f2)} on "
        f"{d['run_info'].get('cpu_count', '?')} cores\n(a loaded machine: times are indicative)."
        "\n\n"
        "| scene | kernel | bias (%, RGB) | rel. RMSE icbtool (%) | Mitsuba seed to seed (%) "
        "| FLIP | time (s) | time to equal RMSE (s) |\n|---|---|---|---|---|---|---|---|\n"
        + "\n".join(rows)
        + "\n"
    )


def block_dl_accuracy(results: Path) -> str:
    d = load("raster/dl_accuracy.json", results)

    def pct(x: float) -> str:
        return f"{100 * x:.2f}"

    lines = [
        "**Client DL accuracy** (`benchmarks.raster_dl_accuracy`): the raster's DL against "
        "the tracer's direct light\n(box-filtered pixels, max_depth 2, "
        "the reference spp below), mean bias (largest channel) and 5x5-blurred relative RMSE "
        "over\nthe covered pixels without those that see the ceiling light itself (+2 px: "
        "at this size a sliver whose\ncoverage is a matter of sample positions; the whole "
        "image is in the JSON) and on penumbra/edge pixels; cost\nof `dl` at 512x512 "
        "(median of 5 frames, loaded machine) by `RasterConfig.dl_supersample` k (k x k "
        "points per pixel).",
        "",
        "| scene, size | k | bias | blurred RMSE | penumbra/edge blurred RMSE | ms at 512^2 |",
        "|---|---|---|---|---|---|",
    ]
    for name, sc in d["scenes"].items():
        h, w = sc["size"]
        for row in sc["by_supersample"]:
            a = row["without_emitter_pixels"]
            e = row["penumbra_and_edge_pixels"]
            b = max(a["bias_per_channel"], key=abs)
            lines.append(
                f"| {name} {h}x{w} ({sc['reference']['spp']} spp) | {row['dl_supersample']} | "
                f"{100 * b:+.2f} % | {pct(a['blurred_rel_rmse'])} % | "
                f"{pct(e['blurred_rel_rmse'])} % | {row['cost_ms_512']:.0f} |"
            )
    return "\n".join(lines) + "\n"


def block_shadow_accuracy(results: Path) -> str:
    d = load("raster/shadow_accuracy.json", results)

    def pcts(x: list[float]) -> str:
        return " / ".join(f"{100 * v:+.2f}" for v in x)

    lines = [
        "**Client soft shadows** (`benchmarks.raster_shadow_accuracy`): the raster's DL against "
        "the tracer's direct light\n(max_depth 2, the reference spp below), bias per channel "
        "(R / G / B, %) of the sums over interior pixels (footprint on one\nplane, not the "
        "emitter seen) in a penumbra (traced / unshadowed light in 0.05-0.95) and fully lit "
        "(>= 0.98),\n`icbtool.raster.accuracy.shadow_bias`; shading: the same on "
        "`dl / albedo` (each renderer's own albedo: apart from texture\nfiltering); "
        "`before`: the raster before the "
        "along-the-ray area offset and penumbra\nsamples; `dl` ms at 512x512 (median; before "
        "and after run back to back, 1-minute load "
        f"{d['load_average_start'][0]:.1f} at the start\non 2 cores: the sun-only Sponza, "
        "whose shading code is unchanged, shows how far such times move).",
        "",
        "| view, size | raster | penumbra bias % (px) | lit bias % (px) | shading: penumbra / "
        "lit bias % | dl ms at 512^2 |",
        "|---|---|---|---|---|---|",
    ]
    order = ("before_default", "before_supersample2", "default", "supersample2")
    names = {
        "before_default": "before, default",
        "before_supersample2": "before, dl_supersample 2",
        "default": "default",
        "supersample2": "dl_supersample 2",
    }
    for view, v in d["views"].items():
        h, w = v["size"]
        for key in order:
            if key not in v["configs"]:
                continue
            c = v["configs"][key]
            sh = c["shading"]
            lines.append(
                f"| {view} {h}x{w} ({v['reference']['spp']} spp) | {names[key]} | "
                f"{pcts(c['penumbra_bias_per_channel'])} ({c['penumbra_pixels']}) | "
                f"{pcts(c['lit_bias_per_channel'])} ({c['lit_pixels']}) | "
                f"{pcts(sh['penumbra_bias_per_channel'])}; {pcts(sh['lit_bias_per_channel'])} | "
                f"{c['dl_ms_512_median']:.0f} |"
            )
    return "\n".join(lines) + "\n"


def block_raster_glossy(results: Path) -> str:
    """Client DL cost of the tracer's BSDFs (``benchmarks.raster_glossy``)."""
    after = load("raster_glossy/results_after.json", results)
    before = load("raster_glossy/results_before.json", results)
    rows = (
        ("cornell_box", "cornell_box (Lambert)", "-"),
        ("cornell_box_glossy_as_lambert", "cornell_box_glossy, Lambert stand-ins", "-"),
        ("cornell_box_glossy_n4", "cornell_box_glossy", "4"),
        ("cornell_box_glossy", "cornell_box_glossy", "8 (default)"),
        ("cornell_box_glossy_n16", "cornell_box_glossy", "16"),
    )
    n = after["size"]
    lines = [
        "**Client glossy DL** (`benchmarks.raster_glossy`): ms per `dl` frame of "
        "`icbtool.raster` (OSMesa) at "
        f"{n}x{n} from the\ndefault camera, median of {after['frames']} frames after 2 "
        "warm-up frames, configurations interleaved round by round;\n"
        "`glossy_area_samples`: points per area light for the glossy lobes; "
        "`before`: the raster before glossy support\n(Lambert only). 1-minute load "
        f"{after['load_average_start'][0]:.1f} at the start on 2 cores: times move by "
        "tens of % between runs (see the repeats).",
        "",
        f"| scene | glossy_area_samples | dl ms at {n}^2 | before |",
        "|---|---|---|---|",
    ]
    for key, scene, k in rows:
        if key not in after["ms_median"]:
            continue
        b = before["ms_median"].get(key)
        was = "-" if b is None else f"{b:.0f}"
        lines.append(f"| {scene} | {k} | {after['ms_median'][key]:.0f} | {was} |")
    reps = []
    for i in (1, 2):
        path = results / "raster_glossy" / f"results_before_lambert{i}.json"
        if not path.is_file():
            continue
        b = load(f"raster_glossy/results_before_lambert{i}.json", results)
        a = load(f"raster_glossy/results_after_lambert{i}.json", results)
        reps.append(
            f"{b['ms_median']['cornell_box']:.0f} before / "
            f"{a['ms_median']['cornell_box']:.0f} after"
        )
    if reps:
        lines += [
            "",
            "Lambert box alone (`--lambert-only`, before and after back to back, "
            "median ms): " + "; ".join(reps) + ".",
        ]
    return "\n".join(lines) + "\n"


def block_trace_refactor(results: Path) -> str:
    rows = []
    for name, label in (("cornell_box", "Cornell box"), ("sponza", "Sponza"), ("aa", "A/A")):
        path = results / "trace" / f"ab_{name}.json"
        if not path.is_file():
            continue
        d = json.loads(path.read_text())
        q = d["cpu_ratio_quartiles"]
        rows.append(
            f"{label} {d['args']['size']}^2: {d['median_cpu_ratio_b_over_a']:.3f} "
            f"(quartiles {q[0]:.3f}-{q[-1]:.3f}, {len(d['rounds'])} rounds)"
        )
    tp = ""
    path = results / "trace" / "refactor_throughput.json"
    if path.is_file():
        d = json.loads(path.read_text())
        med = d["median_tracer_Mrays_per_s"]
        loads = [r["load_average_1min"] for r in d["runs"]]
        n_runs = len({(r["version"], r["run"]) for r in d["runs"]}) // 2
        tp = (
            f"\n`benchmarks.trace_throughput` ({d['args']}), {n_runs} runs of "
            "each version interleaved, median tracer Mrays/s (wall, 2 threads)\nbefore / after: "
            + "; ".join(f"{k} {v['before']:.2f} / {v['after']:.2f}" for k, v in med.items())
            + f" (1-minute load {min(loads):.1f}-{max(loads):.1f}: wall times this loaded "
            "vary 2-5x between runs)."
        )
    return (
        "**Tracer refactor** (`benchmarks.trace_ab`: the split `trace_paths` (B) against the "
        "62-argument kernel (A),\none process per checkout, renders alternating; rays per "
        "second of process CPU time, single-threaded,\nmedian B/A): "
        + "; ".join(rows)
        + ".\nImages are bit-identical (Cornell, plane under a peaked sky, boxes, Sponza; both "
        "samplers)." + tp + "\n"
    )


#: paired A/B runs of the tracer's speed changes: (results name, what B changed against A,
#: kept in the code)
TRACE_SPEED_AB = (
    ("nrt", "megakernel without numba's reference counting (`_nrt=False`)", True),
    ("zero_in_kernel", "per-sample outputs zeroed in the kernel, not in a separate pass", True),
    ("branch", "both, against the branch's base", True),
    ("bitrev", "LLVM's bitreverse in the Sobol scrambling", False),
    ("tiles", "pixels walked in 8x8 tiles instead of rows", False),
    (
        "concentric",
        "cosine sampling on Shirley-Chiu's concentric disk, sin/cos by short polynomials "
        "(other samples: RMSE per spp checked, `trace_rmse_ab.py`)",
        True,
    ),
    (
        "fused",
        "samples added to their pixels' statistics in the kernel (no per-sample buffers, no "
        "serial merge)",
        True,
    ),
    ("fused2t", "the same, 2 threads", True),
    ("divisions", "reciprocals instead of repeated divisions (normalising, RR, MIS)", False),
    (
        "stride",
        "scratch rows 64 apart (8 apart, both threads' one-byte first-hit flags shared a cache "
        "line)",
        True,
    ),
    (
        "cameras",
        "camera rays from one helper that also gives thin-lens and orthographic cameras an "
        "origin per sample (a pinhole: one branch on the camera kind)",
        True,
    ),
    (
        "fastmath",
        "LLVM fast-math flags but NaN/Inf semantics (contract, arcp, nsz, afn, reassoc; images "
        "not bit-identical)",
        False,
    ),
    (
        "overhead",
        "per render: only the sample counts zeroed (a pixel's first sample sets its "
        "statistics), no copies of the outputs",
        True,
    ),
    (
        "queue",
        "the two threads take blocks of samples from one shared queue (an atomic counter) "
        "instead of every other block (blocks of 64 pixels alternated: column bands of unequal "
        "cost on Sponza, and a thread the VM slows holds up the pass)",
        True,
    ),
    (
        "queue1spp",
        "the same, 1 spp (a block is then one whole row: the old split alternated rows, little "
        "to balance)",
        True,
    ),
    (
        "passes1spp",
        "each pass's (pixel, sample) lists: the whole image's kept by the workspace per (size, "
        "k), only the first sample index added per pass (they were rebuilt from numpy repeats "
        "every pass: 5-10 ms at 256^2, 4 spp a pass), 1 spp",
        True,
    ),
    ("passes8spp", "the same, 8 spp (2 passes)", True),
    ("passes32spp", "the same, 32 spp (8 passes)", True),
    (
        "outputs1spp",
        "a render's float32 outputs as views of one block (one allocation of >= 4 MiB gets huge "
        "pages: fewer page faults on first write), 1 spp",
        True,
    ),
    ("outputs4spp", "the same, 4 spp", True),
    (
        "wrap",
        "a texel index's repeat wrap by a bit mask where the texture's side is a power of two "
        "(two integer divisions a texture lookup before)",
        True,
    ),
    ("wrap2t", "the same, 2 threads", True),
    (
        "texprefetch",
        "a textured vertex's texels prefetched at its hit and read after its shadow rays, its "
        "light samples held until then: the wait for a bounce's texels, anywhere in the "
        "textures' megabytes, overlaps the shadow rays (Cornell box: no textures)",
        True,
    ),
    (
        "specialised",
        "what the Cornell box does not use (textures, sky, suns, point/spot lights, branches, "
        "the ray log) compiled out of the kernel: the cost of one kernel for every scene "
        "(an experiment; a kernel per scene kind would cost a ~45 s compile each)",
        False,
    ),
)
#: rows of TRACE_SPEED_AB whose ratio is of wall time: they change how the threads share the
#: work, which saves one thread's waiting for the other, not CPU time
TRACE_SPEED_WALL = {
    "queue",
    "queue1spp",
    "passes1spp",
    "passes8spp",
    "passes32spp",
    "outputs1spp",
    "outputs4spp",
}


def block_trace_cameras(results: Path) -> str:
    d = load("trace/cameras.json", results)
    a, s = d["args"], d["summary"]
    loads = d["load_1min"]
    lines = [
        "**Camera models** (`benchmarks.trace_cameras`): the Cornell box through the scene's "
        "pinhole, a thin lens focused\non the box's centre (aperture 5 % of that distance) and an "
        "orthographic camera framing the box, alternating in\none process; median rays per "
        "second of process CPU time and median per-round ratio to the pinhole (the views\n"
        "differ, so the ratio bounds the camera's cost rather than isolating it), "
        f"{a['size']}^2, {a['spp']} spp, {a['threads']} thread(s),\n{a['rounds']} rounds, "
        f"1-minute load {min(loads):.1f}-{max(loads):.1f}.",
        "",
        "| camera | Mrays / CPU s | ratio to pinhole | rays per render |",
        "|---|---|---|---|",
    ]
    for name, row in s.items():
        lines.append(
            f"| {name} | {row['median_mrays_per_cpu_s']:.3f} | "
            f"{row['median_cpu_ratio_to_pinhole']:.3f} | {row['rays_per_render']} |"
        )
    return "\n".join(lines) + "\n"


def block_trace_speed(results: Path) -> str:
    lines = [
        "**Tracer speed changes** (`benchmarks.trace_ab`, paired A/B: one process per "
        "checkout, renders alternating,",
        "median ratio B/A of rays per second of process CPU time (quartiles; of wall time "
        "where the cell says so); images "
        "bit-identical, so the error per sample is unchanged, unless the change says otherwise):",
        "",
        "| change (B) | kept | Cornell box | Sponza | size, spp, threads, rounds, 1-minute load |",
        "|---|---|---|---|---|",
    ]
    for key, what, kept in TRACE_SPEED_AB:
        cells, meta, rounds, loads = [], "", [], []
        for scene in ("cornell_box", "sponza"):
            found = sorted((results / "trace").glob(f"ab_{key}_{scene}*.json"))
            if not found:
                cells.append("n/a")
                continue
            runs = []  # every run of this change (a rerun: ab_<key>_<scene>_rerun.json)
            for path in found:
                d = json.loads(path.read_text())
                if key in TRACE_SPEED_WALL:
                    q = d["ratio_quartiles"]
                    runs.append(
                        f"wall {d['median_ratio_b_over_a']:.3f} ({q[0]:.3f}-{q[-1]:.3f}), CPU "
                        f"{d['median_cpu_ratio_b_over_a']:.3f}"
                    )
                else:
                    q = d["cpu_ratio_quartiles"]
                    runs.append(f"{d['median_cpu_ratio_b_over_a']:.3f} ({q[0]:.3f}-{q[-1]:.3f})")
                meta = f"{d['args']['size']}^2, {d['args']['spp']}, {d['args']['threads']}"
                rounds.append(str(len(d["rounds"])))
                loads += d["load_1min"]
            cells.append("; rerun ".join(runs))
        if loads:
            meta += f", {'/'.join(rounds)}, {min(loads):.1f}-{max(loads):.1f}"
        lines.append(
            f"| {what} | {'yes' if kept else 'no'} | " + " | ".join(cells) + f" | {meta} |"
        )
    lines.append("")
    # changes that alter the samples: their error per sample (trace_rmse_ab.py)
    for path in sorted((results / "trace").glob("rmse_ab_*.json")):
        d = json.loads(path.read_text())
        a, rows = d["args"], d["rows"]
        worst_se = max(max(r["se_a"], r["se_b"]) / r["rmse_a"] for r in rows)
        lines.append(
            f"- Error per sample, `{path.name}` (`benchmarks.trace_rmse_ab`, {a['scene']}, "
            f"{a['size']}^2, {a['seeds']} seeds a point, robust Embree in both): RMSE B/A "
            + ", ".join(f"{r['b_over_a']:.3f} at {r['spp']} spp" for r in rows)
            + f" (standard errors up to {100 * worst_se:.1f} % of the RMSE)."
        )
    lines.append("")
    return "\n".join(lines)


def block_gan_figure7(results: Path) -> str:
    d = load("gan/figure7.json", results)
    cfg = load("gan/figure7_config.json", results)
    a, sm, ce = cfg["args"], d["summary"], d["noise_ceiling"]
    tc = next(iter(cfg["train_configs"].values()))
    it = sm["common_iteration"]
    at = sm["at_common_iteration"]
    fs = d.get("final_scores", {})
    paths = [p for p in ("test", "walk") if any(p in v for v in fs.values())]
    tag = "cover" if "cover" in tc["train_path"] else "train"

    def scores(v: dict | None) -> str:
        return " | ".join(
            f"{v[p]['ssim']:.3f} / {v[p]['mse']:.0f}" if v and p in v else "-" for p in paths
        )

    rows = "\n".join(
        f"| {c} | {at[c]['ssim']:.3f} | {at[c]['mse']:.0f} | "
        f"{sm['first_iteration_reaching_target'][c] or '-'} |"
        + (f" {scores(fs.get(c))} |" if paths else "")
        for c in sorted(at)
    )
    base_rows = ""
    if paths and (results / f"gan/baselines_{tag}.json").is_file():
        bl = load(f"gan/baselines_{tag}.json", results)["paths"]
        names = ("constant", "albedo x k", "nearest irradiance", "warp + inpaint",
                 "tracer 1 spp + OIDN")  # fmt: skip
        base_rows = "\n" + "\n".join(
            f"| {n} (no network) | - | - | - | "
            + scores({p: bl[p]["methods"][n] for p in paths if n in bl[p]["methods"]})
            + " |"
            for n in names
        )
    pairs = ", ".join(
        f"{p['world']} vs {p['view']} {p['ssim_world_minus_view']:+.3f}"
        for p in sm["world_vs_view_normals"]
    )
    ceiling = (
        f"the test truth's own noise ceiling (two traces with other seeds, {len(ce['views'])} "
        f"views) is SSIM {ce['ssim_mean']:.3f}"
        if ce
        else "no noise ceiling measured"
    )
    preset = a.get("preset", "paper-cpu")
    what = (
        f"`{preset}` preset (position features in the configurations that have positions), "
        f"trained on `{tc['train_path']}`, {tc['crop']}-pixel crops, base {tc['base']}"
        if preset == "cpu"
        else f"`paper-cpu` preset, {tc['crop']}-pixel crops, base {tc['base']}, no VGG19 file so "
        "no perceptual term"
    )
    head = "| configuration | SSIM | MSE | reaches target at |"
    sep = "|---|---|---|---|"
    if paths:
        head += " " + " | ".join(f"{p} (every view)" for p in paths) + " |"
        sep += "---|" * len(paths)
    n_test = next((v["test"]["views"] for v in fs.values() if "test" in v), None)
    n_walk = next((v["walk"]["views"] for v in fs.values() if "walk" in v), None)
    views = (
        f" Last two columns: SSIM / MSE of the last checkpoint over every view of the test path "
        f"({n_test}) and of the held-out walk ({n_walk}); the no-network rows are fitted on the "
        f"same views (`benchmarks.gan_baselines --tag {tag}`)."
        if paths
        else ""
    )
    tail = "" if paths else _demodulated(results) + _baseline_line(results)
    return (
        "**GAN pre-renderer, Figure 7** (`benchmarks.gan_figure7`, Sponza at 128x128; "
        f"{what}; {ceiling}).\nTest SSIM / MSE (display scale, 0-255, every test view) after "
        f"{it} iterations, and the first evaluated iteration reaching SSIM "
        f"{sm['target_ssim']}.{views}\n\n"
        f"{head}\n{sep}\n{rows}{base_rows}\n\nBest: {sm['best']}. World normals minus view "
        f"normals (SSIM): {pairs}.\n" + tail
    )


def _demodulated(results: Path) -> str:
    rel = "gan/demodulated/figure7.json"
    if not (results / rel).is_file():
        return ""
    cv = load(rel, results)["curves"]
    parts = ", ".join(
        f"{c} {v['ssim'][-1]:.3f} at iteration {v['iteration'][-1]}" for c, v in sorted(cv.items())
    )
    return (
        "With albedo demodulation (`--demodulate`, our addition: the network learns GI / albedo, "
        f"`{rel}`): {parts}.\n"
    )


def block_gan_figure8(results: Path) -> str:
    lines = []
    for rel, what in (
        ("gan/figure8.json", "Figure 7's best"),
        ("gan/preset/figure8.json", "the `cpu` preset (the run of the time-against-error block)"),
        (
            "gan/recipe/figure8.json",
            "the `cpu` preset before the speed study (current store)",
        ),
        ("gan/demodulated/figure8.json", "an early study with albedo demodulation"),
    ):
        if not (results / rel).is_file():
            continue
        d = load(rel, results)
        m = d["mean"]
        lines.append(
            f"- {what}: configuration {Path(d['run']).name} ({', '.join(d['inputs'])}) at "
            f"iteration {d['iteration']}, {len(d['frames'])} test frames: SSIM {m['ssim']:.3f}, "
            f"MSE {m['mse']:.0f}, FLIP {m['flip']:.3f} (`{rel.replace('.json', '.png')}`)"
        )
    return (
        "**Figure 8** (`benchmarks.gan_figure8`: generated | traced | difference x4 on test "
        "frames spread along the test path):\n\n"
        + "\n".join(lines)
        + "\n"
        + _baseline_line(results)
    )


def block_gan_time_error(results: Path) -> str:
    d = load("gan/time_error.json", results)
    e = d["summary"]["equal_ssim"]
    sizes = d["summary"]["generator_ms_by_size"]
    targets = e["target_speedup"]
    if not isinstance(targets, dict):  # results written before the equal-quality rule
        targets = {"raw": targets, "denoised": targets}

    def speed(kind: str) -> str:
        from icbtool.gan.baselines import equal_quality

        pts = d["summary"]["tracer"][kind]
        # recomputed from the measured curve (results written before the equal-quality rule
        # took the cheapest point whenever it was already better)
        eq = equal_quality([p["ms"] for p in pts], [p["ssim"] for p in pts], e["ssim"])
        t = {
            "tracer_ms": eq.cost,
            "status": eq.status,
            "cheapest": {"ms": eq.cheapest[0], "ssim": eq.cheapest[1]},
            "speedup": None if eq.cost is None else eq.cost / e["ms"],
        }
        status = t["status"]
        if status == "above":
            c = t["cheapest"]
            return (
                f"{kind}: no equal point, its cheapest setting ({c['ms']:.0f} ms) already scores "
                f"{c['ssim']:.3f}"
            )
        if t["tracer_ms"] is None:
            return f"{kind}: never reaches it in the measured spp"
        ok = "met" if t["speedup"] >= targets[kind] else "NOT met"
        return (
            f"{kind}: {t['tracer_ms']:.0f} ms ({status}), {t['speedup']:.0f}x "
            f"(target {targets[kind]}x: {ok})"
        )

    size_txt = "; ".join(
        f"{side}: torch {v['torch_1t']:.0f} / {v['torch_2t']:.0f} ms, onnxruntime "
        f"{v['onnxruntime_1t']:.0f} / {v['onnxruntime_2t']:.0f} ms"
        for side, v in sizes.items()
    )
    load_txt = ""
    if "load_1min" in d:
        load_txt = f" 1-minute load {d['load_1min'][0]:.1f} at the start."
    return (
        "**Generator against path tracer** (`benchmarks.gan_time_error`, Sponza test frames at "
        f"the store's size, run {Path(d['run']).name}; equal SSIM found on the tracer's measured "
        f"curve):\nthe generator ({e['generator']}) takes "
        f"{e['ms']:.1f} ms for SSIM {e['ssim']:.3f}; the path tracer at that SSIM: "
        f"{speed('raw')}; {speed('denoised')}.\nGenerator alone (1 / 2 threads), by size: "
        f"{size_txt}.{load_txt}\n"
        + _baseline_line(results, "cover" if "cover" in d.get("train_path", "") else "train")
    )


def block_lpm(results: Path) -> str:
    d = load("lpm/sponza.json", results)
    e = d["eval_config"]
    rows = []
    for lv in d["levels"]:
        g, c, ff = lv["geometric"], lv["client"], lv["first_frame"]
        w = lv.get("warp", {})
        rows.append(
            f"| {lv['level']} ({100 * lv['ratio']:.0f} %) | {lv['triangles']:,} | "
            f"{lv['bytes_geometry'] / 1e6:.2f} + {lv['bytes_texture'] / 1e6:.2f} | "
            f"{g['rms']:.1e} / {g['hausdorff']:.1e} | {100 * c['depth_bad_fraction']:.1f} % | "
            f"{c['dl_ssim']:.3f} | {w.get('ssim', float('nan')):.3f} | "
            f"{ff['total_s']['10Mbit']:.2f} s |"
        )
    return (
        "**LPM levels** (`benchmarks.lpm_levels`, Sponza, open3d quadric decimation with one "
        f"queue over the material groups; {e['n_cameras']} cameras of the test path at "
        f"{e['height']}x{e['width']}; geometric error as a fraction of the bounding-box "
        "diagonal; the reference GI warped with the level's depth against the full mesh's; "
        "first frame = chunks, 10 Mbit/s transfer, assemble, first raster; layout in "
        "`docs/lpm.md`):\n\n"
        "| level | triangles | MB geometry + textures | RMS / Hausdorff | depth off > 1 % | "
        "DL SSIM | warp SSIM | first frame |\n|---|---|---|---|---|---|---|---|\n"
        + "\n".join(rows)
        + f"\n\nBuilding all levels: {d['build_total_s']:.1f} s.\n"
    )


def _gated_how(cfg: dict) -> str:
    """How gan_warped's gated generator was trained (its runs before it had none)."""
    g = cfg["train_configs"].get("gated")
    if not g:
        return ""
    return (
        " (gated generator: the warped generator with `reference_gate`, "
        f"`weight_generated` {g['weight_generated']:g}, `reference_dropout` "
        f"{g['reference_dropout']:g})"
    )


def block_gan_warped(results: Path) -> str:
    d = load("gan/warped/warped.json", results)
    cfg = load("gan/warped/warped_config.json", results)
    it = d["evals_pure"][-1]["iteration"]
    ks = sorted(d["offsets"], key=int)
    methods = [m for m in d["offsets"][ks[0]] if isinstance(d["offsets"][ks[0]][m], dict)]

    def frames(k: str) -> str:
        f = d["offsets"][k]["frames_back"]
        return f"{f:.0f}" if float(f).is_integer() else f"{f:.1f}"

    head = " | ".join(f"{frames(k)} frames back" for k in ks)
    rows = "\n".join(
        f"| {m} | "
        + " | ".join(
            f"{d['offsets'][k][m]['ssim_mean']:.3f} ({d['offsets'][k][m]['ssim_holes_mean']:.3f})"
            for k in ks
        )
        + " |"
        for m in methods
    )
    holes = " / ".join(f"{d['offsets'][k]['holes_pct_mean']:.1f}" for k in ks)
    tc = cfg["train_configs"]["pure"]
    preset = cfg["args"].get("preset", "paper-cpu")
    how = (
        f"the `{preset}` preset on `{tc['train_path']}`"
        if preset == "cpu"
        else "the Figure 7 settings"
    )
    tag = "cover" if "cover" in tc["train_path"] else "train"
    return (
        "**Beyond the paper: the generator with the warped reference** "
        f"(`benchmarks.gan_warped`, configuration {cfg['args']['inputs']}, the generators "
        f"trained {it} iterations with {how}{_gated_how(cfg)}; {d['views']} test views, the "
        "reference k test "
        "views earlier (frames back: the median distance along the test path); mean test SSIM "
        "of the frame (in brackets: of the hole pixels alone); holes after warping "
        f"{holes} % of the pixels):\n\n| method | {head} |\n|---|"
        + "---|" * len(ks)
        + f"\n{rows}\n"
        + _baseline_line(results, tag)
    )


def block_gan_spp(results: Path) -> str:
    d = load("gan/spp/spp.json", results)
    rows = "\n".join(
        f"| {name} | {v['bake_s']:.0f} s ({v['bake_s_per_view']:.2f} s/view) | "
        f"{v['final_ssim']:.3f} | {v['final_mse']:.0f} |"
        for name, v in d["sets"].items()
    )
    it = next(iter(d["sets"].values()))["iteration"][-1]
    return (
        "**The cost of the data** (`benchmarks.gan_spp`: configuration J trained "
        f"{it} iterations with the Figure 7 settings on the train path (150 views, 128x128) "
        "baked at each sample count, noisy targets unless denoised; the same 256-spp test truth; "
        "baking times are the records' own, taken when each store was baked, under different "
        "loads of this 2-core machine):\n\n| train targets | baking time | test SSIM | test MSE "
        f"|\n|---|---|---|---|\n{rows}\n" + _baseline_line(results)
    )


def block_net(results: Path) -> str:
    d = load("net/net_latency.json", results)
    c, b = d["config"], d["bytes"]
    nets: dict[str, dict[str, Any]] = {}
    for e in d["latency"]:
        nets.setdefault(e["network"], {})[e["phase"]] = e

    def cell(e: dict[str, Any] | None, mode: str, transfer: bool = True) -> str:
        if e is None or mode not in e["median_request_ms"]:
            return "-"
        key = "median_generate_ms" if mode == "generator" else "median_request_ms"
        txt = f"{e[key][mode]:.0f} ms"
        if transfer and mode != "generator":
            txt += f" ({e['median_transfer_ms'][mode]:.0f})"
        return txt

    def name(net: str) -> str:
        return "loopback" if net.startswith("0ms/inf") else net.replace("/", " / ") + "/s"

    rows = "\n".join(
        f"| {name(n)} | {cell(ph.get('cold'), 'cloud_render')} | "
        f"{cell(ph.get('warm'), 'cache_hit')} | {cell(ph.get('generator'), 'generator')} | "
        f"{ph['generator']['first_frame_ms'] / 1e3:.1f} s |"
        for n, ph in nets.items()
        if "generator" in ph
    )
    ff: dict[str, dict[str, Any]] = {}
    build = ""
    for r in d["first_frame"]["runs"]:
        if "network" in r:
            ff.setdefault(r["network"], {})[r["mesh"]] = r
        elif "lpm_build_s" in r:
            build = f"; LPM build {r['lpm_build_s']:.1f} s once on the server"
    lv0 = next(iter(ff.values()))["lpm_level0"]
    full = next(iter(ff.values()))["full_mesh"]
    ff_rows = "\n".join(
        f"| {name(n)} | {v['lpm_level0']['mesh_in_hand_ms'] / 1e3:.2f} s / "
        f"{v['lpm_level0']['first_frame_ms'] / 1e3:.1f} s | "
        f"{v['full_mesh']['mesh_in_hand_ms'] / 1e3:.2f} s / "
        f"{v['full_mesh']['first_frame_ms'] / 1e3:.1f} s |"
        for n, v in ff.items()
    )
    tp = ", ".join(
        f"{t['clients']} client{'s' if t['clients'] > 1 else ''} {t['replies_per_s']:.0f}/s "
        f"(p50 {t['p50_ms']:.0f} ms, p99 {t['p99_ms']:.0f} ms, {t['errors']} errors)"
        for t in d["throughput"]
        if "clients" in t
    )
    la = d.get("load_average") or [float("nan")]
    return (
        f"**Networked system** (`benchmarks.net_latency`: {c['scene']}, {c['size']} x "
        f"{c['size']} client, {c['spp']} spp GI, default codecs, {c['frames']} frames per run, "
        f"medians; load average {la[0]:.1f} at the end). Request -> reply (of which transfer), "
        "or the local generator's time (an untrained U-Net of the paper's shape, base 32: "
        "timing only), and the time to the first frame when the generator is shipped first:\n\n"
        "| network (RTT / rate) | cloud render | cache hit | local generator | first frame with "
        "the generator |\n|---|---|---|---|---|\n"
        f"{rows}\n\nA GI reply is {b['gi_reply_bytes_per_frame'] / 1e3:.1f} kB; the generator "
        f"{b['generator_bytes'] / 1e6:.1f} MB: shipping it pays off after "
        f"{b['break_even_frames']:.0f} remote frames ({b['break_even_frames'] / 30:.0f} s at 30 "
        "fps).\n\nFirst rasterized frame with the LPM's coarsest level "
        f"({lv0['triangles']:,} triangles; {lv0['bytes_received'] / 1e3:.0f} kB received in all, "
        "handshake and scene_info with the camera paths included: the level itself is its "
        "`scene_info.lpm.levels[0].bytes`, the LPM table below) against the full "
        f"mesh ({full['triangles']:,} triangles, {full['bytes_received'] / 1e6:.1f} MB received), "
        "Sponza; "
        f"mesh in hand / first frame (including the client's rasterizer set-up){build}:\n\n"
        "| network | LPM level 0 | full mesh |\n|---|---|---|\n"
        f"{ff_rows}\n\nThroughput on loopback (cache hits, clients asking at once): {tp}.\n"
    )


def block_web(results: Path) -> str:
    files = [("Cornell box", "web/web_client.json"), ("Sponza", "web/sponza/web_client.json")]
    runs = [(name, load(rel, results)) for name, rel in files if (results / rel).is_file()]
    if not runs:
        load(files[0][1], results)  # raises, naming the missing file
    gl = runs[0][1]["stages"][0]["gl_renderer"]
    backend = "SwiftShader" if "SwiftShader" in gl else gl
    cols = [(name, e) for name, d in runs for e in d["stages"]]
    hdr = " | ".join(f"{n} {e['size']}x{e['size']}" for n, e in cols)

    def row(label: str, get: Callable[[dict[str, Any]], float], unit: str = "ms") -> str:
        return f"| {label} | " + " | ".join(f"{get(e):.1f} {unit}" for _, e in cols) + " |"

    def med(k: str) -> Callable[[dict[str, Any]], float]:
        return lambda e: e["median"][k]

    rows = "\n".join(
        [
            row("raster: G-buffers + DL (one MRT pass, shadows)", med("raster_ms")),
            row("GI request -> reply (cache hit)", med("request_ms")),
            row("of which server", med("server_ms")),
            row("of which transfer", med("transfer_ms")),
            row("decode (f16m7-diff-zstd GI, f16-diff-zstd depth + mask)", med("decode_ms")),
            row("warp + combine + fill + blend", med("warp_ms")),
            row("generate (onnxruntime-web, U-Net base 32)", lambda e: e["generate"]["median_ms"]),
            row(
                "bytes received per frame (gi_reply)",
                lambda e: e["gi_reply_bytes_per_frame"] / 1e3,
                "kB",
            ),
            row("mesh received (all LPM levels)", lambda e: e["mesh_bytes"] / 1e3, "kB"),
        ]
    )
    ff_rows = []
    rtts: list[float] = []
    for name, d in runs:
        ff: dict[str, dict[float, dict[str, Any]]] = {}
        for f in d["first_frame"]:
            ff.setdefault(f["mesh"], {})[f["rtt_ms"]] = f
        rtts = sorted(next(iter(ff.values())))
        for m, label in (("lpm_level0", "LPM level 0"), ("full_mesh", "full mesh")):
            if m in ff:
                kb = ff[m][rtts[0]]["lpm_bytes"] / 1e3
                ff_rows.append(
                    f"| {name}, {label} ({kb:,.0f} kB of mesh in by then) | "
                    + " | ".join(f"{ff[m][r]['first_frame_ms'] / 1e3:.2f} s" for r in rtts)
                    + " |"
                )
    loads = [x for _, d in runs for x in walk_load_averages(d)]
    gen = cols[0][1]["generate"]
    text = (
        f"**Web client** (`benchmarks.web_client`, chromium {runs[0][1]['chromium']} headless: "
        f"WebGL2 on **{backend}**, i.e. on the CPU: no GPU here; every number below is a "
        f"{backend} number. The test path walked twice, medians of the second walk (GI from "
        f"the store); server {runs[0][1]['config']['spp']} spp GI, denoised; load average "
        f"{span(loads, f2)}: other jobs were running):\n\n"
        f"| stage ({backend}) | {hdr} |\n|---|" + "---|" * len(cols) + "\n"
        f"{rows}\n\n"
        f"onnxruntime-web ran with {gen['threads']} WebAssembly thread(s) (the page is "
        "cross-origin isolated). First frame (opening the page to the first finished frame: "
        "page, handshake, mesh, raster, GI (a store hit), warp; 128x128, "
        f"{backend}; median of {runs[0][1]['config'].get('repeats', 1)} runs: differences under "
        "about a second are within this loaded machine's noise) by emulated round trip:\n\n"
        "| scene, mesh sent | "
        + " | ".join(f"{r:g} ms" for r in rtts)
        + " |\n|---|"
        + "---|" * len(rtts)
        + "\n"
        + "\n".join(ff_rows)
        + "\n"
    )
    for name, d in runs:
        acc = d.get("accuracy")
        if not acc:
            continue
        w = acc["wrt"]
        g = [e["generate"] for e in d["stages"] if "max_abs_diff_vs_onnxruntime" in e["generate"]]
        text += (
            f"\nAgainst icbtool ({name}, {acc['size']}x{acc['size']}, {len(w)} cameras): coverage "
            f"agrees on {100 * min(x['mask_agree'] for x in w):.2f} %+ of pixels, depth p99 "
            f"relative error {max(x['depth_rel_p99'] for x in w):.1e}, normals p99 "
            f"{max(x['normal_deg_p99'] for x in w):.2f} degree, albedo mean error "
            f"{max(x['albedo_abs_mean'] for x in w):.1e}, DL mean error "
            f"{100 * max(x['dl_rel_mean'] for x in w if x['dl_rel_mean'] is not None):.1f} % "
            "of the DL mean (p99 "
            f"{max(x['dl_p99'] for x in w):.3f}); final frames vs the Python client's SSIM "
            f"{span(acc['ssim_final'], lambda v: f'{v:.3f}')} over {len(acc['ssim_final'])} "
            "frames"
        )
        if g:
            text += (
                "; the generator in onnxruntime-web vs onnxruntime max abs difference "
                + " / ".join(f"{x['max_abs_diff_vs_onnxruntime']:.1e}" for x in g)
            )
        text += ".\n"
    return text


def _net_profile(d: dict) -> str:
    """The hit profile and the before/after runs of net_scale.json (--part profile / ab)."""
    text = ""
    p = d.get("profile")
    if p:
        su, cu, rec = p["server_us"], p["client_us"], p["record"]
        steps = "; ".join(f"{k} {v:.0f}" for k, v in su.items())
        lo = p["load"]
        one = lo.get("1 lean client", {})
        many = {k: v for k, v in lo.items() if k != "1 lean client"}
        rows = "\n".join(
            f"| {k} | {v['hits_per_s']:.0f} | {v['p50_ms']:.1f} / {v['p99_ms']:.1f} ms | "
            f"{v['server_cpu_ms_per_hit']:.2f} ms ({v['server_event_loop_cpu_ms_per_hit']:.2f}) | "
            f"{v['clients_cpu_ms_per_hit']:.2f} ms | {v['load_average']:.1f} |"
            for k, v in lo.items()
        )
        text += (
            f"\nWhere a hit's time goes (`--part profile`; a {rec['height']}x{rec['width']} "
            f"record, {rec['stored_bytes'] / 1e3:.0f} kB stored, a {rec['reply_bytes'] / 1e3:.1f} "
            f"kB reply). Each step alone, median microseconds on the server: {steps}. A client "
            f"seals a request in {cu['request: build + seal']:.0f}, opens a reply in "
            f"{cu['reply: open + parse + validate']:.0f} and decodes its codecs in "
            f"{cu['reply: codec decode (gi, depth, mask)']:.0f}. Hits alone (no misses), "
            "closed loop; CPU per hit of the server process (of it, its event-loop thread) and of "
            "the clients' process:\n\n"
            "| clients | hits/s | p50 / p99 | server CPU / hit | clients CPU / hit | load avg |\n"
            f"|---|---|---|---|---|---|\n{rows}\n"
        )
        if one and many:
            text += (
                f"\nOne client alone waits {one['p50_ms']:.1f} ms (p50) for a hit. With N "
                "clients that send again as soon as they are answered, latency = N / throughput "
                "(Little's law), and the server's event loop is one thread: at "
                f"{max(v['server_event_loop_cpu_ms_per_hit'] for v in many.values()):.2f} ms "
                "of it per hit, 32 clients wait at least 32 x that per round even with a whole "
                "core for the server.\n"
            )
    ab = d.get("ab")
    if ab:
        b, a = ab["median"]["before"], ab["median"]["after"]
        n = len(ab["rounds"]) // 2
        text += (
            f"\nBefore / after this hit path (`--part ab`: the previous server and this one, "
            f"alternately, {n} rounds each, 32 lean clients, hits alone, medians): "
            f"{b['hits_per_s']:.0f} -> {a['hits_per_s']:.0f} hits/s, p50 {b['p50_ms']:.0f} -> "
            f"{a['p50_ms']:.0f} ms, p99 {b['p99_ms']:.0f} -> {a['p99_ms']:.0f} ms, server CPU "
            f"per hit {b['server_cpu_ms_per_hit']:.2f} -> {a['server_cpu_ms_per_hit']:.2f} ms; "
            "load average " + ", ".join(f"{x['load_average']:.1f}" for x in ab["rounds"]) + ".\n"
        )
    return text


def block_net_scale(results: Path) -> str:
    d = load("net/net_scale.json", results)
    hc = d["config"]["hits"]

    def cost(h: dict, k: str) -> str:
        c = h.get(k)
        return f"{c['hits_per_s']:.0f}/s, {c['server_cpu_ms_per_hit']:.2f} ms" if c else "-"

    def ms(h: dict, k: str) -> str:
        return "-" if h.get(k) is None else f"{h[k]:.0f}"

    rows = "\n".join(
        f"| {h['workers']} | {ms(h, 'idle_hit_p50_ms')} / {ms(h, 'idle_hit_p99_ms')} / "
        f"{ms(h, 'idle_hit_max_ms')} ms | {cost(h, 'idle')} | {h['hits_during_misses']} | "
        f"{h.get('coalesced_during_misses', '-')} | {ms(h, 'hit_p50_ms')} / "
        f"{ms(h, 'hit_p99_ms')} / {ms(h, 'hit_max_ms')} ms | {cost(h, 'during')} | "
        f"{h['miss_median_ms'] / 1e3:.1f} s ({h['misses']}) | {h['n_errors']} | "
        f"{h.get('load_average_start', float('nan')):.1f} / {h['load_average_end']:.1f} |"
        for h in d["hits"]
    )
    cams = {h.get("hit_cameras") for h in d["hits"]}
    cams_text = (
        f"each its own camera ({cams.pop()} distinct cameras along the test path, so every hit "
        "is a lookup of its own; replies shared with another request (`coalesced`) are counted "
        "apart, never as hits)"
        if len(cams) == 1 and None not in cams
        else "replaying a shared set of 4 cameras (most replies coalesced)"
    )
    client = {
        "lean": "one event loop for all of them: each reply opened and verified, its codecs not "
        "decoded",
        "full": "NetworkSource clients, a thread each, codecs decoded",
    }[hc.get("hit_client", "full")]
    b = d["bake"]
    brows = "\n".join(
        f"| {r['mode']} | {r['records_per_min']:.1f} | "
        f"{'yes' if r['identical_to_single'] else 'NO'} | {r['load_average_end']:.1f} |"
        for r in b["runs"]
    )
    a = d["attack"]
    loop = all(x["sockets"]["all_loopback"] for x in [*d["hits"], b])
    rounds = ", ".join(f"{x:.0f}" for x in a["rss_after_each_round_mb"])
    return (
        f"**The cloud at scale** (`benchmarks.net_scale`, cornell_box, `icbtool serve` in its "
        f"own process, in-process renders (0 workers) or local Dask workers, {hc['spp']} spp "
        f"denoised GI). {hc['hit_clients']} clients ask for cache hits, {cams_text} "
        f"({hc['hit_size']}^2; {client}), while {hc['miss_clients']} clients ask for "
        f"{hc['miss_size']}^2 misses; hit latency measured while the misses render (before this "
        "design a miss held every hit behind it: 32-37 s), throughput and server CPU per hit "
        "alone and during the misses. Measured on a shared 2-core machine under the load "
        "given (other work ran beside it): the latencies are of that machine, not of a quiet "
        "one:\n\n"
        "| render workers | hits alone p50 / p99 / max | alone: hits/s, server CPU / hit | "
        "hits during the misses | coalesced replies during | hit p50 / p99 / max | during: "
        "hits/s, server CPU / hit | miss (count) | errors | load avg start / end |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
        f"{rows}\n"
        f"{_net_profile(d)}\n"
        f"Bake throughput, {b['views']} views of the test path at {b['size']}^2, {b['spp']} spp "
        f"(after one warm-up view per worker; median of {b['repeats']} interleaved rounds), and "
        "whether every record equals the single-process bake bit for bit:\n\n"
        "| bake | records/min | identical | load avg |\n|---|---|---|---|\n"
        f"{brows}\n\n"
        f"Server memory under the protocol's attack set (8192^2 requests, id 2^53, LPM ranges "
        f"with no level, velocity 1e308, fx = 0, duplicate ids, bursts, 80 malformed frames, a 9 "
        f"MB message, 30 silent connections), {len(a['rss_after_each_round_mb'])} rounds: RSS "
        f"{a['rss_before_mb']:.0f} MB before, {rounds} MB after each round; still serving: "
        f"{'yes' if a['still_serving_hits'] else 'NO'}. Every socket on 127.0.0.1 "
        f"(`ss -tnp`): {'yes' if loop else 'NO'}.\n"
    )


def block_cloud_memory(results: Path) -> str:
    """Where a miss's memory goes and whether the cloud gives it back (cloud_memory.json)."""
    d = load("net/cloud_memory.json", results)
    b, c = d["breakdown"], d["config"]
    st = {k: v["rss_mb"] for k, v in b["steps"].items()}
    w = st["warm"]
    steps = [
        ("after the trace (GI denoised)", "trace_render"),
        ("after the whole CRT-buffer (raster + trace), outputs still held", "crt_buffer"),
        ("outputs dropped", "crt_dropped"),
        ("tracer workspace dropped", "workspace_dropped"),
        ("heap trimmed (`malloc_trim(0)`)", "trimmed"),
        ("denoiser's device and filter dropped, trimmed again", "denoiser_dropped_trimmed"),
    ]
    brows = "\n".join(f"| {what} | {st[k]:.0f} | {st[k] - w:+.0f} |" for what, k in steps)
    peak = max(v["peak_mb"] for v in b["steps"].values())
    rows = "\n".join(
        f"| {r['workers']} | {r['before_mb']:.0f} | {r['peak_mb']:.0f} | {r['after_mb']:.0f} | "
        f"**{r['delta_mb']:+.0f}** | {r['burst_end_s'] - r['burst_start_s']:.0f} s | "
        f"{len(r['errors'])} | {r['load_average_start']:.1f} / {r['load_average_end']:.1f} |"
        for r in d.get("burst", [])
    )
    return (
        f"**Cloud memory** (`benchmarks.cloud_memory`, cornell_box). One {b['size']}^2 miss at "
        f"{b['spp']} spp rendered in one process as the server's in-process pool does, RSS after "
        f"each step (MB; {w:.0f} MB before, kernels and GL context loaded; peak {peak:.0f} MB). "
        f"The tracer's workspace was {b['workspace_mb']:.0f} MB, its outputs "
        f"{b['trace_outputs_mb']:.0f} MB, the CRT-buffer {b['crt_buffer_mb']:.0f} MB; load "
        f"average {b['load_average'][0]:.1f}:\n\n"
        "| step | RSS MB | vs before |\n|---|---|---|\n"
        f"{brows}\n\n"
        f"A burst of {c['burst']} misses at {c['size']}^2, {c['spp']} spp from 2 clients to "
        "`icbtool serve` (RSS of the server and all its worker processes, sampled every "
        f"{c['sample_s']} s; after: {c['after_s']:.0f} s after the last reply; plot "
        "`benchmarks/results/net/cloud_memory.png`). Measured on a shared 2-core machine under "
        "the load given: the renders are slow there, the memory is what it is:\n\n"
        "| render workers | before MB | peak MB | after MB | after - before | burst took | "
        "errors | load avg start / end |\n|---|---|---|---|---|---|---|---|\n"
        f"{rows}\n"
    )


def _bytes(n: int) -> str:
    """``12 B``, ``103 kB``, ``1.4 MB``."""
    if n < 1000:
        return f"{n} B"
    return f"{n / 1e3:.0f} kB" if n < 1e6 else f"{n / 1e6:.1f} MB"


def block_gi_codec(results: Path) -> str:
    """The codecs of GI and depth maps on the wire (``benchmarks.gi_codec``)."""
    d = load("net/gi_codec.json", results)
    rows = {(r["scene"], r["map"], r["codec"]): r for r in d["rows"]}
    codecs = ["f32-zstd", "f16-zstd", "f16-diff-zstd", "f16m7-diff-zstd", "log-u16-png", "rgbe-png"]

    def kib(scene: str, kind: str, codec: str, fmt: str = "{:.0f}") -> str:
        r = rows.get((scene, kind, codec))
        return "-" if r is None else fmt.format(r["bytes_mean"] / 1024)

    lines = [
        "**Codecs on the wire** (`benchmarks.gi_codec`, 256 x 256 maps of 3 views of the test "
        "path of the Cornell box and of Sponza, GI path-traced at 16 spp and denoised as the "
        'cloud does (and the same GI undenoised, "raw"), depth from a primary ray cast). '
        "Bytes are the mean per frame (raw float32 GI: 768 KiB; depth: 256 KiB); SSIM on the "
        "display scale, worst of all views and GI maps; relative error on values in "
        "[2^-14, 65504] (rgbe-png: of the pixel's largest channel); times are medians on a "
        "shared 2-core machine (compare codecs, not machines).",
        "",
        "| codec | Cornell GI denoised KiB | raw KiB | Sponza GI denoised KiB | raw KiB | worst "
        "display SSIM | largest rel. error | encode / decode ms (Sponza, denoised) | Cornell "
        "depth KiB | Sponza depth KiB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in codecs:
        gi = [r for (_, m, cc), r in rows.items() if cc == c and m.startswith("gi")]
        key = "max_pixel_rel_error" if c == "rgbe-png" else "max_rel_error"
        rel = f"{max(r[key] for r in gi):.1e}" + (" (of pixel max)" if c == "rgbe-png" else "")
        sp = rows["sponza", "gi_denoised", c]
        lines.append(
            f"| `{c}` | {kib('cornell_box', 'gi_denoised', c)} | {kib('cornell_box', 'gi_raw', c)}"
            f" | {kib('sponza', 'gi_denoised', c)} | {kib('sponza', 'gi_raw', c)} | "
            f"{min(r['ssim_min'] for r in gi):.5f} | {rel} | {sp['encode_ms']:.1f} / "
            f"{sp['decode_ms']:.1f} | {kib('cornell_box', 'depth', c, '{:.1f}')} | "
            f"{kib('sponza', 'depth', c, '{:.1f}')} |"
        )
    ch = d["choice"]
    lines += ["", f"Chosen: `{ch['gi']}` for GI, `{ch['depth']}` for depth and mask. {ch['rule']}"]
    return "\n".join(lines) + "\n"


def block_radiance_world(results: Path) -> str:
    """World-space GI on Sponza (``benchmarks.radiance_world``, one file per training set)."""
    runs = [
        ("train", load("radiance/world_sponza128.json", results)),
        ("train + cover", load("radiance/world_sponza128_cover.json", results)),
    ]
    names = {"hash grid": "hash grid", "probes": "probe volume", "albedo x k": "albedo x k"}
    names["constant"] = "constant"
    rows = []
    for fitted, d in runs:
        for key, label in names.items():
            if key == "constant" and fitted != "train":
                continue  # the constant is the same colour fitted on more pixels
            if key in d["table"]:
                rows.append((fitted, label, d["table"][key], d["speed"][key]["onnx_bytes"]))
    best = {
        (path, m): (min if m == "mse" or m == "flip" else max)(r[2][path][m] for r in rows)
        for path in ("test", "walk")
        for m in ("ssim", "mse", "flip")
    }

    def cell(e: dict, path: str) -> str:
        fmt = {"ssim": "{:.3f}", "mse": "{:.0f}", "flip": "{:.3f}"}
        return " / ".join(
            bold(
                fmt[m].format(e[path][m]), fmt[m].format(e[path][m]) == fmt[m].format(best[path, m])
            )
            for m in ("ssim", "mse", "flip")
        )

    c0, c1 = runs[0][1]["config"], runs[1][1]["config"]
    views = {p: runs[0][1]["table"]["hash grid"][p]["views"] for p in ("test", "walk")}
    grid_min = span([d["grid_train_s_total"] / 60 for _, d in runs], lambda x: f"{x:.1f}")
    probe_s = span([d["probe_fit_s"] for _, d in runs])
    loads = span([x for _, d in runs for x in (d["load_1min_before"], d["load_1min_after"])],
                 lambda x: f"{x:.1f}")  # fmt: skip
    lines = [
        "Sponza 128x128 (`benchmarks.radiance_world`, results in `benchmarks/results/radiance/`): "
        "mean SSIM / MSE (display scale 0-255) / FLIP (LDR) over all "
        f"{views['test']} test-path views and all {views['walk']} held-out random-walk views; "
        f"every method is fitted on the same train pixels ({runs[0][1]['train_records']} "
        f'train-path views; "+ cover": {runs[1][1]["train_records"]} views, the train path plus '
        "the views `benchmarks.gan_coverage` planned from the scene's geometry to see what the "
        f"train path missed, never from test cameras). Hash grid: {c0['levels']} levels, "
        f"2^{c0['log2_table']} entries, {c0['iterations']} iterations of {c0['batch_size']} pixels "
        f"({grid_min} min of training); probe volume of resolution {c1['probe_resolution']} "
        f"along the longest axis, L1 ({probe_s} s with reading the store); 1-minute load "
        f"{loads}.",
        "",
        "| fitted on | method | test path: SSIM / MSE / FLIP | held-out walk: SSIM / MSE / FLIP "
        "| ONNX bytes |",
        "|---|---|---|---|---|",
    ]
    for fitted, label, e, nbytes in rows:
        lines.append(f"| {fitted} | {label} | {cell(e, 'test')} | {cell(e, 'walk')} | "
                     f"{_bytes(nbytes)} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def block_instances(results: Path) -> str:
    d = load("instances/instances.json", results)
    c = d["config"]
    lines = [
        "**Instances** (`benchmarks.instances`): N instances of a T-triangle mesh (a Mitsuba",
        "`shapegroup`), traced with a flat BVH of every copy (`flat`), with Embree instancing",
        "(`instanced`, one prototype BVH) and by Mitsuba 3 (`scalar_rgb`); each run a fresh",
        f"process, {c['size']}x{c['size']} px at {c['spp']} spp, depth {c['max_depth']}. "
        "Load = reading the scene (icbtool's",
        "mesh holds every copy either way; Mitsuba's load includes its BVH), BVH = icbtool's",
        "Embree build (instanced: with its check that the mesh still matches), render = the",
        "render call (the tracer's per-face setup included), peak = the process's peak RSS.",
        "The load times of one N x T differ by the machine's load, not the mode. Load average "
        f"{span(list(walk_load_averages(d)), f2)} (a shared machine).",
        "",
        "| N x T | mode | triangles in BVH | load s | BVH s | render s | peak RSS MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in d["rows"]:
        if "error" in r:
            lines.append(f"| {r['instances']} x {r['mesh_triangles']:,} | {r['mode']} | "
                         f"failed: {r['error'][0][:60]} | | | | |")  # fmt: skip
            continue
        bvh = "-" if r["bvh_s"] is None else f"{r['bvh_s']:.2f}"
        tri = f"{r['triangles_in_bvh']:,}" if "triangles_in_bvh" in r else "-"
        lines.append(
            f"| {r['instances']} x {r['mesh_triangles']:,} | {r['mode']} | {tri} | "
            f"{r['load_s']:.2f} | {bvh} | {r['render_s']:.2f} | {r['peak_rss_mb']:,.0f} |"
        )
    lines.append("")
    return "\n".join(lines)


def _frames_s(frames: int | None, dt: float) -> str:
    return "never" if frames is None else f"{frames} ({frames * dt:.1f} s)"


def block_dynamic(results: Path) -> str:
    d = load("dynamic/dynamic_recovery.json", results)
    a = d["args"]
    names = {
        "rule": "invalidation rule (ours)",
        "full": "full invalidation",
        "stale": "stale cache",
        "dl_only": "DL only",
        "oracle": "steady state (oracle)",
    }
    la = d["load_average_start"][0]
    lines = [
        f"**Dynamic scenes** (`benchmarks.dynamic_recovery`: `cornell_box_moving_light`, "
        f"{a['frames']} client frames at {a['size']}x{a['size']} over 6 s along the test "
        f"path at {a['speed']} of its pace,",
        f"T_IL = {1e3 * a['latency']:.0f} ms, cloud GI at {a['spp']} spp denoised, first render "
        f"after a change {a['cheap_spp']} spp denoised; truth {a['truth_spp']} spp at the "
        f"current state;",
        f"1-minute load average {la:.1f} at the start, {d['wall_s'] / 60:.0f} min for both "
        "timelines). Recovery: frames (scene time) after a change until the SSIM (of the final "
        f"frame; of the GI alone)\nstays within {a['tolerance']} of the steady state's: the "
        "oracle, a full-invalidation cloud asked at the frame's own scene time.",
        "",
    ]
    for timeline, r in d["results"].items():
        sm, dt = r["summary"], r["frame_dt_s"]
        if timeline == "steps":
            head = "recovery after each light move"
            lines.append(
                "Steps (the light jumps between its keyed places and rests in between; changes "
                f"at frames {', '.join(map(str, r['changes_at_frames']))}):"
            )
        else:
            head = "recovery after the light rests (4 s)"
            lines.append(
                "Continuous (scene time = path time: the light slides from 0 s to 4 s, every "
                "frame a change, then rests):"
            )
        lines += [
            "",
            f"| method | mean SSIM (GI alone) | mean FLIP | {head}: final frame; GI alone "
            "| stale frames | cloud renders | samples traced (M) | render s | reply MB |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for m in ("rule", "full", "stale", "dl_only", "oracle"):
            s = sm[m]
            if timeline == "steps":
                rec = ", ".join(_frames_s(x, dt) for x in s["recovery_frames"])
                rec += "; " + ", ".join(_frames_s(x, dt) for x in s["recovery_frames_gi"])
            else:
                rec = _frames_s(s["frames_until_recovery_after_rest"], dt)
                rec += "; " + _frames_s(s["frames_until_recovery_after_rest_gi"], dt)
            if m == "dl_only":
                cost = "| - | - | - | - | - |"
            else:
                cost = (
                    f"| {s['stale_frames']} | {s['cloud_renders']} | "
                    f"{s['samples_traced'] / 1e6:.2f} | {s['cloud_render_s']:.1f} | "
                    f"{s['reply_bytes'] / 1e6:.1f} |"
                )
            lines.append(
                f"| {names[m]} | {s['mean_ssim']:.3f} ({s['mean_ssim_gi']:.3f}) | "
                f"{s['mean_flip']:.3f} | {rec} {cost}"
            )
        lines.append("")
    ratio = ", ".join(
        f"{tl} {sm['rule']['samples_traced'] / sm['full']['samples_traced']:.2f}"
        for tl, sm in ((tl, r["summary"]) for tl, r in d["results"].items())
    )
    lines.append(
        f"Samples traced by the invalidation rule over those of full invalidation: {ratio} "
        "(a refinement re-renders, it does not reuse the cheap render's samples).\n"
        "SSIM per frame: `docs/images/dynamic_recovery.png` (a copy of the run's plot)."
    )
    lines.append("")
    return "\n".join(lines)


BLOCKS: dict[str, Callable[[Path], str]] = {
    "intro": block_intro,
    "raster": block_raster,
    "trace-throughput": block_trace_throughput,
    "trace-time-error": block_trace_time_error,
    "trace-profile": block_trace_profile,
    "trace-speed": block_trace_speed,
    "trace-cameras": block_trace_cameras,
    "denoise": block_denoise,
    "store": block_store,
    "warp": block_warp,
    "prefetch": block_prefetch,
    "loop": block_loop,
    "emitters": block_emitters,
    "mitsuba-xml": block_mitsuba_xml,
    "interiors": block_interiors,
    "envmap": block_envmap,
    "mitsuba-materials": block_mitsuba_materials,
    "dl-accuracy": block_dl_accuracy,
    "shadow-accuracy": block_shadow_accuracy,
    "raster-glossy": block_raster_glossy,
    "trace-refactor": block_trace_refactor,
    "gan-figure7": block_gan_figure7,
    "gan-figure8": block_gan_figure8,
    "gan-time-error": block_gan_time_error,
    "gan-warped": block_gan_warped,
    "gan-spp": block_gan_spp,
    "gan-baselines": block_gan_baselines,
    "gan-ablation": block_gan_ablation,
    "gan-coverage": block_gan_coverage,
    "lpm": block_lpm,
    "net": block_net,
    "web": block_web,
    "net-scale": block_net_scale,
    "cloud-memory": block_cloud_memory,
    "radiance-world": block_radiance_world,
    "gi-codec": block_gi_codec,
    "instances": block_instances,
    "dynamic": block_dynamic,
}


#: The benchmark that owns each block: its module writes the results the block is made from,
#: and the block names it (tests/test_benchmarks_page.py checks both).
OWNERS: dict[str, str] = {
    "instances": "instances",
    "raster": "raster_bench",
    "trace-throughput": "trace_throughput",
    "trace-time-error": "trace_time_error",
    "trace-profile": "trace_profile",
    "trace-speed": "trace_ab",
    "trace-cameras": "trace_cameras",
    "denoise": "denoise_quality",
    "store": "store_bench",
    "warp": "warp_bench",
    "prefetch": "prefetch_experiment",
    "loop": "loop_demo",
    "emitters": "emitter_split",
    "mitsuba-xml": "mitsuba_xml_compare",
    "interiors": "interiors",
    "envmap": "envmap_mitsuba",
    "mitsuba-materials": "mitsuba_materials",
    "dl-accuracy": "raster_dl_accuracy",
    "shadow-accuracy": "raster_shadow_accuracy",
    "raster-glossy": "raster_glossy",
    "trace-refactor": "trace_ab",
    "gan-figure7": "gan_figure7",
    "gan-figure8": "gan_figure8",
    "gan-time-error": "gan_time_error",
    "gan-warped": "gan_warped",
    "gan-spp": "gan_spp",
    "gan-baselines": "gan_baselines",
    "gan-ablation": "gan_ablation",
    "gan-coverage": "gan_coverage",
    "lpm": "lpm_levels",
    "net": "net_latency",
    "web": "web_client",
    "net-scale": "net_scale",
    "cloud-memory": "cloud_memory",
    "radiance-world": "radiance_world",
    "gi-codec": "gi_codec",
    "dynamic": "dynamic_recovery",
}


def regenerate(text: str, results: Path = RESULTS) -> str:
    """``text`` (docs/benchmarks.md's content) with every bench block rewritten from ``results``.

    Args:
        text: the page's text with ``<!-- bench:NAME -->`` ... ``<!-- /bench:NAME -->`` blocks.
        results: the benchmarks/results folder.

    Returns:
        The new page text.

    Raises:
        PageBlockError: a block in BLOCKS has no markers in ``text``, or ``text`` has a block
            this script does not know.
        FileNotFoundError: a results file is missing.
    """
    found = [m.group(1) for m in MARKER.finditer(text)]
    unknown = sorted(set(found) - set(BLOCKS))
    missing = sorted(set(BLOCKS) - set(found))
    dup = sorted({n for n in found if found.count(n) > 1})
    if unknown or missing or dup:
        raise PageBlockError(
            f"docs/benchmarks.md bench markers: unknown {unknown}, missing {missing}, "
            f"duplicated {dup}"
        )
    return MARKER.sub(
        lambda m: (
            f"<!-- bench:{m.group(1)} -->\n{BLOCKS[m.group(1)](results)}"
            f"<!-- /bench:{m.group(1)} -->"
        ),
        text,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="fail if the page is stale")
    ap.add_argument("--page", default=str(PAGE), help="the page to write")
    ap.add_argument("--results", default=str(RESULTS))
    args = ap.parse_args(argv)
    path = Path(args.page)
    old = path.read_text()
    new = regenerate(old, Path(args.results))
    if args.check:
        if new != old:
            diff = difflib.unified_diff(
                old.splitlines(), new.splitlines(), str(path), "from results", lineterm=""
            )
            print("\n".join(diff))
            print(
                f"{path}'s benchmark numbers differ from benchmarks/results/: run "
                "`benchmarks.page`",
                file=sys.stderr,
            )
            return 1
        print(f"{path}'s benchmark numbers match benchmarks/results/")
        return 0
    if new != old:
        path.write_text(new)
        print(f"rewrote the bench blocks of {path}")
    else:
        print(f"{path} already up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
