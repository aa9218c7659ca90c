"""Error per sample of the path tracer in two checkouts (a sampling change's "same noise" check).

``trace_ab.py`` times two checkouts; a change that alters the samples themselves (another mapping
of random numbers to directions, say) must also show that the noise per sample did not grow. This
renders each scene at a few spp with many seeds in each checkout (one process each, its own
``icbtool``) and compares the mean RMSE against one shared high-spp reference (checkout B, the
independent sampler, so it shares no sampler structure with what it measures), with the standard
error of each mean.

    .venv/bin/python -m benchmarks.trace_rmse_ab --a /tmp/before --b . [--seeds 12] [--size 128]

Writes --out/rmse_ab_<name>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument, run_info, write_json
from benchmarks.trace_ab import add_checkout_args

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"

CHILD = r"""
import json, os, sys
import numpy as np
import icbtool as icb
from icbtool.trace import TraceConfig, render
name, size, root, ref_path, seeds, spps, robust = sys.argv[1:8]
size, seeds = int(size), int(seeds)
if name == "sponza":
    sc = icb.scene.load(os.path.join(root, "data", "scenes", "sponza.toml"))
else:
    sc = getattr(icb.scene, name)()
cam = sc.default_camera.resized(size, size)
ref = np.load(ref_path)
out = {}
for spp in map(int, spps.split(",")):
    e = []
    for s in range(seeds):
        cfg = TraceConfig(spp=spp, seed=s, max_depth=8, robust=robust == "1")
        e.append(float(np.sqrt(np.mean((render(sc, cam, cfg).full - ref) ** 2))))
    out[spp] = e
print(json.dumps(out))
"""


def reference(scene: str, size: int, spp: int, path: Path) -> None:
    """The shared reference, rendered by this checkout (independent sampler, robust Embree)."""
    import icbtool as icb
    from icbtool.trace import TraceConfig, render

    if scene == "sponza":
        sc = icb.scene.load(REPO / "data" / "scenes" / "sponza.toml")
    else:
        sc = getattr(icb.scene, scene)()
    cam = sc.default_camera.resized(size, size)
    cfg = TraceConfig(spp=spp, seed=999, sampler="independent", max_depth=8, robust=True)
    np.save(path, render(sc, cam, cfg, progress=True).full)


def run(root: Path, args: argparse.Namespace, ref: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(root))
    argv = [args.scene, args.size, root, ref, args.seeds, args.spps, args.robust]
    cp = subprocess.run(
        [sys.executable, "-c", CHILD, *map(str, argv)],
        capture_output=True,
        text=True,
        cwd=root,
        env=env,
        check=True,
    )
    return {int(k): v for k, v in json.loads(cp.stdout.strip().splitlines()[-1]).items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_checkout_args(ap)
    ap.add_argument("--spps", default="1,2,4,8,16")
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--robust", choices=("0", "1"), default="1", help="Embree robust in both")
    ap.add_argument("--name", default=None, help="results file rmse_ab_<name>.json")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    os.environ.setdefault("ICBTOOL_SPONZA", str(REPO.parent / "shared" / "scenes" / "sponza"))
    ref = Path(f"/tmp/icb_rmse_ab_ref_{args.scene}_{args.size}_{args.ref_spp}.npy")
    if not ref.is_file():
        reference(args.scene, args.size, args.ref_spp, ref)
    res = {side: run(root.resolve(), args, ref) for side, root in (("a", args.a), ("b", args.b))}
    rows = []
    for spp in res["a"]:
        row = {"spp": spp}
        for side in ("a", "b"):
            e = np.asarray(res[side][spp])
            row[f"rmse_{side}"] = float(e.mean())
            row[f"se_{side}"] = float(e.std(ddof=1) / np.sqrt(len(e)))
        row["b_over_a"] = row["rmse_b"] / row["rmse_a"]
        rows.append(row)
        print(
            f"{args.scene} {spp} spp: RMSE A {row['rmse_a']:.5f} +- {row['se_a']:.5f}, "
            f"B {row['rmse_b']:.5f} +- {row['se_b']:.5f} (B/A {row['b_over_a']:.3f})",
            flush=True,
        )
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"rmse_ab_{args.name or args.scene}.json"
    write_json(
        path,
        {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows, "run_info": run_info()},
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
