"""The resumable GAN training loop (docs/design.md section 5) and its presets.

A run directory holds:

- ``config.json``: the resolved :class:`TrainConfig`, the input encoding, the perceptual-loss
  status ("on: FILE" / "off: REASON"), TensorBoard status, versions and machine;
- ``checkpoints/last.pt``: models, optimisers, the RNG states (torch, numpy, python, the GP's
  generator, the batch sampler) and the evaluation history; written atomically, never after a
  non-finite loss, so it is always the last good state;
- ``generator.pt``: what :meth:`icbtool.gan.Generator.load` reads (weights, configs, encoding);
- ``evals.csv`` / ``evals.json``: every evaluation (iteration, SSIM, MSE on the test split);
- ``samples/iter_NNNNNN.png``: generated | truth | |difference| of the first test frame;
- ``tb/``: TensorBoard event files (losses, SSIM, MSE) when ``torch.utils.tensorboard`` works.

Resuming (``resume=True``) restores all of it: a run stopped at any checkpoint and resumed ends
with bit-identical weights to an uninterrupted run on the same machine and thread count.
"""

from __future__ import annotations

import csv
import json
import math
import os
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from icbtool.gan.data import BatchSampler, InputEncoding, PairData, resolve_inputs
from icbtool.gan.hdr import HDRTransform
from icbtool.gan.losses import (
    build_perceptual,
    critic_score,
    gradient_penalty,
    l1_loss,
)
from icbtool.gan.models import (
    MULTIPLE,
    DiscriminatorConfig,
    GeneratorConfig,
    PatchDiscriminator,
    UNetGenerator,
    init_weights,
)
from icbtool.imageio import to_display, write_png
from icbtool.metrics import mse as mse_metric
from icbtool.metrics import ssim as ssim_metric
from icbtool.provenance import run_info, write_json
from icbtool.store.dataset import Dataset


class TrainingDivergedError(RuntimeError):
    """A loss became NaN/Inf or exceeded ``TrainConfig.divergence_limit``; training stopped and
    the last good checkpoint is kept."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines a training run (written to ``config.json``).

    Attributes:
        inputs: input configuration letter "A".."J" or comma-separated buffer names.
        iterations: generator updates in all (a resumed run may raise it).
        crop: side of the square training crops (multiple of 32).
        base: width of the generator's and critic's first layer.
        norm: generator normalisation ("batch", "instance", "none").
        critic_norm: critic normalisation ("instance", "none").
        batch_size: pairs per mini-batch.
        lr: Adam learning rate of both networks.
        betas: Adam betas.
        n_critic: critic updates per generator update.
        lambda_gp: weight of the WGAN-GP gradient penalty.
        gp_target: target gradient norm k.
        weight_adv: weight of L_a (0: no critic, pure L1 (+ perceptual) regression).
        weight_l1: weight of L_c.
        weight_perceptual: weight of L_p (needs ``vgg19_weights``; 0 turns it off silently).
        vgg19_weights: local torchvision VGG19 state-dict file; None or missing: L_p off + warning.
        hdr_scale, hdr_max: the :class:`~icbtool.gan.hdr.HDRTransform` of DL and GI.
        demodulate: learn the indirect irradiance GI / albedo and multiply the output by the
            albedo (:class:`~icbtool.gan.data.InputEncoding`; our addition, off in the presets).
        warped_reference: the generator also reads the GI of another view of the path warped to
            this view and its hole mask (:class:`~icbtool.gan.data.WarpedReferences`; our
            addition, off in the presets): what a client holds when it warps a cached reference.
        reference_offsets: training draws the reference this many views away (uniformly from
            these, earlier or later along the train path).
        test_reference_offset: the test frames' reference is this many views earlier.
        train_path, test_path: the camera-path tags of the two splits in the store.
        flip: random horizontal flips (paired augmentation).
        eval_every: evaluate (and write a sample) every this many iterations (and at the end).
        eval_frames: at most this many test frames per evaluation (the first ones).
        checkpoint_every: checkpoint every this many iterations (and at the end).
        display_exposure: exposure of the display transform of the metrics (RGB 0-255).
        divergence_limit: a loss whose magnitude exceeds this stops training.
        seed: seed of initialisation, batches and the gradient penalty.
        device: "cpu" or "cuda" (an error if CUDA is not available).
    """

    inputs: str = "I"
    iterations: int = 3000
    crop: int = 128
    base: int = 32
    norm: Literal["batch", "instance", "none"] = "batch"
    critic_norm: Literal["instance", "none"] = "instance"
    batch_size: int = 4
    lr: float = 1e-4
    betas: tuple[float, float] = (0.5, 0.999)
    n_critic: int = 1
    lambda_gp: float = 10.0
    gp_target: float = 1.0
    weight_adv: float = 1.0
    weight_l1: float = 100.0
    weight_perceptual: float = 1.0
    vgg19_weights: str | None = None
    hdr_scale: float = 0.25
    hdr_max: float = 64.0
    demodulate: bool = False
    warped_reference: bool = False
    reference_offsets: tuple[int, ...] = (1, 2, 3, 4, 6)
    test_reference_offset: int = 1
    train_path: str = "train"
    test_path: str = "test"
    flip: bool = True
    eval_every: int = 250
    eval_frames: int = 8
    checkpoint_every: int = 250
    display_exposure: float = 1.0
    divergence_limit: float = 1e6
    seed: int = 0
    device: Literal["cpu", "cuda"] = "cpu"

    def __post_init__(self) -> None:
        resolve_inputs(self.inputs)
        for n in ("iterations", "crop", "base", "batch_size", "n_critic", "eval_every",
                  "eval_frames", "checkpoint_every"):  # fmt: skip
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"TrainConfig.{n} must be an integer >= 1, got {v!r}")
        if self.crop % MULTIPLE:
            raise ValueError(f"TrainConfig.crop must be a multiple of {MULTIPLE}, got {self.crop}")
        for n in ("lr", "lambda_gp", "gp_target", "weight_adv", "weight_l1", "weight_perceptual",
                  "display_exposure", "divergence_limit"):  # fmt: skip
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"TrainConfig.{n} must be a finite number >= 0, got {v!r}")
        if self.lr <= 0:
            raise ValueError(f"TrainConfig.lr must be > 0, got {self.lr}")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ValueError(f"TrainConfig.betas must be two numbers in [0, 1), got {self.betas}")
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        offs = tuple(self.reference_offsets)
        if not offs or any(isinstance(k, bool) or int(k) != k or k < 1 for k in offs):
            raise ValueError(
                "TrainConfig.reference_offsets must be integers >= 1, got "
                f"{self.reference_offsets!r}"
            )
        object.__setattr__(self, "reference_offsets", tuple(int(k) for k in offs))
        k = self.test_reference_offset
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(
                f"TrainConfig.test_reference_offset must be an integer >= 1, got {k!r}"
            )
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"TrainConfig.device must be 'cpu' or 'cuda', got {self.device!r}")
        GeneratorConfig(1, base=self.base, norm=self.norm)
        DiscriminatorConfig(1, base=self.base, norm=self.critic_norm)
        HDRTransform(self.hdr_scale, self.hdr_max)

    @property
    def input_buffers(self) -> tuple[str, ...]:
        return resolve_inputs(self.inputs)

    @classmethod
    def preset(cls, name: Literal["cpu", "paper"], **overrides: Any) -> TrainConfig:
        """A named preset with field overrides.

        - ``cpu``: 128 x 128 crops, base 32, 3000 iterations, no VGG (sized for 2 CPU cores).
        - ``paper``: 256 x 256, base 64, VGG19 perceptual loss (``vgg19_weights`` defaults to
          torchvision's file name ``vgg19-dcbb9e9d.pth`` in the working directory), 20k
          iterations (a GPU job).

        Raises:
            ValueError: unknown preset or field.
        """
        presets = {
            "cpu": dict(crop=128, base=32, iterations=3000, vgg19_weights=None),
            "paper": dict(crop=256, base=64, iterations=20000, vgg19_weights="vgg19-dcbb9e9d.pth"),
        }
        if name not in presets:
            raise ValueError(f"unknown preset {name!r}: {sorted(presets)}")
        known = {f.name for f in fields(cls)}
        bad = sorted(set(overrides) - known)
        if bad:
            raise ValueError(f"unknown TrainConfig field(s) {bad}")
        return cls(**{**presets[name], **overrides})

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["betas"] = list(self.betas)
        d["reference_offsets"] = list(self.reference_offsets)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        bad = sorted(set(d) - known)
        if bad:
            raise ValueError(f"unknown TrainConfig field(s) {bad}")
        d = dict(d)
        for k in ("betas", "reference_offsets"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)


@dataclass(frozen=True)
class TrainResult:
    """What :func:`train` returns.

    Attributes:
        run_dir: the run directory.
        step: iterations done.
        evals: every evaluation so far (dicts: iteration, ssim, mse, l1).
        perceptual: "on: FILE" or "off: REASON".
        seconds: wall time of this call.
    """

    run_dir: Path
    step: int
    evals: list[dict[str, float]]
    perceptual: str
    seconds: float


def _device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("TrainConfig.device is 'cuda' but torch sees no CUDA device here")
    return torch.device(name)


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _eval_frames(
    data: PairData, n: int, reference_offset: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(N, C, h, w) inputs (with the warped reference ``reference_offset`` views earlier when the
    encoding is ``warped``), (N, 3, h, w) linear GI and raw albedo (None without one),
    centre-cropped to multiples of 32."""
    h, w = data.height // MULTIPLE * MULTIPLE, data.width // MULTIPLE * MULTIPLE
    if h == 0 or w == 0:
        raise ValueError(
            f"test images ({data.height} x {data.width}) are smaller than {MULTIPLE} pixels"
        )
    t, l = (data.height - h) // 2, (data.width - w) // 2
    crop = (slice(None, n), slice(None), slice(t, t + h), slice(l, l + w))
    albedo = None if data.albedo is None else data.albedo[crop]
    return data.with_reference(reference_offset, n)[crop], data.gi[crop], albedo


def evaluate(
    gen: torch.nn.Module,
    x: np.ndarray,
    gi: np.ndarray,
    hdr: HDRTransform,
    exposure: float,
    device: torch.device,
    encoding: InputEncoding | None = None,
    albedo: np.ndarray | None = None,
) -> tuple[dict[str, float], np.ndarray]:
    """Mean SSIM / MSE (display scale 0-255) and linear L1 of the generator on test frames.

    ``encoding`` and ``albedo`` ((N, 3, H, W) raw) remodulate a demodulating generator's output.

    Returns:
        (metrics, (H, W, 3) linear prediction of the first frame).
    """
    was = gen.training
    gen.eval()
    s, m, l1, first = [], [], [], None
    with torch.no_grad():
        for k in range(len(x)):
            out = gen(torch.from_numpy(x[k : k + 1]).to(device))
            pred = hdr.decode(out)[0].permute(1, 2, 0).cpu().numpy()
            if encoding is not None and albedo is not None:
                pred = encoding.remodulate(pred, albedo[k].transpose(1, 2, 0))
            truth = gi[k].transpose(1, 2, 0)
            s.append(ssim_metric(pred, truth, exposure))
            m.append(mse_metric(pred, truth, exposure))
            l1.append(float(np.abs(pred - truth).mean()))
            if first is None:
                first = pred
    gen.train(was)
    return {"ssim": float(np.mean(s)), "mse": float(np.mean(m)), "l1": float(np.mean(l1))}, first


def _sample_png(path: Path, pred: np.ndarray, truth: np.ndarray, exposure: float) -> None:
    a, b = to_display(pred, exposure), to_display(truth, exposure)
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).astype(np.uint8)
    write_png(path, np.concatenate([a, b, diff], axis=1))


def _scene_key(scene: Any) -> str | None:
    if scene is None or isinstance(scene, str):
        return scene
    return f"{getattr(scene, 'name', '?')} ({scene.content_hash}, light {scene.light_hash})"


def _write_evals(run_dir: Path, evals: list[dict[str, float]]) -> None:
    write_json(run_dir / "evals.json", evals)
    cols = ["iteration", "ssim", "mse", "l1", "seconds"]
    tmp = run_dir / "evals.csv.tmp"
    with open(tmp, "w", newline="") as f:
        wr = csv.DictWriter(f, cols, extrasaction="ignore")
        wr.writeheader()
        wr.writerows(evals)
    os.replace(tmp, run_dir / "evals.csv")


def train(
    store: Any,
    config: TrainConfig,
    out_dir: str | os.PathLike,
    scene: Any = None,
    resume: bool = False,
    progress: bool = True,
    on_step: Callable[[int, dict[str, float]], None] | None = None,
) -> TrainResult:
    """Train a generator on a store's train path, evaluating on its test path.

    Args:
        store: an open :class:`~icbtool.store.Store` with records tagged ``path`` =
            ``config.train_path`` / ``config.test_path`` (see :func:`icbtool.bake.bake`).
        config: the run's configuration.
        out_dir: the run directory (module doc).
        scene: which scene's records (Scene, hash or name; None: all).
        resume: continue from ``out_dir/checkpoints/last.pt`` (the config must match except
            ``iterations``); without a checkpoint the run starts from scratch.
        progress: show a tqdm progress bar with the losses.
        on_step: called after every generator update with the iteration (1-based) and that
            iteration's losses (``g``, ``l1``, and with a critic ``d``, ``gp``, ``w``, ``g_adv``;
            ``g_p`` with the perceptual term), e.g. to log live loss curves
            (``icbtool_gui.train_job`` writes them to ``losses.csv``).

    Returns:
        The :class:`TrainResult`.

    Raises:
        ValueError: bad data (no records, NaN maps, sizes), a run already in ``out_dir`` without
            ``resume``, a config that differs from the resumed run's, CUDA not available.
        TrainingDivergedError: a loss became non-finite or exceeded ``divergence_limit``.
    """
    t0 = time.perf_counter()
    device = _device(config.device)
    run_dir = Path(out_dir)
    ckpt_dir = run_dir / "checkpoints"
    ckpt_path = ckpt_dir / "last.pt"
    if ckpt_path.exists() and not resume:
        raise ValueError(
            f"{run_dir} already holds a run: resume it (resume=True, --resume) or choose another "
            "output directory"
        )
    cfg_path = run_dir / "config.json"
    if resume and ckpt_path.exists() and cfg_path.exists():
        old = TrainConfig.from_dict(json.loads(cfg_path.read_text())["train_config"])
        if replace(old, iterations=config.iterations) != config:
            diff = {
                k: (v, getattr(config, k))
                for k, v in old.to_dict().items()
                if k != "iterations" and config.to_dict()[k] != v
            }
            raise ValueError(f"cannot resume {run_dir}: config differs (old, new): {diff}")

    hdr = HDRTransform(config.hdr_scale, config.hdr_max)
    paths = {"train": config.train_path, "test": config.test_path}
    inputs = config.input_buffers
    ds_train = Dataset(store, scene, "train", inputs, paths=paths)
    ds_test = Dataset(store, scene, "test", inputs, paths=paths)
    enc = InputEncoding.fit(
        inputs, hdr, list(ds_train), demodulate=config.demodulate, warped=config.warped_reference
    )
    train_data, test_data = PairData(ds_train, enc), PairData(ds_test, enc)
    x_eval, gi_eval, albedo_eval = _eval_frames(
        test_data, config.eval_frames, config.test_reference_offset
    )

    perceptual, p_status = (None, "off: TrainConfig.weight_perceptual is 0")
    if config.weight_perceptual > 0:
        perceptual, p_status = build_perceptual(config.vgg19_weights)
    if perceptual is not None:
        perceptual = perceptual.to(device)

    # -- models, optimisers, RNGs
    torch.manual_seed(config.seed)
    random.seed(config.seed)
    init_gen = torch.Generator().manual_seed(config.seed)
    gp_gen = torch.Generator().manual_seed(config.seed + 1)
    g_cfg = GeneratorConfig(enc.n_channels, 3, config.base, config.norm)
    d_cfg = DiscriminatorConfig(enc.n_channels, 3, config.base, config.critic_norm)
    gen, critic = UNetGenerator(g_cfg), PatchDiscriminator(d_cfg)
    init_weights(gen, init_gen)
    init_weights(critic, init_gen)
    gen.to(device).train()
    critic.to(device).train()
    opt_g = torch.optim.Adam(gen.parameters(), lr=config.lr, betas=config.betas)
    opt_d = torch.optim.Adam(critic.parameters(), lr=config.lr, betas=config.betas)
    sampler = BatchSampler(
        train_data,
        config.batch_size,
        config.crop,
        config.flip,
        config.seed,
        config.reference_offsets,
    )
    step, evals = 0, []
    if resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=device, weights_only=False)
        gen.load_state_dict(ck["generator"])
        critic.load_state_dict(ck["critic"])
        opt_g.load_state_dict(ck["opt_g"])
        opt_d.load_state_dict(ck["opt_d"])
        sampler.load_state_dict(ck["sampler"])
        gp_gen.set_state(ck["gp_rng"])
        torch.set_rng_state(ck["torch_rng"])
        np.random.set_state(ck["numpy_rng"])  # noqa: NPY002 - global state, saved
        random.setstate(ck["python_rng"])
        step, evals = int(ck["step"]), list(ck["evals"])
    saved_step = step

    # -- run directory, config, TensorBoard
    (run_dir / "samples").mkdir(parents=True, exist_ok=True)
    ckpt_dir.mkdir(exist_ok=True)
    writer, tb_status = None, "off"
    try:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run_dir / "tb"), purge_step=step or None)
        tb_status = f"on: {run_dir / 'tb'}"
    except Exception as e:  # noqa: BLE001 - tensorboard missing or broken: say so, go on
        tb_status = f"unavailable: {type(e).__name__}: {e}"
        print(f"TensorBoard event files are not written ({tb_status}); evals.csv/json are.")
    write_json(
        cfg_path,
        {
            "train_config": config.to_dict(),
            "scene": _scene_key(scene),
            "store": str(getattr(store, "root", store)),
            "encoding": enc.to_dict(),
            "generator_config": asdict(g_cfg),
            "critic_config": asdict(d_cfg),
            "perceptual": p_status,
            "tensorboard": tb_status,
            "train_records": train_data.record_ids,
            "test_records": test_data.record_ids,
            "eval_records": test_data.record_ids[: len(x_eval)],
            "run": run_info(),
        },
    )

    def save_checkpoint() -> None:
        nonlocal saved_step
        _atomic_save(
            {
                "step": step,
                "generator": gen.state_dict(),
                "critic": critic.state_dict(),
                "opt_g": opt_g.state_dict(),
                "opt_d": opt_d.state_dict(),
                "sampler": sampler.state_dict(),
                "gp_rng": gp_gen.get_state(),
                "torch_rng": torch.get_rng_state(),
                "numpy_rng": np.random.get_state(),  # noqa: NPY002
                "python_rng": random.getstate(),
                "evals": evals,
            },
            ckpt_path,
        )
        _atomic_save(
            {
                "step": step,
                "generator": gen.state_dict(),
                "generator_config": asdict(g_cfg),
                "encoding": enc.to_dict(),
                "train_config": config.to_dict(),
            },
            run_dir / "generator.pt",
        )
        saved_step = step

    def to_t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a).to(device)

    from tqdm import tqdm

    bar = tqdm(total=config.iterations, initial=step, disable=not progress, desc="gan", unit="it")
    try:
        while step < config.iterations:
            losses: dict[str, float] = {}
            x = y = None
            if config.weight_adv > 0:
                for _ in range(config.n_critic):
                    xb, yb = sampler.next()
                    x, y = to_t(xb), to_t(yb)
                    with torch.no_grad():
                        fake = gen(x)
                    d_real = critic_score(critic, x, y).mean()
                    d_fake = critic_score(critic, x, fake).mean()
                    gp = gradient_penalty(
                        critic, x, y, fake, config.lambda_gp, config.gp_target, gp_gen
                    )
                    d_loss = d_fake - d_real + gp
                    opt_d.zero_grad(set_to_none=True)
                    d_loss.backward()
                    opt_d.step()
                    losses.update(
                        d=float(d_loss.detach()),
                        gp=float(gp.detach()),
                        w=float((d_real - d_fake).detach()),
                    )
            if x is None:
                xb, yb = sampler.next()
                x, y = to_t(xb), to_t(yb)
            fake = gen(x)
            g_l1 = l1_loss(fake, y)
            g_loss = config.weight_l1 * g_l1
            if config.weight_adv > 0:
                g_adv = -critic_score(critic, x, fake).mean()
                g_loss = g_loss + config.weight_adv * g_adv
                losses["g_adv"] = float(g_adv.detach())
            if perceptual is not None:
                g_p = perceptual(fake, y)
                g_loss = g_loss + config.weight_perceptual * g_p
                losses["g_p"] = float(g_p.detach())
            losses.update(g=float(g_loss.detach()), l1=float(g_l1.detach()))
            bad = {
                k: v
                for k, v in losses.items()
                if not math.isfinite(v) or abs(v) > config.divergence_limit
            }
            if bad:
                last = (
                    f"{ckpt_path} (iteration {saved_step})"
                    if ckpt_path.exists()
                    else "none (no checkpoint was written yet)"
                )
                raise TrainingDivergedError(
                    f"training diverged at iteration {step + 1}: losses {bad} are non-finite or "
                    f"beyond divergence_limit={config.divergence_limit:g}. The last good "
                    f"checkpoint is kept: {last}. Lower TrainConfig.lr or check the data."
                )
            opt_g.zero_grad(set_to_none=True)
            g_loss.backward()
            opt_g.step()
            step += 1
            bar.update(1)
            if on_step is not None:
                on_step(step, dict(losses))
            bar.set_postfix({k: f"{v:.3g}" for k, v in losses.items()})
            if writer is not None:
                for k, v in losses.items():
                    writer.add_scalar(f"loss/{k}", v, step)
            if step % config.eval_every == 0 or step == config.iterations:
                m, first = evaluate(
                    gen, x_eval, gi_eval, hdr, config.display_exposure, device, enc, albedo_eval
                )
                row = {"iteration": step, **m, "seconds": time.perf_counter() - t0}
                evals.append(row)
                _write_evals(run_dir, evals)
                _sample_png(
                    run_dir / "samples" / f"iter_{step:06d}.png",
                    first,
                    gi_eval[0].transpose(1, 2, 0),
                    config.display_exposure,
                )
                if writer is not None:
                    for k, v in m.items():
                        writer.add_scalar(f"test/{k}", v, step)
                bar.write(f"iteration {step}: test SSIM {m['ssim']:.4f}  MSE {m['mse']:.2f}")
            if step % config.checkpoint_every == 0 or step == config.iterations:
                save_checkpoint()
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    if evals:
        _write_evals(run_dir, evals)
    return TrainResult(run_dir, step, evals, p_status, time.perf_counter() - t0)


__all__ = ["TrainConfig", "TrainResult", "TrainingDivergedError", "evaluate", "train"]
