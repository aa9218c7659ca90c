"""icbtool.radiance: world-space irradiance models against known answers.

The scene is a procedural room (the inside of an axis-aligned box) ray-cast analytically from
cameras inside it, with a checker albedo (black squares included) and a GI that is exactly
``albedo * f(position, normal)`` for a smooth ``f`` we define. Tiny sizes, one thread.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import icbtool.store as S  # noqa: E402
from icbtool.camera import Camera  # noqa: E402
from icbtool.radiance import coverage as C  # noqa: E402
from icbtool.radiance import data as D  # noqa: E402
from icbtool.radiance.model import RadianceModel  # noqa: E402
from icbtool.radiance.training import (  # noqa: E402
    ProbeConfig,
    RadianceConfig,
    fit_probe_volume,
    probe_spec,
    train,
)

ROOM = np.array([4.0, 3.0, 5.0])  # the room is [0, 4] x [0, 3] x [0, 5]


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def smooth_irradiance(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """A smooth irradiance field (N, 3) of position and normal (not in any model's space)."""
    s = 0.5 + 0.25 * np.sin(1.1 * p[:, 0]) + 0.15 * np.cos(0.9 * p[:, 2]) + 0.1 * p[:, 1]
    d = 1.0 + 0.3 * n[:, 1] - 0.2 * n[:, 0]
    return (s * d)[:, None] * np.array([1.0, 0.8, 0.6])


def trilinear_l1_irradiance(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """An irradiance field in the L1 probe volume's space: coefficients affine (and x*z
    bilinear) in position, times the basis (1, nx, ny, nz)."""
    a = 0.6 + 0.05 * p[:, 0] + 0.03 * p[:, 1] + 0.02 * p[:, 2] + 0.01 * p[:, 0] * p[:, 2]
    b = 0.1 + 0.02 * p[:, 1]
    return (a + b * n[:, 1] - 0.05 * n[:, 2])[:, None] * np.array([1.0, 0.7, 0.4])


def room_view(cam: Camera, field, path: str, index: int) -> S.CRTBuffer:
    """Ray-cast the room from ``cam`` (inside it); GI = albedo * field(position, normal)."""
    o, d, dpd = cam.rays()
    with np.errstate(divide="ignore"):
        t_axes = np.where(d > 0, (ROOM - o) / d, np.where(d < 0, -o / d, np.inf))
    axis = np.argmin(t_axes, -1)
    t = np.take_along_axis(t_axes, axis[..., None], -1)[..., 0]
    pos = o + t[..., None] * d
    nrm = np.zeros_like(pos)
    np.put_along_axis(
        nrm, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], -1)), -1
    )
    cell = np.floor(2 * pos).astype(int).sum(-1) % 2
    albedo = np.where(cell[..., None] == 1, [0.8, 0.6, 0.4], [0.3, 0.5, 0.7])
    black = (np.floor(3 * pos[..., 1]).astype(int) % 5) == 0  # black stripes: albedo 0
    albedo = np.where(black[..., None], 0.0, albedo)
    h, w = pos.shape[:2]
    e = field(pos.reshape(-1, 3), nrm.reshape(-1, 3)).reshape(h, w, 3)
    f32 = np.float32
    return S.CRTBuffer(
        camera=cam,
        meta=S.RecordMeta("room", "room-hash", "light", spp=1, tags={"path": path, "index": index}),
        gi=(albedo * e).astype(f32),
        dl=np.zeros((h, w, 3), f32),
        albedo=albedo.astype(f32),
        normal_world=nrm.astype(f32),
        depth=(t * dpd)[..., None].astype(f32),
        position=pos.astype(f32),
        mask=np.ones((h, w, 1), f32),
    )


def room_cameras(n: int, seed: int, size: int) -> list[Camera]:
    r = np.random.default_rng(seed)
    cams = []
    for k in range(n):
        eye = r.uniform([1.0, 1.0, 1.0], ROOM - 1.0)
        yaw = 2 * np.pi * (k / n) + r.uniform(-0.3, 0.3)
        target = eye + [np.cos(yaw), r.uniform(-0.4, 0.4), np.sin(yaw)]
        cams.append(Camera.look_at(eye, target, fov_y_deg=75.0, height=size, width=size))
    return cams


def make_store(root, field, n_train=12, n_test=4, size=24, extra=None):
    st = S.open(root, S.StoreConfig(fsync=False))
    for i, cam in enumerate(room_cameras(n_train, 0, size)):
        st.put(room_view(cam, field, "train", i))
    for i, cam in enumerate(room_cameras(n_test, 1, size)):
        st.put(room_view(cam, field, "test", i))
    for rec in extra or []:
        st.put(rec)
    return st


def tiny_grid(**kw) -> RadianceConfig:
    base = dict(
        levels=4, features=2, log2_table=10, base_resolution=2, max_resolution=16, hidden=16,
        iterations=300, batch_size=2048, lr=2e-2, eval_every=300, checkpoint_every=300,
    )  # fmt: skip
    return RadianceConfig(**{**base, **kw})


# ------------------------------------------------------------------------------ basics
def test_import_radiance_does_not_import_torch():
    code = "import sys, icbtool, icbtool.radiance as r; r.__dir__(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_demodulate_divides_by_the_albedo_and_weights_dark_texels_down():
    gi = np.array([[0.2, 0.1, 0.0], [0.05, 0.0, 0.3]], np.float32)
    alb = np.array([[0.5, 0.25, 0.0], [0.025, 0.0, 1.0]], np.float32)
    e, w = D.demodulate(gi, alb, 0.05)
    np.testing.assert_allclose(e, [[0.4, 0.4, 0.0], [1.0, 0.0, 0.3]], rtol=1e-6)
    np.testing.assert_allclose(w, [[1.0, 1.0, 0.0], [0.5, 0.0, 1.0]], rtol=1e-6)
    assert np.isfinite(e).all()


def test_grid_layout_dense_then_hashed_and_lookup_weights():
    from icbtool.radiance.models import corner_lookup, corner_lookup_np, level_layout

    lay = level_layout(np.array([2.0, 1.0, 1.0]), [2, 4, 64], log2_table=8)
    np.testing.assert_array_equal(lay.cells, [[2, 1, 1], [4, 2, 2], [64, 32, 32]])
    assert list(lay.hashed) == [False, False, True]
    np.testing.assert_array_equal(lay.sizes, [3 * 2 * 2, 5 * 3 * 3, 256])
    x = np.random.default_rng(0).random((50, 3)).astype(np.float32)
    t = [torch.tensor(a) for a in (lay.cells.astype(np.float32), lay.strides, lay.sizes)]
    idx, w = corner_lookup(
        torch.from_numpy(x), *t, torch.tensor(lay.offsets), torch.tensor(
            np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], np.int64))
    )  # fmt: skip
    np.testing.assert_allclose(w.sum(-1).numpy(), 1.0, atol=1e-6)
    assert (idx[:, 0] < lay.offsets[1]).all() and (idx[:, 2] >= lay.offsets[2]).all()
    assert (idx[:, 2] < lay.total).all()
    # the dense level's interpolation reproduces a linear function of the vertex coordinates
    i_np, w_np = corner_lookup_np(x, lay.cells[1])
    np.testing.assert_array_equal(i_np + lay.offsets[1], idx[:, 1].numpy())
    np.testing.assert_allclose(w_np, w[:, 1].numpy(), atol=1e-6)
    vx = np.arange(lay.sizes[1]) % 5  # vertex x index (x fastest)
    np.testing.assert_allclose((vx[i_np] * w_np).sum(1), x[:, 0] * 4, atol=1e-5)


def test_coverage_distances_are_known_fractions_of_the_diagonal():
    train = np.stack([np.linspace(0, 10, 101), np.zeros(101), np.zeros(101)], 1)
    q = np.array([[5.0, 3.0, 0.0], [0.0, 0.0, 4.0], [10.0, 0.0, 0.0]])
    d = C.coverage_distances(train, q, diagonal=20.0)
    np.testing.assert_allclose(d, [0.15, 0.2, 0.0], atol=1e-12)
    cov = C.TrainCoverage(train, 20.0)
    assert C.view_coverage(cov, q) == pytest.approx(0.15)


# ------------------------------------------------------------------------------ known answers
def test_probe_volume_is_exact_on_a_field_in_its_space(tmp_path):
    """Trilinear coefficient fields x the L1 basis are reproduced exactly on held-out views."""
    st = make_store(tmp_path / "s", trilinear_l1_irradiance)
    cfg = ProbeConfig(resolution=5, sh_order=1, normal_offset=0.0, smoothness=1e-3,
                      cg_rtol=1e-12, cg_maxiter=20_000)  # fmt: skip
    r = train(st, cfg, tmp_path / "run", progress=False)
    model = RadianceModel.load(r.run_dir)
    worst = 0.0
    for rid in D.records_of_path(st, "test"):
        rec = st.get(rid)
        pred = model.generate(rec)
        worst = max(worst, float(np.abs(pred - rec.gi).max()))
    assert worst < 2e-5, worst  # float32 evaluation of an exact least-squares fit
    assert r.last("test")["ssim"] > 0.9999
    cfg_json = json.loads((r.run_dir / "config.json").read_text())
    assert cfg_json["kind"] == "probes" and cfg_json["probe_config"]["resolution"] == 5


def test_probe_fit_is_least_squares_on_data_outside_its_space(tmp_path):
    """Off its space the fit is the weighted least-squares optimum: any nudge of the coefficients
    raises the objective (the normal equations hold)."""
    st = make_store(tmp_path / "s", smooth_irradiance, n_train=6, n_test=1, size=16)
    samples = D.pixels_from_records(st, D.records_of_path(st, "train"))
    cfg = ProbeConfig(resolution=4, sh_order=1, smoothness=1e-2, normal_offset=0.0)
    spec = probe_spec(D.Bounds.of_points(samples.position), cfg)
    coef = fit_probe_volume(samples, spec, cfg.albedo_floor, cfg.smoothness, 1e-12, 20_000)
    from icbtool.radiance.models import ProbeVolume

    e, w = samples.targets(cfg.albedo_floor)
    from icbtool.radiance.training import _second_differences

    dd = _second_differences(spec.probes)

    def objective(c: np.ndarray) -> float:
        with torch.no_grad():
            pred = (
                ProbeVolume(spec, c)(
                    torch.from_numpy(samples.position), torch.from_numpy(samples.normal)
                )
                .double()
                .numpy()
            )
        data = float(((pred - e) ** 2 * w).sum(0).dot(1 / w.sum(0)))
        smooth = sum(float(((dd @ c[:, k, ch].astype(np.float64)) ** 2).sum())
                     for k in range(c.shape[1]) for ch in range(3))  # fmt: skip
        return data + cfg.smoothness * smooth / spec.count

    base = objective(coef)
    r = np.random.default_rng(3)
    for _ in range(3):
        nudge = coef + 1e-2 * r.standard_normal(coef.shape).astype(np.float32)
        assert objective(nudge) > base


def test_grid_model_reproduces_a_smooth_field_on_held_out_views(tmp_path):
    """Tolerance: mean relative GI error below 6 % on the test views' lit pixels, SSIM > 0.97."""
    st = make_store(tmp_path / "s", smooth_irradiance)
    r = train(st, tiny_grid(), tmp_path / "run", progress=False)
    model = RadianceModel.load(r.run_dir)
    errs = []
    for rid in D.records_of_path(st, "test"):
        rec = st.get(rid)
        pred = model.generate(rec)
        lit = rec.albedo > 0.05
        errs.append(np.abs(pred - rec.gi)[lit] / rec.gi[lit])
    rel = float(np.mean(np.concatenate(errs)))
    assert rel < 0.06, rel
    assert r.last("test")["ssim"] > 0.97
    # a constant field cannot do that: the test has teeth
    const = float(np.mean(np.concatenate([st.get(i).gi[st.get(i).albedo > 0.05] /
                                          st.get(i).albedo[st.get(i).albedo > 0.05]
                                          for i in D.records_of_path(st, "train")])))  # fmt: skip
    errs_c = []
    for rid in D.records_of_path(st, "test"):
        rec = st.get(rid)
        lit = rec.albedo > 0.05
        errs_c.append(np.abs(const * rec.albedo - rec.gi)[lit] / rec.gi[lit])
    assert float(np.mean(np.concatenate(errs_c))) > 3 * rel


# ------------------------------------------------------------------------------ inference, ONNX
@pytest.mark.parametrize("kind", ["grid", "probes"])
def test_onnx_equals_torch(tmp_path, kind):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    st = make_store(tmp_path / "s", smooth_irradiance, n_train=4, n_test=1, size=16)
    cfg = tiny_grid(iterations=20) if kind == "grid" else ProbeConfig(resolution=6, sh_order=2)
    r = train(st, cfg, tmp_path / "run", progress=False)
    model = RadianceModel.load(r.run_dir)
    path = model.export_onnx(tmp_path / "m.onnx")
    sidecar = json.loads((tmp_path / "m.onnx.json").read_text())
    assert sidecar["kind"] == kind and sidecar["parameter_bytes"] == model.nbytes
    rec = st.get(D.records_of_path(st, "test")[0])
    g = np.random.default_rng(5)
    b = model.module.spec.bounds
    # surface points, points off the grid (clamped), and a batch size other than the export's
    pos = np.concatenate(
        [rec.position.reshape(-1, 3), g.uniform(np.array(b.lo) - 1, np.array(b.hi) + 1, (77, 3))]
    ).astype(np.float32)
    nrm = g.standard_normal(pos.shape).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (got,) = sess.run(None, {"position": pos, "normal": nrm})
    want = model.irradiance(pos, nrm)
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= 1e-5 * max(1.0, float(np.abs(want).max()))


def test_generate_any_size_background_zero_and_bad_buffers(tmp_path):
    st = make_store(tmp_path / "s", smooth_irradiance, n_train=4, n_test=1, size=16)
    model = RadianceModel.load(train(st, ProbeConfig(resolution=4), tmp_path / "r",
                                     progress=False).run_dir)  # fmt: skip
    rec = st.get(D.records_of_path(st, "test")[0])
    maps = {n: getattr(rec, n)[:13, :7] for n in ("albedo", "normal_world", "position", "mask")}
    maps["mask"] = maps["mask"].copy()
    maps["mask"][0, 0] = 0.0
    maps["position"] = maps["position"].copy()
    maps["position"][0, 0] = np.nan  # background: not read
    gi = model.generate(maps)
    assert gi.shape == (13, 7, 3) and gi.dtype == np.float32
    assert (gi[0, 0] == 0).all() and np.isfinite(gi).all()
    maps["position"][2, 3] = np.nan  # a surface pixel: refused, naming the map and the pixel
    with pytest.raises(ValueError, match=r"position holds NaN.*row 2, column 3"):
        model.generate(maps)
    with pytest.raises(ValueError, match="lacks the 'normal_world' map"):
        model.generate({"albedo": maps["albedo"], "position": maps["position"]})
    with pytest.raises(ValueError, match=r"normal must be \(N, 3\)"):
        model.irradiance(np.zeros((4, 3)), np.zeros((4, 2)))
    with pytest.raises(FileNotFoundError, match="no world-space radiance model"):
        RadianceModel.load(tmp_path / "nothing")


# ------------------------------------------------------------------------------ runs
def test_resume_continues_exactly(tmp_path):
    st = make_store(tmp_path / "s", smooth_irradiance, n_train=4, n_test=1, size=16)
    cfg = tiny_grid(iterations=40, eval_every=10, checkpoint_every=10)
    full = train(st, cfg, tmp_path / "full", progress=False)
    part = train(st, tiny_grid(iterations=20, eval_every=10, checkpoint_every=10),
                 tmp_path / "part", progress=False)  # fmt: skip
    assert part.steps == 20
    with pytest.raises(ValueError, match="already holds a run"):
        train(st, cfg, tmp_path / "part", progress=False)
    with pytest.raises(ValueError, match="config differs"):
        train(st, tiny_grid(iterations=40, lr=1e-3), tmp_path / "part", resume=True,
              progress=False)  # fmt: skip
    # a run planned for 40 iterations stopped after 20 (as a kill would), then resumed
    plan = tiny_grid(iterations=40, eval_every=10, checkpoint_every=10)
    a = train(st, plan, tmp_path / "a", progress=False, stop_at=20)
    assert a.steps == 20
    b = train(st, plan, tmp_path / "a", resume=True, progress=False)
    assert b.steps == 40
    wa = torch.load(tmp_path / "a" / "radiance.pt", weights_only=False)["state"]
    wf = torch.load(tmp_path / "full" / "radiance.pt", weights_only=False)["state"]
    for k in wf:
        assert torch.equal(wa[k], wf[k]), k
    its = [row["iteration"] for row in b.evals]
    assert its == [10, 20, 30, 40]  # no step lost or repeated
    secs = [row["seconds"] for row in b.evals]
    assert secs == sorted(secs)  # the clock goes on across the resume
    assert [row["ssim"] for row in b.evals] == [row["ssim"] for row in full.evals]
    csv_rows = (tmp_path / "a" / "evals.csv").read_text().splitlines()
    assert csv_rows[0] == "iteration,path,views,ssim,mse,seconds" and len(csv_rows) == 5


# ------------------------------------------------------------------------------ bad input
def test_nan_positions_and_empty_data_are_refused(tmp_path):
    bad = room_view(room_cameras(1, 9, 16)[0], smooth_irradiance, "train", 99)
    bad.position[4, 5, 1] = np.nan
    st = make_store(tmp_path / "s", smooth_irradiance, n_train=2, n_test=1, size=16, extra=[bad])
    with pytest.raises(ValueError, match=r"store record \d+\.position holds NaN"):
        train(st, ProbeConfig(resolution=4), tmp_path / "r", progress=False)
    empty = S.open(tmp_path / "empty", S.StoreConfig(fsync=False))
    with pytest.raises(ValueError, match="no records on the train path 'train'"):
        train(empty, tiny_grid(), tmp_path / "r2", progress=False)
    st2 = make_store(tmp_path / "s2", smooth_irradiance, n_train=2, n_test=1, size=16)
    with pytest.raises(ValueError, match="no records on the evaluation path 'walk'"):
        train(st2, tiny_grid(eval_paths=("walk",)), tmp_path / "r3", progress=False)
    with pytest.raises(ValueError, match="no records"):
        D.pixels_from_records(st2, [])


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(levels=0), "levels must be an integer >= 1"),
        (dict(max_resolution=4, base_resolution=8), "max_resolution"),
        (dict(lr=0.0), "lr must be a finite number > 0"),
        (dict(albedo_floor=float("nan")), "albedo_floor"),
        (dict(eval_paths=("test", "test")), "eval_paths must be distinct"),
        (dict(loss="l3"), "loss must be 'l2' or 'l1'"),
        (dict(sh_order=3), "sh_order must be 0, 1 or 2"),
        (dict(log2_table=30), "log2_table must be <= 24"),
    ],
)
def test_radiance_config_validation(kw, msg):
    with pytest.raises(ValueError, match=msg):
        RadianceConfig(**kw)


def test_configs_round_trip_and_reject_unknown_keys():
    c = RadianceConfig(eval_paths=("test", "walk"), betas=(0.8, 0.9))
    assert RadianceConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    p = ProbeConfig(resolution=7)
    assert ProbeConfig.from_dict(p.to_dict()) == p
    with pytest.raises(ValueError, match="unknown keys"):
        ProbeConfig.from_dict({**p.to_dict(), "probes": 3})
    with pytest.raises(ValueError, match="resolution must be an integer >= 2"):
        ProbeConfig(resolution=1)


# ------------------------------------------------------------------------------ the loop
def test_generator_source_serves_world_space_gi(tmp_path):
    from types import SimpleNamespace

    from icbtool.system import GeneratorSource, GIRequest

    st = make_store(tmp_path / "s", smooth_irradiance, n_train=4, n_test=1, size=16)
    run = train(st, ProbeConfig(resolution=4), tmp_path / "r", progress=False).run_dir
    from icbtool.pipeline import load_client_model

    model = load_client_model(run)
    assert isinstance(model, RadianceModel)
    rec = st.get(D.records_of_path(st, "test")[0])
    wrt = SimpleNamespace(
        camera=rec.camera, albedo=rec.albedo[:15, :9], normal_world=rec.normal_world[:15, :9],
        position=rec.position[:15, :9], mask=rec.mask[:15, :9], depth=rec.depth[:15, :9],
    )  # fmt: skip
    src = GeneratorSource(model)
    reply = src.request(GIRequest(rec.camera, np.zeros(3), np.zeros(3), 0.0, seq=3), wrt)
    assert reply.reference.gi.shape == (15, 9, 3)  # no padding to 32: any size
    np.testing.assert_array_equal(reply.reference.gi, model.generate(wrt))
    assert src.generated == 1


# ------------------------------------------------------------------------------ command line
def test_cli_world_probes_fit_generate_and_export(tmp_path, capsys):
    """``icbtool world probes`` fits the exact field (known answer as above) and prints the
    evaluation with its view count; ``icbtool export`` takes the run like a GAN run."""
    from icbtool.cli import main
    from icbtool.pipeline import load_client_model

    st = make_store(tmp_path / "s", trilinear_l1_irradiance)
    test_recs = [st.get(i) for i in D.records_of_path(st, "test")]
    st.close()
    run = tmp_path / "probes"
    argv = ["world", "probes", "--store", str(tmp_path / "s"), "--out", str(run),
            "--resolution", "5", "--sh-order", "1", "--normal-offset", "0", "--cg-rtol", "1e-12",
            "--cg-maxiter", "20000", "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert re.search(r"test SSIM (0\.999\d|1\.0000) MSE \S+ \(4 views\)", out), out
    model = load_client_model(run)
    assert max(float(np.abs(model.generate(r) - r.gi).max()) for r in test_recs) < 2e-5
    assert main(["export", str(run), "--onnx", str(tmp_path / "p.onnx")]) == 0
    assert (tmp_path / "p.onnx").stat().st_size > 0
    assert json.loads((tmp_path / "p.onnx.json").read_text())["inputs"].startswith("position")


def test_cli_world_grid_resumes_and_rejects_a_bad_setting(tmp_path, capsys):
    from icbtool.cli import main

    make_store(tmp_path / "s", smooth_irradiance, n_train=4, n_test=1, size=16).close()
    run = str(tmp_path / "grid")
    base = ["world", "grid", "--store", str(tmp_path / "s"), "--out", run, "--levels", "4",
            "--log2-table", "10", "--base-resolution", "2", "--max-resolution", "16",
            "--hidden", "16", "--batch-size", "512", "--eval-every", "10",
            "--checkpoint-every", "10", "--no-progress"]  # fmt: skip
    assert main([*base, "--iterations", "10"]) == 0
    assert "(10 steps)" in capsys.readouterr().out
    assert main([*base, "--iterations", "20", "--resume"]) == 0
    assert "(20 steps)" in capsys.readouterr().out
    assert main([*base, "--lr", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--lr" in err and err.count("\n") == 1, err
