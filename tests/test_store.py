"""Tests of icbtool.store: persistence, exact lookup, crash safety, corruption, eviction, baking."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation

import icbtool as icb
import icbtool.bake as B
import icbtool.store as S
from icbtool.camera import Camera

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable


def make_cam(pos, rot=None, size=(8, 8), fov=60.0) -> Camera:
    m = np.eye(4)
    if rot is not None:
        m[:3, :3] = rot
    m[:3, 3] = pos
    return Camera.from_fov(fov, size[0], size[1], m)


def make_record(cam: Camera, sh="scene", lh="light", seed=0, **tags) -> S.CRTBuffer:
    r = np.random.default_rng(seed)
    h, w = cam.height, cam.width
    return S.CRTBuffer(
        camera=cam,
        meta=S.RecordMeta("s", sh, lh, spp=4, tags=tags),
        gi=r.random((h, w, 3), np.float32),
        dl=r.random((h, w, 3), np.float32),
        albedo=r.random((h, w, 3), np.float32),
        normal_world=r.standard_normal((h, w, 3)).astype(np.float32),
        depth=r.random((h, w, 1), np.float32),
        mask=(r.random((h, w, 1)) > 0.3).astype(np.float32),
    )


def same_buffers(a: S.CRTBuffer, b: S.CRTBuffer) -> bool:
    if a.present != b.present or a.camera != b.camera:
        return False
    return all(
        np.array_equal(getattr(a, n).view(np.uint32), getattr(b, n).view(np.uint32))
        for n in a.present
    )


# ------------------------------------------------------------------------------ round trip
_shape = st.tuples(st.integers(1, 6), st.integers(1, 6))


@st.composite
def records(draw):
    h, w = draw(_shape)
    cam = make_cam(draw(hnp.arrays(np.float64, 3, elements=st.floats(-5, 5))), size=(h, w))
    names = draw(st.sets(st.sampled_from(S.BUFFER_NAMES)))
    maps = {}
    for n in names:
        c = S.BUFFER_CHANNELS[n]
        if n == "mask" and draw(st.booleans()):
            el = st.sampled_from([0.0, 1.0])
        else:
            el = st.floats(width=32, allow_nan=True, allow_infinity=True)
        maps[n] = draw(hnp.arrays(np.float32, (h, w, c), elements=el))
    tags = draw(st.dictionaries(st.text(max_size=5), st.integers(-10, 10), max_size=3))
    return S.CRTBuffer(cam, S.RecordMeta("s", "sh", "lh", tags=tags), **maps)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(recs=st.lists(records(), min_size=1, max_size=3))
def test_put_get_roundtrip_is_bit_exact(recs):
    with tempfile.TemporaryDirectory() as d:
        with S.open(Path(d) / "s", S.StoreConfig(fsync=False)) as store:
            ids = [store.put(r) for r in recs]
            for rid, r in zip(ids, recs):
                got = store.get(rid)
                assert same_buffers(got, r)
                assert got.meta == r.meta
            assert len(store) == len(recs)
            assert [i.record_id for i in store] == ids


# ------------------------------------------------------------------------------ lookup
_TABLES: dict = {}


def brute_force(query: Camera, entries, a_pos, a_dir, rtol=1e-4):
    """Reference: a plain scan of every (id, camera) entry of the query's group ("same" policy).

    Returns (score, id, distance, 1 - dot) of the best match, or None.
    """
    key = id(entries)
    if _TABLES.get("key") != (key, len(entries)):
        _TABLES["key"] = (key, len(entries))
        _TABLES["t"] = (
            np.array([rid for rid, _ in entries]),
            np.array([c.position for _, c in entries]),
            np.array([c.forward for _, c in entries]),
            np.array([[c.height, c.width, c.fx, c.fy, c.cx, c.cy] for _, c in entries]),
        )
    ids, pos, fwd, intr = _TABLES["t"]
    q = np.array([query.height, query.width, query.fx, query.fy, query.cx, query.cy])
    same = np.all(np.abs(intr - q) <= rtol * np.abs(q), axis=1)
    dist = np.sqrt(np.sum((pos - query.position) ** 2, axis=1))
    dd = 1.0 - fwd @ query.forward
    ok = same & (dist < a_pos) & (dd < a_dir)
    if not ok.any():
        return None
    score = dist / a_pos + dd / a_dir
    k = min(np.flatnonzero(ok), key=lambda i: (score[i], ids[i]))
    return score[k], int(ids[k]), dist[k], dd[k]


@pytest.mark.parametrize("leaf_size", [0.05, 0.3, 2.0])
def test_lookup_equals_brute_force(tmp_path, leaf_size):
    rng = np.random.default_rng(7)
    cfg = S.StoreConfig(alpha_pos=0.3, alpha_dir=0.05, leaf_size=leaf_size, fsync=False)
    entries = []
    with S.open(tmp_path / "s", cfg) as store:
        store.register_scene(scene_hash="scene", bounds=[[0, 0, 0], [4, 2, 4]])
        centres = rng.uniform([0, 0, 0], [4, 2, 4], (12, 3))
        for k in range(400):
            pos = centres[k % 12] + rng.normal(0, 0.25, 3)
            if k % 40 == 0:
                pos = rng.uniform(-3, 7, 3)  # some outside the bounds
            rot = Rotation.random(random_state=k).as_matrix()
            fov = 60.0 if k % 7 else 75.0  # some with other intrinsics
            lh = "light" if k % 11 else "other-light"
            cam = make_cam(pos, rot, size=(2, 2), fov=fov)
            rid = store.put(make_record(cam, lh=lh, seed=k))
            if lh == "light":
                entries.append((rid, cam))
        n_hits = 0
        for q in range(300):
            base = entries[rng.integers(len(entries))][1]
            pos = base.position + rng.normal(0, 0.2, 3)
            rot = Rotation.from_matrix(base.world_from_cam[:3, :3]) * Rotation.from_rotvec(
                rng.normal(0, 0.15, 3)
            )
            query = make_cam(pos, rot.as_matrix(), size=(2, 2), fov=60.0 if q % 5 else 75.0)
            # alternate the configured thresholds and larger per-call ones
            a_pos, a_dir = (0.3, 0.05) if q % 2 else (0.9, 0.2)
            hit = store.lookup(query, "scene", "light", alpha_pos=a_pos, alpha_dir=a_dir)
            ref = brute_force(query, entries, a_pos, a_dir)
            if ref is None:
                assert hit is None, (q, hit)
            else:
                n_hits += 1
                assert hit is not None and hit.record_id == ref[1], (q, hit, ref)
                assert hit.distance == pytest.approx(ref[2], abs=1e-12)
                assert hit.dir_score == pytest.approx(ref[3], abs=1e-12)
                ang = np.degrees(np.arccos(np.clip(1 - ref[3], -1, 1)))
                assert hit.angle_deg == pytest.approx(ang, abs=1e-6)
        assert 50 < n_hits < 290  # the test exercises both hits and misses


def test_lookup_matches_across_a_cell_boundary(tmp_path):
    cfg = S.StoreConfig(alpha_pos=0.1, alpha_dir=0.01, leaf_size=1.0, fsync=False)
    with S.open(tmp_path / "s", cfg) as store:
        store.register_scene(scene_hash="scene", bounds=[[0, 0, 0], [8, 8, 8]])
        g = store.geometry("scene")
        assert g.leaf_size <= 1.0 and g.depth >= 3
        # a corner shared by 8 leaves
        corner = np.asarray(g.root_min) + 3 * g.leaf_size
        stored = make_cam(corner - 0.02)
        rid = store.put(make_record(stored))
        query = make_cam(corner + 0.02)
        tree = store._trees[("scene", "light")]
        a, b = tree.cell_of(stored.position), tree.cell_of(query.position)
        assert all(x != y for x, y in zip(a, b))  # different leaf on every axis
        assert b in [(i + 1, j + 1, k + 1) for i, j, k in [a]]
        assert a in tree.adjacent(b) or b not in tree.leaves  # the paper's "Adjacent"
        hit = store.lookup(query, "scene", "light")
        assert hit is not None and hit.record_id == rid
        assert hit.distance == pytest.approx(0.04 * np.sqrt(3))
        assert store.lookup(make_cam(corner + 0.05), "scene", "light") is None  # 0.12 away


def test_cameras_outside_the_scene_bounds(tmp_path):
    cfg = S.StoreConfig(alpha_pos=0.2, alpha_dir=0.05, fsync=False)
    with S.open(tmp_path / "s", cfg) as store:
        store.register_scene(scene_hash="scene", bounds=[[0, 0, 0], [1, 1, 1]])
        far = [np.array([5.0, 5.0, 5.0]), np.array([-3.0, 0.5, 0.5]), np.array([0.5, 40, -9])]
        ids = [store.put(make_record(make_cam(p), seed=i)) for i, p in enumerate(far)]
        tree = store._trees[("scene", "light")]
        assert not any(tree.is_inside(p) for p in far)
        for rid, p in zip(ids, far):
            hit = store.lookup(make_cam(p + [0.1, 0.05, 0.0]), "scene", "light")
            assert hit is not None and hit.record_id == rid
            assert store.lookup(make_cam(p + [0.3, 0.0, 0.0]), "scene", "light") is None
        # clamped to the same border leaf but far apart: no false hit
        assert store.lookup(make_cam([9.0, 5.0, 5.0]), "scene", "light") is None


def test_other_light_setup_or_scene_never_matches(tmp_path):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        cam = make_cam([1.0, 2.0, 3.0])
        rid = store.put(make_record(cam, lh="sun-noon"))
        assert store.lookup(cam, "scene", "sun-evening") is None
        assert store.lookup(cam, "other-scene", "sun-noon") is None
        assert store.lookup(cam, "scene", "sun-noon").record_id == rid


def test_intrinsics_policy(tmp_path):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        wide = make_cam([0, 0, 0], fov=90.0)
        rid = store.put(make_record(wide))
        narrow = make_cam([0, 0, 0.01], fov=60.0)
        assert store.lookup(narrow, "scene", "light") is None  # "same": not a direct reuse
        hit = store.lookup(narrow, "scene", "light", intrinsics="covering")
        assert hit is not None and hit.record_id == rid and not hit.same_intrinsics
        assert (
            store.lookup(make_cam([0, 0, 0], fov=100.0), "scene", "light", intrinsics="covering")
            is None
        )  # the stored one is narrower
        assert (
            store.lookup(
                make_cam([0, 0, 0], fov=100.0), "scene", "light", intrinsics="any"
            ).record_id
            == rid
        )


# ------------------------------------------------------------------------------ persistence
def test_restart_keeps_everything(tmp_path):
    cams = [make_cam([i * 0.5, 0, 0], size=(4, 5)) for i in range(12)]
    with S.open(tmp_path / "s") as store:
        ids = [store.put(make_record(c, seed=i, path="train")) for i, c in enumerate(cams)]
        hits_before = [store.lookup(c, "scene", "light").record_id for c in cams]
    with S.open(tmp_path / "s") as store:
        assert len(store) == 12 and store.ids() == ids
        for i, (rid, c) in enumerate(zip(ids, cams)):
            assert same_buffers(store.get(rid), make_record(c, seed=i))
            assert store.lookup(c, "scene", "light").record_id == hits_before[i]
        assert sum(i.hits for i in store) == 24  # 12 flushed at close + 12 pending
        assert store.check().ok


WRITER = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {repo!r})
    import numpy as np
    import icbtool.store as S
    from icbtool.camera import Camera
    d, start, n, sleep = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
    with S.open(d, S.StoreConfig(lock_timeout_s=20)) as store:
        print("open", flush=True)
        for k in range(start, start + n):
            m = np.eye(4); m[:3, 3] = [k * 0.01, 0, 0]
            r = np.random.default_rng(k)
            cam = Camera.from_fov(60, 16, 16, m)
            buf = S.CRTBuffer(cam, S.RecordMeta("s", "scene", "light", tags={{"k": k}}),
                              gi=r.random((16, 16, 3), np.float32),
                              depth=r.random((16, 16, 1), np.float32))
            rid = store.put(buf)
            print(k, rid, flush=True)
            time.sleep(sleep)
    """
)


def expected(k: int) -> S.CRTBuffer:
    m = np.eye(4)
    m[:3, 3] = [k * 0.01, 0, 0]
    r = np.random.default_rng(k)
    cam = Camera.from_fov(60, 16, 16, m)
    return S.CRTBuffer(
        cam,
        S.RecordMeta("s", "scene", "light", tags={"k": k}),
        gi=r.random((16, 16, 3), np.float32),
        depth=r.random((16, 16, 1), np.float32),
    )


def _writer(tmp_path: Path, d: Path, start: int, n: int, sleep: float) -> subprocess.Popen:
    script = tmp_path / "writer.py"
    if not script.exists():
        script.write_text(WRITER.format(repo=str(REPO)))
    return subprocess.Popen(
        [PY, str(script), str(d), str(start), str(n), str(sleep)], stdout=subprocess.PIPE, text=True
    )


def test_sigkill_during_writes_loses_nothing_committed(tmp_path):
    d = tmp_path / "s"
    rng = np.random.default_rng(3)
    committed: dict[int, int] = {}  # record id -> k
    start = 0
    for _round in range(20):
        p = _writer(tmp_path, d, start, 10_000, 0.0)
        assert p.stdout.readline().strip() == "open"
        time.sleep(rng.uniform(0.0, 0.25))
        p.send_signal(signal.SIGKILL)
        out, _ = p.communicate()
        for line in out.splitlines(keepends=True):
            if not line.endswith("\n"):  # killed while printing: this id is not known for sure
                continue
            k, rid = map(int, line.split())
            committed[rid] = k
            start = max(start, k + 1)
        with S.open(d, S.StoreConfig(readonly=True)) as store:  # readable right after the kill
            assert set(committed) <= set(store.ids())
    assert len(committed) > 20
    with S.open(d) as store:  # the writer cleans orphan payloads on open
        assert set(committed) <= set(store.ids())
        for rid, k in committed.items():
            assert same_buffers(store.get(rid), expected(k))
        report = store.check()
        assert report.ok and not report.orphans


def test_readers_while_a_writer_writes(tmp_path):
    d = tmp_path / "s"
    with S.open(d) as store:
        store.put(expected(0))
    reader_code = textwrap.dedent(
        f"""
        import sys, time; sys.path.insert(0, {str(REPO)!r})
        import icbtool.store as S
        with S.open({str(d)!r}, S.StoreConfig(readonly=True)) as st:
            seen = 0
            t0 = time.time()
            while time.time() - t0 < 20:
                n = len(st)
                assert n >= seen; seen = n
                for rid in st.ids():
                    st.get(rid)
                if n >= 31: break
                time.sleep(0.02)
            print(seen)
        """
    )
    reader = subprocess.Popen([PY, "-c", reader_code], stdout=subprocess.PIPE, text=True)
    writer = _writer(tmp_path, d, 1, 30, 0.01)
    assert writer.stdout.readline().strip() == "open"
    with S.open(d, S.StoreConfig(readonly=True)) as store:
        seen, lookups_hit = 0, 0
        while writer.poll() is None or len(store) < 31:
            n = len(store)
            assert n >= seen
            seen = n
            for rid in store.ids():
                assert store.get(rid).gi.shape == (16, 16, 3)
            k = max(0, n - 1)
            hit = store.lookup(expected(k).camera, "scene", "light", alpha_pos=0.001)
            lookups_hit += hit is not None
            if n >= 31:
                break
        assert len(store) == 31 and lookups_hit > 0
        for rid in store.ids():
            k = store.info(rid).meta.tags["k"]
            assert same_buffers(store.get(rid), expected(k))
    assert writer.wait(30) == 0
    out, _ = reader.communicate(timeout=30)
    assert reader.returncode == 0 and int(out) == 31


def test_second_writer_is_refused_clearly(tmp_path):
    with S.open(tmp_path / "s"):
        p = _writer(tmp_path, tmp_path / "s", 0, 1, 0.0)  # waits for the lock (20 s)
        time.sleep(0.5)
        assert p.poll() is None  # blocked, not writing
        with pytest.raises(S.StoreLockedError, match="open for writing"):
            S.open(tmp_path / "s", S.StoreConfig(lock_timeout_s=0.1))
    assert p.wait(30) == 0  # got the lock once we closed


# ------------------------------------------------------------------------------ damage
def test_corrupted_payloads_are_reported_by_check_and_get(tmp_path, capsys):
    from icbtool.cli import main

    d = tmp_path / "s"
    with S.open(d) as store:
        ids = [store.put(make_record(make_cam([i, 0, 0], size=(8, 8)), seed=i)) for i in range(4)]
        paths = [store.info(i).payload for i in ids]
    flip = bytearray(paths[0].read_bytes())
    flip[len(flip) // 2] ^= 0xFF
    paths[0].write_bytes(bytes(flip))
    paths[1].write_bytes(paths[1].read_bytes()[:-10])
    paths[2].unlink()
    with S.open(d, S.StoreConfig(readonly=True)) as store:
        rep = store.check()
        assert not rep.ok
        bad = {x.record_id: x.problem for x in rep.damaged}
        assert set(bad) == set(ids[:3])
        assert "checksum" in bad[ids[0]] and "size" in bad[ids[1]] and "missing" in bad[ids[2]]
        for rid, what in zip(ids[:3], ("damaged", "damaged", "missing")):
            with pytest.raises(S.PayloadError, match=f"record {rid}: payload file .* {what}"):
                store.get(rid)
        assert same_buffers(store.get(ids[3]), make_record(make_cam([3, 0, 0]), seed=3))
    assert main(["store", "check", str(d)]) == 1
    out = capsys.readouterr().out
    assert out.count("DAMAGED") == 3 and "DAMAGE: 3" in out
    assert main(["store", "check", str(d), "--drop-damaged"]) == 1  # damage found (and dropped)
    assert main(["store", "check", str(d)]) == 0
    with S.open(d) as store:
        assert store.ids() == [ids[3]]


def test_orphan_payloads_are_cleaned(tmp_path):
    d = tmp_path / "s"
    with S.open(d) as store:
        store.put(make_record(make_cam([0, 0, 0])))
    orphan = d / "payloads" / "ff" / ("f" * 32 + ".icbp")
    orphan.parent.mkdir()
    orphan.write_bytes(b"partial")
    (d / "payloads" / "tmp" / "x.tmp").write_bytes(b"half-written")
    with S.open(d, S.StoreConfig(readonly=True)) as store:
        assert store.check().ok  # orphans are harmless; a reader only reports them
    with S.open(d) as store:
        assert store.orphans_removed_on_open == 2 and not orphan.exists()


def test_non_store_and_corrupt_db_are_refused_untouched(tmp_path):
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"jpeg")
    with pytest.raises(S.StoreFormatError, match="not an icbtool store"):
        S.open(other)
    assert sorted(p.name for p in other.iterdir()) == ["holiday.jpg"]

    bad = tmp_path / "bad"
    bad.mkdir()
    junk = os.urandom(4096)
    (bad / "icbstore.sqlite").write_bytes(junk)
    with pytest.raises(S.StoreFormatError, match="icbstore.sqlite"):
        S.open(bad)
    assert (bad / "icbstore.sqlite").read_bytes() == junk

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    con = sqlite3.connect(foreign / "icbstore.sqlite")
    con.execute("CREATE TABLE t (x)")
    con.commit()
    con.close()
    before = (foreign / "icbstore.sqlite").read_bytes()
    with pytest.raises(S.StoreFormatError, match="not an icbtool store"):
        S.open(foreign)
    assert (foreign / "icbstore.sqlite").read_bytes() == before

    newer = tmp_path / "newer"
    with S.open(newer) as store:
        store.put(make_record(make_cam([0, 0, 0])))
    con = sqlite3.connect(newer / "icbstore.sqlite")
    con.execute("UPDATE meta SET value='99' WHERE key='format_version'")
    con.commit()
    con.close()
    with pytest.raises(S.StoreFormatError, match="version '99' is not supported"):
        S.open(newer)

    with pytest.raises(FileNotFoundError):
        S.open(tmp_path / "missing", S.StoreConfig(readonly=True))
    with pytest.raises(S.RecordNotFoundError, match="no record 12345"):
        with S.open(tmp_path / "fresh") as store:
            store.get(12345)


def test_bad_inputs_raise_clear_errors(tmp_path):
    cam = make_cam([0, 0, 0], size=(4, 4))
    with pytest.raises(ValueError, match=r"CRTBuffer.gi must be \(H, W, 3\)"):
        S.CRTBuffer(cam, S.RecordMeta("s", "h", "l"), gi=np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="alpha_pos"):
        S.StoreConfig(alpha_pos=0)
    with pytest.raises(ValueError, match="eviction"):
        S.StoreConfig(eviction="random")
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        with pytest.raises(ValueError, match="scene_hash and light_hash"):
            store.lookup(cam)
    with S.open(tmp_path / "s", S.StoreConfig(readonly=True)) as store:
        with pytest.raises(S.ReadOnlyStoreError):
            store.put(make_record(cam))


# ------------------------------------------------------------------------------ eviction
def test_eviction_keeps_the_store_within_capacity(tmp_path):
    cfg = S.StoreConfig(max_records=10, eviction="lru", fsync=False)
    cams = [make_cam([i * 1.0, 0, 0]) for i in range(30)]
    with S.open(tmp_path / "s", cfg) as store:
        first = store.put(make_record(cams[0]))
        for i, c in enumerate(cams[1:], 1):
            assert store.lookup(cams[0], "scene", "light").record_id == first  # keep it hot
            store.put(make_record(c, seed=i))
            assert len(store) <= 10
        assert first in store  # recently hit: survives LRU
        assert store.check().ok and len(list(store)) == len(store)
        n_files = sum(1 for p in (tmp_path / "s" / "payloads").rglob("*.icbp"))
        assert n_files == len(store)  # evicted payloads are gone from disk too

    one = (tmp_path / "s" / "payloads").rglob("*.icbp").__next__().stat().st_size
    cfg = S.StoreConfig(max_bytes=int(5.5 * one), eviction="least_hit", fsync=False)
    with S.open(tmp_path / "b", cfg) as store:
        for i, c in enumerate(cams[:15]):
            store.put(make_record(c, seed=i))
            assert store.total_bytes <= 5.5 * one * 1.05

    cfg = S.StoreConfig(max_records=5, eviction="farthest", evict_to=1.0, fsync=False)
    with S.open(tmp_path / "f", cfg) as store:
        with pytest.raises(ValueError, match="focus"):
            store.put(make_record(cams[0]))
        store.set_focus([0.0, 0.0, 0.0])
        for i, c in enumerate(cams[:10]):
            store.put(make_record(c, seed=i))
        kept = sorted(info.camera.position[0] for info in store)
        assert kept == [0.0, 1.0, 2.0, 3.0, 9.0]  # the newest is protected at its own put


def test_cli_stats_and_evict(tmp_path, capsys):
    from icbtool.cli import main

    d = tmp_path / "s"
    with S.open(d) as store:
        for i in range(6):
            store.put(make_record(make_cam([i * 1.0, 0, 0]), seed=i))
    assert main(["store", "stats", str(d)]) == 0
    assert "records: 6" in capsys.readouterr().out
    assert main(["store", "evict", str(d), "--max-records", "2"]) == 0
    assert "6 -> 2 records" in capsys.readouterr().out
    assert main(["store", "stats", str(d), "--json"]) == 0
    assert '"records": 2' in capsys.readouterr().out
    assert main(["store", "stats", str(tmp_path / "nothing")]) == 1


# ------------------------------------------------------------------------------ dataset
def test_dataset_splits_and_configurations(tmp_path):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        for i in range(6):
            cam = make_cam([i * 1.0, 0, 0], size=(4, 6))
            rec = make_record(cam, seed=i, path="train" if i < 4 else "test", index=i)
            rec.normal_view = rec.normal_world
            rec.position = rec.normal_world
            store.put(rec)
        train = S.Dataset(store, scene="scene", split="train", inputs="I")
        test = S.Dataset(store, scene="scene", split="test", inputs="I")
        assert len(train) == 4 and len(test) == 2
        assert not set(train.record_ids) & set(test.record_ids)
        s = train[0]
        assert s.inputs.shape == (10, 4, 6) and s.inputs.dtype == np.float32
        assert s.target.shape == (3, 4, 6)
        rec = store.get(s.record_id)
        assert np.array_equal(s.inputs[:3], rec.albedo.transpose(2, 0, 1))
        assert np.array_equal(s.inputs[9], rec.depth[..., 0])
        assert np.array_equal(s.target, rec.gi.transpose(2, 0, 1))
        for cfg, n in (("A", 6), ("D", 10), ("G", 12), ("J", 12)):
            assert S.Dataset(store, split="train", inputs=cfg).n_channels == n
        r1 = S.Dataset(store, split="test", split_by="random", seed=3).record_ids
        r2 = S.Dataset(store, split="test", split_by="random", seed=3).record_ids
        r3 = S.Dataset(store, split="train", split_by="random", seed=3).record_ids
        assert r1 == r2 and not set(r1) & set(r3) and len(r1) + len(r3) == 6
        with pytest.raises(ValueError, match="unknown input configuration"):
            S.Dataset(store, inputs="Z")


# ------------------------------------------------------------------------------ baking
def _tiny_scene():
    from icbtool.camera import CameraPath
    from icbtool.scene import cornell_box, cornell_camera

    scene = cornell_box()
    base = cornell_camera(32, 32)
    poses = []
    for dx in (0.0, 0.05, 0.1):
        m = np.array(base.world_from_cam)
        m[:3, 3] += [dx, 0, 0]
        poses.append(m)
    tiny = CameraPath(np.arange(3.0), np.stack(poses), base, "tiny")
    return replace(scene, paths={**scene.paths, "tiny": tiny})


def test_bake_denoise_quality_reaches_the_tracer(tmp_path):
    pytest.importorskip("pyoidn")
    scene = _tiny_scene()
    with pytest.raises(ValueError, match="denoise_quality"):
        B.BakeConfig(denoise_quality="best")
    cfg = B.BakeConfig(spp=2, gbuffer="trace", progress=False, limit=1, denoise=True,
                       denoise_quality="fast")  # fmt: skip
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        (rid,) = B.bake(scene, "tiny", store, cfg).rendered
        rec = store.get(rid)
    cam = scene.paths["tiny"].cameras()[0]
    tcfg = icb.trace.TraceConfig(spp=2, seed=0, denoise=True, denoise_quality="fast")
    fast = icb.trace.render(scene, cam, tcfg)
    high = icb.trace.render(scene, cam, replace(tcfg, denoise_quality="high"))
    assert np.array_equal(rec.gi, fast.gi) and not np.array_equal(rec.gi, high.gi)


def test_bake_without_gl_is_resumable(tmp_path):
    scene = _tiny_scene()
    cfg = B.BakeConfig(spp=2, gbuffer="trace", progress=False)
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        r1 = B.bake(
            scene, "tiny", store, B.BakeConfig(spp=2, gbuffer="trace", progress=False, limit=2)
        )
        assert len(r1.rendered) == 2 and r1.skipped == []
        r2 = B.bake(scene, "tiny", store, cfg)
        assert len(r2.rendered) == 1 and r2.skipped == [0, 1]
        r3 = B.bake(scene, "tiny", store, cfg)
        assert r3.rendered == [] and len(store) == 3
        rec = store.get(r2.rendered[0])
        assert rec.meta.tags["path"] == "tiny" and rec.meta.tags["index"] == 2
        assert rec.meta.scene_hash == scene.content_hash
        assert np.all(np.isfinite(rec.gi)) and rec.gi.shape == (32, 32, 3)
        m = rec.mask[..., 0] > 0
        assert m.mean() > 0.5  # mostly walls
        uv, z = rec.camera.project(rec.position[m])  # G-buffers agree with the camera
        assert np.allclose(uv, rec.camera.pixel_centers()[m], atol=1e-3)
        assert np.allclose(z, rec.depth[m][:, 0], rtol=1e-4)
        hit = store.lookup(scene.paths["tiny"][2], scene=scene, alpha_pos=0.01)
        assert hit is not None and hit.record_id == r2.rendered[0] and hit.distance == 0.0


@pytest.mark.gl
def test_bake_with_raster_is_resumable(tmp_path):
    pytest.importorskip("icbtool.raster")
    from icbtool import raster

    if not hasattr(raster, "Rasterizer"):
        pytest.skip("icbtool.raster.Rasterizer has not landed yet")
    scene = _tiny_scene()
    cfg = B.BakeConfig(spp=2, progress=False)
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        r1 = B.bake(scene, "tiny", store, cfg)
        assert len(r1.rendered) == 3
        r2 = B.bake(scene, "tiny", store, cfg)
        assert r2.rendered == [] and r2.skipped == [0, 1, 2]
        rec = store.get(r1.rendered[0])
        assert set(rec.present) == set(S.BUFFER_NAMES)


def test_cloud_camera_modes():
    scene = _tiny_scene()
    path = scene.paths["tiny"]
    client = path[1]
    assert B.cloud_camera(client, B.BakeConfig()) == client
    w = B.cloud_camera(client, B.BakeConfig(cloud_camera="wider", fov_multiplier=1.5, pullback=0.5))
    assert w.fov_y_deg == pytest.approx(1.5 * client.fov_y_deg)
    assert np.allclose(w.position, client.position - 0.5 * client.forward)
    assert np.allclose(w.forward, client.forward)
    p = B.cloud_camera(client, B.BakeConfig(cloud_camera="prefetch"), path, 1, scene)
    assert np.allclose(p.forward, client.forward) and p.fov_y_deg >= client.fov_y_deg - 1e-9
    with pytest.raises(ValueError, match="needs the camera path"):
        B.cloud_camera(client, B.BakeConfig(cloud_camera="prefetch"))


def test_put_many_and_exclude(tmp_path):
    cams = [make_cam([0.01 * i, 0, 0]) for i in range(5)]
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        ids = store.put_many([make_record(c, seed=i) for i, c in enumerate(cams)])
        assert ids == sorted(ids) and len(store) == 5
        assert store.lookup(cams[2], "scene", "light").record_id == ids[2]
        h = store.lookup(cams[2], "scene", "light", exclude=(ids[2],))
        assert h.record_id in (ids[1], ids[3]) and h.distance == pytest.approx(0.01)
        assert store.find_exact(cams[4], "scene", "light") == ids[4]
        assert store.find_exact(make_cam([0.015, 0, 0]), "scene", "light") is None
    with S.open(tmp_path / "s") as store:
        assert all(
            same_buffers(store.get(r), make_record(c, seed=i))
            for i, (r, c) in enumerate(zip(ids, cams))
        )


# ------------------------------------------------------------------------------ index rebuild
def _seven_records(d: Path) -> tuple[list[int], dict]:
    """7 records in 2 light setups, some hit; returns their ids and what the index says."""
    with S.open(d, S.StoreConfig(fsync=False)) as store:
        ids = [
            store.put(make_record(make_cam([0.3 * i, 0, 0]), lh=f"light{i % 2}", seed=i, k=i))
            for i in range(7)
        ]
        for _ in range(3):
            store.lookup(make_cam([0.6, 0, 0]), "scene", "light0")
        before = {i.record_id: i for i in store}
    return ids, before


def _damage_db(db: Path, how: str) -> None:
    if how == "truncate":
        data = db.read_bytes()
        db.write_bytes(data[: len(data) // 2])
    elif how == "overwrite":  # a page in the middle: the records' b-tree
        data = bytearray(db.read_bytes())
        data[8192:12288] = np.random.default_rng(5).bytes(4096)
        db.write_bytes(bytes(data))
    else:
        db.unlink()


@pytest.mark.parametrize("how", ["truncate", "overwrite", "delete"])
def test_rebuild_recovers_every_record_from_a_damaged_index(tmp_path, how):
    d = tmp_path / "s"
    ids, before = _seven_records(d)
    payload_bytes = {rid: info.payload.read_bytes() for rid, info in before.items()}
    db = d / "icbstore.sqlite"
    _damage_db(db, how)
    damaged_db = db.read_bytes() if db.exists() else None
    for cfg in (S.StoreConfig(), S.StoreConfig(readonly=True)):
        with pytest.raises(S.StoreIndexError, match=rf"icbtool store check {d} --rebuild"):
            S.open(d, cfg)
    if damaged_db is not None:
        assert db.read_bytes() == damaged_db  # refused untouched
    rep = S.rebuild(d)
    assert rep.recovered == ids and rep.damaged == [] and rep.quarantined == [] and rep.ok
    assert rep.orphans == [] and rep.renumbered == {}
    if damaged_db is None:
        assert rep.old_index is None
    else:  # the old database is kept aside, byte for byte
        assert Path(rep.old_index).name.startswith("icbstore.sqlite.damaged-")
        assert Path(rep.old_index).read_bytes() == damaged_db
    assert not (d / "icbstore.sqlite.rebuild-tmp").exists()
    with S.open(d, S.StoreConfig(fsync=False)) as store:
        assert store.ids() == ids and store.orphans_removed_on_open == 0
        for rid in ids:
            a, b = store.info(rid), before[rid]
            assert a.meta == b.meta and a.camera == b.camera and a.buffers == b.buffers
            assert (a.nbytes, a.checksum) == (b.nbytes, b.checksum)
            assert a.payload.read_bytes() == payload_bytes[rid]
            k = a.meta.tags["k"]
            assert same_buffers(store.get(rid), make_record(make_cam([0.3 * k, 0, 0]), seed=k))
        # hit counts come back from the old database where it can still be read
        if how == "delete":
            assert rep.hits_restored == 0 and all(store.info(r).hits == 0 for r in ids)
        assert rep.hits_restored in (0, 7)
        if rep.hits_restored:
            assert [store.info(r).hits for r in ids] == [before[r].hits for r in ids]
        hit = store.lookup(make_cam([0.61, 0, 0]), "scene", "light0")
        assert hit.record_id == ids[2] and store.lookup(make_cam([0.6, 0, 0]), "scene", "x") is None
        assert store.geometry("scene") == S.OctreeGeometry(*_geometry_of(before[ids[0]], store))
        new = store.put(make_record(make_cam([5, 0, 0]), seed=99))
        assert new == ids[-1] + 1  # ids are never reused
        assert store.check().ok


def _geometry_of(info, store):
    g = store.geometry(info.meta.scene_hash)
    return g.root_min, g.root_size, g.depth


def test_rebuild_quarantines_damaged_payloads_and_reports_orphans(tmp_path):
    d = tmp_path / "s"
    ids, before = _seven_records(d)
    flipped, cut = before[ids[1]].payload, before[ids[4]].payload
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit
    flipped.write_bytes(bytes(data))
    cut.write_bytes(cut.read_bytes()[:-100])
    bad_bytes = {flipped.name: flipped.read_bytes(), cut.name: cut.read_bytes()}
    (d / "payloads" / "tmp" / "half.tmp").write_bytes(b"half-written")
    (d / "icbstore.sqlite").unlink()
    rep = S.rebuild(d)
    assert rep.recovered == [i for i in ids if i not in (ids[1], ids[4])] and not rep.ok
    assert sorted(Path(x.path).name for x in rep.damaged) == sorted(bad_bytes)
    assert all("digest mismatch" in x.problem for x in rep.damaged)
    assert len(rep.orphans) == 1 and rep.orphans[0].endswith("half.tmp")
    assert len(rep.quarantined) == 2  # moved aside, not deleted
    for q in map(Path, rep.quarantined):
        assert q.parent.parent.parent.name == "quarantine" and q.read_bytes() == bad_bytes[q.name]
    assert not flipped.exists() and not cut.exists()
    with S.open(d) as store:
        assert store.ids() == rep.recovered and store.check().ok
        assert store.orphans_removed_on_open == 1  # the tmp file only
    assert all(Path(q).exists() for q in rep.quarantined)

    # an intact index that lists a missing payload: the rebuild names the lost record
    with S.open(d) as store:
        store.info(ids[6]).payload.unlink()
    rep = S.rebuild(d)
    assert [(x.record_id, x.problem) for x in rep.damaged] == [(ids[6], "payload file missing")]
    assert rep.hits_restored == 4 and rep.recovered == [ids[0], ids[2], ids[3], ids[5]]
    # that index was healthy: kept (not copied aside), without the lost record's row
    assert not rep.rebuilt and rep.old_index is None
    assert not list(d.glob("icbstore.sqlite.damaged-*"))
    with S.open(d) as store:
        assert store.ids() == rep.recovered and store.check().ok


def test_rebuild_leaves_a_healthy_index_alone(tmp_path, capsys):
    """A healthy index that lists exactly the intact payloads is not swapped: no
    ``damaged-<time>`` file, the database byte for byte, hit counts kept, run after run."""
    from icbtool.cli import main

    d = tmp_path / "s"
    ids, before = _seven_records(d)
    db = d / "icbstore.sqlite"

    def listing():  # SQLite's own -wal/-shm side files come and go with connections
        return sorted(p.name for p in d.iterdir() if not p.name.endswith(("-wal", "-shm")))

    files = listing()
    db_bytes = db.read_bytes()
    for _ in range(2):
        rep = S.rebuild(d)
        assert not rep.rebuilt and rep.ok and rep.old_index is None
        assert rep.recovered == ids and rep.hits_restored == 7 and rep.quarantined == []
        assert listing() == files  # nothing new in the store
        assert db.read_bytes() == db_bytes
    assert main(["store", "check", str(d), "--rebuild"]) == 0
    assert "is healthy and complete: left alone (7 record(s) recovered)" in capsys.readouterr().out
    assert not list(d.glob("icbstore.sqlite.damaged-*"))
    with S.open(d) as store:
        assert [store.info(r).hits for r in ids] == [before[r].hits for r in ids]
    # a healthy index that lists a record whose payload is bad: kept, without that row; the
    # payload quarantined, no .damaged copy of the index
    before[ids[0]].payload.write_bytes(b"ICBP garbage")
    rep = S.rebuild(d)
    assert not rep.rebuilt and rep.recovered == ids[1:] and rep.old_index is None
    assert [x.record_id for x in rep.damaged] == [ids[0]] and len(rep.quarantined) == 1
    assert not list(d.glob("icbstore.sqlite.damaged-*"))
    with S.open(d) as store:
        assert store.ids() == ids[1:] and store.check().ok
    assert main(["store", "check", str(d), "--rebuild"]) == 0  # now healthy and complete
    assert "healthy and complete: left alone (6 record(s)" in capsys.readouterr().out


def test_cli_check_rebuild(tmp_path, capsys):
    from icbtool.cli import main

    d = tmp_path / "s"
    ids, before = _seven_records(d)
    before[ids[3]].payload.write_bytes(b"ICBP garbage")
    _damage_db(d / "icbstore.sqlite", "truncate")
    assert main(["store", "check", str(d)]) == 1
    err = capsys.readouterr().err
    assert "is damaged" in err and f"`icbtool store check {d} --rebuild`" in err
    assert main(["store", "stats", str(d)]) == 1
    assert "--rebuild" in capsys.readouterr().err
    assert main(["store", "check", str(d), "--rebuild"]) == 1  # one payload was lost
    out = capsys.readouterr().out
    assert f"rebuilt the index of {d}: 6 record(s) recovered" in out
    assert "old index database kept as" in out and "icbstore.sqlite.damaged-" in out
    assert "DAMAGED record" in out and "1 damaged payload(s) moved to" in out
    assert "DAMAGE: 1 payload(s) not recovered" in out
    assert main(["store", "check", str(d)]) == 0
    assert "checked 6 records" in capsys.readouterr().out
    assert main(["store", "check", str(d), "--rebuild"]) == 0  # an intact store rebuilds too
    assert "6 record(s) recovered" in capsys.readouterr().out
    assert main(["store", "check", str(d), "--rebuild", "--repair"]) == 1
    assert "cannot be combined" in capsys.readouterr().err


def _downgrade_to_v1(d: Path) -> None:
    """Rewrite a store as icbtool format 1 wrote it: payloads without record nor trailer."""
    import json
    import struct

    from icbtool.store.record import payload_header

    con = sqlite3.connect(d / "icbstore.sqlite")
    for rid, rel in con.execute("SELECT id, payload FROM records").fetchall():
        p = d / "payloads" / rel
        data = p.read_bytes()
        h = payload_header(data)
        start, end = h["_body"]
        head = json.dumps({"buffers": h["buffers"]}).encode()
        v1 = b"ICBP" + struct.pack("<II", 1, len(head)) + head + data[start:end]
        p.write_bytes(v1)
        con.execute(
            "UPDATE records SET nbytes=?, checksum=? WHERE id=?",
            (len(v1), S.store._checksum(v1), rid),
        )
    con.execute("UPDATE meta SET value='1' WHERE key='format_version'")
    con.commit()
    con.close()


def test_format_1_store_is_read_and_migrated(tmp_path):
    from icbtool.store.record import payload_header

    d = tmp_path / "s"
    ids, before = _seven_records(d)
    _downgrade_to_v1(d)
    with S.open(d, S.StoreConfig(readonly=True)) as store:  # a reader reads it as it is
        assert same_buffers(store.get(ids[3]), make_record(make_cam([0.3 * 3, 0, 0]), seed=3))
        assert payload_header(store.info(ids[3]).payload.read_bytes())["version"] == 1
    with S.open(d) as store:  # a writer migrates it
        assert store.migrated_from == 1 and store.ids() == ids
        for rid in ids:
            info = store.info(rid)
            assert payload_header(info.payload.read_bytes())["version"] == 2
            k = info.meta.tags["k"]
            assert same_buffers(store.get(rid), make_record(make_cam([0.3 * k, 0, 0]), seed=k))
        assert store.check().ok and store.orphans_removed_on_open == 0
        assert sum(1 for _ in (d / "payloads").rglob("*.icbp")) == 7  # the v1 files are gone
    assert S.rebuild(d).recovered == ids  # and the index can now be rebuilt from them
    con = sqlite3.connect(d / "icbstore.sqlite")
    assert con.execute("SELECT value FROM meta WHERE key='format_version'").fetchone() == ("2",)
    con.close()


# ------------------------------------------------------------------------------ damaged records
def _damage_payload(p: Path, how: str) -> None:
    if how == "flip":
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x10
        p.write_bytes(bytes(data))
    elif how == "truncate":
        p.write_bytes(p.read_bytes()[:-7])
    else:
        p.unlink()


def test_evict_removes_damaged_records_first(tmp_path, capsys):
    from icbtool.cli import main

    d = tmp_path / "s"
    with S.open(d, S.StoreConfig(fsync=False)) as store:
        ids = [store.put(make_record(make_cam([float(i), 0, 0]), seed=i)) for i in range(6)]
        # the two newest (LRU would keep them longest) are damaged: one same-size bit flip,
        # one truncation
        _damage_payload(store.info(ids[4]).payload, "flip")
        _damage_payload(store.info(ids[5]).payload, "truncate")
        assert store.damaged_ids(deep=False) == {
            ids[5]: f"size {_size(store, ids[5])} != recorded {store.info(ids[5]).nbytes}"
        }
        assert set(store.damaged_ids()) == {ids[4], ids[5]}
        gone = store.evict(max_records=3, policy="lru", deep=True)
        assert gone == [ids[4], ids[5], ids[0]]  # damaged first, then the least recently used
        assert store.ids() == ids[1:4] and store.check().ok
    # automatic eviction (stat check) on put: the truncated record goes before any intact one
    cfg = S.StoreConfig(max_records=4, evict_to=1.0, fsync=False)
    with S.open(tmp_path / "a", cfg) as store:
        ids = [store.put(make_record(make_cam([float(i), 0, 0]), seed=i)) for i in range(4)]
        _damage_payload(store.info(ids[3]).payload, "missing")
        new = store.put(make_record(make_cam([9.0, 0, 0]), seed=9))
        assert store.ids() == [*ids[:3], new]
    # the CLI: damaged first even within capacity
    with S.open(tmp_path / "c", S.StoreConfig(fsync=False)) as store:
        ids = [store.put(make_record(make_cam([float(i), 0, 0]), seed=i)) for i in range(5)]
        _damage_payload(store.info(ids[1]).payload, "flip")
    assert main(["store", "evict", str(tmp_path / "c"), "--max-records", "3"]) == 0
    out = capsys.readouterr().out
    assert f"evicted 1 damaged record(s) first: [{ids[1]}]" in out
    assert "evicted 2 records: 5 -> 3 records" in out
    with S.open(tmp_path / "c") as store:
        assert store.ids() == [ids[2], ids[3], ids[4]]


def _size(store, rid):
    return store.info(rid).payload.stat().st_size


@pytest.mark.parametrize("how", ["flip", "truncate", "missing"])
def test_get_intact_and_replace_damaged(tmp_path, caplog, how):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        a, b = (store.put(make_record(make_cam([float(i), 0, 0]), seed=i)) for i in range(2))
        _damage_payload(store.info(a).payload, how)
        with caplog.at_level("WARNING", logger="icbtool.store.store"):
            assert store.get_intact(a) is None
        assert f"record {a}: payload file" in caplog.text and "treating it as a miss" in caplog.text
        assert same_buffers(store.get_intact(b), make_record(make_cam([1.0, 0, 0]), seed=1))
        # replacing an intact record never deletes it
        c = store.replace_damaged(b, make_record(make_cam([1.0, 0, 0]), seed=5))
        assert b in store and c in store
        new = store.replace_damaged(a, make_record(make_cam([0.0, 0, 0]), seed=7))
        assert a not in store and store.ids() == [b, c, new] and store.check().ok


def test_bake_rerenders_damaged_records(tmp_path):
    scene = _tiny_scene()
    cfg = B.BakeConfig(spp=2, gbuffer="trace", progress=False)
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as store:
        first = B.bake(scene, "tiny", store, cfg)
        assert len(first.rendered) == 3 and first.replaced == []
        keep = store.info(first.rendered[0]).payload.read_bytes()
        _damage_payload(store.info(first.rendered[1]).payload, "flip")
        _damage_payload(store.info(first.rendered[2]).payload, "missing")
        again = B.bake(scene, "tiny", store, cfg)
        assert again.skipped == [0] and again.replaced == first.rendered[1:]
        assert len(again.rendered) == 2 and not set(again.rendered) & set(first.rendered)
        assert store.ids() == [first.rendered[0], *again.rendered] and store.check().ok
        assert store.info(first.rendered[0]).payload.read_bytes() == keep  # intact: untouched
        assert [store.info(r).meta.tags["index"] for r in again.rendered] == [1, 2]
        assert B.bake(scene, "tiny", store, cfg).rendered == []


def _read_only_mount(d: Path, script: str) -> subprocess.CompletedProcess:
    """Run ``script`` (bash) where ``d`` is a read-only bind mount (a private mount namespace),
    as a user who may only read the store finds it; skipped where mounts are not allowed."""
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private mount namespace here (unshare -m: {probe.stderr.decode()!r})")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cmd = f"mount --bind {d} {d} && mount -o remount,bind,ro {d} && {script}"
    return subprocess.run(["unshare", "-m", "bash", "-c", cmd], capture_output=True, text=True,
                          env=env, timeout=300)  # fmt: skip


def test_a_store_the_user_may_only_read_is_readable(tmp_path):
    """A closed store (SQLite removed its -wal and -shm files) on a read-only file system: the
    reader, `store stats` and `store check` read it (they called it damaged: SQLite could not
    create the -shm file a WAL reader needs); a writer is refused with a clear error."""
    d = tmp_path / "s"
    ids, before = _seven_records(d)
    assert not Path(f"{d}/icbstore.sqlite-shm").exists()
    code = textwrap.dedent(f"""
        import icbtool.store as S
        with S.open({str(d)!r}, S.StoreConfig(readonly=True)) as s:
            assert s.ids() == {ids!r} and s.check().ok
            assert [s.info(i).hits for i in s.ids()] == {[before[i].hits for i in ids]!r}
            s.get({ids[3]})
        try:
            S.open({str(d)!r})
        except OSError as e:
            print("writer refused:", e)
        print("read ok")
    """)  # fmt: skip
    (tmp_path / "read.py").write_text(code)
    icbtool = f"{sys.executable} -m icbtool"
    r = _read_only_mount(d, f"{sys.executable} {tmp_path / 'read.py'} && "
                            f"{icbtool} store stats {d} && {icbtool} store check {d}")  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    assert "read ok" in r.stdout and "writer refused:" in r.stdout
    assert "records: 7" in r.stdout and "checked 7 records" in r.stdout and "OK" in r.stdout
