"""Inference with a world-space irradiance model: ``RadianceModel.load(run).generate(buffers)``.

A run directory (:func:`icbtool.radiance.train`) holds ``radiance.pt``: the model's kind
(``"grid"``: :class:`~icbtool.radiance.models.IrradianceField`, ``"probes"``:
:class:`~icbtool.radiance.models.ProbeVolume`), its shape and its weights. ``generate`` reads the
client's albedo, world normals, world positions and surface mask, evaluates the irradiance at
every surface pixel and returns ``GI = albedo * E`` (0 on the background), at any image size.

ONNX: :meth:`RadianceModel.export_onnx` writes the per-point model: inputs ``position`` (N, 3)
and ``normal`` (N, 3) float32 (world space; N dynamic: the client passes its surface pixels
only), output ``irradiance`` (N, 3); the client multiplies by its albedo. Only elementwise ops,
one Gather per table, MatMul/Gemm and Relu/Exp (docs/radiance.md).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from icbtool.provenance import write_json
from icbtool.radiance.data import INPUTS, surface_maps
from icbtool.radiance.models import FieldSpec, IrradianceField, ProbeSpec, ProbeVolume

#: Name of the model file in a run directory.
MODEL_FILE = "radiance.pt"
FORMAT = "icbtool.radiance/1"

Kind = Literal["grid", "probes"]


def build_module(kind: str, spec: dict[str, Any]) -> torch.nn.Module:
    """An untrained module of ``kind`` from its saved spec."""
    if kind == "grid":
        return IrradianceField(FieldSpec.from_dict(spec))
    if kind == "probes":
        return ProbeVolume(ProbeSpec.from_dict(spec))
    raise ValueError(f"unknown radiance model kind {kind!r} (expected 'grid' or 'probes')")


def save_model(path: Path, kind: str, module: torch.nn.Module, extra: dict[str, Any]) -> None:
    """Write a model file atomically (``extra``: config, step ...)."""
    d = {
        "format": FORMAT,
        "kind": kind,
        "spec": module.spec.to_dict(),
        "state": module.state_dict(),
        **extra,
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(d, tmp)
    os.replace(tmp, path)


class RadianceModel:
    """A world-space irradiance model ready for inference (eval mode, no gradients).

    Args:
        module: an :class:`~icbtool.radiance.models.IrradianceField` or
            :class:`~icbtool.radiance.models.ProbeVolume`.
        kind: ``"grid"`` or ``"probes"``.
        device: where it runs.
        batch: points per forward call (bounds memory on large images).

    Attributes:
        inputs: the buffers :meth:`generate` reads.
        size_multiple: image sizes it takes are multiples of this (1: any size).
    """

    inputs: tuple[str, ...] = INPUTS
    size_multiple = 1

    def __init__(
        self, module: torch.nn.Module, kind: str, device: str = "cpu", batch: int = 1 << 17
    ) -> None:
        if kind not in ("grid", "probes"):
            raise ValueError(f"kind must be 'grid' or 'probes', got {kind!r}")
        if device == "cuda" and not torch.cuda.is_available():
            raise ValueError("device 'cuda' asked for but torch sees no CUDA device here")
        self.device = torch.device(device)
        self.module = module.to(self.device).eval()
        self.kind = kind
        self.batch = int(batch)

    @classmethod
    def load(cls, run_dir: str | os.PathLike, device: str = "cpu") -> RadianceModel:
        """The model of a run (``run_dir/radiance.pt``, or that file itself).

        Raises:
            FileNotFoundError: no model file there.
            ValueError: the file is not an icbtool radiance model.
        """
        p = Path(run_dir)
        f = p / MODEL_FILE if p.is_dir() else p
        if not f.is_file():
            raise FileNotFoundError(
                f"no world-space radiance model at {str(f)!r} (icbtool.radiance.train writes it "
                "at its first checkpoint)"
            )
        d = torch.load(f, map_location="cpu", weights_only=False)
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ValueError(f"{str(f)!r} is not an icbtool radiance model ({FORMAT})")
        module = build_module(d["kind"], d["spec"])
        module.load_state_dict(d["state"])
        return cls(module, d["kind"], device)

    @property
    def nbytes(self) -> int:
        """Bytes of the parameters and buffers a client needs (float32 weights)."""
        return int(sum(t.numel() * t.element_size() for t in self.module.state_dict().values()))

    def irradiance(self, position: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Irradiance at world points.

        Args:
            position: (N, 3) world positions.
            normal: (N, 3) unit world normals.

        Returns:
            (N, 3) float32 E >= 0.

        Raises:
            ValueError: shapes other than (N, 3), or NaN/Inf values.
        """
        p = np.asarray(position, np.float32)
        n = np.asarray(normal, np.float32)
        for name, a in (("position", p), ("normal", n)):
            if a.ndim != 2 or a.shape[1] != 3:
                raise ValueError(f"{name} must be (N, 3), got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"{name} holds NaN or Inf values")
        if p.shape != n.shape:
            raise ValueError(f"position {p.shape} and normal {n.shape} differ in length")
        out = np.empty_like(p)
        with torch.no_grad():
            for s in range(0, len(p), self.batch):
                e = self.module(
                    torch.from_numpy(p[s : s + self.batch]).to(self.device),
                    torch.from_numpy(n[s : s + self.batch]).to(self.device),
                )
                out[s : s + self.batch] = e.cpu().numpy()
        return out

    def generate(self, buffers: Any) -> np.ndarray:
        """GI from the client's buffers (or a CRT-buffer record).

        Args:
            buffers: a mapping of (H, W, C) maps or an object with buffer attributes, holding
                ``albedo``, ``normal_world``, ``position`` and (optionally) ``mask``.

        Returns:
            (H, W, 3) float32 linear GI: ``albedo * E`` on surface pixels, 0 elsewhere.

        Raises:
            ValueError: a missing or mis-shaped map, or NaN/Inf in a surface pixel's maps.
        """
        m = surface_maps(buffers)
        s = m["surface"]
        gi = np.zeros(m["albedo"].shape, np.float32)
        if s.any():
            e = self.irradiance(m["position"][s], m["normal_world"][s])
            gi[s] = m["albedo"][s] * e
        return gi

    def export_onnx(self, path: str | os.PathLike, n_points: int = 1024) -> Path:
        """Write the per-point model as ONNX (module doc) and ``PATH.json`` describing it.

        Args:
            path: the ``.onnx`` file.
            n_points: points of the tracing example (N stays dynamic).

        Raises:
            MissingOptionalDependency: the ``onnx`` package is missing (extra ``gan``).
        """
        from icbtool.optional import require

        require("onnx", "ONNX export of the world-space radiance model")
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        module = self.module.cpu().eval()
        spec = module.spec
        b = spec.bounds
        g = torch.Generator().manual_seed(0)
        lo, hi = torch.tensor(b.lo), torch.tensor(b.hi)
        pos = lo + (hi - lo) * torch.rand(n_points, 3, generator=g)
        nrm = torch.nn.functional.normalize(torch.randn(n_points, 3, generator=g), dim=1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            torch.onnx.export(
                module,
                (pos, nrm),
                str(p),
                dynamo=False,
                input_names=["position", "normal"],
                output_names=["irradiance"],
                dynamic_axes={"position": {0: "n"}, "normal": {0: "n"}, "irradiance": {0: "n"}},
                opset_version=17,
            )
        self.module.to(self.device)
        write_json(
            p.with_suffix(p.suffix + ".json"),
            {
                "kind": self.kind,
                "inputs": "position (N, 3), normal (N, 3): float32 world space, surface pixels",
                "output": "irradiance (N, 3) float32 >= 0; GI = albedo * irradiance",
                "spec": spec.to_dict(),
                "parameter_bytes": self.nbytes,
            },
        )
        return p


def load(run_dir: str | os.PathLike, device: str = "cpu") -> RadianceModel:
    """:meth:`RadianceModel.load` (``icb.radiance.load(run)``)."""
    return RadianceModel.load(run_dir, device)


__all__ = ["MODEL_FILE", "RadianceModel", "build_module", "load", "save_model"]
