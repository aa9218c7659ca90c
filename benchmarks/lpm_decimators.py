"""Which quadric decimator for the LPM: open3d against fast-simplification and pyfqmr.

The same input for each: Sponza's decimatable material groups, each welded on its own (as
:func:`icbtool.lpm.build` does), one mesh; decimated to each ratio of its triangles. Measured:
seconds, triangles reached, and the symmetric surface distance to the input (RMS and Hausdorff
over 100,000 area-uniform samples each way, exact closest points, fractions of the diagonal).
fast-simplification and pyfqmr are NOT icbtool dependencies: install them aside, e.g.
``pip install --target /tmp/fsimp fast-simplification==0.2.0 pyfqmr==0.5.0`` and run with
``PYTHONPATH=/tmp/fsimp``; a missing one is reported as such.

    PYTHONPATH=.:/tmp/fsimp nice -n 10 .venv/bin/python -m benchmarks.lpm_decimators

Writes --out/decimators.json.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]


def _input(scene_path: str):
    import icbtool as icb
    from icbtool.lpm import LPMConfig
    from icbtool.lpm import build as _b  # noqa: F401
    from icbtool.lpm.build import group_targets, sub_mesh, weld

    s = icb.scene.load(scene_path)
    cfg = LPMConfig()
    targets = group_targets(s, 0.05, cfg)
    verts, faces, off = [], [], 0
    for m in range(len(s.materials)):
        idx = np.flatnonzero(s.face_material == m)
        if len(idx) == 0 or targets[m] >= len(idx):
            continue
        part = sub_mesh(s, idx, m)
        w, wm = weld(part.vertices, cfg.weld_tolerance * s.diagonal)
        wf = wm[part.faces]
        ok = (wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])
        verts.append(w)
        faces.append(wf[ok] + off)
        off += len(w)
    return np.concatenate(verts), np.concatenate(faces), s.diagonal


def _sample(v, f, n, seed):
    rng = np.random.default_rng(seed)
    tri = v[f]
    a = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = rng.choice(len(f), n, p=a / a.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return (w[:, :, None] * tri[k]).sum(1)


def _error(v0, f0, v1, f1, diag, n=100_000):
    from icbtool.lpm.closest import ClosestPointQuery

    d01 = ClosestPointQuery(v1, f1).query(_sample(v0, f0, n, 0)).distance / diag
    d10 = ClosestPointQuery(v0, f0).query(_sample(v1, f1, n, 1)).distance / diag
    both = np.concatenate([d01, d10])
    return float(np.sqrt(np.mean(both**2))), float(max(d01.max(), d10.max()))


def _open3d(v, f, target):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32))
    )
    d = m.simplify_quadric_decimation(int(target))
    return np.asarray(d.vertices), np.asarray(d.triangles)


def _fast_simplification(v, f, target):
    fs = importlib.import_module("fast_simplification")
    pv, pf = fs.simplify(v.astype(np.float32), f.astype(np.int32), 1 - target / len(f))
    return np.asarray(pv, np.float64), np.asarray(pf)


def _pyfqmr(v, f, target):
    pyfqmr = importlib.import_module("pyfqmr")
    s = pyfqmr.Simplify()
    s.setMesh(v, f.astype(np.int32))
    s.simplify_mesh(target_count=int(target), aggressiveness=7, preserve_border=True, verbose=False)
    pv, pf, _ = s.getMesh()
    return np.asarray(pv, np.float64), np.asarray(pf)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default = REPO / "data" / "scenes" / "sponza.toml"
    ap.add_argument("--scene", default=str(default))
    ap.add_argument("--ratios", default="0.05,0.1,0.25")
    add_out_argument(ap, "lpm")
    a = ap.parse_args()
    v, f, diag = _input(a.scene)
    rows = []
    for name, fn in (
        ("open3d", _open3d),
        ("fast_simplification", _fast_simplification),
        ("pyfqmr", _pyfqmr),
    ):
        for r in (float(x) for x in a.ratios.split(",")):
            try:
                t0 = time.perf_counter()
                pv, pf = fn(v, f, round(r * len(f)))
                dt = time.perf_counter() - t0
            except ImportError as e:
                rows.append({"decimator": name, "ratio": r, "missing": str(e)})
                print(name, "missing:", e)
                break
            rms, hd = _error(v, f, pv, pf, diag)
            row = {
                "decimator": name,
                "ratio": r,
                "target": round(r * len(f)),
                "triangles": int(len(pf)),
                "seconds": dt,
                "rms": rms,
                "hausdorff": hd,
            }
            rows.append(row)
            print(row)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "scene": a.scene,
        "input_triangles": int(len(f)),
        "machine": platform.processor(),
        "cpus": os.cpu_count(),
    }
    (out / "decimators.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
