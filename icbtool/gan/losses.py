"""Losses of docs/design.md section 5: L = w_a L_a + w_c L_c + w_p L_p. Torch tensors are BCHW.

- L_a: conditional WGAN-GP. The critic's score of a sample is the mean of its patch scores;
  critic loss = E[D(c, fake)] - E[D(c, real)] + lambda_gp * E[(||grad_x D(c, x_hat)||_2 - k)^2]
  on interpolates x_hat = eps real + (1 - eps) fake (eps ~ U[0, 1] per sample, k = 1);
  generator loss = -E[D(c, fake)].
- L_c: per-pixel L1, mean over all elements.
- L_p: for each chosen VGG19 layer i (taken after its ReLU), ||phi_i(y) - phi_i(y_hat)||_2^2 /
  (C_i H_i W_i), averaged over the batch and summed over the layers (Johnson et al. 2016). Images
  enter VGG as (y + 1) / 2 (the HDR transform's [-1, 1] mapped to [0, 1]) with ImageNet's mean/std.

VGG19 weights are never downloaded and never random: :func:`load_vgg19_features` reads a local
file in torchvision's state-dict format (``features.N.weight`` / ``features.N.bias``, e.g.
``vgg19-dcbb9e9d.pth``); torchvision itself is not needed.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import torch
from torch import nn

#: torchvision's VGG19 ("E") feature layout: numbers are conv widths, "M" a 2x2 max pool.
VGG19_LAYOUT: tuple[int | str, ...] = (
    64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M",
    512, 512, 512, 512, "M", 512, 512, 512, 512, "M",
)  # fmt: skip
#: Default perceptual layers: indices in ``features`` of relu1_1, relu2_1, relu3_1, relu4_1,
#: relu5_1 (after the activation).
VGG19_RELU_X_1: tuple[int, ...] = (1, 6, 11, 20, 29)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

#: The text of the warning when the perceptual term is off (tests match it).
PERCEPTUAL_OFF_WARNING = (
    "perceptual loss L_p is OFF: no VGG19 weights ({reason}). Set TrainConfig.vgg19_weights "
    "(CLI: --vgg19-weights) to a local torchvision state-dict file such as vgg19-dcbb9e9d.pth; "
    "random VGG weights are never used. The run's config.json records this."
)


def critic_score(critic: nn.Module, cond: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """(B,) score per sample: the mean of the critic's patch scores."""
    out = critic(cond, image)
    return out.reshape(out.shape[0], -1).mean(dim=1)


def gradient_penalty(
    critic: nn.Module,
    cond: torch.Tensor,
    real: torch.Tensor,
    fake: torch.Tensor,
    lambda_gp: float = 10.0,
    k: float = 1.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """WGAN-GP penalty lambda_gp * E[(||grad D(c, x_hat)||_2 - k)^2] (module doc).

    Args:
        critic: ``critic(cond, image)`` -> (B, 1, h, w) patch scores (or (B, 1, 1, 1)).
        cond: (B, C, H, W) input maps.
        real, fake: (B, 3, H, W) images (``fake`` is detached here).
        lambda_gp: weight.
        k: target gradient norm.
        generator: RNG of the interpolation weights (seeded training).

    Returns:
        Scalar tensor (differentiable w.r.t. the critic's parameters).
    """
    if real.shape != fake.shape:
        raise ValueError(f"gradient_penalty: real {tuple(real.shape)} != fake {tuple(fake.shape)}")
    b = real.shape[0]
    eps = torch.rand((b, 1, 1, 1), generator=generator, dtype=real.dtype, device="cpu")
    eps = eps.to(real.device)
    x_hat = (eps * real.detach() + (1.0 - eps) * fake.detach()).requires_grad_(True)
    score = critic_score(critic, cond, x_hat)
    (grad,) = torch.autograd.grad(score.sum(), x_hat, create_graph=True)
    norm = grad.reshape(b, -1).norm(2, dim=1)
    return lambda_gp * ((norm - k) ** 2).mean()


def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference over all elements (L_c)."""
    if pred.shape != target.shape:
        raise ValueError(f"l1_loss: pred {tuple(pred.shape)} != target {tuple(target.shape)}")
    return (pred - target).abs().mean()


def ssim_loss(pred: torch.Tensor, target: torch.Tensor, window: int = 7) -> torch.Tensor:
    """1 - mean SSIM of two (B, C, H, W) maps in the HDR transform's [-1, 1] range (mapped to
    [0, 1]; kornia's SSIM, Gaussian window ``window``, "same" padding). Our addition to the paper's
    loss: a structure term that needs no pretrained weights (docs/gan.md, "Losses")."""
    import kornia

    if pred.shape != target.shape:
        raise ValueError(f"ssim_loss: pred {tuple(pred.shape)} != target {tuple(target.shape)}")
    s = kornia.metrics.ssim((pred + 1) / 2, (target + 1) / 2, window, max_val=1.0)
    return 1 - s.mean()


class VGG19Features(nn.Sequential):
    """torchvision's ``vgg19().features`` rebuilt layer by layer (same indices, same state-dict
    keys without the ``features.`` prefix), with untrained weights until loaded."""

    def __init__(self) -> None:
        layers: list[nn.Module] = []
        c = 3
        for v in VGG19_LAYOUT:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, int(v), 3, padding=1), nn.ReLU(inplace=False)]
                c = int(v)
        super().__init__(*layers)


def load_vgg19_features(path: str | os.PathLike) -> VGG19Features:
    """VGG19 feature layers with the weights of a torchvision state-dict file.

    Args:
        path: a ``.pth`` holding torchvision's ``vgg19`` state dict (``features.N.weight`` ...;
            the classifier keys are ignored).

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a VGG19 state dict (missing or mis-shaped feature keys).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"VGG19 weights file {str(p)!r} does not exist")
    try:
        sd = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling problem is a bad file
        msg = f"VGG19 weights file {str(p)!r} cannot be read as a state dict: {e}"
        raise ValueError(msg) from e
    if not isinstance(sd, dict):
        raise ValueError(f"VGG19 weights file {str(p)!r} holds a {type(sd).__name__}, not a dict")
    net = VGG19Features()
    want = net.state_dict()
    feats = {k[len("features.") :]: v for k, v in sd.items() if k.startswith("features.")}
    missing = sorted(set(want) - set(feats))
    if missing:
        raise ValueError(
            f"VGG19 weights file {str(p)!r} lacks torchvision keys "
            f"{['features.' + m for m in missing[:4]]}"
            f"{' ...' if len(missing) > 4 else ''}"
        )
    for k, v in want.items():
        if tuple(feats[k].shape) != tuple(v.shape):
            raise ValueError(
                f"VGG19 weights file {str(p)!r}: features.{k} has shape {tuple(feats[k].shape)}, "
                f"VGG19 needs {tuple(v.shape)}"
            )
    net.load_state_dict({k: feats[k] for k in want})
    net.eval().requires_grad_(False)
    return net


class PerceptualLoss(nn.Module):
    """L_p over the activations of chosen layers of a feature network (module doc).

    Args:
        features: a sequential network (VGG19 features, or a stand-in in tests); frozen here.
        layers: indices in ``features`` whose outputs are compared (after their activation).
        imagenet_input: map [-1, 1] images to [0, 1] and normalise with ImageNet's mean/std
            (what VGG was trained on); False feeds the images as they are.
    """

    def __init__(
        self, features: nn.Sequential, layers: tuple[int, ...], imagenet_input: bool = True
    ) -> None:
        super().__init__()
        if not layers:
            raise ValueError("PerceptualLoss needs at least one layer index")
        n = len(features)
        bad = [i for i in layers if not (0 <= i < n)]
        if bad:
            raise ValueError(f"PerceptualLoss layers {bad} out of range for a {n}-layer network")
        # a plain Sequential of the layers used (slicing a Sequential subclass such as
        # VGG19Features would call its own constructor with the layers, which takes none)
        kept = list(features.children())[: max(layers) + 1]
        self.features = nn.Sequential(*kept).eval().requires_grad_(False)
        self.layers = tuple(sorted(set(layers)))
        self.imagenet_input = imagenet_input
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    def train(self, mode: bool = True) -> PerceptualLoss:  # the feature net stays in eval
        super().train(mode)
        self.features.eval()
        return self

    def _prep(self, x: torch.Tensor) -> torch.Tensor:
        if not self.imagenet_input:
            return x
        return ((x + 1.0) * 0.5 - self.mean) / self.std

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """pred, target: (B, 3, H, W) in [-1, 1] -> scalar loss."""
        if pred.shape != target.shape:
            raise ValueError(f"PerceptualLoss: pred {tuple(pred.shape)} != {tuple(target.shape)}")
        a, b = self._prep(pred), self._prep(target)
        total = pred.new_zeros(())
        for i, layer in enumerate(self.features):
            a, b = layer(a), layer(b)
            if i in self.layers:
                chw = a[0].numel()
                total = total + ((a - b.detach()) ** 2).reshape(a.shape[0], -1).sum(1).mean() / chw
        return total


def build_perceptual(
    weights_path: str | os.PathLike | None, layers: tuple[int, ...] = VGG19_RELU_X_1
) -> tuple[PerceptualLoss | None, str]:
    """The VGG19 perceptual loss from a local weights file, or None (with a warning) without one.

    Returns:
        (loss or None, status text for the run's config: "on: PATH" or "off: REASON").

    Raises:
        ValueError: the file exists but is not a VGG19 state dict.
    """
    if weights_path is None:
        reason = "TrainConfig.vgg19_weights is not set"
    elif not Path(weights_path).is_file():
        reason = f"TrainConfig.vgg19_weights file {str(weights_path)!r} does not exist"
    else:
        return PerceptualLoss(load_vgg19_features(weights_path), layers), f"on: {weights_path}"
    warnings.warn(PERCEPTUAL_OFF_WARNING.format(reason=reason), UserWarning, stacklevel=2)
    return None, f"off: {reason}"


__all__ = [
    "PERCEPTUAL_OFF_WARNING",
    "VGG19_LAYOUT",
    "VGG19_RELU_X_1",
    "PerceptualLoss",
    "VGG19Features",
    "build_perceptual",
    "critic_score",
    "gradient_penalty",
    "l1_loss",
    "load_vgg19_features",
    "ssim_loss",
]
