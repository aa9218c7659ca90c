"""Prefetch experiment: holes and SSIM of warped maps as the client moves faster.

For client cameras along a scene's "test" path, the client is given a constant velocity (its
path's direction of travel, at ``speed`` units/s) and a yaw rate (``rot`` rad/s). The cloud saw
the client ``T_IL`` ago (camera ``old``) and renders a reference for it; the client warps that
reference to its current camera ``now`` with its own raster depth (icbtool.warp.backward) and
inpaints what is left. Conditions:

  a  no prefetch: the reference is the client camera T_IL ago (client size and FOV);
  b  the paper's prefetch: wider FOV, pulled back (icbtool.prefetch), at the client's resolution;
  c  prefetch with our resolution rule (same centre pixel density as the client);
  d  two references combined: c, and the client's previous map (c computed T_IL earlier).

Measured on the target's geometry pixels: hole ratio (outside | disoccluded, before inpainting),
and SSIM (icbtool.metrics.ssim, display scale, valid padding) of the inpainted warp against the
truth. The warped signal is the raster DL for the speed sweeps (holes are measured identically
for any signal) and the path-traced GI (icb.trace.render_gi, denoised) at walking speed.

Speed scale: Sponza is in metres; the Cornell box (~2 units wide) is taken as a 2 m room, so
1 unit = 1 m and walking speed is 1.4 units/s in both.

    .venv/bin/python -m benchmarks.prefetch_experiment [--frames 8] [--size 128] [--gi-frames 3]

Writes --out/{prefetch_experiment.json, *.png}.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

import icbtool as icb
from benchmarks.common import add_out_argument, run_info, write_json
from icbtool.camera import Camera
from icbtool.imageio import auto_exposure
from icbtool.metrics import ssim
from icbtool.prefetch import PrefetchConfig, depth_range_from_depth, prefetch_camera
from icbtool.warp import WarpConfig, backward, combine, inpaint

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "prefetch"
CONDITIONS = ("a_no_prefetch", "b_paper_prefetch", "c_prefetch_resolution_rule", "d_combined")


def motion(v: np.ndarray, w: np.ndarray, t: float) -> np.ndarray:
    """(4, 4) ``client_now_from_client_later`` for constant velocity over ``t`` seconds."""
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(w * t).as_matrix()
    m[:3, 3] = v * t
    return m


class Renderer:
    """Raster buffers (and optionally GI) per camera, cached for the run."""

    def __init__(self, scene, gi_spp: int) -> None:
        from icbtool.raster import RasterConfig, Rasterizer

        self.scene = scene
        self.r = Rasterizer(scene, RasterConfig(backend="auto"))
        self.gi_spp = gi_spp
        self.gi_times_s: list[float] = []  # per render, in call order (the first pays the JIT)

    def raster(self, cam: Camera):
        return self.r.render(cam, buffers=("dl", "depth"))

    def gi(self, cam: Camera, seed: int) -> np.ndarray:
        t0 = time.perf_counter()
        g = icb.trace.render_gi(self.scene, cam, spp=self.gi_spp, seed=seed, denoise=True)
        self.gi_times_s.append(time.perf_counter() - t0)
        return g

    def close(self) -> None:
        self.r.close()


def one_case(rend: Renderer, now: Camera, v, w, args, signal: str, seed: int) -> dict:
    T = args.latency
    m = motion(v, w, T)
    old = now.with_pose(now.world_from_cam @ np.linalg.inv(m))
    older = now.with_pose(old.world_from_cam @ np.linalg.inv(m))
    truth = rend.raster(now)
    cams: dict[str, Camera] = {"a": old}
    info: dict[str, dict] = {}
    for key, base, rule in (("b", old, "same"), ("c", old, "center"), ("c_prev", older, "center")):
        rb = rend.raster(base)
        dr = depth_range_from_depth(rb.depth, rb.mask, (1.0, 100.0))
        cfg = PrefetchConfig(
            latency_s=T,
            margin_deg=args.margin_deg,
            resolution_rule=rule,
            max_pixels=args.max_ref_pixels,
        )
        res = prefetch_camera(base, v, w, cfg, depth_range=dr)
        cams[key] = res.camera
        info[key] = {
            "fov_y_deg": res.fov_y_deg,
            "pullback": res.pullback,
            "clamped": res.clamped,
            "size": [res.camera.height, res.camera.width],
            "depth_range": dr,
        }
    if signal == "gi":
        target = rend.gi(now, seed)
    else:
        target = truth.dl
    warps = {}
    for key, cam in cams.items():
        rb = rend.raster(cam)
        img = rend.gi(cam, seed + 1000 + len(warps)) if signal == "gi" else rb.dl
        warps[key] = backward(
            img,
            rb.depth,
            cam,
            truth.depth,
            now,
            src_mask=rb.mask,
            dst_mask=truth.mask,
            config=WarpConfig(),
        )
    results = {
        "a_no_prefetch": warps["a"],
        "b_paper_prefetch": warps["b"],
        "c_prefetch_resolution_rule": warps["c"],
        "d_combined": combine([warps["c"], warps["c_prev"]]),
    }
    geo = truth.valid
    exposure = auto_exposure(target, truth.mask[..., 0] > 0.5)
    out = {"prefetch": info}
    for name, r in results.items():
        filled = inpaint(r, truth.depth)
        final = np.where(geo[..., None], filled.image, target)
        n = max(int(geo.sum()), 1)
        out[name] = {
            "hole_ratio": float((r.holes & geo).sum() / n),
            "outside_ratio": float((r.outside & geo).sum() / n),
            "disoccluded_ratio": float((r.disoccluded & geo).sum() / n),
            "ssim": ssim(final, target, exposure),
        }
    out["_images"] = {"target": target, **{k: inpaint(r, truth.depth) for k, r in results.items()}}
    return out


def frames_of(path, n: int) -> list[float]:
    t0, t1 = path.times[0], path.times[-1]
    return list(np.linspace(t0 + 0.05 * (t1 - t0), t1 - 0.05 * (t1 - t0), n))


def run_scene(name: str, scene, args) -> dict:
    path = scene.paths["test"]
    intr = path.intrinsics.resized(args.size, args.size)
    path = path.with_intrinsics(intr)
    rend = Renderer(scene, args.gi_spp)
    cases = [(s, 0.0) for s in args.speeds] + [(args.walk, r) for r in args.rot_speeds if r > 0]
    rows = []
    times = frames_of(path, args.frames)
    try:
        for t in tqdm(times, desc=f"{name} DL sweep"):
            now = path.camera_at(t)
            vd = path.velocity_cam(t)[0]
            vd = vd / np.linalg.norm(vd) if np.linalg.norm(vd) > 1e-9 else np.array([0, 0, 1.0])
            for speed, rot in cases:
                r = one_case(rend, now, vd * speed, np.array([0.0, rot, 0.0]), args, "dl", 0)
                r.pop("_images")
                rows.append({"t": float(t), "speed": speed, "rot": rot, **r})
        gi_rows = []
        example = None
        for i, t in enumerate(tqdm(frames_of(path, args.gi_frames), desc=f"{name} GI")):
            now = path.camera_at(t)
            vd = path.velocity_cam(t)[0]
            vd = vd / np.linalg.norm(vd) if np.linalg.norm(vd) > 1e-9 else np.array([0, 0, 1.0])
            r = one_case(
                rend, now, vd * args.walk, np.array([0.0, args.gi_rot, 0.0]), args, "gi", 10 * i
            )
            imgs = r.pop("_images")
            if example is None:
                example = imgs
            gi_rows.append({"t": float(t), "speed": args.walk, "rot": args.gi_rot, **r})
    finally:
        rend.close()
    return {
        "rows": rows,
        "gi_rows": gi_rows,
        "example": example,
        # no mean: the first render pays numba's JIT/cache load and OIDN's weight loading
        "gi_seconds_per_render": {
            "first_s": rend.gi_times_s[0] if rend.gi_times_s else None,
            "median_s": float(np.median(rend.gi_times_s)) if rend.gi_times_s else None,
            "median_after_first_s": (
                float(np.median(rend.gi_times_s[1:])) if len(rend.gi_times_s) > 1 else None
            ),
            "per_render_s": rend.gi_times_s,
        },
    }


def summarise(rows: list[dict], key: str) -> dict:
    out: dict = {}
    groups = sorted({(r["speed"], r["rot"]) for r in rows})
    for g in groups:
        sel = [r for r in rows if (r["speed"], r["rot"]) == g]
        out[f"speed={g[0]},rot={g[1]}"] = {
            c: {
                "hole_ratio_mean": float(np.mean([r[c]["hole_ratio"] for r in sel])),
                "hole_ratio_max": float(np.max([r[c]["hole_ratio"] for r in sel])),
                "outside_mean": float(np.mean([r[c]["outside_ratio"] for r in sel])),
                "disoccluded_mean": float(np.mean([r[c]["disoccluded_ratio"] for r in sel])),
                key: float(np.mean([r[c]["ssim"] for r in sel])),
            }
            for c in CONDITIONS
        }
    return out


def plot(all_res: dict, args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from icbtool.imageio import to_display

    for sweep, xkey, fixed in (
        ("speed", "speed", ("rot", 0.0)),
        ("rot", "rot", ("speed", args.walk)),
    ):
        fig, axes = plt.subplots(2, len(all_res), figsize=(5 * len(all_res), 7), squeeze=False)
        for j, (scene, res) in enumerate(all_res.items()):
            rows = [r for r in res["rows"] if r[fixed[0]] == fixed[1]]
            xs = sorted({r[xkey] for r in rows})
            for c in CONDITIONS:
                h = [100 * np.mean([r[c]["hole_ratio"] for r in rows if r[xkey] == x]) for x in xs]
                s = [np.mean([r[c]["ssim"] for r in rows if r[xkey] == x]) for x in xs]
                axes[0, j].plot(xs, h, "o-", label=c)
                axes[1, j].plot(xs, s, "o-", label=c)
            axes[0, j].axhline(1.0, color="k", ls=":", lw=0.8)
            axes[0, j].axhline(5.0, color="r", ls=":", lw=0.8)
            axes[0, j].set_title(f"{scene}: holes, T_IL={args.latency * 1e3:.0f} ms")
            axes[0, j].set_ylabel("hole pixels (% of geometry)")
            axes[1, j].set_ylabel("SSIM of inpainted warped DL")
            unit = "speed (units/s = m/s)" if xkey == "speed" else "yaw rate (rad/s)"
            axes[1, j].set_xlabel(f"{unit}; {fixed[0]}={fixed[1]}")
            axes[0, j].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(OUT / f"prefetch_{sweep}.png", dpi=90)
        plt.close(fig)
    # example panel (GI at walking speed)
    fig, axes = plt.subplots(len(all_res), 5, figsize=(15, 3.2 * len(all_res)), squeeze=False)
    for i, (scene, res) in enumerate(all_res.items()):
        ex = res["example"]
        if ex is None:
            continue
        e = auto_exposure(ex["target"])
        axes[i, 0].imshow(to_display(ex["target"], e))
        axes[i, 0].set_title(f"{scene}: true GI")
        for k, c in enumerate(CONDITIONS):
            r = ex[c]
            img = to_display(r.image, e).copy()
            img[r.holes & ~r.no_geometry] = [255, 0, 255]
            axes[i, k + 1].imshow(img)
            axes[i, k + 1].set_title(f"{c}\nholes {100 * r.hole_ratio:.2f} % (magenta)", fontsize=8)
        for a in axes[i]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(OUT / "prefetch_examples.png", dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["cornell_box", "sponza"])
    ap.add_argument("--frames", type=int, default=8, help="client frames per scene (DL sweeps)")
    ap.add_argument("--gi-frames", type=int, default=3, help="frames per scene with GI")
    ap.add_argument("--size", type=int, default=128, help="client image size (square)")
    ap.add_argument("--latency", type=float, default=0.1, help="T_IL in seconds")
    ap.add_argument("--walk", type=float, default=1.4, help="walking speed, units/s")
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.0, 0.5, 1.0, 1.4, 2.0, 3.0])
    ap.add_argument("--rot-speeds", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--gi-rot", type=float, default=0.5, help="yaw rate of the GI runs, rad/s")
    ap.add_argument("--gi-spp", type=int, default=16)
    ap.add_argument("--margin-deg", type=float, default=2.0)
    ap.add_argument("--max-ref-pixels", type=int, default=512 * 512)
    add_out_argument(ap, "prefetch")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    OUT.mkdir(parents=True, exist_ok=True)
    all_res = {}
    t0 = time.perf_counter()
    for name in args.scenes:
        scene = (
            icb.scene.cornell_box()
            if name == "cornell_box"
            else icb.scene.load(REPO / "data" / "scenes" / f"{name}.toml")
        )
        all_res[name] = run_scene(name, scene, args)
    summary = {
        name: {
            "dl_sweeps": summarise(res["rows"], "ssim_dl_inpainted"),
            "gi_walking": summarise(res["gi_rows"], "ssim_gi_inpainted"),
            "gi_seconds_per_render": res["gi_seconds_per_render"],
        }
        for name, res in all_res.items()
    }
    write_json(
        OUT / "prefetch_experiment.json",
        {
            "config": vars(args),
            "speed_scale": "1 unit = 1 m in both scenes (Cornell box taken as a 2 m room)",
            "summary": summary,
            "rows": {n: {"dl": r["rows"], "gi": r["gi_rows"]} for n, r in all_res.items()},
            "seconds": time.perf_counter() - t0,
            "run_info": run_info(),
        },
    )
    plot(all_res, args)
    for name, s in summary.items():
        print(f"== {name}")
        for group, d in list(s["dl_sweeps"].items()) + [
            ("GI " + k, v) for k, v in s["gi_walking"].items()
        ]:
            line = "  ".join(
                f"{c[:1]}: {100 * v['hole_ratio_mean']:5.2f}% {list(v.values())[-1]:.3f}"
                for c, v in d.items()
            )
            print(f"  {group:22s} {line}")
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
