"""Inference: a trained generator makes HDR GI from raster buffers (docs/design.md section 6).

``Generator.load(run_dir)`` reads ``run_dir/generator.pt`` (written by :func:`icbtool.gan.train`
at every checkpoint); ``generate(buffers)`` encodes the input maps exactly as in training, runs
the U-Net and decodes its tanh output with the run's HDR transform.

ONNX: :meth:`Generator.export_onnx` writes the U-Net (input "maps" (B, C, H, W) encoded, output
"gi_encoded" (B, 3, H, W) in [-1, 1], dynamic B, H, W) and a ``.json`` sidecar with the input
encoding and the HDR transform a client applies around it.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from icbtool.gan.data import InputEncoding
from icbtool.gan.models import MULTIPLE, GeneratorConfig, UNetGenerator
from icbtool.provenance import write_json


class Generator:
    """A trained generator ready for inference (eval mode, no gradients).

    Args:
        module: the U-Net.
        encoding: the input encoding of its run.
        device: where it runs.
    """

    def __init__(self, module: UNetGenerator, encoding: InputEncoding, device: str = "cpu") -> None:
        if module.config.in_channels != encoding.n_channels:
            raise ValueError(
                f"generator takes {module.config.in_channels} channels, encoding gives "
                f"{encoding.n_channels}"
            )
        if device == "cuda" and not torch.cuda.is_available():
            raise ValueError("device 'cuda' asked for but torch sees no CUDA device here")
        self.device = torch.device(device)
        self.module = module.to(self.device).eval()
        self.encoding = encoding

    @property
    def inputs(self) -> tuple[str, ...]:
        """Maps the generator needs, in channel order (buffer names, then ``warped_gi`` and
        ``warp_holes`` for a generator conditioned on a warped reference)."""
        return self.encoding.all_inputs

    @classmethod
    def load(cls, run_dir: str | os.PathLike, device: str = "cpu") -> Generator:
        """The generator of a training run (``run_dir/generator.pt``, or that file itself).

        Raises:
            FileNotFoundError: no generator file there.
            ValueError: the file is not a generator of this version.
        """
        p = Path(run_dir)
        f = p / "generator.pt" if p.is_dir() else p
        if not f.is_file():
            raise FileNotFoundError(
                f"no trained generator at {str(f)!r} (train writes it at its first checkpoint)"
            )
        d = torch.load(f, map_location="cpu", weights_only=False)
        if not isinstance(d, dict) or not {"generator", "generator_config", "encoding"} <= set(d):
            raise ValueError(f"{str(f)!r} is not an icbtool generator file")
        module = UNetGenerator(GeneratorConfig(**d["generator_config"]))
        module.load_state_dict(d["generator"])
        return cls(module, InputEncoding.from_dict(d["encoding"]), device)

    def _maps(self, buffers: Any) -> dict[str, np.ndarray]:
        if isinstance(buffers, Mapping):
            return {n: buffers.get(n) for n in self.inputs}
        return {n: getattr(buffers, n, None) for n in self.inputs}

    def encode(self, buffers: Any) -> np.ndarray:
        """(C, H, W) encoded input from a buffer set (mapping or object with buffer attributes).

        Raises:
            ValueError: a missing/mis-shaped/non-finite input buffer, or H, W not multiples of 32.
        """
        x = self.encoding.encode(self._maps(buffers))
        h, w = x.shape[1:]
        if h % MULTIPLE or w % MULTIPLE or h == 0 or w == 0:
            raise ValueError(
                f"the U-Net takes images whose height and width are multiples of {MULTIPLE}; got "
                f"{h} x {w} (nearest: {max(MULTIPLE, h // MULTIPLE * MULTIPLE)} x "
                f"{max(MULTIPLE, w // MULTIPLE * MULTIPLE)}; crop or render at that size)"
            )
        return x

    def generate(self, buffers: Any) -> np.ndarray:
        """GI from the client's buffers.

        Args:
            buffers: the input maps by name (a dict of (H, W, C) arrays, a CRTBuffer, a raster
                result): every name of :attr:`inputs`, H and W multiples of 32.

        Returns:
            (H, W, 3) float32 linear HDR GI.

        Raises:
            ValueError: see :meth:`encode`.
        """
        x = torch.from_numpy(self.encode(buffers))[None].to(self.device)
        with torch.no_grad():
            y = self.module(x)
        gi = self.encoding.hdr.decode(y)[0].permute(1, 2, 0).cpu().numpy().astype(np.float32)
        if self.encoding.demodulate:
            gi = self.encoding.remodulate(gi, np.asarray(self._maps(buffers)["albedo"], np.float32))
        return gi

    def export_onnx(self, path: str | os.PathLike, height: int = 128, width: int = 128) -> Path:
        """Write the U-Net as ONNX (module doc) plus ``PATH.json`` with the encoding.

        Args:
            path: the ``.onnx`` file.
            height, width: size of the example input used for tracing (H, W stay dynamic).

        Raises:
            ValueError: size not a multiple of 32.
            MissingOptionalDependency: the ``onnx`` package is missing (the message says
                ``pip install ".[gan]"`` in the checkout).
        """
        if height % MULTIPLE or width % MULTIPLE:
            raise ValueError(f"export size must be multiples of {MULTIPLE}, got {height}x{width}")
        from icbtool.optional import require

        require("onnx", "ONNX export of the generator")  # torch.onnx.export needs it
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        module = self.module.cpu().eval()
        x = torch.zeros(1, self.encoding.n_channels, height, width)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            torch.onnx.export(
                module,
                (x,),
                str(p),
                dynamo=False,
                input_names=["maps"],
                output_names=["gi_encoded"],
                dynamic_axes={
                    "maps": {0: "batch", 2: "height", 3: "width"},
                    "gi_encoded": {0: "batch", 2: "height", 3: "width"},
                },
                opset_version=17,
            )
        self.module.to(self.device)
        write_json(
            p.with_suffix(p.suffix + ".json"),
            {
                "input": "maps (B, C, H, W) float32, H and W multiples of 32",
                "output": "gi_encoded (B, 3, H, W) in [-1, 1]; linear GI = hdr.decode(output), "
                "times the albedo input map when encoding.demodulate is true",
                "channels": list(self.encoding.all_inputs),
                "encoding": self.encoding.to_dict(),
                "hdr_decode": "scale * expm1((clip(y, -1, 1) + 1) / 2 * log1p(max_value / scale))",
            },
        )
        return p


def load_onnx_sidecar(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON written next to an exported ``.onnx``."""
    return json.loads(Path(str(path) + ".json").read_text())


__all__ = ["Generator", "load_onnx_sidecar"]
