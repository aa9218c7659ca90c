"""GI learned in world space: a static scene's diffuse indirect irradiance as a function of
surface position and normal, fitted from the cloud's CRT-buffers (docs/radiance.md).

Two models with one API: the multi-resolution grid + MLP (``RadianceConfig``; instant-ngp's
encoding, trained with Adam) and the classical irradiance probe volume (``ProbeConfig``; fitted
by least squares). ``icb.radiance.train(store, config, out_dir)`` writes a run directory;
``RadianceModel.load(run).generate(buffers)`` gives the client's GI ``albedo * E`` from its
albedo, world normals and world positions; ``export_onnx`` writes the per-point model.

``import icbtool.radiance`` does not import torch: the names below load on first access.

Modules:
    data: surface pixels of a store as (position, normal) -> irradiance samples (numpy).
    models: the grid encoding, the MLP field and the probe volume (torch).
    model: ``RadianceModel`` (load, generate, ONNX export).
    training: ``RadianceConfig``, ``ProbeConfig``, :func:`train`, the probe fit, evaluation.
    coverage: how far test pixels are from any train pixel in world space (numpy + scipy).
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES: dict[str, str] = {
    "Bounds": "data",
    "PixelSamples": "data",
    "demodulate": "data",
    "pixels_from_records": "data",
    "records_of_path": "data",
    "FieldSpec": "models",
    "ProbeSpec": "models",
    "GridEncoding": "models",
    "IrradianceField": "models",
    "ProbeVolume": "models",
    "RadianceModel": "model",
    "load": "model",
    "RadianceConfig": "training",
    "ProbeConfig": "training",
    "RadianceResult": "training",
    "RadianceDivergedError": "training",
    "fit_probe_volume": "training",
    "train": "training",
    "coverage_distances": "coverage",
    "view_coverage": "coverage",
}
_MODULES = ("data", "models", "model", "training", "coverage")


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    if name in _MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'icbtool.radiance' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_NAMES, *_MODULES])
