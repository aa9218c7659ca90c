"""Tiny client-model runs with random weights, in the formats training writes (a GAN run's
``generator.pt``, a radiance run's ``radiance.pt``, and ``evals.json`` with a chosen test SSIM):
enough to test how a server chooses, announces and ships a model and how clients run it; not
for quality."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

GAN_INPUTS = ("dl", "albedo", "normal_world", "depth", "position")


def _evals(path: Path, ssim: float | None, radiance: bool) -> None:
    if ssim is None:
        return
    row = {"iteration": 10, "ssim": ssim, "mse": 100.0, "views": 3, "seconds": 1.0}
    rows = [{**row, "ssim": ssim - 0.2, "iteration": 5}, row]  # the last row counts
    if radiance:
        rows = [{**r, "path": "test"} for r in rows] + [{**row, "path": "walk", "ssim": 0.99}]
    (path / "evals.json").write_text(json.dumps(rows))


def write_gan_run(
    path: Path,
    bounds: np.ndarray,
    seed: int = 0,
    ssim: float | None = None,
    base: int = 4,
    inputs: tuple[str, ...] = GAN_INPUTS,
    demodulate: bool = True,
    warped: bool = False,
) -> Path:
    """A U-Net of ``base`` width with random weights, reading every client buffer encoding
    (HDR dl, albedo, normals, depth, position), demodulated."""
    import torch

    from icbtool.gan.data import InputEncoding
    from icbtool.gan.models import GeneratorConfig, UNetGenerator

    lo, hi = np.asarray(bounds, float)
    enc = InputEncoding(
        inputs,
        depth_max=float(np.linalg.norm(hi - lo)),
        position_center=tuple(float(v) for v in (lo + hi) / 2),
        position_half_extent=float((hi - lo).max() / 2),
        demodulate=demodulate,
        warped=warped,
    )
    cfg = GeneratorConfig(enc.n_channels, base=base)
    torch.manual_seed(seed)
    g = UNetGenerator(cfg).eval()
    path.mkdir(parents=True, exist_ok=True)
    torch.save(
        {"generator": g.state_dict(), "generator_config": asdict(cfg), "encoding": enc.to_dict()},
        path / "generator.pt",
    )
    _evals(path, ssim, radiance=False)
    return path


def write_radiance_run(
    path: Path, bounds: np.ndarray, seed: int = 0, ssim: float | None = None
) -> Path:
    """A small hash grid + MLP irradiance field with random weights (its table spread to +-1, so
    the irradiance varies with position, not only with the normal)."""
    import torch

    from icbtool.radiance.data import Bounds
    from icbtool.radiance.model import save_model
    from icbtool.radiance.models import FieldSpec, IrradianceField

    lo, hi = np.asarray(bounds, float)
    pad = 0.05 * (hi - lo).max()
    spec = FieldSpec(
        bounds=Bounds(tuple(lo - pad), tuple(hi + pad)),
        levels=4,
        features=2,
        log2_table=10,
        base_resolution=4,
        max_resolution=32,
        hidden=16,
        layers=1,
        sh_order=2,
        normal_offset=0.01,
        scale=1.0,
    )
    gen = torch.Generator().manual_seed(seed)
    m = IrradianceField(spec, gen)
    with torch.no_grad():
        m.grid.table.uniform_(-1.0, 1.0, generator=gen)
    path.mkdir(parents=True, exist_ok=True)
    save_model(path / "radiance.pt", "grid", m, {"step": 0})
    _evals(path, ssim, radiance=True)
    return path
