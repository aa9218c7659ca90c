"""Interiors: icbtool's whole ``trace`` (load + render) against Mitsuba 3's whole run.

For each Mitsuba scene file of an interior (many meshes and textures: the scenes live outside
the repository, in the folder ``--scenes`` or ``$ICBTOOL_INTERIORS``; they are never committed),
both renderers run in child processes, back to back, at the same size and spp:

* icbtool: the command line itself, ``python -m icbtool trace SCENE --spp N --seed S ...``
  (load, BVH, packing, render, EXR/PNG/JSON writing: what a user waits for);
* Mitsuba 3 (``--variant``, default ``llvm_ad_rgb``): import, ``load_file``, ``render``, in a
  child of its own (its JIT included: its whole run).

Per run the child's wall time and peak memory (the RSS high-water mark, ``ru_maxrss`` from
``wait4``) are recorded. Load alone is timed in a separate child per renderer (icbtool:
``icbtool.scene.load``; Mitsuba: ``load_file``). Image quality against a reference (Mitsuba at
``--ref-spp``): relative RMSE, bias per channel, FLIP (HDR). The time icbtool needs for
Mitsuba's RMSE is its load plus its render time times ``(rmse_icbtool / rmse_mitsuba)^2`` (Monte
Carlo variance falls as 1/spp; the bias does not, so it is reported beside it).

What both render (the approximations taken): each scene is first prepared once (a copy in the
output folder, file names made absolute, a Mitsuba 0.6 ``scale`` texture on a bump map folded
into the bumpmap's ``scale``): shapes whose mesh file is missing are dropped (public
snapshots of scenes lack their largest files: named in the results), a bitmap texture whose
image file is missing becomes the constant ``MISSING_TEXTURE_RGB`` (a bump map missing its
height field, the BSDF it wraps; named in the results and counted in the table), the
integrator becomes ``path`` with ``--max-depth``, the sampler ``independent``, the film
``--width`` x ``--height``.
Mitsuba then renders the prepared file's twin
(:func:`icbtool.scene.mitsuba.diffuse_twin`): a BSDF icbtool traces exactly (its general
kernel: Mitsuba's own plugins, :mod:`icbtool.scene.bsdf`) stays as written, so both render the
same BSDFs; only a BSDF icbtool approximates becomes the two-sided diffuse BSDF icbtool renders
for it (its warnings are listed in the results), and every pixel filter ``box``.

The machine may be shared: the load average is recorded before and after every child, and the
ratios reported are those of runs made back to back (icbtool then Mitsuba, ``--repeats`` times,
median of the per-pair ratios), not absolute times.

    .venv/bin/python -m benchmarks.interiors --scenes ~/scenes/interiors --spp 256 \\
        --width 160 --height 90 --ref-spp 2048 --out benchmarks/results/interiors

Writes ``<out>/interiors.json`` and ``<out>/<scene>.png`` (icbtool | Mitsuba | reference |
|icbtool - reference| x 4). Mitsuba is a benchmark peer only (``make bench-deps``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, add_out_argument, load_average, write_results

#: Scene files searched for under --scenes: any .xml up to this many folders down.
MAX_SCENE_DEPTH = 2
#: The constant reflectance (linear RGB) that stands for a texture whose image file is missing.
MISSING_TEXTURE_RGB = "0.5 0.5 0.5"
#: Most mesh files Mitsuba cannot read that a scene may lose before the benchmark gives up.
MAX_UNREADABLE = 20


# --------------------------------------------------------------------------- scene preparation
def find_scenes(folder: Path) -> list[Path]:
    """The Mitsuba scene files (root ``<scene>``) under ``folder`` holding at least 20 shapes."""
    out = []
    for depth in range(MAX_SCENE_DEPTH + 1):
        for p in sorted(folder.glob("/".join(["*"] * depth + ["*.xml"]))):
            text = p.read_text(errors="replace")
            if "<scene" in text[:2000] and text.count("<shape") >= 20:
                out.append(p)
    return out


def prepare(
    xml: Path, out_dir: Path, width: int, height: int, max_depth: int, exclude: tuple = ()
) -> dict:
    """A copy of a scene file both renderers read alike (see the module docstring).

    Args:
        exclude: names of mesh files whose shapes are dropped too (files Mitsuba cannot read).

    Returns:
        {"file": the copy, "dropped": shapes dropped (their missing files),
        "replaced_textures": image files missing, their textures made constant}.
    """
    tree = ET.parse(xml)
    root = tree.getroot()
    dropped, replaced = [], []
    for parent in list(root.iter()):
        for c in list(parent):
            fn = c.find("string[@name='filename']")
            if fn is not None and "$" not in fn.get("value", ""):
                path = (xml.parent / fn.get("value", "").replace("\\", "/")).resolve()
                rel = str(path.relative_to(xml.parent.resolve()))
                if c.tag == "shape" and (not path.is_file() or path.name in exclude):
                    parent.remove(c)
                    dropped.append(rel)
                    continue
                if c.tag == "texture" and not path.is_file() and _replace_texture(root, parent, c):
                    replaced.append(rel)
                    continue
                fn.set("value", str(path))
            if c.tag in ("integrator", "sampler", "rfilter"):
                parent.remove(c)
            if c.tag == "srgb":  # Mitsuba 0.5's sRGB colour, which Mitsuba 3 does not read
                c.tag, c.attrib["value"] = "rgb", _linear_rgb(c.get("value", "0"))
    for bump in root.iter("bsdf"):
        if bump.get("type") == "bumpmap":
            _fold_scale_texture(bump)
    integ = ET.SubElement(root, "integrator", {"type": "path"})
    old = tuple(int(x) for x in root.get("version", "3.0.0").split(".")[:1])
    depth_name = "maxDepth" if old < (2,) else "max_depth"
    ET.SubElement(integ, "integer", {"name": depth_name, "value": str(max_depth)})
    sensor = root.find("sensor")
    if sensor is None:
        raise SystemExit(f"FAIL: {xml} has no <sensor>: no view to compare")
    ET.SubElement(sensor, "sampler", {"type": "independent"})
    for film in sensor.findall("film"):  # its formats and flags: nothing both read
        sensor.remove(film)
    film = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    ET.SubElement(film, "integer", {"name": "width", "value": str(width)})
    ET.SubElement(film, "integer", {"name": "height", "value": str(height)})
    out_dir.mkdir(parents=True, exist_ok=True)
    dst = out_dir / f"{xml.stem.split('.')[0]}.xml"
    tree.write(dst)
    return {"file": dst, "dropped": dropped, "replaced_textures": sorted(set(replaced))}


def _replace_texture(root: ET.Element, parent: ET.Element, tex: ET.Element) -> bool:
    """A bitmap texture whose image file is missing becomes the constant
    :data:`MISSING_TEXTURE_RGB` in both renderers' files (a named parameter of a BSDF); a
    bump map whose height field is missing becomes the BSDF it wraps. Returns False (the
    texture is left as written) where neither applies: a texture declared at the top level."""
    if parent.tag == "bsdf" and parent.get("type") == "bumpmap" and tex.get("name") is None:
        inner = parent.find("bsdf")
        holder = next((p for p in root.iter() if parent in list(p)), None)
        if inner is None or holder is None:
            return False
        idx = list(holder).index(parent)
        holder.remove(parent)
        for k in ("id", "name"):
            if parent.get(k) is not None:
                inner.set(k, parent.get(k))
        holder.insert(idx, inner)
        return True
    name = tex.get("name")
    if name is None or parent.tag == "scene":
        return False
    idx = list(parent).index(tex)
    parent.remove(tex)
    parent.insert(idx, ET.Element("rgb", {"name": name, "value": MISSING_TEXTURE_RGB}))
    return True


def _fold_scale_texture(bump: ET.Element) -> None:
    """Mitsuba 0.6's ``scale`` texture around a bump map's height field (a plugin Mitsuba 3
    lacks) becomes the bumpmap's own ``scale``: the same displacement, read alike by both."""
    for tex in list(bump.findall("texture")):
        inner = tex.find("texture")
        if tex.get("type") != "scale" or inner is None:
            continue
        f = tex.find("float[@name='scale']")
        s = float(f.get("value", "1")) if f is not None else 1.0
        old = bump.find("float[@name='scale']")
        if old is None:
            old = ET.SubElement(bump, "float", {"name": "scale", "value": "1"})
        old.set("value", repr(float(old.get("value", "1")) * s))
        idx = list(bump).index(tex)
        bump.remove(tex)
        bump.insert(idx, inner)


def _linear_rgb(srgb: str) -> str:
    """An sRGB colour (``"r g b"``, ``"r, g, b"``, one value or ``#rrggbb``) as linear RGB."""
    from icbtool.imageio import srgb_decode

    if srgb.startswith("#"):
        x = [int(srgb[i : i + 2], 16) / 255 for i in (1, 3, 5)]
    else:
        x = [float(v) for v in re.split(r"[,\s]+", srgb.strip()) if v]
    rgb = srgb_decode(np.resize(np.array(x, np.float32), 3))
    return " ".join(f"{v:.9g}" for v in rgb)


# --------------------------------------------------------------------------- child processes
#: Prefixed to every child's code: at exit it prints its own peak RSS (VmHWM of its address
#: space, which starts afresh at exec; ``ru_maxrss`` would count the parent's pages at fork).
_PEAK_AT_EXIT = r"""
import atexit, json as _json
def _peak():
    with open("/proc/self/status") as f:
        kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM"))
    print(_json.dumps({"peak_rss_mb": kb / 1024.0}), flush=True)
atexit.register(_peak)
"""

_ICBTOOL_CLI_CHILD = r"""
import runpy, sys
sys.argv = ["icbtool", *sys.argv[1:]]
runpy.run_module("icbtool", run_name="__main__")
"""

_MITSUBA_CHILD = r"""
import sys, time, json
t0 = time.perf_counter()
import numpy as np, mitsuba as mi
mi.set_variant(sys.argv[1])
xml, spp, seed, out = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
scene = mi.load_file(xml)
t1 = time.perf_counter()
if spp > 0:
    img = np.asarray(mi.render(scene, spp=spp, seed=seed))[..., :3]
    np.save(out, img.astype(np.float32))
t2 = time.perf_counter()
print(json.dumps({"load_s": t1 - t0, "render_s": t2 - t1}))
"""

_ICBTOOL_LOAD_CHILD = r"""
import sys, time, json, warnings
t0 = time.perf_counter()
import icbtool as icb
from icbtool.scene import MaterialApproximationWarning
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    s = icb.scene.load(sys.argv[1])
t1 = time.perf_counter()
approx = sorted({str(w.message) for w in caught if w.category is MaterialApproximationWarning})
print(json.dumps({"load_s": t1 - t0, "triangles": s.n_triangles, "materials": len(s.materials),
                  "textured": sum(m.is_textured for m in s.materials),
                  "texels": int(sum(m.texture.size // 3 for m in s.materials if m.is_textured)),
                  "approximated_bsdfs": approx}))
"""


class ChildFailed(Exception):
    """A child process exited with an error (its stderr is in ``log``)."""

    def __init__(self, log: Path) -> None:
        self.log = log
        self.log_text = log.read_text(errors="replace")
        super().__init__(f"child failed: see {log}")


def run_child(code: str, args: list[str], log: Path, cwd: Path = REPO) -> dict:
    """Run ``python -c code args`` in ``cwd`` (first on its ``sys.path``: the ``icbtool`` it
    imports); its wall time, peak RSS (MB) and the machine load around it, and what it
    reported (JSON objects on stdout)."""
    cmd = [sys.executable, "-c", _PEAK_AT_EXIT + code, *args]
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=f, text=True, cwd=cwd)
        out = proc.stdout.read() if proc.stdout else ""
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise ChildFailed(log)
    rec = {
        "wall_s": wall,
        "ru_maxrss_mb": usage.ru_maxrss / 1024.0,  # an upper bound (see _PEAK_AT_EXIT)
        "load_average_before": list(load0),
        "load_average_after": list(os.getloadavg()),
    }
    # the child's reports: lines holding a JSON object (Mitsuba's log shares stdout)
    for line in out.splitlines():
        if '{"' in line:
            rec.update(json.loads(line[line.find('{"') :]))
    return rec


def icbtool_trace(
    xml: Path, spp: int, seed: int, out: Path, max_depth: int, checkout: Path = REPO
) -> dict:
    """``icbtool trace`` of ``checkout`` (default this one) in a child (see run_child)."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = ["trace", str(xml), "--out", str(out)]
    cmd += ["--spp", str(spp), "--seed", str(seed), "--max-depth", str(max_depth)]
    rec = run_child(_ICBTOOL_CLI_CHILD, cmd, out / "log.txt", cwd=checkout)
    summary = json.loads((out / "summary.json").read_text())
    rec["stats_times_s"] = summary["views"][0]["stats"].get("time_s")
    return rec


def mitsuba(xml: Path, spp: int, seed: int, out: Path, variant: str) -> dict:
    args = [variant, str(xml), str(spp), str(seed), str(out)]
    return run_child(_MITSUBA_CHILD, args, out.with_suffix(".log"))


# --------------------------------------------------------------------------- metrics
def metrics(img: np.ndarray, ref: np.ndarray) -> dict:
    """Relative RMSE (over the reference's mean), bias per channel, FLIP (HDR) against ``ref``."""
    import flip_evaluator

    mean = max(float(ref.mean()), 1e-12)
    rmse = float(np.sqrt(np.mean((img - ref) ** 2))) / mean
    bias = img.mean((0, 1)) / np.maximum(ref.mean((0, 1)), 1e-12) - 1
    _, flip, _ = flip_evaluator.evaluate(
        np.ascontiguousarray(ref, np.float32), np.ascontiguousarray(img, np.float32), "HDR"
    )
    return {"rel_rmse": rmse, "bias_per_channel": bias.tolist(), "flip_hdr": float(flip)}


def side_by_side(images: list[np.ndarray], path: Path) -> None:
    from icbtool.imageio import auto_exposure, to_display, write_png

    exposure = auto_exposure(images[2])
    diff = np.abs(images[0] - images[2]) * 4
    strip = np.concatenate([*images, diff], axis=1)
    write_png(path, to_display(strip.astype(np.float32), exposure=exposure))


def measure_scene(xml: Path, args: argparse.Namespace, work: Path) -> dict:
    from icbtool.imageio import read_exr
    from icbtool.scene.mitsuba import diffuse_twin

    key = re.sub(r"[^A-Za-z0-9_]+", "_", f"{xml.parent.name}_{xml.stem.split('.')[0]}")
    sdir = work / key
    unreadable: list[str] = []
    for _ in range(MAX_UNREADABLE):  # shapes Mitsuba cannot read are dropped from both
        prep = prepare(xml, sdir / "prepared", args.width, args.height, args.max_depth,
                       tuple(unreadable))  # fmt: skip
        twin = diffuse_twin(prep["file"], sdir / "twin")
        try:
            mi_load = _mitsuba_load(twin, sdir, args.variant)
            break
        except ChildFailed as e:
            m = re.search(r'Error while loading \w+ file "([^"]+)"', e.log_text)
            if m is None:
                raise SystemExit(f"FAIL: Mitsuba cannot load {twin}: see {e.log}") from None
            unreadable.append(Path(m.group(1)).name)
    else:
        raise SystemExit(f"FAIL: more than {MAX_UNREADABLE} mesh files Mitsuba cannot read")
    print(
        f"{key}: {len(prep['dropped'])} shapes dropped (missing or unreadable), "
        f"{len(prep['replaced_textures'])} missing textures made constant",
        flush=True,
    )
    rec: dict = {
        "file": str(xml),
        "dropped_shapes": prep["dropped"],
        "replaced_textures": prep["replaced_textures"],
        "unreadable_by_mitsuba": unreadable,
    }
    rec["icbtool_load"] = run_child(_ICBTOOL_LOAD_CHILD, [str(prep["file"])], sdir / "load_icb.log")
    rec["mitsuba_load"] = mi_load
    print(
        f"  {rec['icbtool_load']['triangles']} triangles, load icbtool "
        f"{rec['icbtool_load']['load_s']:.1f} s / Mitsuba {rec['mitsuba_load']['load_s']:.1f} s",
        flush=True,
    )
    ref_path = sdir / "reference.npy"
    rec["reference"] = mitsuba(twin, args.ref_spp, 1000, ref_path, args.variant)
    ref = np.load(ref_path)
    pairs = []
    for r in range(args.repeats):
        icb_dir = sdir / f"icbtool_{r}"
        a = icbtool_trace(prep["file"], args.spp, r, icb_dir, args.max_depth)
        b = mitsuba(twin, args.spp, r, sdir / f"mitsuba_{r}.npy", args.variant)
        ours, theirs = read_exr(icb_dir / "full.exr")[..., :3], np.load(sdir / f"mitsuba_{r}.npy")
        a["quality"], b["quality"] = metrics(ours, ref), metrics(theirs, ref)
        pairs.append({"icbtool": a, "mitsuba": b})
        print(
            f"  run {r}: icbtool {a['wall_s']:.1f} s {a['peak_rss_mb']:.0f} MB rmse "
            f"{a['quality']['rel_rmse']:.3f} | Mitsuba {b['wall_s']:.1f} s "
            f"{b['peak_rss_mb']:.0f} MB rmse {b['quality']['rel_rmse']:.3f}",
            flush=True,
        )
        if r == 0:
            side_by_side([ours, theirs, ref], args.out / f"{key}.png")
    rec["runs"] = pairs
    rec["ratios"] = ratios(pairs, rec["icbtool_load"]["load_s"])
    return key, rec


def _mitsuba_load(twin: Path, sdir: Path, variant: str) -> dict:
    """Mitsuba's load of the twin; a property Mitsuba 3 refuses as unreferenced (one the file
    gives a plugin that has no such parameter: icbtool ignores it with a warning) is deleted
    from the twin and the load retried."""
    for _ in range(MAX_UNREADABLE):
        try:
            return mitsuba(twin, 0, 0, sdir / "load_mi.npy", variant)
        except ChildFailed as e:
            m = re.search(r"\(line (\d+), col \d+\): Found \d+ unreferenced propert", e.log_text)
            names = re.findall(r'^\s+- \w+ "(\w+)"', e.log_text, re.M)
            if m is None or not names:
                raise
            lines = twin.read_text().splitlines(keepends=True)
            start = int(m.group(1)) - 1
            for name in names:  # as Mitsuba names it, or as a 0.6 file spells it (camelCase)
                camel = re.sub(r"_(\w)", lambda c: c.group(1).upper(), name)
                spelt = (f'name="{name}"', f'name="{camel}"')
                hit = next(i for i in range(start, len(lines)) if any(x in lines[i] for x in spelt))
                del lines[hit]
            twin.write_text("".join(lines))
    raise SystemExit(f"FAIL: Mitsuba cannot load {twin}: too many unreferenced properties")


def ratios(pairs: list[dict], icb_load_s: float) -> dict:
    """Medians over back-to-back pairs of icbtool / Mitsuba."""

    def med(f):
        return float(statistics.median(f(p["icbtool"], p["mitsuba"]) for p in pairs))

    def equal_rmse_time(a: dict, b: dict) -> float:
        k = (a["quality"]["rel_rmse"] / max(b["quality"]["rel_rmse"], 1e-12)) ** 2
        render = max(a["wall_s"] - icb_load_s, 0.0)
        return (icb_load_s + render * k) / b["wall_s"]

    return {
        "whole_run_time": med(lambda a, b: a["wall_s"] / b["wall_s"]),
        "time_to_equal_rmse": med(equal_rmse_time),
        "peak_memory": med(lambda a, b: a["peak_rss_mb"] / b["peak_rss_mb"]),
        "rel_rmse": med(lambda a, b: a["quality"]["rel_rmse"] / b["quality"]["rel_rmse"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=Path, default=os.environ.get("ICBTOOL_INTERIORS"),
                    help="folder of interior scenes (default $ICBTOOL_INTERIORS)")  # fmt: skip
    ap.add_argument("--scene", type=Path, action="append", default=[],
                    help="one scene file (repeatable; instead of or besides --scenes)")  # fmt: skip
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--max-depth", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    add_out_argument(ap, "interiors")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (prepared files)")
    args = ap.parse_args()
    scenes = list(args.scene) + (find_scenes(args.scenes) if args.scenes else [])
    if not scenes:
        raise SystemExit("FAIL: no scene: give --scenes DIR (or $ICBTOOL_INTERIORS) or --scene")
    args.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="interiors_"))
    load_start = load_average()
    results: dict = {
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "scenes": {},
    }
    try:
        import mitsuba as mi

        results["mitsuba_version"] = mi.__version__
        for xml in scenes:
            key, rec = measure_scene(xml.resolve(), args, work)
            results["scenes"][key] = rec
            r = rec["ratios"]
            print(
                f"  icbtool / Mitsuba: whole run {r['whole_run_time']:.2f}x, time to equal RMSE "
                f"{r['time_to_equal_rmse']:.2f}x, peak memory {r['peak_memory']:.2f}x",
                flush=True,
            )
            write_results(args.out / "interiors.json", results, load_start)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(f"-> {args.out / 'interiors.json'}")


if __name__ == "__main__":
    main()
