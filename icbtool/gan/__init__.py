"""GAN pre-renderer (docs/design.md section 5): the cloud trains a cGAN on its CRT-buffers, the
client generates its GI maps from its WRT-buffer.

``import icbtool.gan`` does not import torch: the names below are loaded from their modules on
first access (``icb.gan.train``, ``icb.gan.Generator`` ...).

Modules:
    hdr: the invertible linear HDR <-> [-1, 1] transform (numpy and torch).
    models: U-Net generator and PatchGAN critic (torch).
    losses: WGAN-GP, L1 and VGG19 perceptual losses (torch).
    data: training pairs from a store, input encoding, paired augmentation.
    training: ``TrainConfig`` presets and the resumable training loop (:func:`train`).
    generate: ``Generator.load(run_dir)``, ``generate(buffers)``, ONNX export.
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES: dict[str, str] = {
    "HDRTransform": "hdr",
    "GeneratorConfig": "models",
    "DiscriminatorConfig": "models",
    "UNetGenerator": "models",
    "PatchDiscriminator": "models",
    "gradient_penalty": "losses",
    "PerceptualLoss": "losses",
    "VGG19Features": "losses",
    "load_vgg19_features": "losses",
    "InputEncoding": "data",
    "PairData": "data",
    "BatchSampler": "data",
    "TrainConfig": "training",
    "TrainResult": "training",
    "TrainingDivergedError": "training",
    "train": "training",
    "Generator": "generate",
}
_MODULES = ("hdr", "models", "losses", "data", "training", "generate")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'icbtool.gan' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_NAMES, *_MODULES])
