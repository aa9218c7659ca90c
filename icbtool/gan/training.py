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

import copy
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
    ssim_loss,
)
from icbtool.gan.models import (
    MULTIPLE,
    DiscriminatorConfig,
    GeneratorConfig,
    PatchDiscriminator,
    UNetGenerator,
    init_weights,
)
from icbtool.metrics import mse as mse_metric
from icbtool.metrics import ssim as ssim_metric
from icbtool.provenance import run_info, write_json
from icbtool.runs import atomic_save, sample_png, scene_key, write_evals
from icbtool.store.dataset import Dataset


class TrainingDivergedError(RuntimeError):
    """A loss became NaN/Inf or exceeded ``TrainConfig.divergence_limit``; training stopped and
    the last good checkpoint is kept."""


#: The columns of a GAN run's evals.csv.
_EVAL_COLUMNS = ("iteration", "ssim", "mse", "l1", "seconds", "views")


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
        weight_ssim: weight of an SSIM term, 1 - SSIM of output and target in the network's
            range (our addition: structure without pretrained weights; 0: off).
        vgg19_weights: local torchvision VGG19 state-dict file; None or missing: L_p off + warning.
        hdr_scale, hdr_max: the :class:`~icbtool.gan.hdr.HDRTransform` of DL and GI.
        demodulate: learn the indirect irradiance GI / albedo and multiply the output by the
            albedo (:class:`~icbtool.gan.data.InputEncoding`; our addition, on in the cpu
            preset, off in the paper presets).
        warped_reference: the generator also reads the GI of another view of the path warped to
            this view and its hole mask (:class:`~icbtool.gan.data.WarpedReferences`; our
            addition, off in the presets): what a client holds when it warps a cached reference.
        reference_gate: with ``warped_reference``, the generator also outputs a per-pixel gate
            and blends the warped reference with what it generates (``GeneratorConfig``
            ``reference_gate``; our addition, off in the presets): where the reference saw, the
            network only has to say how far to trust it.
        weight_generated: with ``reference_gate``, the L_c and SSIM terms are also applied with
            this weight to the generated image before the blend, so that it stays a whole
            prediction (otherwise only the holes and the distrusted pixels would train it).
        reference_dropout: with ``warped_reference``, the probability that a training sample's
            reference is replaced by an empty one (all holes), so that the generator also
            learns to generate without a reference, which is what it does in the holes
            (:class:`~icbtool.gan.data.BatchSampler`; our addition; 0: off).
        reference_offsets: training draws the reference this many views away (uniformly from
            these, earlier or later along the train path).
        test_reference_offset: the test frames' reference is this many views earlier.
        train_path, test_path: the camera-path tags of the two splits in the store; several
            comma-separated tags ("train,cover") train on the records of each.
        full_res_skip: the generator's last level also sees the input at full resolution
            (:class:`~icbtool.gan.models.GeneratorConfig`; our addition).
        lr_schedule: "constant", or "cosine": the learning rate falls from ``lr`` to
            ``lr * lr_final`` along a half cosine over ``iterations`` (a resume that raises
            ``iterations`` stretches the rest of the schedule; one with the same ``iterations``
            is bit-exact).
        lr_final: the cosine schedule's last learning rate as a fraction of ``lr``.
        position_octaves: the generator appends Fourier features (sin, cos at ``2^k pi``,
            k < ``position_octaves``) of its encoded world-position input (our addition; needs
            "position" among the inputs; 0: off; :class:`~icbtool.gan.models.GeneratorConfig`).
        position_resolution, head_kernel, skip_features, input_reduce, top_width: the
            generator's cost at the client (:class:`~icbtool.gan.models.GeneratorConfig`
            ``fourier_resolution``, ``head_kernel``, ``skip_features``, ``reduce``,
            ``top_width``; benchmarks.gan_speed): the Fourier features at "full" or "half"
            resolution, the full-resolution head's kernel (3 or 1), whether the
            full-resolution skip carries the full-resolution features, a 1 x 1 reduction of the
            input to this many channels (0: none), the last level's width (0: ``base``). The
            defaults are the network of the first runs (saved configs without these fields
            load as that).
        ema: decay of an exponential moving average of the generator's weights, which is then
            what is evaluated and saved (our addition; 0: off, e.g. 0.999; at iteration t the
            decay is min(ema, (1 + t) / (10 + t)), so early averages forget the initial weights).
        flip: random horizontal flips (paired augmentation).
        eval_every: evaluate (and write a sample) every this many iterations (and at the end).
        eval_frames: at most this many test frames per evaluation (the first ones; 0: all).
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
    weight_ssim: float = 0.0
    vgg19_weights: str | None = None
    hdr_scale: float = 0.25
    hdr_max: float = 64.0
    demodulate: bool = False
    warped_reference: bool = False
    reference_gate: bool = False
    weight_generated: float = 1.0
    reference_dropout: float = 0.0
    reference_offsets: tuple[int, ...] = (1, 2, 3, 4, 6)
    test_reference_offset: int = 1
    train_path: str = "train"
    test_path: str = "test"
    flip: bool = True
    full_res_skip: bool = False
    lr_schedule: Literal["constant", "cosine"] = "constant"
    lr_final: float = 0.05
    position_octaves: int = 0
    position_resolution: Literal["full", "half"] = "full"
    head_kernel: int = 3
    skip_features: bool = True
    input_reduce: int = 0
    top_width: int = 0
    ema: float = 0.0
    eval_every: int = 250
    eval_frames: int = 0
    checkpoint_every: int = 250
    display_exposure: float = 1.0
    divergence_limit: float = 1e6
    seed: int = 0
    device: Literal["cpu", "cuda"] = "cpu"

    def __post_init__(self) -> None:
        resolve_inputs(self.inputs)
        for n in ("iterations", "crop", "base", "batch_size", "n_critic", "eval_every",
                  "eval_frames", "checkpoint_every", "position_octaves", "input_reduce",
                  "top_width"):  # fmt: skip
            zero_ok = ("eval_frames", "position_octaves", "input_reduce", "top_width")
            v, lo = getattr(self, n), 0 if n in zero_ok else 1
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"TrainConfig.{n} must be an integer >= {lo}, got {v!r}")
        if self.crop % MULTIPLE:
            raise ValueError(f"TrainConfig.crop must be a multiple of {MULTIPLE}, got {self.crop}")
        for n in ("lr", "lambda_gp", "gp_target", "weight_adv", "weight_l1", "weight_perceptual",
                  "weight_ssim", "weight_generated", "display_exposure",
                  "divergence_limit"):  # fmt: skip
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
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(
                f"TrainConfig.lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}"
            )
        for n in ("lr_final", "ema", "reference_dropout"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and 0 <= v < 1) or isinstance(v, bool):
                raise ValueError(f"TrainConfig.{n} must be a number in [0, 1), got {v!r}")
        if self.reference_gate and not self.warped_reference:
            raise ValueError("TrainConfig.reference_gate needs warped_reference on")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"TrainConfig.device must be 'cpu' or 'cuda', got {self.device!r}")
        self.generator_config(
            5 if self.reference_gate else 1,
            (0, 1) if self.position_octaves else None,
            (1, 5) if self.reference_gate else None,
        )
        DiscriminatorConfig(1, base=self.base, norm=self.critic_norm)
        HDRTransform(self.hdr_scale, self.hdr_max)

    def generator_config(
        self,
        in_channels: int,
        position: tuple[int, int] | None,
        reference: tuple[int, int] | None = None,
    ) -> GeneratorConfig:
        """The generator of this configuration for ``in_channels`` encoded input channels whose
        world positions are the channels ``position`` (start, stop), or None, and whose warped
        reference and its holes are the channels ``reference`` (start, stop; used by
        ``reference_gate``)."""
        return GeneratorConfig(
            in_channels, 3, self.base, self.norm, full_res_skip=self.full_res_skip,
            fourier_channels=position if self.position_octaves else None,
            fourier_octaves=self.position_octaves,
            fourier_resolution=self.position_resolution, head_kernel=self.head_kernel,
            skip_features=self.skip_features, reduce=self.input_reduce, top_width=self.top_width,
            reference_gate=reference if self.reference_gate else None,
        )  # fmt: skip

    @property
    def input_buffers(self) -> tuple[str, ...]:
        return resolve_inputs(self.inputs)

    @classmethod
    def preset(cls, name: Literal["cpu", "paper-cpu", "paper"], **overrides: Any) -> TrainConfig:
        """A named preset with field overrides.

        - ``cpu``: the recipe measured best on 2 CPU cores (docs/gan.md; docs/benchmarks.md,
          "Learned GI"):
          configuration J (albedo, DL, world normals, positions) with 6 octaves of Fourier
          features of the position computed at half resolution, demodulated targets, the
          full-resolution skip with a 1 x 1 head (the client's 256 x 256 frame budget:
          benchmarks.gan_speed), width 8,
          L1 + SSIM without the critic, a constant learning rate of 2e-4 (measured better than a
          cosine decay over 3000 iterations), weight averaging,
          64-pixel crops in batches of 8, 20000 iterations (the narrow network needs several
          times the iterations of the width-16 one for the same SSIM; each costs about a third).
          Give it the coverage views too (``train_path="train,cover"``, benchmarks.gan_coverage).
        - ``paper-cpu``: the paper's design at CPU size (configuration I, L_a + 100 L_c with the
          WGAN-GP critic, base 32, 128-pixel crops, no VGG): what ``cpu`` was before.
        - ``paper``: 256 x 256, base 64, VGG19 perceptual loss (``vgg19_weights`` defaults to
          torchvision's file name ``vgg19-dcbb9e9d.pth`` in the working directory), 20k
          iterations (a GPU job).

        Raises:
            ValueError: unknown preset or field.
        """
        presets = {
            "cpu": dict(
                inputs="J",
                demodulate=True,
                full_res_skip=True,
                position_octaves=6,
                position_resolution="half",
                head_kernel=1,
                base=8,
                crop=64,
                batch_size=8,
                weight_adv=0.0,
                weight_l1=100.0,
                weight_ssim=20.0,
                weight_perceptual=0.0,
                lr=2e-4,
                lr_schedule="constant",
                ema=0.999,
                hdr_scale=0.05,
                hdr_max=4.0,
                iterations=20000,
                vgg19_weights=None,
            ),  # fmt: skip
            "paper-cpu": dict(crop=128, base=32, iterations=3000, vgg19_weights=None),
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
        evals: every evaluation so far (dicts: iteration, ssim, mse, l1, seconds, views).
        perceptual: "on: FILE" or "off: REASON".
        seconds: wall time of this call.
        eval_views: test views each evaluation scores.
    """

    run_dir: Path
    step: int
    evals: list[dict[str, float]]
    perceptual: str
    seconds: float
    eval_views: int = 0


def _device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("TrainConfig.device is 'cuda' but torch sees no CUDA device here")
    return torch.device(name)


def _eval_frames(
    data: PairData, n: int, reference_offset: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(N, C, h, w) inputs (with the warped reference ``reference_offset`` views earlier when the
    encoding is ``warped``), (N, 3, h, w) linear GI and raw albedo (None without one),
    centre-cropped to multiples of 32. ``n`` = 0: every frame."""
    h, w = data.height // MULTIPLE * MULTIPLE, data.width // MULTIPLE * MULTIPLE
    if h == 0 or w == 0:
        raise ValueError(
            f"test images ({data.height} x {data.width}) are smaller than {MULTIPLE} pixels"
        )
    n = len(data) if n == 0 else min(n, len(data))
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
        (metrics, (H, W, 3) linear prediction of the first frame); metrics hold ``views``, the
        number of frames scored.
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
    metrics = {
        "ssim": float(np.mean(s)),
        "mse": float(np.mean(m)),
        "l1": float(np.mean(l1)),
        "views": len(x),
    }
    return metrics, first


def learning_rate(config: TrainConfig, step: int) -> float:
    """The learning rate of update ``step`` (0-based) under ``config.lr_schedule``."""
    if config.lr_schedule == "constant":
        return config.lr
    t = min(step / max(config.iterations, 1), 1.0)
    f = config.lr_final + (1 - config.lr_final) * 0.5 * (1 + math.cos(math.pi * t))
    return config.lr * f


def _check_resumable(run_dir: Path, config: TrainConfig) -> None:
    """A run's config may change only in ``iterations`` when resumed."""
    cfg_path = run_dir / "config.json"
    if not cfg_path.exists():
        return
    old_d = json.loads(cfg_path.read_text())["train_config"]
    # fields added after a run was started take their defaults
    old = TrainConfig.from_dict({k: v for k, v in old_d.items() if k in config.to_dict()})
    if replace(old, iterations=config.iterations) != config:
        diff = {
            k: (v, getattr(config, k))
            for k, v in old.to_dict().items()
            if k != "iterations" and config.to_dict()[k] != v
        }
        raise ValueError(f"cannot resume {run_dir}: config differs (old, new): {diff}")


class TrainingRun:
    """The state of one training run: data, models, optimisers, RNGs, history (pix2pix's model
    lifecycle: :meth:`critic_step`, :meth:`generator_step`, :meth:`evaluate`, :meth:`save`)."""

    def __init__(self, store: Any, config: TrainConfig, run_dir: Path, scene: Any) -> None:
        self.config, self.run_dir = config, run_dir
        self.device = _device(config.device)
        self.hdr = HDRTransform(config.hdr_scale, config.hdr_max)
        self.ckpt_path = run_dir / "checkpoints" / "last.pt"
        self._load_data(store, scene)
        self._build_models()
        self.step, self.evals, self.elapsed0, self.saved_step = 0, [], 0.0, 0

    # -- set-up
    def _load_data(self, store: Any, scene: Any) -> None:
        c = self.config
        paths = {"train": c.train_path, "test": c.test_path}
        inputs = c.input_buffers
        ds_train = Dataset(store, scene, "train", inputs, paths=paths)
        ds_test = Dataset(store, scene, "test", inputs, paths=paths)
        self.enc = InputEncoding.fit(
            inputs, self.hdr, list(ds_train), demodulate=c.demodulate, warped=c.warped_reference
        )
        self.train_data = PairData(ds_train, self.enc)
        self.test_data = PairData(ds_test, self.enc)
        self.x_eval, self.gi_eval, self.albedo_eval = _eval_frames(
            self.test_data, c.eval_frames, c.test_reference_offset
        )
        self.sampler = BatchSampler(
            self.train_data, c.batch_size, c.crop, c.flip, c.seed, c.reference_offsets,
            c.reference_dropout,
        )  # fmt: skip

    def _build_models(self) -> None:
        c, dev = self.config, self.device
        torch.manual_seed(c.seed)
        random.seed(c.seed)
        init_gen = torch.Generator().manual_seed(c.seed)
        self.gp_gen = torch.Generator().manual_seed(c.seed + 1)
        pos = self.enc.channel_slices().get("position")
        if c.position_octaves and pos is None:
            raise ValueError(
                f"TrainConfig.position_octaves needs 'position' among the inputs, got "
                f"{self.enc.inputs}: add it, or set position_octaves=0 (--position-octaves 0)"
            )
        sl = self.enc.channel_slices()
        ref = (sl["warped_gi"].start, sl["warp_holes"].stop) if c.reference_gate else None
        self.g_cfg = c.generator_config(
            self.enc.n_channels, None if pos is None else (pos.start, pos.stop), ref
        )
        self.d_cfg = DiscriminatorConfig(self.enc.n_channels, 3, c.base, c.critic_norm)
        self.gen, self.critic = UNetGenerator(self.g_cfg), PatchDiscriminator(self.d_cfg)
        init_weights(self.gen, init_gen)
        init_weights(self.critic, init_gen)
        self.gen.to(dev).train()
        self.critic.to(dev).train()
        self.ema = None
        if c.ema > 0:
            self.ema = copy.deepcopy(self.gen).eval()
            for p in self.ema.parameters():
                p.requires_grad_(False)
        self.opt_g = torch.optim.Adam(self.gen.parameters(), lr=c.lr, betas=c.betas)
        self.opt_d = torch.optim.Adam(self.critic.parameters(), lr=c.lr, betas=c.betas)
        self.perceptual, self.p_status = None, "off: TrainConfig.weight_perceptual is 0"
        if c.weight_perceptual > 0:
            self.perceptual, self.p_status = build_perceptual(c.vgg19_weights)
        if self.perceptual is not None:
            self.perceptual = self.perceptual.to(dev)

    def restore(self) -> None:
        """Everything from the last checkpoint (module doc: resuming is bit-exact)."""
        ck = torch.load(self.ckpt_path, map_location=self.device, weights_only=False)
        self.gen.load_state_dict(ck["generator"])
        self.critic.load_state_dict(ck["critic"])
        if self.ema is not None:
            self.ema.load_state_dict(ck["generator_ema"])
        self.opt_g.load_state_dict(ck["opt_g"])
        self.opt_d.load_state_dict(ck["opt_d"])
        self.sampler.load_state_dict(ck["sampler"])
        self.gp_gen.set_state(ck["gp_rng"])
        torch.set_rng_state(ck["torch_rng"])
        np.random.set_state(ck["numpy_rng"])  # noqa: NPY002 - global state, saved
        random.setstate(ck["python_rng"])
        self.step, self.evals = int(ck["step"]), list(ck["evals"])
        self.saved_step = self.step
        last = self.evals[-1]["seconds"] if self.evals else 0.0
        self.elapsed0 = float(ck.get("elapsed", last))

    def write_config(self, store: Any, scene: Any, tb_status: str) -> None:
        write_json(
            self.run_dir / "config.json",
            {
                "train_config": self.config.to_dict(),
                "scene": scene_key(scene),
                "store": str(getattr(store, "root", store)),
                "encoding": self.enc.to_dict(),
                "generator_config": asdict(self.g_cfg),
                "critic_config": asdict(self.d_cfg),
                "perceptual": self.p_status,
                "tensorboard": tb_status,
                "train_records": self.train_data.record_ids,
                "test_records": self.test_data.record_ids,
                "eval_records": self.test_data.record_ids[: len(self.x_eval)],
                "run": run_info(),
            },
        )

    # -- one iteration
    def _batch(self) -> tuple[torch.Tensor, torch.Tensor]:
        xb, yb = self.sampler.next()
        return torch.from_numpy(xb).to(self.device), torch.from_numpy(yb).to(self.device)

    def critic_step(self) -> tuple[dict[str, float], torch.Tensor, torch.Tensor]:
        """``n_critic`` WGAN-GP critic updates; returns their losses and the last batch."""
        c, losses = self.config, {}
        for _ in range(c.n_critic):
            x, y = self._batch()
            with torch.no_grad():
                fake = self.gen(x)
            d_real = critic_score(self.critic, x, y).mean()
            d_fake = critic_score(self.critic, x, fake).mean()
            gp = gradient_penalty(self.critic, x, y, fake, c.lambda_gp, c.gp_target, self.gp_gen)
            d_loss = d_fake - d_real + gp
            self.opt_d.zero_grad(set_to_none=True)
            d_loss.backward()
            self.opt_d.step()
            losses.update(
                d=float(d_loss.detach()), gp=float(gp.detach()), w=float((d_real - d_fake).detach())
            )
        return losses, x, y

    def generator_loss(
        self, x: torch.Tensor, y: torch.Tensor, losses: dict[str, float]
    ) -> torch.Tensor:
        c = self.config
        fake, generated, _ = self.gen.parts(x)
        g_l1 = l1_loss(fake, y)
        g_loss = c.weight_l1 * g_l1
        if generated is not fake and c.weight_generated > 0:
            g_gen = c.weight_l1 * l1_loss(generated, y)
            if c.weight_ssim > 0:
                g_gen = g_gen + c.weight_ssim * ssim_loss(generated, y)
            g_loss = g_loss + c.weight_generated * g_gen
            losses["g_generated"] = float(g_gen.detach())
        if c.weight_adv > 0:
            g_adv = -critic_score(self.critic, x, fake).mean()
            g_loss = g_loss + c.weight_adv * g_adv
            losses["g_adv"] = float(g_adv.detach())
        if self.perceptual is not None:
            g_p = self.perceptual(fake, y)
            g_loss = g_loss + c.weight_perceptual * g_p
            losses["g_p"] = float(g_p.detach())
        if c.weight_ssim > 0:
            g_s = ssim_loss(fake, y)
            g_loss = g_loss + c.weight_ssim * g_s
            losses["g_ssim"] = float(g_s.detach())
        losses.update(g=float(g_loss.detach()), l1=float(g_l1.detach()))
        return g_loss

    def check_finite(self, losses: dict[str, float]) -> None:
        limit = self.config.divergence_limit
        bad = {k: v for k, v in losses.items() if not math.isfinite(v) or abs(v) > limit}
        if bad:
            last = (
                f"{self.ckpt_path} (iteration {self.saved_step})"
                if self.ckpt_path.exists()
                else "none (no checkpoint was written yet)"
            )
            raise TrainingDivergedError(
                f"training diverged at iteration {self.step + 1}: losses {bad} are non-finite or "
                f"beyond divergence_limit={limit:g}. The last good checkpoint is kept: {last}. "
                "Lower TrainConfig.lr or check the data."
            )

    def iteration(self) -> dict[str, float]:
        """One generator update (after ``n_critic`` critic updates when L_a is on)."""
        c = self.config
        lr = learning_rate(c, self.step)
        for opt in (self.opt_g, self.opt_d):
            for g in opt.param_groups:
                g["lr"] = lr
        losses: dict[str, float] = {}
        if c.weight_adv > 0:
            losses, x, y = self.critic_step()
        else:
            x, y = self._batch()
        g_loss = self.generator_loss(x, y, losses)
        self.check_finite(losses)
        self.opt_g.zero_grad(set_to_none=True)
        g_loss.backward()
        self.opt_g.step()
        if self.ema is not None:
            self._update_ema()
        self.step += 1
        return losses

    @torch.no_grad()
    def _update_ema(self) -> None:
        # warm-up: early averages would otherwise hold the random initial weights for ~1/(1-ema)
        # iterations
        d = min(self.config.ema, (1 + self.step) / (10 + self.step))
        for pe, p in zip(self.ema.parameters(), self.gen.parameters()):
            pe.mul_(d).add_(p.detach(), alpha=1 - d)
        for be, b in zip(self.ema.buffers(), self.gen.buffers()):
            be.copy_(b)

    @property
    def model(self) -> torch.nn.Module:
        """The generator that is evaluated and saved (the weight average when ``ema`` > 0)."""
        return self.gen if self.ema is None else self.ema

    # -- evaluation and checkpoints
    def evaluate(self, t0: float) -> dict[str, float]:
        c = self.config
        m, first = evaluate(
            self.model, self.x_eval, self.gi_eval, self.hdr, c.display_exposure, self.device,
            self.enc, self.albedo_eval,
        )  # fmt: skip
        row = {
            "iteration": self.step,
            **m,
            "seconds": self.elapsed0 + time.perf_counter() - t0,
        }
        self.evals.append(row)
        write_evals(self.run_dir, self.evals, _EVAL_COLUMNS)
        sample_png(
            self.run_dir / "samples" / f"iter_{self.step:06d}.png",
            first,
            self.gi_eval[0].transpose(1, 2, 0),
            c.display_exposure,
        )
        return row

    def save(self, t0: float) -> None:
        """Checkpoint (everything, to resume) and ``generator.pt`` (to generate), atomically."""
        g_state = self.model.state_dict()
        ck = {
            "step": self.step,
            "generator": self.gen.state_dict(),
            "critic": self.critic.state_dict(),
            "opt_g": self.opt_g.state_dict(),
            "opt_d": self.opt_d.state_dict(),
            "sampler": self.sampler.state_dict(),
            "gp_rng": self.gp_gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "numpy_rng": np.random.get_state(),  # noqa: NPY002
            "python_rng": random.getstate(),
            "evals": self.evals,
            "elapsed": self.elapsed0 + time.perf_counter() - t0,
        }
        if self.ema is not None:
            ck["generator_ema"] = g_state
        atomic_save(ck, self.ckpt_path)
        atomic_save(
            {
                "step": self.step,
                "generator": g_state,
                "generator_config": asdict(self.g_cfg),
                "encoding": self.enc.to_dict(),
                "train_config": self.config.to_dict(),
            },
            self.run_dir / "generator.pt",
        )
        self.saved_step = self.step


def _open_tensorboard(run_dir: Path, step: int) -> tuple[Any, str]:
    """A SummaryWriter continuing at ``step`` (events after the checkpoint are dropped, the
    checkpoint's own step kept), or None and why not."""
    try:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run_dir / "tb"), purge_step=step + 1 if step else None)
        return writer, f"on: {run_dir / 'tb'}"
    except Exception as e:  # noqa: BLE001 - tensorboard missing or broken: say so, go on
        status = f"unavailable: {type(e).__name__}: {e}"
        print(f"TensorBoard event files are not written ({status}); evals.csv/json are.")
        return None, status


def train(
    store: Any,
    config: TrainConfig,
    out_dir: str | os.PathLike,
    scene: Any = None,
    resume: bool = False,
    progress: bool = True,
    on_step: Callable[[int, dict[str, float]], bool | None] | None = None,
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
            ``g_p`` with the perceptual term, ``g_ssim`` with the SSIM term), e.g. to log live
            loss curves (``icbtool_gui.train_job`` writes them to ``losses.csv``). Returning
            True stops the training after that iteration, with a checkpoint of it (the
            desktop app's Stop and closing window keep every iteration done).

    Returns:
        The :class:`TrainResult`.

    Raises:
        ValueError: bad data (no records, NaN maps, sizes), a run already in ``out_dir`` without
            ``resume``, a config that differs from the resumed run's, CUDA not available.
        TrainingDivergedError: a loss became non-finite or exceeded ``divergence_limit``.
    """
    t0 = time.perf_counter()
    run_dir = Path(out_dir)
    ckpt_path = run_dir / "checkpoints" / "last.pt"
    if ckpt_path.exists() and not resume:
        raise ValueError(
            f"{run_dir} already holds a run: resume it (resume=True, --resume) or choose another "
            "output directory"
        )
    if resume and ckpt_path.exists():
        _check_resumable(run_dir, config)
    run = TrainingRun(store, config, run_dir, scene)
    if resume and ckpt_path.exists():
        run.restore()
    (run_dir / "samples").mkdir(parents=True, exist_ok=True)
    ckpt_path.parent.mkdir(exist_ok=True)
    writer, tb_status = _open_tensorboard(run_dir, run.step)
    run.write_config(store, scene, tb_status)
    n_views = len(run.x_eval)

    from tqdm import tqdm

    bar = tqdm(
        total=config.iterations, initial=run.step, disable=not progress, desc="gan", unit="it"
    )
    try:
        while run.step < config.iterations:
            losses = run.iteration()
            step = run.step
            bar.update(1)
            stop = on_step is not None and bool(on_step(step, dict(losses)))
            bar.set_postfix({k: f"{v:.3g}" for k, v in losses.items()})
            if writer is not None:
                for k, v in losses.items():
                    writer.add_scalar(f"loss/{k}", v, step)
            if step % config.eval_every == 0 or step == config.iterations:
                row = run.evaluate(t0)
                if writer is not None:
                    for k in ("ssim", "mse", "l1"):
                        writer.add_scalar(f"test/{k}", row[k], step)
                bar.write(
                    f"iteration {step}: test SSIM {row['ssim']:.4f}  MSE {row['mse']:.2f} "
                    f"(mean of {n_views} test views)"
                )
            if step % config.checkpoint_every == 0 or step == config.iterations or stop:
                run.save(t0)
            if stop:
                break
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    if run.evals:
        write_evals(run_dir, run.evals, _EVAL_COLUMNS)
    return TrainResult(
        run_dir, run.step, run.evals, run.p_status, time.perf_counter() - t0, n_views
    )


__all__ = [
    "TrainConfig",
    "TrainResult",
    "TrainingDivergedError",
    "TrainingRun",
    "evaluate",
    "learning_rate",
    "train",
]
