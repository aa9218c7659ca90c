"""The generator (U-Net) and the critic (PatchGAN) of docs/design.md section 5. Torch tensors: BCHW.

Generator: 5 stride-2 4x4 convolutions down (LeakyReLU 0.2), 5 stride-2 4x4 transposed
convolutions up (ReLU), each up level concatenated with the encoder level of the same size (skip),
tanh on the last layer. H and W must be multiples of 32 (2^5); the output has the input's H, W.

Critic: a Markovian PatchGAN of 4 convolutions (LeakyReLU 0.2 after the first three), conditioned
on the input maps by channel concatenation; one unbounded score per patch (WGAN critic, no
sigmoid). Its normalisation is "instance" or "none": batch norm mixes the samples of a batch,
which the per-sample gradient penalty of WGAN-GP forbids.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

Norm = Literal["batch", "instance", "none"]
NORMS: tuple[str, ...] = ("batch", "instance", "none")
#: Number of down (and up) levels; the U-Net takes H, W that are multiples of 2**LEVELS.
LEVELS = 5
MULTIPLE = 2**LEVELS


def _check_int(owner: str, name: str, v: object, lo: int) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < lo:
        raise ValueError(f"{owner}.{name} must be an integer >= {lo}, got {v!r}")


@dataclass(frozen=True)
class GeneratorConfig:
    """U-Net generator.

    Attributes:
        in_channels: channels of the stacked input maps (e.g. 10 for configuration I).
        out_channels: channels of the output (3: RGB GI).
        base: width of the first level; levels have base * (1, 2, 4, 8, 8) channels.
        norm: normalisation after each inner convolution.
        full_res_skip: the last level also sees the input maps at full resolution (our addition:
            the paper's U-Net has no skip at full resolution, so its last transposed
            convolution invents every pixel's detail from half-resolution features; with the
            skip, the last up level outputs ``base`` features that are concatenated with the
            input and mapped to the output by a 3x3 convolution).
        fourier_channels, fourier_octaves: the network appends ``sin(2^k pi x)`` and
            ``cos(2^k pi x)`` (k < ``fourier_octaves``) of the input channels ``fourier_channels``
            (start, stop), e.g. the encoded world positions, to its input (our addition: a
            convolutional network represents a high-frequency function of position, such as a
            scene's irradiance, far better from such features; NeRF's positional encoding).
            Computed inside the network, so its ONNX export takes the same input.
        fourier_resolution: where the Fourier features are computed (our addition, for the
            client's frame budget): "full" (the input's resolution; they join the input of the
            first convolution and the full-resolution skip) or "half" (of the 2x2-averaged
            input channels, a quarter of the sines; a 1x1 convolution adds them to the first
            level's output, and the full-resolution skip carries the input maps alone).
        head_kernel: kernel side of the full-resolution head, 3 or 1 (1: a per-pixel mix of the
            last level's features and the skip; at 256 x 256 the 3 x 3 head with its 3 output
            channels is the slowest layer in onnxruntime).
        skip_features: the full-resolution skip carries the full-resolution Fourier features
            too (False: the input maps alone).
        reduce: 0, or a 1 x 1 convolution maps the input and its full-resolution Fourier
            features to this many channels (LeakyReLU 0.2) before the first level.
        top_width: 0, or the width of the last up level's output (default ``base``).
        reference_gate: None, or (start, stop): the input channels of an encoded reference image
            warped to the view (``out_channels`` channels, in the output's encoding) followed by
            its hole mask (1 channel, 1 on holes, encoded 2 h - 1). The network then also
            outputs a per-pixel gate logit and returns ``a * reference + (1 - a) * generated``
            with ``a = sigmoid(logit)`` where the reference saw and 0 on its holes (our
            addition, docs/gan.md "The generator": the network decides where to trust the
            warp instead of regenerating it). :meth:`UNetGenerator.parts` gives the generated
            image and the gate too.
    """

    in_channels: int
    out_channels: int = 3
    base: int = 32
    norm: Norm = "batch"
    full_res_skip: bool = False
    fourier_channels: tuple[int, int] | None = None
    fourier_octaves: int = 0
    fourier_resolution: Literal["full", "half"] = "full"
    head_kernel: int = 3
    skip_features: bool = True
    reduce: int = 0
    top_width: int = 0
    reference_gate: tuple[int, int] | None = None

    @property
    def n_features(self) -> int:
        """Channels the network computes from the input: Fourier features of the channels
        ``fourier_channels`` (start, stop), ``2 * fourier_octaves`` per channel."""
        if not self.fourier_octaves or self.fourier_channels is None:
            return 0
        a, b = self.fourier_channels
        return 2 * self.fourier_octaves * (b - a)

    @property
    def full_features(self) -> int:
        """Fourier feature channels computed at full resolution (0 when they are at half)."""
        return self.n_features if self.fourier_resolution == "full" else 0

    def __post_init__(self) -> None:
        _check_int("GeneratorConfig", "in_channels", self.in_channels, 1)
        _check_int("GeneratorConfig", "out_channels", self.out_channels, 1)
        _check_int("GeneratorConfig", "base", self.base, 1)
        if self.norm not in NORMS:
            raise ValueError(f"GeneratorConfig.norm must be one of {NORMS}, got {self.norm!r}")
        _check_int("GeneratorConfig", "fourier_octaves", self.fourier_octaves, 0)
        _check_int("GeneratorConfig", "reduce", self.reduce, 0)
        _check_int("GeneratorConfig", "top_width", self.top_width, 0)
        if self.fourier_resolution not in ("full", "half"):
            raise ValueError(
                "GeneratorConfig.fourier_resolution must be 'full' or 'half', got "
                f"{self.fourier_resolution!r}"
            )
        if self.head_kernel not in (1, 3) or isinstance(self.head_kernel, bool):
            raise ValueError(
                f"GeneratorConfig.head_kernel must be 1 or 3, got {self.head_kernel!r}"
            )
        if self.reduce and self.fourier_resolution == "half":
            raise ValueError(
                "GeneratorConfig.reduce maps full-resolution features: it needs "
                "fourier_resolution='full'"
            )
        if self.fourier_channels is not None:
            a, b = (int(v) for v in self.fourier_channels)
            if not 0 <= a < b <= self.in_channels:
                raise ValueError(
                    f"GeneratorConfig.fourier_channels must be (start, stop) within the "
                    f"{self.in_channels} input channels, got {self.fourier_channels}"
                )
            object.__setattr__(self, "fourier_channels", (a, b))
        if self.reference_gate is not None:
            a, b = (int(v) for v in self.reference_gate)
            if b - a != self.out_channels + 1 or not 0 <= a < b <= self.in_channels:
                raise ValueError(
                    f"GeneratorConfig.reference_gate must be (start, stop) of {self.out_channels}"
                    f" reference channels and 1 hole channel within the {self.in_channels} input "
                    f"channels, got {self.reference_gate}"
                )
            object.__setattr__(self, "reference_gate", (a, b))


@dataclass(frozen=True)
class DiscriminatorConfig:
    """PatchGAN critic.

    Attributes:
        in_channels: input map channels (the condition).
        target_channels: channels of the real / generated image.
        base: width of the first layer (layers: base, 2 base, 4 base, 1).
        norm: "instance" or "none" (not "batch": see module doc).
    """

    in_channels: int
    target_channels: int = 3
    base: int = 32
    norm: Norm = "instance"

    def __post_init__(self) -> None:
        _check_int("DiscriminatorConfig", "in_channels", self.in_channels, 1)
        _check_int("DiscriminatorConfig", "target_channels", self.target_channels, 1)
        _check_int("DiscriminatorConfig", "base", self.base, 1)
        if self.norm not in ("instance", "none"):
            raise ValueError(
                "DiscriminatorConfig.norm must be 'instance' or 'none' (batch norm breaks the "
                f"per-sample gradient penalty of WGAN-GP), got {self.norm!r}"
            )


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "instance":
        return nn.InstanceNorm2d(channels, affine=True)
    return nn.Identity()


class UNetGenerator(nn.Module):
    """U-Net with 5 down / 5 up levels and skips (module doc).

    ``forward(x)``: x (B, in_channels, H, W) -> (B, out_channels, H, W) in [-1, 1].
    """

    def __init__(self, config: GeneratorConfig) -> None:
        super().__init__()
        self.config = config
        b, n = config.base, config.norm
        widths = [b * m for m in (1, 2, 4, 8, 8)]
        c_raw, c_full = config.in_channels, config.in_channels + config.full_features
        c_skip = c_full if config.skip_features else c_raw
        gated = config.reference_gate is not None
        c_out = config.out_channels + gated  # + the gate's logit
        last = nn.Identity() if gated else nn.Tanh()  # no parameters: state dicts unchanged
        self.reduce = None
        c_in = c_full
        if config.reduce:
            self.reduce = nn.Sequential(nn.Conv2d(c_full, config.reduce, 1), nn.LeakyReLU(0.2))
            c_in = config.reduce
        self.half_features = None
        if config.n_features and config.fourier_resolution == "half":
            self.half_features = nn.Conv2d(config.n_features, widths[0], 1, bias=False)
        self.down = nn.ModuleList()
        for i, w in enumerate(widths):
            inner = 0 < i < LEVELS - 1  # no norm on the first level nor the 1/32 bottleneck
            conv = nn.Conv2d(c_in, w, 4, 2, 1, bias=not inner or n == "none")
            self.down.append(
                nn.Sequential(conv, _norm(n if inner else "none", w), nn.LeakyReLU(0.2))
            )
            c_in = w
        self.up = nn.ModuleList()
        for i in range(LEVELS - 1):
            w = widths[LEVELS - 2 - i]  # size of the skip it meets
            self.up.append(
                nn.Sequential(
                    nn.ConvTranspose2d(c_in, w, 4, 2, 1, bias=n == "none"),
                    _norm(n, w),
                    nn.ReLU(),
                )
            )
            c_in = 2 * w
        if config.full_res_skip:
            top = config.top_width or b
            self.up.append(
                nn.Sequential(
                    nn.ConvTranspose2d(c_in, top, 4, 2, 1, bias=n == "none"),
                    _norm(n, top),
                    nn.ReLU(),
                )  # fmt: skip
            )
            k = config.head_kernel
            self.head = nn.Sequential(nn.Conv2d(top + c_skip, c_out, k, 1, k // 2), last)
        else:
            self.up.append(nn.Sequential(nn.ConvTranspose2d(c_in, c_out, 4, 2, 1), last))
            self.head = None

    def fourier(self, p: torch.Tensor) -> torch.Tensor:
        """(B, 2 * octaves * C, H, W): ``sin(2^k pi p)``, ``cos(2^k pi p)`` of (B, C, H, W)
        ``p``, k = 0, 1, ... in that order."""
        feats = []
        for k in range(self.config.fourier_octaves):
            w = math.pi * 2.0**k
            feats += [torch.sin(w * p), torch.cos(w * p)]
        return torch.cat(feats, dim=1)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` with the full-resolution Fourier features of :class:`GeneratorConfig` appended
        (``x`` itself when there are none at full resolution)."""
        c = self.config
        if not c.full_features:
            return x
        a, b = c.fourier_channels
        return torch.cat([x, self.fourier(x[:, a:b])], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.parts(x)[0]

    def parts(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(output, generated, gate): the output of :meth:`forward`; the generated image alone
        (the output itself without :attr:`GeneratorConfig.reference_gate`); the (B, 1, H, W)
        gate in [0, 1] (None without one)."""
        y = self._unet(x)
        rg = self.config.reference_gate
        if rg is None:
            return y, y, None
        n = self.config.out_channels
        generated = torch.tanh(y[:, :n])
        ref, holes = x[:, rg[0] : rg[0] + n], x[:, rg[0] + n : rg[1]]
        gate = torch.sigmoid(y[:, n:]) * (0.5 - 0.5 * holes)
        return generated + gate * (ref - generated), generated, gate

    def _unet(self, x: torch.Tensor) -> torch.Tensor:
        c = self.config
        raw = x
        x = self.features(x)
        inp = x if c.skip_features else raw
        if self.reduce is not None:
            x = self.reduce(x)
        skips = []
        for i, layer in enumerate(self.down):
            if i == 0 and self.half_features is not None:
                a, b = c.fourier_channels
                p = nn.functional.avg_pool2d(raw[:, a:b], 2)
                conv, rest = layer[0], layer[1:]
                x = rest(conv(x) + self.half_features(self.fourier(p)))
            else:
                x = layer(x)
            skips.append(x)
        skips.pop()  # the bottleneck is not a skip
        for layer in self.up[:-1]:
            x = torch.cat([layer(x), skips.pop()], dim=1)
        x = self.up[-1](x)
        if self.head is not None:
            x = self.head(torch.cat([x, inp], dim=1))
        return x


class PatchDiscriminator(nn.Module):
    """Conditional PatchGAN critic (module doc).

    ``forward(cond, image)``: cond (B, in_channels, H, W), image (B, target_channels, H, W) ->
    (B, 1, H/4 - 2, W/4 - 2) patch scores (4x4 kernels; strides 2, 2, 1, 1).
    """

    def __init__(self, config: DiscriminatorConfig) -> None:
        super().__init__()
        self.config = config
        b, n = config.base, config.norm
        c0 = config.in_channels + config.target_channels
        self.layers = nn.Sequential(
            nn.Conv2d(c0, b, 4, 2, 1),
            nn.LeakyReLU(0.2),
            nn.Conv2d(b, 2 * b, 4, 2, 1),
            _norm(n, 2 * b),
            nn.LeakyReLU(0.2),
            nn.Conv2d(2 * b, 4 * b, 4, 1, 1),
            _norm(n, 4 * b),
            nn.LeakyReLU(0.2),
            nn.Conv2d(4 * b, 1, 4, 1, 1),
        )

    def forward(self, cond: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        return self.layers(torch.cat([cond, image], dim=1))


def init_weights(module: nn.Module, generator: torch.Generator | None = None) -> None:
    """pix2pix initialisation: conv weights N(0, 0.02), norm scales N(1, 0.02), biases 0."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.normal_(m.weight, 0.0, 0.02, generator=generator)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.BatchNorm2d, nn.InstanceNorm2d)) and m.weight is not None:
            nn.init.normal_(m.weight, 1.0, 0.02, generator=generator)
            nn.init.zeros_(m.bias)


__all__ = [
    "LEVELS",
    "MULTIPLE",
    "NORMS",
    "DiscriminatorConfig",
    "GeneratorConfig",
    "PatchDiscriminator",
    "UNetGenerator",
    "init_weights",
]
