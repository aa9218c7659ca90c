"""Store benchmark: lookup latency (octree vs brute-force scan), insert throughput, bytes/record.

Lookup: stores of 10^3, 10^4 and 10^5 records (cameras along random walks through a Sponza-sized
box, 35 x 16 x 16 m; tiny 4x4 payloads, bulk-imported with ``put_many``); the store is closed and
reopened, so the octree is the one loaded from SQLite; 2000 queries, half near a stored camera
(hits) and half anywhere (mostly misses), each timed alone. The brute-force scan evaluates the same
criterion over numpy arrays of all records of the group in the same run; answers are compared.

Insert: ``put`` of realistic 128x128 CRT-buffers (all 8 maps), with fsync (durable against power
loss) and without; payloads are a real baked Sponza record if out/store_sponza/train exists
(written by store_sponza_experiment.py), else smooth synthetic maps.

    .venv/bin/python -m benchmarks.store_bench
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np

from benchmarks.common import add_out_argument

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "store"
BOUNDS = np.array([[-17.5, -1.0, -8.0], [17.5, 15.0, 8.0]])


def walk_cameras(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4, 4) poses along random walks (5 cm steps, smoothly turning), inside BOUNDS."""
    from icbtool.camera import look_at_pose

    rng = np.random.default_rng(seed)
    poses = np.empty((n, 4, 4))
    p = rng.uniform(BOUNDS[0], BOUNDS[1])
    heading = rng.uniform(0, 2 * np.pi)
    pitch = 0.0
    for i in range(n):
        if i % 2000 == 0:  # a new walk
            p = rng.uniform(BOUNDS[0], BOUNDS[1])
        heading += rng.normal(0, 0.05)
        pitch = float(np.clip(pitch + rng.normal(0, 0.02), -0.6, 0.6))
        f = np.array(
            [np.cos(heading) * np.cos(pitch), np.sin(pitch), np.sin(heading) * np.cos(pitch)]
        )
        p = p + 0.05 * f
        if np.any((p < BOUNDS[0]) | (p > BOUNDS[1])):  # left the box: start a new walk
            p = rng.uniform(BOUNDS[0], BOUNDS[1])
        poses[i] = look_at_pose(p, p + f)
    return poses


def brute_force(P, D, ids, p, d, a_pos, a_dir):
    diff = P - p
    dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    dd = 1.0 - D @ d
    ok = (dist < a_pos) & (dd < a_dir)
    if not ok.any():
        return None
    score = np.where(ok, dist / a_pos + dd / a_dir, np.inf)
    return int(ids[np.argmin(score)])


def bench_lookup(n: int, root: Path, n_queries: int, a_pos: float, a_dir: float) -> dict:
    import icbtool.store as S
    from icbtool.camera import Camera

    d = root / f"lookup_{n}"
    shutil.rmtree(d, ignore_errors=True)
    poses = walk_cameras(n, seed=n)
    z = np.zeros((4, 4, 3), np.float32)
    cfg = S.StoreConfig(alpha_pos=a_pos, alpha_dir=a_dir, fsync=False)
    t0 = time.perf_counter()
    with S.open(d, cfg) as st:
        st.register_scene(scene_hash="bench", bounds=BOUNDS)
        for k in range(0, n, 5000):
            st.put_many(
                [
                    S.CRTBuffer(
                        Camera.from_fov(60, 4, 4, m), S.RecordMeta("bench", "bench", "sun"), gi=z
                    )
                    for m in poses[k : k + 5000]
                ]
            )
    t_fill = time.perf_counter() - t0
    t0 = time.perf_counter()
    st = S.open(d, S.StoreConfig(alpha_pos=a_pos, alpha_dir=a_dir, readonly=True))
    t_open = time.perf_counter() - t0
    # brute-force arrays: the same records, read back from the DB
    rows = st._db().execute("SELECT id, px, py, pz, dx, dy, dz FROM records").fetchall()
    a = np.array(rows, np.float64)
    ids, P, D = a[:, 0].astype(np.int64), a[:, 1:4], a[:, 4:7]
    rng = np.random.default_rng(1)
    queries = []
    for q in range(n_queries):
        if q % 2 == 0:
            m = poses[rng.integers(n)].copy()
            m[:3, 3] += rng.normal(0, a_pos / 3, 3)
        else:
            m = walk_cameras(1, seed=10_000 + q)[0]
        queries.append(Camera.from_fov(60, 4, 4, m))
    t_oct, t_bf, agree, hits = [], [], 0, 0
    for cam in queries:
        t1 = time.perf_counter_ns()
        h = st.lookup(cam, "bench", "sun")
        t2 = time.perf_counter_ns()
        ref = brute_force(
            P, D, ids, cam.world_from_cam[:3, 3], cam.world_from_cam[:3, 2], a_pos, a_dir
        )
        t3 = time.perf_counter_ns()
        t_oct.append(t2 - t1)
        t_bf.append(t3 - t2)
        agree += (None if h is None else h.record_id) == ref
        hits += h is not None
    occ = st.stats()["groups"][0]["octree"]
    st.close()
    t_oct_us, t_bf_us = np.array(t_oct) / 1e3, np.array(t_bf) / 1e3
    return {
        "records": n,
        "fill_s": t_fill,
        "open_s": t_open,
        "queries": n_queries,
        "hit_fraction": hits / n_queries,
        "agreement_with_brute_force": agree / n_queries,
        "octree_us_median": float(np.median(t_oct_us)),
        "octree_us_p95": float(np.percentile(t_oct_us, 95)),
        # no mean: the first lookup (index load, cold caches) and load spikes would dominate it
        "octree_us_first_query": float(t_oct_us[0]),
        "octree_us_median_after_first": float(np.median(t_oct_us[1:])),
        "brute_force_us_median": float(np.median(t_bf_us)),
        "brute_force_us_p95": float(np.percentile(t_bf_us, 95)),
        "octree": occ,
    }


def realistic_record(size: int):
    import icbtool.store as S
    from icbtool.camera import Camera

    src = REPO / "out" / "store_sponza" / "train"
    if (src / "icbstore.sqlite").exists():
        try:
            with S.open(src, S.StoreConfig(readonly=True)) as st:
                for info in st:
                    if info.camera.height == size and len(info.buffers) == 8:
                        return st.get(info.record_id), "sponza record"
        except S.StoreError:
            pass
    h = w = size
    y, x = np.mgrid[0:h, 0:w] / size
    rng = np.random.default_rng(0)
    smooth = np.stack([x, y, x * y], -1).astype(np.float32)
    maps = {
        "dl": smooth * 3,
        "albedo": smooth * 0.8,
        "gi": (smooth + rng.normal(0, 0.05, smooth.shape)).astype(np.float32),
        "normal_world": smooth / np.linalg.norm(smooth + 1e-3, axis=-1, keepdims=True),
        "normal_view": smooth[..., ::-1].copy(),
        "depth": (5 + x[..., None] * 3).astype(np.float32),
        "position": smooth * 10,
        "mask": np.ones((h, w, 1), np.float32),
    }
    return S.CRTBuffer(
        Camera.from_fov(60, h, w), S.RecordMeta("syn", "syn", "sun"), **maps
    ), "synthetic smooth maps"


def bench_insert(root: Path, n: int, size: int, fsync: bool) -> dict:
    import icbtool.store as S

    rec, kind = realistic_record(size)
    d = root / f"insert_fsync{int(fsync)}"
    shutil.rmtree(d, ignore_errors=True)
    recs = []
    for k in range(n):
        m = np.eye(4)
        m[:3, 3] = [0.01 * k, 0, 0]
        recs.append(S.CRTBuffer(rec.camera.with_pose(m), rec.meta, **rec.buffers()))
    with S.open(d, S.StoreConfig(fsync=fsync)) as st:
        t0 = time.perf_counter()
        for r in recs:
            st.put(r)
        dt = time.perf_counter() - t0
        nbytes = st.total_bytes
        t0 = time.perf_counter()
        for rid in st.ids()[:50]:
            st.get(rid)
        t_get = (time.perf_counter() - t0) / 50
    raw = sum(a.nbytes for a in rec.buffers().values())
    return {
        "payload": kind,
        "size": size,
        "fsync": fsync,
        "records": n,
        "records_per_s": n / dt,
        "ms_per_put": 1e3 * dt / n,
        "ms_per_get": 1e3 * t_get,
        "bytes_per_record": nbytes / n,
        "raw_float32_bytes": raw,
        "compression_ratio": raw / (nbytes / n),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10_000, 100_000])
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--alpha-pos", type=float, default=0.1)
    ap.add_argument("--alpha-dir", type=float, default=0.1)
    ap.add_argument("--inserts", type=int, default=100)
    ap.add_argument("--work", default=str(REPO / "out" / "store_bench"))
    add_out_argument(ap, "store")
    args = ap.parse_args()

    from tqdm import tqdm

    from benchmarks.common import run_info, write_json

    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    lookups = []
    for n in tqdm(args.sizes, desc="lookup benchmark", unit="store"):
        lookups.append(bench_lookup(n, work, args.queries, args.alpha_pos, args.alpha_dir))
        print(lookups[-1], flush=True)
    inserts = [bench_insert(work, args.inserts, 128, fs) for fs in (True, False)]
    for r in inserts:
        print(r, flush=True)
    result = {"lookup": lookups, "insert": inserts}
    write_json(out / "store_bench.json", result)
    write_json(out / "store_bench_config.json", {"args": vars(args), "run_info": run_info()})

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ns = [r["records"] for r in lookups]
    ax[0].loglog(ns, [r["octree_us_median"] for r in lookups], "o-", label="octree (median)")
    ax[0].loglog(ns, [r["octree_us_p95"] for r in lookups], "o--", label="octree (p95)")
    ax[0].loglog(
        ns,
        [r["brute_force_us_median"] for r in lookups],
        "s-",
        label="brute-force numpy scan (median)",
    )
    ax[0].axhline(100, color="gray", lw=0.8, ls=":", label="100 us target")
    ax[0].set_xlabel("records")
    ax[0].set_ylabel("lookup latency (us)")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"lookup, alpha_pos={args.alpha_pos}, alpha_dir={args.alpha_dir}")
    labels = [f"fsync={r['fsync']}" for r in inserts]
    ax[1].bar(labels, [r["records_per_s"] for r in inserts])
    for i, r in enumerate(inserts):
        ax[1].text(
            i,
            r["records_per_s"],
            f"{r['bytes_per_record'] / 1024:.0f} KiB/rec",
            ha="center",
            va="bottom",
        )
    ax[1].set_ylabel("puts per second (128x128, 8 maps)")
    ax[1].set_title(f"insert ({inserts[0]['payload']})")
    fig.tight_layout()
    fig.savefig(out / "store_bench.png", dpi=110)


if __name__ == "__main__":
    main()
