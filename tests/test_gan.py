"""icbtool.gan: known-answer tests of the losses, the U-Net, the HDR transform, data, training
(overfit, exact resume, divergence guard), inference and ONNX export. Tiny sizes, one thread."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import icbtool.store as S  # noqa: E402
from icbtool.camera import Camera  # noqa: E402
from icbtool.gan import data as D  # noqa: E402
from icbtool.gan import losses as L  # noqa: E402
from icbtool.gan import models as M  # noqa: E402
from icbtool.gan import training as T  # noqa: E402
from icbtool.gan.generate import Generator  # noqa: E402
from icbtool.gan.hdr import HDRTransform  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def make_record(i: int, size: int = 32, path: str = "train", nan: bool = False) -> S.CRTBuffer:
    """A smooth synthetic CRT-buffer whose GI is a simple function of its inputs."""
    r = np.random.default_rng(i)
    h = w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / size
    ph = r.uniform(0, 2 * np.pi)
    albedo = np.stack(
        [0.5 + 0.4 * np.sin(6 * xx + ph), 0.5 + 0.4 * np.cos(5 * yy), 0.6 + 0 * xx], 2
    )
    dl = np.stack([2.0 * (xx > 0.5), 1.5 * (yy > 0.4), 0.5 + xx], 2).astype(np.float32)
    nw = np.stack([np.sin(3 * xx), np.cos(3 * xx), 0 * xx], 2)
    nv = np.stack([0 * xx, np.sin(2 * yy), np.cos(2 * yy)], 2)
    depth = (1.0 + yy + 0.2 * i)[..., None]
    pos = np.stack([xx, yy, 0 * xx + i], 2)
    gi = 0.3 * albedo * (0.5 + dl.mean(2, keepdims=True)) * (0.6 + 0.4 * nw[..., 1:2])
    if nan:
        dl[3, 4, 1] = np.nan
    m = np.eye(4)
    m[:3, 3] = [i, 0.0, 0.0]
    return S.CRTBuffer(
        camera=Camera.from_fov(60.0, h, w, m),
        meta=S.RecordMeta("synthetic", "sh", "lh", spp=4, tags={"path": path, "index": i}),
        gi=gi.astype(np.float32),
        dl=dl,
        albedo=albedo.astype(np.float32),
        normal_world=nw.astype(np.float32),
        normal_view=nv.astype(np.float32),
        depth=depth.astype(np.float32),
        position=pos.astype(np.float32),
        mask=np.ones((h, w, 1), np.float32),
    )


@pytest.fixture
def store(tmp_path):
    with S.open(tmp_path / "store", S.StoreConfig(fsync=False)) as st:
        for i in range(3):
            st.put(make_record(i, path="train"))
        for i in range(3, 5):
            st.put(make_record(i, path="test"))
        yield st


def tiny(**kw) -> T.TrainConfig:
    base = dict(crop=32, base=4, batch_size=2, iterations=4, eval_every=2, checkpoint_every=2)
    base["weight_perceptual"] = 0.0  # no VGG here (its own test checks the warning)
    return T.TrainConfig.preset("paper-cpu", **{**base, **kw})


def assert_cut_at_2_resumes_to(store, cfg, full, cut) -> None:
    """Training ``cfg`` stopped after 2 iterations in ``cut`` and resumed there ends with the
    generator weights of the uninterrupted run in ``full``, bit for bit."""
    T.train(store, T.TrainConfig.from_dict({**cfg.to_dict(), "iterations": 2}), cut,
            progress=False)  # fmt: skip
    T.train(store, cfg, cut, resume=True, progress=False)
    a = torch.load(full / "generator.pt", weights_only=False)["generator"]
    b = torch.load(cut / "generator.pt", weights_only=False)["generator"]
    assert all(torch.equal(v, b[k]) for k, v in a.items())


# ------------------------------------------------------------------------------ lazy import
def test_import_icbtool_and_gan_does_not_import_torch():
    code = "import sys, icbtool, icbtool.gan; icbtool.gan.__dir__(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------------------------ losses
class LinearCritic(torch.nn.Module):
    """D(c, x) = sum(w * x) + sum(c): gradient w.r.t. x is w everywhere."""

    def __init__(self, w):
        super().__init__()
        self.w = torch.nn.Parameter(w)

    def forward(self, cond, x):
        return ((self.w * x).sum((1, 2, 3)) + cond.sum((1, 2, 3))).reshape(-1, 1, 1, 1)


def test_gradient_penalty_of_a_linear_critic_is_analytic():
    w = torch.full((3, 2, 2), 0.5)  # ||w|| = sqrt(12 * 0.25) = sqrt(3)
    critic = LinearCritic(w)
    real, fake = torch.rand(5, 3, 2, 2), torch.rand(5, 3, 2, 2)
    cond = torch.rand(5, 1, 2, 2)
    gp = L.gradient_penalty(critic, cond, real, fake, lambda_gp=10.0, k=1.0)
    assert gp.item() == pytest.approx(10.0 * (math.sqrt(3) - 1) ** 2, rel=1e-5)  # 5.3590
    gp2 = L.gradient_penalty(critic, cond, real, fake, lambda_gp=2.0, k=3.0)
    assert gp2.item() == pytest.approx(2.0 * (math.sqrt(3) - 3) ** 2, rel=1e-5)
    gp.backward()  # differentiable w.r.t. the critic: d/dw = 2 lambda (|w| - k) w / |w|
    expect = 2 * 10.0 * (math.sqrt(3) - 1) * 0.5 / math.sqrt(3)
    assert torch.allclose(critic.w.grad, torch.full((3, 2, 2), expect), rtol=1e-5)


def test_l1_is_the_mean_absolute_difference():
    a = torch.tensor([[[[0.0, 1.0], [2.0, -1.0]]]])
    b = torch.tensor([[[[1.0, 1.0], [0.0, 1.0]]]])
    assert L.l1_loss(a, b).item() == pytest.approx((1 + 0 + 2 + 2) / 4)


def test_perceptual_distance_is_normalised_by_chw():
    conv = torch.nn.Conv2d(3, 2, 1, bias=False)
    with torch.no_grad():
        conv.weight[:] = torch.tensor([[1.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]).reshape(2, 3, 1, 1)
    net = torch.nn.Sequential(conv, torch.nn.ReLU())
    loss = L.PerceptualLoss(net, layers=(1,), imagenet_input=False)
    pred, target = torch.zeros(2, 3, 2, 3), torch.ones(2, 3, 2, 3)
    # activations of ones: channel 0 relu(3) = 3, channel 1 relu(-1) = 0; of zeros: 0.
    # per sample: (9 * 6 + 0) / (C H W = 2 * 2 * 3) = 4.5; the batch mean is 4.5 too.
    assert loss(pred, target).item() == pytest.approx(4.5)
    # two layers (conv output, then ReLU) add: conv layer gives (9 * 6 + 1 * 6) / 12 = 5
    both = L.PerceptualLoss(net, layers=(0, 1), imagenet_input=False)
    assert both(pred, target).item() == pytest.approx(9.5)


def test_vgg19_features_have_torchvision_keys_and_load(tmp_path):
    net = L.VGG19Features()
    keys = [k for k in net.state_dict() if k.endswith(".weight")]
    assert len(keys) == 16 and keys[0] == "0.weight" and keys[-1] == "34.weight"
    assert isinstance(net[L.VGG19_RELU_X_1[-1]], torch.nn.ReLU)
    sd = {f"features.{k}": v for k, v in net.state_dict().items()}
    sd["classifier.0.weight"] = torch.zeros(2, 2)
    torch.save(sd, tmp_path / "vgg19.pth")
    loaded = L.load_vgg19_features(tmp_path / "vgg19.pth")
    assert torch.equal(loaded[34].weight, net[34].weight)
    del sd["features.10.weight"]
    torch.save(sd, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="features.10.weight"):
        L.load_vgg19_features(tmp_path / "bad.pth")


def test_a_vgg19_weights_file_turns_the_perceptual_loss_on_in_training(store, tmp_path):
    """The paper preset's path: a VGG19 state-dict file (untrained weights here; the ImageNet file
    cannot be fetched) builds the perceptual loss, which is 0 for equal images and > 0 otherwise,
    and a training run uses it. (Building it from the loaded VGG19Features once failed: slicing
    the Sequential subclass called its constructor with arguments; found on a GPU run.)"""
    torch.manual_seed(0)
    sd = {f"features.{k}": v for k, v in L.VGG19Features().state_dict().items()}
    torch.save(sd, tmp_path / "vgg19.pth")
    loss, status = L.build_perceptual(tmp_path / "vgg19.pth")
    assert status == f"on: {tmp_path / 'vgg19.pth'}" and len(loss.features) == 30
    x = torch.rand(1, 3, 32, 32) * 2 - 1
    assert loss(x, x).item() == 0.0 and loss(x, -x).item() > 0.0
    cfg = tiny(iterations=1, weight_perceptual=1.0, vgg19_weights=str(tmp_path / "vgg19.pth"))
    T.train(store, cfg, tmp_path / "run", progress=False)
    import json

    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["perceptual"] == f"on: {tmp_path / 'vgg19.pth'}"


def test_missing_vgg_file_warns_once_and_is_recorded(store, tmp_path):
    with pytest.warns(UserWarning, match=r"perceptual loss L_p is OFF.*TrainConfig.vgg19_weights"):
        loss, status = L.build_perceptual(tmp_path / "nope.pth")
    assert loss is None and status.startswith("off:")
    cfg = tiny(iterations=1, weight_perceptual=1.0, vgg19_weights=str(tmp_path / "missing.pth"))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        T.train(store, cfg, tmp_path / "run", progress=False)
    texts = [str(w.message) for w in rec if "perceptual loss L_p is OFF" in str(w.message)]
    assert len(texts) == 1 and "missing.pth" in texts[0]
    import json

    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["perceptual"].startswith("off:") and "missing.pth" in saved["perceptual"]


# ------------------------------------------------------------------------------ models, HDR
def test_unet_has_5_down_5_up_and_keeps_size():
    g = M.UNetGenerator(M.GeneratorConfig(in_channels=7, base=4, norm="instance"))
    assert len(g.down) == 5 and len(g.up) == 5
    for layer in g.down:
        assert isinstance(layer[0], torch.nn.Conv2d) and layer[0].stride == (2, 2)
        assert isinstance(layer[-1], torch.nn.LeakyReLU)
    for layer in g.up[:-1]:
        assert isinstance(layer[0], torch.nn.ConvTranspose2d) and isinstance(
            layer[-1], torch.nn.ReLU
        )
    assert isinstance(g.up[-1][-1], torch.nn.Tanh)
    y = g(torch.randn(2, 7, 64, 96))
    assert y.shape == (2, 3, 64, 96) and y.abs().max() <= 1
    d = M.PatchDiscriminator(M.DiscriminatorConfig(in_channels=7, base=4))
    assert sum(isinstance(m, torch.nn.Conv2d) for m in d.modules()) == 4
    assert d(torch.randn(2, 7, 64, 64), torch.randn(2, 3, 64, 64)).shape == (2, 1, 14, 14)
    with pytest.raises(ValueError, match="batch norm"):
        M.DiscriminatorConfig(in_channels=7, norm="batch")


def test_hdr_transform_round_trips_numpy_and_torch():
    h = HDRTransform(scale=0.25, max_value=64.0)
    x = np.concatenate([[0.0, 64.0], np.geomspace(1e-4, 64.0, 200)]).astype(np.float32)
    y = h.encode(x)
    assert y[0] == -1.0 and y[1] == pytest.approx(1.0) and np.all(np.diff(y[2:]) > 0)
    assert np.allclose(h.decode(y), x, rtol=2e-5, atol=1e-6)
    yt = h.encode(torch.from_numpy(x))
    assert torch.allclose(yt, torch.from_numpy(y), atol=1e-6)
    assert torch.allclose(h.decode(yt), torch.from_numpy(x), rtol=2e-5, atol=1e-6)
    # log1p(1 / 0.25) / log1p(256) maps radiance 1 to 2 * 0.28990 - 1
    assert h.encode(np.float32(1.0)) == pytest.approx(2 * math.log(5) / math.log(257) - 1, 1e-6)
    with pytest.raises(ValueError, match="scale"):
        HDRTransform(scale=0.0)


# ------------------------------------------------------------------------------ data
def test_dataset_configuration_picks_exactly_the_named_channels(store):
    enc = D.InputEncoding(D.resolve_inputs("E"), HDRTransform())
    data = D.PairData(S.Dataset(store, split="train", inputs="E"), enc)
    assert data.channels == [f"{n}.{c}" for n in ("albedo", "dl", "normal_view") for c in "rgb"]
    assert data.x.shape == (3, 9, 32, 32)
    rec = store.get(data.record_ids[0])
    assert np.array_equal(data.x[0, 0:3], (2 * rec.albedo - 1).transpose(2, 0, 1))
    assert np.allclose(data.x[0, 3:6], HDRTransform().encode(rec.dl).transpose(2, 0, 1))
    assert np.array_equal(data.x[0, 6:9], rec.normal_view.transpose(2, 0, 1))  # not the world one
    enc_i = D.InputEncoding.fit(D.resolve_inputs("I"), HDRTransform(), list(S.Dataset(store)))
    assert enc_i.inputs == ("albedo", "dl", "normal_world", "depth")
    assert enc_i.depth_max == pytest.approx(1.0 + 31 / 32 + 0.4)  # record 2, last row
    assert D.resolve_inputs("albedo, depth") == ("albedo", "depth")
    with pytest.raises(ValueError, match="target"):
        D.resolve_inputs(("albedo", "gi"))


def test_paired_augmentation_applies_one_crop_and_flip_to_both(store):
    enc = D.InputEncoding(D.resolve_inputs("E"), HDRTransform())
    data = D.PairData(S.Dataset(store, split="train", inputs="E"), enc)
    # a target equal to the first 3 input channels shows whether both got the same crop/flip
    data.y = data.x[:, :3].copy()
    data.x[:, 6] = 0.5  # normal_view.x: a flip makes it -0.5
    s1 = D.BatchSampler(data, 16, 16, True, seed=5)
    x, y = s1.next()
    assert x.shape == (16, 9, 16, 16) and np.array_equal(x[:, :3], y)
    state = s1.state_dict()
    x2, _ = s1.next()
    s2 = D.BatchSampler(data, 16, 16, True, seed=99)
    s2.load_state_dict(state)
    assert np.array_equal(s2.next()[0], x2)
    signs = x[:, 6].reshape(16, -1)
    assert np.all(np.abs(signs) == 0.5) and np.all(signs == signs[:, :1])  # one flip per sample
    assert set(signs[:, 0]) == {-0.5, 0.5}  # both drawn (seeded)
    with pytest.raises(ValueError, match="larger than"):
        D.BatchSampler(data, 2, 64, True, 0)


# ------------------------------------------------------------------------------ training
def test_tiny_generator_overfits_one_pair(tmp_path):
    with S.open(tmp_path / "one", S.StoreConfig(fsync=False)) as st:
        st.put(make_record(0, size=64, path="only"))
        cfg = T.TrainConfig(
            inputs="I", crop=64, base=8, batch_size=1, iterations=300, lr=2e-3, flip=False,
            norm="batch", weight_adv=0.0, weight_perceptual=0.0, train_path="only",
            test_path="only", eval_every=300, checkpoint_every=300,
        )  # fmt: skip
        res = T.train(st, cfg, tmp_path / "run", progress=False)
    assert res.step == 300 and res.evals[-1]["ssim"] > 0.95, res.evals
    gen = Generator.load(tmp_path / "run")
    rec = make_record(0, size=64)
    gi = gen.generate(rec)
    assert gi.shape == (64, 64, 3) and gi.dtype == np.float32
    from icbtool.metrics import ssim

    assert ssim(gi, rec.gi) == pytest.approx(res.evals[-1]["ssim"], abs=1e-6)


def test_resume_equals_uninterrupted_bitwise(store, tmp_path):
    cfg = tiny(iterations=6, n_critic=2, eval_every=3, checkpoint_every=3)
    T.train(store, cfg, tmp_path / "full", progress=False)
    T.train(store, T.TrainConfig.from_dict({**cfg.to_dict(), "iterations": 3}), tmp_path / "cut",
            progress=False)  # fmt: skip
    res = T.train(store, cfg, tmp_path / "cut", resume=True, progress=False)
    assert res.step == 6 and [e["iteration"] for e in res.evals] == [3, 6]
    a = torch.load(tmp_path / "full" / "checkpoints" / "last.pt", weights_only=False)
    b = torch.load(tmp_path / "cut" / "checkpoints" / "last.pt", weights_only=False)
    for part in ("generator", "critic"):
        for k, v in a[part].items():
            assert torch.equal(v, b[part][k]), (part, k)
    assert a["evals"][-1]["ssim"] == b["evals"][-1]["ssim"]
    with pytest.raises(ValueError, match="already holds a run"):
        T.train(store, cfg, tmp_path / "full", progress=False)
    with pytest.raises(ValueError, match="config differs"):
        T.train(store, tiny(iterations=6, lr=1e-3), tmp_path / "full", resume=True, progress=False)
    assert (tmp_path / "full" / "evals.csv").read_text().count("\n") == 3
    assert (tmp_path / "full" / "samples" / "iter_000006.png").is_file()
    if importlib.util.find_spec("tensorboard") is not None:
        assert any((tmp_path / "full" / "tb").glob("events.out.tfevents.*"))


def test_on_step_sees_every_iteration_with_its_losses(store, tmp_path):
    seen = []
    res = T.train(store, tiny(iterations=4), tmp_path / "run", progress=False,
                  on_step=lambda step, losses: seen.append((step, losses)))  # fmt: skip
    assert [s for s, _ in seen] == [1, 2, 3, 4] and res.step == 4
    for _, losses in seen:
        assert {"g", "l1", "d", "gp", "w", "g_adv"} <= set(losses)
        assert all(np.isfinite(v) for v in losses.values())
    assert seen[-1][1]["g"] == pytest.approx(
        100.0 * seen[-1][1]["l1"] + seen[-1][1]["g_adv"], rel=1e-5
    )  # g = weight_l1 * L_c + weight_adv * L_a (no perceptual term)


def test_nan_input_is_a_clear_error(tmp_path):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as st:
        st.put(make_record(0, path="train", nan=True))
        st.put(make_record(1, path="test"))
        with pytest.raises(ValueError, match=r"store record \d+\.dl holds NaN"):
            T.train(st, tiny(), tmp_path / "run", progress=False)


def test_divergence_stops_and_keeps_the_last_good_checkpoint(store, tmp_path, monkeypatch):
    calls = {"n": 0}
    real_l1 = T.l1_loss

    def l1_nan_at_5(a, b):
        calls["n"] += 1
        out = real_l1(a, b)
        return out * float("nan") if calls["n"] == 5 else out

    monkeypatch.setattr(T, "l1_loss", l1_nan_at_5)
    with pytest.raises(T.TrainingDivergedError, match=r"iteration 5.*l1.*last.pt \(iteration 4\)"):
        T.train(store, tiny(iterations=8), tmp_path / "run", progress=False)
    ck = torch.load(tmp_path / "run" / "checkpoints" / "last.pt", weights_only=False)
    assert ck["step"] == 4
    assert all(torch.isfinite(v).all() for v in ck["generator"].values() if v.is_floating_point())


def test_config_validation_and_presets():
    p = T.TrainConfig.preset("paper")
    assert (p.crop, p.base, p.iterations, p.lr, p.batch_size) == (256, 64, 20000, 1e-4, 4)
    assert p.vgg19_weights is not None
    c = T.TrainConfig.preset("paper-cpu")
    assert (c.crop, c.base, c.device, c.inputs, c.weight_adv) == (128, 32, "cpu", "I", 1.0)
    r = T.TrainConfig.preset("cpu")  # the measured recipe (docs/gan.md)
    assert (r.crop, r.base, r.inputs, r.demodulate, r.full_res_skip) == (64, 8, "J", True, True)
    assert r.position_octaves == 6
    assert (r.weight_adv, r.weight_ssim, r.lr_schedule, r.ema) == (0.0, 20.0, "constant", 0.999)
    with pytest.raises(ValueError, match="multiple of 32"):
        T.TrainConfig(crop=100)
    with pytest.raises(ValueError, match="unknown TrainConfig field"):
        T.TrainConfig.preset("cpu", crops=1)
    with pytest.raises(ValueError, match="unknown input configuration"):
        T.TrainConfig(inputs="Z")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA"):
            T._device("cuda")


# ------------------------------------------------------------------------------ inference
@pytest.fixture
def trained(store, tmp_path):
    T.train(store, tiny(iterations=2), tmp_path / "run", progress=False)
    return Generator.load(tmp_path / "run")


def test_generate_checks_its_input(trained):
    rec = make_record(7, size=32)
    assert trained.generate(rec).shape == (32, 32, 3)
    maps = {n: getattr(rec, n) for n in trained.inputs}
    with pytest.raises(ValueError, match="multiples of 32"):
        trained.generate({n: a[:30] for n, a in maps.items()})
    with pytest.raises(ValueError, match="lacks the input buffer 'depth'"):
        trained.generate({n: a for n, a in maps.items() if n != "depth"})
    bad = dict(maps, dl=maps["dl"].copy())
    bad["dl"][0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="dl holds NaN or Inf"):
        trained.generate(bad)


def test_onnx_export_matches_torch(trained, tmp_path):
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime not installed (extra 'gan')")
    pytest.importorskip("onnx", reason="onnx not installed (extra 'gan')")
    path = trained.export_onnx(tmp_path / "g.onnx", 32, 32)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = np.stack([trained.encode(make_record(k, size=64)) for k in (5, 6)])  # other size, batch 2
    got = sess.run(None, {"maps": x})[0]
    with torch.no_grad():
        want = trained.module(torch.from_numpy(x)).numpy()
    assert got.shape == (2, 3, 64, 64) and np.abs(got - want).max() < 1e-5


# ------------------------------------------------------------------------------ CLI
@pytest.mark.filterwarnings("ignore:perceptual loss L_p is OFF")
def test_cli_train_resume_export(store, tmp_path, capsys):
    from icbtool.cli import main

    root = str(store.root)
    store.close()
    run = tmp_path / "runs" / "r"

    def args(n: int, *more: str) -> list[str]:
        return [
            "train",
            "--store",
            root,
            "--preset",
            "paper-cpu",
            "--inputs",
            "H",
            "--out",
            str(run),
            "--iterations",
            str(n),
            "--crop",
            "32",
            "--base",
            "4",
            "--eval-every",
            "2",
            "--no-progress",
            *more,
        ]

    assert main(args(2)) == 0
    assert "trained to iteration 2" in capsys.readouterr().out
    assert main(args(2)) == 1 and "already holds a run" in capsys.readouterr().err
    assert main(args(3, "--resume")) == 0
    assert "iteration 3" in capsys.readouterr().out
    gen = Generator.load(run)
    assert gen.inputs == ("albedo", "dl", "normal_world")
    if importlib.util.find_spec("onnx") is not None:
        onnx_path = str(tmp_path / "g.onnx")
        assert (
            main(["export", str(run), "--onnx", onnx_path, "--height", "32", "--width", "32"]) == 0
        )
        assert (tmp_path / "g.onnx").is_file() and (tmp_path / "g.onnx.json").is_file()
    assert main(["train", "--store", str(tmp_path / "nostore"), "--out", str(tmp_path / "x")]) == 1


@pytest.mark.gl
def test_cli_generate_on_a_procedural_scene(store, tmp_path, capsys):
    from icbtool.cli import main
    from icbtool.imageio import read_exr

    T.train(store, tiny(iterations=1, inputs="I"), tmp_path / "run", progress=False)
    out = tmp_path / "gen"
    rc = main(["generate", str(tmp_path / "run"), "cornell_box", "--height", "64", "--width", "64",
               "--out", str(out)])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    gi = read_exr(out / "default_gi.exr")
    assert gi.shape == (64, 64, 3) and np.isfinite(gi).all() and gi.min() >= 0
    from icbtool.cli.gan import GAN_SIZE_MULTIPLE
    from icbtool.gan.models import MULTIPLE

    assert GAN_SIZE_MULTIPLE == MULTIPLE
    bad = tmp_path / "bad"
    rc = main(["generate", str(tmp_path / "run"), "cornell_box", "--height", "60", "--width", "64",
               "--out", str(bad)])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [
        "icbtool generate: error: --height 60: a GAN generator's sides are multiples of 32 "
        "(e.g. 64)"
    ]
    assert not bad.exists()  # refused before any work


def test_package_names_are_not_shadowed_by_submodules():
    """``icb.gan.train`` stays the training function after every submodule is imported."""
    import importlib

    import icbtool.gan as G

    for m in ("hdr", "models", "losses", "data", "training", "generate"):
        importlib.import_module(f"icbtool.gan.{m}")
    assert callable(G.train) and G.train.__name__ == "train"
    assert G.TrainConfig.__name__ == "TrainConfig" and G.Generator.__name__ == "Generator"


@pytest.mark.gl
def test_loop_with_a_generator_never_asks_the_cloud(store, tmp_path):
    """The paper's rule in the loop: with a local generator every frame's GI is generated and the
    cloud renders nothing (the exact GI is checked with a stub in tests/test_system.py)."""
    import icbtool as icb
    from icbtool.gan import Generator
    from icbtool.pipeline import LoopConfig, run_loop

    T.train(store, tiny(iterations=1, inputs="E"), tmp_path / "run", progress=False)
    scene = icb.scene.cornell_box()
    cfg = LoopConfig(frames=3, height=32, width=32, truth_every=0, generator=str(tmp_path / "run"))
    rep = run_loop(scene, cfg, out_dir=tmp_path / "loop", progress=False)
    s = rep.summary()
    assert rep.cloud_renders == 0
    assert s["generated_frames"] == 3 and s["cloud_fallback_frames"] == 0
    assert [f.gi_source for f in rep.frames] == ["generator"] * 3
    assert s["median_generate_ms"] > 0
    # configuration E needs normal_view, which the WRT-buffer lacks: the client rasterized it
    assert Generator.load(tmp_path / "run").inputs == ("albedo", "dl", "normal_view")


def test_loop_compares_generated_with_cloud_gi_and_truth(store, tmp_path):
    """With a generator, truth frames also get the cloud's warped GI side by side; on the first
    frame it is exactly what a cloud-only loop shows (same request, same seeds, no history)."""
    import icbtool as icb
    from icbtool.imageio import read_png
    from icbtool.pipeline import LoopConfig, run_loop

    T.train(store, tiny(iterations=1, inputs="E"), tmp_path / "run", progress=False)
    scene = icb.scene.cornell_box()
    kw = dict(frames=3, height=32, width=32, truth_every=2, truth_spp=4, spp=4, denoise=False)
    rep = run_loop(scene, LoopConfig(**kw, generator=str(tmp_path / "run")),
                   out_dir=tmp_path / "gen", progress=False)  # fmt: skip
    ref = run_loop(scene, LoopConfig(**kw), out_dir=tmp_path / "cloud", progress=False)
    assert rep.cloud_renders == 0 and rep.comparison_renders >= 1
    assert [f.ssim_gi_cloud is not None for f in rep.frames] == [True, False, True]
    assert rep.frames[0].ssim_gi_cloud == pytest.approx(ref.frames[0].ssim_gi, abs=1e-12)
    assert rep.frames[0].ssim_gi != rep.frames[0].ssim_gi_cloud  # the generated GI is its own
    strip = read_png(tmp_path / "gen" / "frames" / "000_gi.png")
    from icbtool.pipeline import LABEL_HEIGHT

    assert strip.shape[:2] == (LABEL_HEIGHT + 32, 3 * 32 + 2 * 2)  # under caption bands
    assert not (tmp_path / "gen" / "frames" / "001_gi.png").exists()
    s = rep.summary()
    assert s["mean_ssim_gi_cloud_vs_truth"] == pytest.approx(
        np.mean([rep.frames[0].ssim_gi_cloud, rep.frames[2].ssim_gi_cloud])
    )


def test_demodulated_targets_round_trip_and_the_generator_remodulates(store, tmp_path):
    from icbtool.gan.data import ALBEDO_FLOOR, InputEncoding

    rec = make_record(9)
    enc = InputEncoding(("albedo", "dl"), HDRTransform(0.05, 4.0), demodulate=True)
    t = enc.encode_target(rec.gi, rec.albedo)
    assert t.shape == (3, 32, 32)
    back = enc.remodulate(enc.hdr.decode(t).transpose(1, 2, 0), rec.albedo)
    assert rec.albedo.min() > ALBEDO_FLOOR  # so the round trip is exact up to float rounding
    np.testing.assert_allclose(back, rec.gi, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="demodulate needs 'albedo' among the inputs"):
        InputEncoding(("dl", "depth"), demodulate=True)
    # a demodulating run: generate() = decoded network output times the albedo input
    T.train(
        store, tiny(iterations=1, inputs="A", demodulate=True), tmp_path / "run", progress=False
    )
    gen = Generator.load(tmp_path / "run")
    assert gen.encoding.demodulate
    raw = gen.encoding.hdr.decode(gen.module(torch.from_numpy(gen.encode(rec))[None]).detach())
    expect = raw[0].permute(1, 2, 0).numpy() * rec.albedo
    np.testing.assert_allclose(gen.generate(rec), expect, rtol=1e-5, atol=1e-7)


# ------------------------------------------------------------------------------ warped reference
def plane_record(i: int, size: int = 32, path: str = "train") -> S.CRTBuffer:
    """A view of the plane z = 2 from a camera at x = 0.1 i looking down +z; GI is a function of
    the world x coordinate, so another view's GI warped here must equal this view's GI."""
    h = w = size
    m = np.eye(4)
    m[0, 3] = 0.1 * i
    cam = Camera.from_fov(60.0, h, w, m)
    u = np.arange(w, dtype=np.float64) + 0.5
    wx = 0.1 * i + (u - cam.cx) / cam.fx * 2.0
    g = (0.2 + 0.1 * np.sin(3.0 * wx))[None, :, None] * np.array([1.0, 0.8, 0.6])
    gi = np.broadcast_to(g, (h, w, 3)).astype(np.float32)
    ones = np.ones((h, w, 3), np.float32)
    return S.CRTBuffer(
        camera=cam,
        meta=S.RecordMeta("plane", "ph", "lh", spp=4, tags={"path": path, "index": i}),
        gi=gi,
        dl=0.5 * ones,
        albedo=0.7 * ones,
        normal_world=np.broadcast_to(np.float32([0, 0, -1]), (h, w, 3)).copy(),
        depth=np.full((h, w, 1), 2.0, np.float32),
        mask=np.ones((h, w, 1), np.float32),
    )


@pytest.fixture
def plane_store(tmp_path):
    with S.open(tmp_path / "plane", S.StoreConfig(fsync=False)) as st:
        for i in range(4):
            st.put(plane_record(i, path="train"))
        for i in range(4, 7):
            st.put(plane_record(i, path="test"))
        yield st


def test_warped_reference_matches_the_view_and_marks_the_uncovered_columns(plane_store):
    ds = S.Dataset(plane_store, split="train", inputs="H")
    refs = D.WarpedReferences(plane_store, ds.record_ids)
    assert [refs.reference(i, 1) for i in range(4)] == [1, 0, 1, 2]  # earlier, else later
    assert refs.reference(0, 9) == 3  # clamped to the path
    with pytest.raises(ValueError, match="reference offset must be >= 1"):
        refs.reference(0, 0)
    with pytest.raises(ValueError, match="at least 2 views"):
        D.WarpedReferences(plane_store, ds.record_ids[:1]).reference(0, 1)
    assert [refs.reference(i, 1, later=True) for i in range(4)] == [1, 2, 3, 2]
    assert refs.reference(1, 2, later=True) == 3 and refs.reference(2, 3, later=True) == 3
    img, holes = refs.warped(2, 1)  # reference 0.1 to the left: shifted by fx * 0.1 / 2 pixels
    cam = plane_record(2).camera
    shift = cam.fx * 0.1 / 2.0
    # a target column c (centre c + 0.5) samples the reference at c + 0.5 + shift: outside the
    # reference's image (0..32) exactly when that passes 32
    cols = np.flatnonzero(holes.any(0))
    assert holes.all(0)[cols].all()
    assert set(cols) == {c for c in range(32) if c + 0.5 + shift > 32} and len(cols) >= 1
    truth = plane_record(2).gi
    inner = np.array([c + 0.5 + shift <= 31.5 for c in range(32)])  # between reference centres
    np.testing.assert_allclose(img[:, inner], truth[:, inner], atol=1e-3)  # bilinear error only
    assert np.abs(img[~holes] - truth[~holes]).max() < 1e-2  # the last column: edge-clamped
    assert np.all(img[holes] == 0)
    img_r, holes_r = refs.warped(1, 2)  # reference to the right: the holes are on the left
    assert set(np.flatnonzero(holes_r.any(0))) == {c for c in range(32) if c + 0.5 - shift < 0}
    enc = D.InputEncoding(("albedo", "dl", "normal_world"), HDRTransform(), warped=True)
    assert enc.n_channels == 9 + 4 and enc.all_inputs[-2:] == ("warped_gi", "warp_holes")
    e = refs.encoded(2, 1, enc)
    assert e.shape == (4, 32, 32)
    np.testing.assert_allclose(e[:3], enc.hdr.encode(img).transpose(2, 0, 1))
    assert np.array_equal(e[3], np.where(holes, 1.0, -1.0))
    assert D.InputEncoding.from_dict(enc.to_dict()) == enc


def test_training_with_a_warped_reference_resumes_exactly_and_generates(plane_store, tmp_path):
    cfg = tiny(
        inputs="H", iterations=4, n_critic=1, warped_reference=True, reference_offsets=(1, 2)
    )
    res = T.train(plane_store, cfg, tmp_path / "full", progress=False)
    assert res.step == 4 and len(res.evals) == 2
    assert_cut_at_2_resumes_to(plane_store, cfg, tmp_path / "full", tmp_path / "cut")
    gen = Generator.load(tmp_path / "full")
    assert gen.inputs == ("albedo", "dl", "normal_world", "warped_gi", "warp_holes")
    assert gen.module.config.in_channels == 13
    rec = plane_record(5)
    with pytest.raises(ValueError, match="lacks the input buffer 'warped_gi'"):
        gen.generate(rec)
    maps = {n: getattr(rec, n) for n in ("albedo", "dl", "normal_world")}
    maps.update(warped_gi=rec.gi, warp_holes=np.zeros((32, 32), np.float32))
    assert gen.generate(maps).shape == (32, 32, 3)
    from icbtool.system import GeneratorSource

    with pytest.raises(ValueError, match="warped reference"):
        GeneratorSource(gen)
    with pytest.raises(ValueError, match="reference_offsets"):
        tiny(reference_offsets=(0,))
    with pytest.raises(ValueError, match="test_reference_offset must be an integer >= 1"):
        tiny(test_reference_offset=0)


# ------------------------------------------- coverage, demodulation, position features, baselines
def test_ssim_loss_is_zero_for_equal_maps_and_grows_with_noise():
    from icbtool.gan.losses import ssim_loss

    g = torch.Generator().manual_seed(0)
    y = torch.rand(2, 3, 32, 32, generator=g) * 2 - 1
    assert float(ssim_loss(y, y)) == pytest.approx(0.0, abs=1e-6)
    small = ssim_loss(y + 0.05 * torch.randn(y.shape, generator=g), y)
    large = ssim_loss(y + 0.5 * torch.randn(y.shape, generator=g), y)
    assert 0 < float(small) < float(large) <= 2
    with pytest.raises(ValueError, match="ssim_loss"):
        ssim_loss(y, y[:, :1])


def test_cosine_learning_rate_falls_from_lr_to_lr_final():
    c = T.TrainConfig(iterations=100, lr=1e-3, lr_schedule="cosine", lr_final=0.1)
    assert T.learning_rate(c, 0) == pytest.approx(1e-3)
    assert T.learning_rate(c, 50) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))
    assert T.learning_rate(c, 100) == pytest.approx(1e-4)
    assert T.learning_rate(T.TrainConfig(lr=3e-4), 77) == 3e-4
    with pytest.raises(ValueError, match="lr_schedule"):
        T.TrainConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="ema"):
        T.TrainConfig(ema=1.0)


def test_full_resolution_skip_sees_the_input_pixel():
    """With the skip, one input pixel changes the output at that pixel through the 3x3 head even
    with every U-Net weight zeroed; without it, a zeroed U-Net outputs a constant."""
    cfg = M.GeneratorConfig(in_channels=2, base=4, norm="none", full_res_skip=True)
    g = M.UNetGenerator(cfg).eval()
    with torch.no_grad():
        for p in g.parameters():
            p.zero_()
        g.head[0].weight[:, :, 1, 1] = 1.0  # centre tap: out = tanh(sum of features + inputs)
        x = torch.zeros(1, 2, 32, 32)
        x[0, 1, 7, 9] = 0.5
        out = g(x)
    assert out.shape == (1, 3, 32, 32)
    assert float(out[0, 0, 7, 9]) == pytest.approx(np.tanh(0.5), abs=1e-6)
    assert float(out.abs().sum()) == pytest.approx(3 * np.tanh(0.5), abs=1e-5)


def test_weight_average_is_what_is_saved_and_resumes_exactly(store, tmp_path):
    cfg = tiny(iterations=4, ema=0.9, weight_ssim=1.0, lr_schedule="cosine", full_res_skip=True)
    T.train(store, cfg, tmp_path / "full", progress=False)

    class Killed(Exception):
        pass

    def kill_at_3(step, losses):
        if step == 3:
            raise Killed  # as a kill after the checkpoint of iteration 2

    with pytest.raises(Killed):
        T.train(store, cfg, tmp_path / "cut", progress=False, on_step=kill_at_3)
    T.train(store, cfg, tmp_path / "cut", resume=True, progress=False)
    a = torch.load(tmp_path / "full" / "checkpoints" / "last.pt", weights_only=False)
    b = torch.load(tmp_path / "cut" / "checkpoints" / "last.pt", weights_only=False)
    for part in ("generator", "generator_ema", "critic"):
        for k, v in a[part].items():
            assert torch.equal(v, b[part][k]), (part, k)
    saved = torch.load(tmp_path / "full" / "generator.pt", weights_only=False)["generator"]
    for k, v in a["generator_ema"].items():
        assert torch.equal(saved[k], v)
    assert any(not torch.equal(a["generator"][k], v) for k, v in a["generator_ema"].items())


def test_evaluation_covers_every_test_view_and_says_so(store, tmp_path, capsys):
    res = T.train(store, tiny(iterations=2), tmp_path / "run", progress=False)
    assert res.eval_views == 2 and res.evals[-1]["views"] == 2  # the store's 2 test records
    assert "(mean of 2 test views)" in capsys.readouterr().out
    one = T.train(store, tiny(iterations=2, eval_frames=1), tmp_path / "one", progress=False)
    assert one.eval_views == 1


def test_resume_continues_seconds_and_tensorboard_steps(store, tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = tiny(iterations=4, eval_every=2, checkpoint_every=2)
    T.train(store, T.TrainConfig.from_dict({**cfg.to_dict(), "iterations": 2}), tmp_path / "r",
            progress=False)  # fmt: skip
    res = T.train(store, cfg, tmp_path / "r", resume=True, progress=False)
    s = [e["seconds"] for e in res.evals]
    assert s[1] > s[0] > 0  # the clock goes on from the checkpoint
    steps = set()
    for f in sorted((tmp_path / "r" / "tb").glob("events.out.tfevents.*")):
        acc = EventAccumulator(str(f))
        acc.Reload()
        if "loss/g" in acc.Tags()["scalars"]:
            steps |= {e.step for e in acc.Scalars("loss/g")}
    assert steps == {1, 2, 3, 4}


def test_training_on_several_paths_takes_each_paths_records(tmp_path):
    with S.open(tmp_path / "s", S.StoreConfig(fsync=False)) as st:
        for i, p in enumerate(["train", "train", "cover", "test", "other"]):
            st.put(make_record(i, path=p))
        from icbtool.store import Dataset

        ds = Dataset(st, None, "train", "I", paths={"train": "train,cover", "test": "test"})
        assert len(ds) == 3
        tags = [st.get(r).meta.tags["path"] for r in ds.record_ids]
        assert tags == ["train", "train", "cover"]


# ------------------------------------------------------------------------------ baselines
def test_albedo_scale_and_constant_are_the_least_squares_fits():
    from icbtool.gan.baselines import AlbedoScaledGI, ConstantGI

    rng = np.random.default_rng(0)
    a = rng.uniform(0.1, 0.9, (3, 3, 8, 8)).astype(np.float32)
    k_true = np.array([0.3, 0.5, 0.7], np.float32)
    gi = a * k_true[None, :, None, None]
    mask = np.ones((3, 1, 8, 8), np.float32)
    mask[0, 0, :4] = 0  # background pixels do not count
    gi[0, :, :4] = 100.0
    fit = AlbedoScaledGI.fit(a, gi, mask)
    np.testing.assert_allclose(fit.k, k_true, rtol=1e-5)
    const = ConstantGI.fit(a, gi, mask)
    m = mask[:, 0] > 0.5
    np.testing.assert_allclose(const.colour, gi.transpose(0, 2, 3, 1)[m].mean(0), rtol=1e-5)
    rec = {"albedo": a[1].transpose(1, 2, 0), "mask": np.ones((8, 8, 1), np.float32)}
    np.testing.assert_allclose(fit.generate(rec), gi[1].transpose(1, 2, 0), rtol=1e-5)
    rec["mask"][0, 0] = 0
    assert np.all(const.generate(rec)[0, 0] == 0)
    with pytest.raises(ValueError, match="no surface pixels"):
        AlbedoScaledGI.fit(a, gi, np.zeros_like(mask))


def test_nearest_irradiance_reproduces_a_function_of_position_and_keeps_wall_sides_apart():
    from icbtool.gan.baselines import NearestIrradiance

    rng = np.random.default_rng(1)
    p = rng.uniform(0, 1, (2000, 3))
    p = np.concatenate([p, p])  # the two sides of a wall share positions
    n = np.tile([0.0, 0.0, 1.0], (4000, 1))
    n[2000:] *= -1
    e = np.where(n[:, 2:] > 0, 0.2, 0.8) * np.ones((1, 3))
    nn = NearestIrradiance(p, n, e, np.array([[0, 0, 0], [1, 1, 1.0]]), k=4, normal_weight=0.5)
    q = rng.uniform(0, 1, (16, 16, 3)).astype(np.float32)
    qn = np.tile(np.float32([0, 0, 1]), (16, 16, 1))
    qn[:8] *= -1
    albedo = np.full((16, 16, 3), 0.5, np.float32)
    out = nn.generate({"albedo": albedo, "position": q, "normal_world": qn})
    expect = np.where(qn[..., 2:] > 0, 0.2, 0.8) * albedo
    np.testing.assert_allclose(out, expect, rtol=1e-6)


def test_equal_quality_interpolates_in_log_cost_and_says_when_there_is_no_equal_point():
    from icbtool.gan.baselines import equal_quality

    costs, q = [10.0, 100.0, 1000.0], [0.5, 0.7, 0.9]
    r = equal_quality(costs, q, 0.6)  # halfway in log cost between 10 and 100
    assert r.status == "interpolated" and r.cost == pytest.approx(10**1.5)
    assert equal_quality(costs, q, 0.7).cost == pytest.approx(100.0)
    above = equal_quality(costs, q, 0.4)
    assert above.status == "above" and above.cost is None and above.cheapest == (10.0, 0.5)
    assert equal_quality(costs, q, 0.95).status == "below"
    # a slower setting that scores lower is never chosen (monotone envelope)
    assert equal_quality([10, 50, 100], [0.5, 0.95, 0.7], 0.9).cost < 50
    with pytest.raises(ValueError, match="costs"):
        equal_quality([0.0, 1.0], [0.1, 0.2], 0.15)


def test_fourier_features_of_the_position_channels_are_computed_inside_the_network(store, tmp_path):
    cfg = M.GeneratorConfig(in_channels=5, base=4, fourier_channels=(1, 4), fourier_octaves=2)
    g = M.UNetGenerator(cfg)
    assert cfg.n_features == 12
    x = torch.zeros(1, 5, 32, 32)
    x[0, 1:4] = 0.25
    f = g.features(x)
    assert f.shape == (1, 17, 32, 32)
    # channel order: x, then sin/cos per octave: sin(pi p), cos(pi p), sin(2 pi p), cos(2 pi p)
    np.testing.assert_allclose(f[0, 5:8, 0, 0], np.sin(np.pi * 0.25), atol=1e-6)
    np.testing.assert_allclose(f[0, 8:11, 0, 0], np.cos(np.pi * 0.25), atol=1e-6)
    np.testing.assert_allclose(f[0, 11:14, 0, 0], np.sin(2 * np.pi * 0.25), atol=1e-6)
    assert g(x).shape == (1, 3, 32, 32)
    with pytest.raises(ValueError, match="fourier_channels"):
        M.GeneratorConfig(in_channels=3, fourier_channels=(1, 4), fourier_octaves=2)
    with pytest.raises(ValueError, match="position_octaves needs 'position'"):
        T.train(store, tiny(inputs="I", position_octaves=2), tmp_path / "bad", progress=False)
    T.train(store, tiny(inputs="J", position_octaves=2), tmp_path / "run", progress=False)
    gen = Generator.load(tmp_path / "run")
    assert gen.module.config.fourier_octaves == 2
    assert gen.generate(make_record(9)).shape == (32, 32, 3)


# ------------------------------------------------------------------------------ client frame time
def test_generator_config_saved_before_the_speed_fields_builds_the_first_network():
    old = {"in_channels": 12, "out_channels": 3, "base": 4, "norm": "batch",
           "full_res_skip": True, "fourier_channels": [9, 12], "fourier_octaves": 2}  # fmt: skip
    cfg = M.GeneratorConfig(**old)
    assert (cfg.fourier_resolution, cfg.head_kernel, cfg.skip_features) == ("full", 3, True)
    assert (cfg.reduce, cfg.top_width) == (0, 0)
    g = M.UNetGenerator(cfg)
    # the first network: 12 + 12 feature channels into the first level, a 3x3 head over
    # base + 24 channels, no other modules
    assert g.down[0][0].weight.shape == (4, 24, 4, 4)
    assert g.head[0].weight.shape == (3, 4 + 24, 3, 3)
    assert g.reduce is None and g.half_features is None
    with pytest.raises(ValueError, match="head_kernel must be 1 or 3"):
        M.GeneratorConfig(in_channels=3, head_kernel=2)
    with pytest.raises(ValueError, match="fourier_resolution must be 'full' or 'half'"):
        M.GeneratorConfig(in_channels=3, fourier_resolution="quarter")
    with pytest.raises(ValueError, match="reduce maps full-resolution features"):
        M.GeneratorConfig(in_channels=3, reduce=8, fourier_resolution="half")


def test_half_resolution_features_are_those_of_the_2x2_mean_position():
    """With every weight zero but the features' 1x1 convolution (all ones), the first level's
    output is LeakyReLU of the sum of sin / cos of the 2x2-averaged position."""
    cfg = M.GeneratorConfig(in_channels=4, base=4, norm="none", full_res_skip=True,
                            fourier_channels=(1, 2), fourier_octaves=2,
                            fourier_resolution="half", head_kernel=1)  # fmt: skip
    g = M.UNetGenerator(cfg).eval()
    assert cfg.full_features == 0 and g.down[0][0].weight.shape[1] == 4  # raw input only
    assert g.head[0].weight.shape == (3, 4 + 4, 1, 1)  # skip: the input maps alone
    seen = {}
    g.down[0][2].register_forward_hook(lambda m, i, o: seen.setdefault("first", o))
    with torch.no_grad():
        for p in g.parameters():
            p.zero_()
        g.half_features.weight.fill_(1.0)
        x = torch.zeros(1, 4, 32, 32)
        x[0, 1] = torch.rand(32, 32, generator=torch.Generator().manual_seed(0)) - 0.5
        g(x)
    p = x[0, 1].numpy().reshape(16, 2, 16, 2).mean((1, 3))
    s = sum(f(np.pi * 2.0**k * p) for k in range(2) for f in (np.sin, np.cos))
    want = np.where(s > 0, s, 0.2 * s)
    got = seen["first"][0].numpy()
    assert got.shape == (4, 16, 16)
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-5)


def test_one_by_one_head_sees_only_its_own_pixel():
    cfg = M.GeneratorConfig(in_channels=2, base=4, norm="none", full_res_skip=True, head_kernel=1)
    g = M.UNetGenerator(cfg).eval()
    with torch.no_grad():
        for p in g.parameters():
            p.zero_()
        g.head[0].weight[:, 4 + 1] = 1.0  # the second input map
        x = torch.zeros(1, 2, 32, 32)
        x[0, 1, 7, 9] = 0.5
        out = g(x)
    assert float(out[0, 0, 7, 9]) == pytest.approx(np.tanh(0.5), abs=1e-6)
    assert float(out.abs().sum()) == pytest.approx(3 * np.tanh(0.5), abs=1e-5)


def test_fast_generator_trains_loads_and_exports_to_onnx_equal_to_torch(store, tmp_path):
    cfg = tiny(inputs="J", position_octaves=2, full_res_skip=True, position_resolution="half",
               head_kernel=1, top_width=2)  # fmt: skip
    T.train(store, cfg, tmp_path / "run", progress=False)
    gen = Generator.load(tmp_path / "run")
    c = gen.module.config
    assert (c.fourier_resolution, c.head_kernel, c.top_width) == ("half", 1, 2)
    assert gen.generate(make_record(9)).shape == (32, 32, 3)
    r = T.TrainConfig.preset("cpu")
    assert (r.position_resolution, r.head_kernel) == ("half", 1)
    with pytest.raises(ValueError, match="head_kernel"):
        T.TrainConfig.preset("cpu", head_kernel=5)
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime not installed (extra 'gan')")
    pytest.importorskip("onnx", reason="onnx not installed (extra 'gan')")
    sess = ort.InferenceSession(
        str(gen.export_onnx(tmp_path / "g.onnx", 32, 32)), providers=["CPUExecutionProvider"]
    )
    x = np.stack([gen.encode(make_record(k, size=64)) for k in (5, 6)])
    with torch.no_grad():
        want = gen.module(torch.from_numpy(x)).numpy()
    assert np.abs(sess.run(None, {"maps": x})[0] - want).max() < 1e-5


def test_demodulated_warped_reference_is_divided_by_the_views_albedo(plane_store, tmp_path):
    ds = S.Dataset(plane_store, split="train", inputs="H")
    refs = D.WarpedReferences(plane_store, ds.record_ids)
    enc = D.InputEncoding.fit(
        ("albedo", "dl", "normal_world"), HDRTransform(0.05, 4.0), list(ds),
        demodulate=True, warped=True,
    )  # fmt: skip
    assert enc.demodulate_warped
    img, holes = refs.warped(2, 1)
    e = refs.encoded(2, 1, enc)
    # the plane's albedo is 0.7: input and demodulated target agree where the reference saw
    np.testing.assert_allclose(e[:3], enc.hdr.encode(img / 0.7).transpose(2, 0, 1), rtol=1e-6)
    t = enc.encode_target(plane_record(2).gi, plane_record(2).albedo)
    shift = plane_record(2).camera.fx * 0.1 / 2.0
    inner = np.array([c + 0.5 + shift <= 31.5 for c in range(32)])  # between reference centres
    assert np.abs(e[:3] - t)[:, :, inner].max() < 5e-3  # bilinear error only
    rec = plane_record(2)
    maps = {n: getattr(rec, n) for n in ("albedo", "dl", "normal_world")}
    x = enc.encode({**maps, "warped_gi": img, "warp_holes": holes.astype(np.float32)})
    np.testing.assert_allclose(x[9:12], e[:3], rtol=1e-6)
    old = {k: v for k, v in enc.to_dict().items() if k != "demodulate_warped"}
    assert not D.InputEncoding.from_dict(old).demodulate_warped  # runs written before it
    assert D.InputEncoding.from_dict(enc.to_dict()) == enc
    with pytest.raises(ValueError, match="demodulate_warped needs demodulate and warped"):
        D.InputEncoding(("albedo", "dl"), demodulate=True, demodulate_warped=True)
    # a run trains and generates with it
    cfg = tiny(inputs="H", iterations=2, warped_reference=True, demodulate=True,
               reference_offsets=(1,))  # fmt: skip
    T.train(plane_store, cfg, tmp_path / "run", progress=False)
    gen = Generator.load(tmp_path / "run")
    assert gen.encoding.demodulate_warped
    assert gen.generate({**maps, "warped_gi": img, "warp_holes": holes}).shape == (32, 32, 3)


def _gated(n_in=6, **kw):
    """A U-Net whose input channels 2-5 are a warped reference (3) and its hole mask (1)."""
    cfg = M.GeneratorConfig(in_channels=n_in, base=4, norm="none", full_res_skip=True,
                            head_kernel=1, reference_gate=(2, 6), **kw)  # fmt: skip
    return M.UNetGenerator(cfg).eval()


def test_reference_gate_blends_the_warp_where_it_saw_and_generates_in_its_holes():
    g = _gated()
    with torch.no_grad():
        for p in g.parameters():
            p.zero_()
        head = g.head[0]
        assert head.out_channels == 4  # RGB + the gate's logit
        head.bias[:3] = 0.25  # generated: tanh(0.25) everywhere
        head.bias[3] = 1.5  # gate logit: sigmoid(1.5) where the reference saw
        x = torch.zeros(1, 6, 32, 32)
        x[:, 2:5] = torch.linspace(-0.9, 0.9, 32)  # the reference, in the output's range
        x[:, 5] = -1.0  # no holes ...
        x[:, 5, :, :8] = 1.0  # ... except the first 8 columns
        out, gen, gate = g.parts(x)
    a, t = float(1 / (1 + np.exp(-1.5))), float(np.tanh(0.25))
    assert torch.allclose(gen, torch.full_like(gen, t))
    assert torch.all(gate[..., :8] == 0) and torch.allclose(gate[..., 8:], torch.tensor(a))
    want = a * x[:, 2:5] + (1 - a) * t
    assert torch.allclose(out[..., 8:], want[..., 8:], atol=1e-6)  # the warp, trusted by a
    assert torch.allclose(out[..., :8], torch.full_like(out[..., :8], t))  # holes: generated
    assert torch.equal(g(x), out)
    with torch.no_grad():
        head.bias[3] = 40.0  # full trust: the reference itself where it saw
        assert torch.allclose(g(x)[..., 8:], x[:, 2:5, :, 8:], atol=1e-6)
    with pytest.raises(ValueError, match="reference_gate"):
        M.GeneratorConfig(in_channels=5, reference_gate=(2, 6))
    with pytest.raises(ValueError, match="reference_gate"):
        M.GeneratorConfig(in_channels=8, reference_gate=(2, 5))
    with pytest.raises(ValueError, match="reference_gate needs warped_reference"):
        tiny(reference_gate=True)


def test_gated_generator_trains_its_generated_image_too_resumes_and_exports(plane_store, tmp_path):
    cfg = tiny(inputs="H", iterations=4, warped_reference=True, reference_gate=True,
               demodulate=True, reference_offsets=(1, 2))  # fmt: skip
    seen = []
    T.train(plane_store, cfg, tmp_path / "full", progress=False,
            on_step=lambda step, losses: seen.append(losses))  # fmt: skip
    assert all("g_generated" in s for s in seen)
    assert_cut_at_2_resumes_to(plane_store, cfg, tmp_path / "full", tmp_path / "cut")
    gen = Generator.load(tmp_path / "full")
    assert gen.module.config.reference_gate == (9, 13)  # warped_gi, warp_holes after H's 9
    rec = plane_record(5)
    maps = {n: getattr(rec, n) for n in ("albedo", "dl", "normal_world")}
    holes = np.zeros((32, 32), np.float32)
    holes[:, :5] = 1.0
    maps.update(warped_gi=rec.gi, warp_holes=holes)
    assert gen.generate(maps).shape == (32, 32, 3)
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime not installed (extra 'gan')")
    pytest.importorskip("onnx", reason="onnx not installed (extra 'gan')")
    sess = ort.InferenceSession(
        str(gen.export_onnx(tmp_path / "g.onnx", 32, 32)), providers=["CPUExecutionProvider"]
    )
    x = gen.encode(maps)[None]
    with torch.no_grad():
        want = gen.module(torch.from_numpy(x)).numpy()
    assert np.abs(sess.run(None, {"maps": x})[0] - want).max() < 1e-5


def test_reference_dropout_empties_whole_references_at_its_rate(plane_store):
    ds = S.Dataset(plane_store, split="train", inputs="H")
    enc = D.InputEncoding.fit(("albedo", "dl", "normal_world"), HDRTransform(0.05, 4.0),
                              list(ds), warped=True)  # fmt: skip
    data = D.PairData(ds, enc)
    kept = D.BatchSampler(data, 400, 32, False, seed=3, reference_offsets=(1,))
    dropped = D.BatchSampler(data, 400, 32, False, seed=3, reference_offsets=(1,),
                             reference_dropout=0.3)  # fmt: skip
    xk, yk = kept.next()
    xd, yd = dropped.next()
    assert np.array_equal(yk, yd) and np.array_equal(xk[:, :9], xd[:, :9])  # same draws
    empty = (xd[:, 12] == 1.0).all(axis=(1, 2)) & (xd[:, 9:12] == -1.0).all(axis=(1, 2, 3))
    assert 0.2 < empty.mean() < 0.4  # 400 draws at p = 0.3
    assert np.array_equal(xd[~empty], xk[~empty])  # the others keep their reference
    assert not ((xk[:, 12] == 1.0).all(axis=(1, 2))).any()  # the plane's references see
    with pytest.raises(ValueError, match="reference_dropout"):
        D.BatchSampler(data, 2, 32, False, seed=0, reference_dropout=1.0)
    with pytest.raises(ValueError, match="reference_dropout"):
        tiny(warped_reference=True, reference_dropout=-0.1)


def test_every_gi_model_declares_the_one_interface():
    """The generator, the world-space model and the baselines all answer "GI for these
    buffers" through icbtool.buffers.GIModel; a baseline instance is one at run time."""
    from icbtool.buffers import GIModel
    from icbtool.gan import baselines
    from icbtool.gan.generate import Generator
    from icbtool.radiance.model import RadianceModel

    for cls in (Generator, RadianceModel, baselines.ConstantGI, baselines.AlbedoScaledGI,
                baselines.NearestIrradiance):  # fmt: skip
        assert issubclass(cls, GIModel), cls
    albedo = np.full((2, 3, 3), 0.5, np.float32)
    model = baselines.ConstantGI(np.array([0.1, 0.2, 0.3], np.float32))
    assert isinstance(model, GIModel)
    assert model.generate({"albedo": albedo}).shape == (2, 3, 3)
    assert not isinstance(object(), GIModel)


def test_on_step_true_stops_with_a_checkpoint_that_resumes_bitwise(store, tmp_path):
    """Stopping between periodic checkpoints (the desktop app's Stop, or closing it) loses no
    iteration: the run checkpoints where it is, and resuming ends where the uninterrupted run
    does, bit for bit."""
    cfg = tiny(iterations=5, eval_every=5, checkpoint_every=100)
    T.train(store, cfg, tmp_path / "full", progress=False)
    res = T.train(store, cfg, tmp_path / "cut", progress=False, on_step=lambda s, _: s == 3)
    assert res.step == 3
    ck = torch.load(tmp_path / "cut" / "checkpoints" / "last.pt", weights_only=False)
    assert ck["step"] == 3
    assert T.train(store, cfg, tmp_path / "cut", resume=True, progress=False).step == 5
    a = torch.load(tmp_path / "full" / "generator.pt", weights_only=False)["generator"]
    b = torch.load(tmp_path / "cut" / "generator.pt", weights_only=False)["generator"]
    assert all(torch.equal(v, b[k]) for k, v in a.items())
