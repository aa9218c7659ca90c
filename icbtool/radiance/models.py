"""World-space irradiance models (torch): a multi-resolution grid + MLP and a probe volume.

Both map a surface point ``(position (N, 3), normal (N, 3))`` in world space to the indirect
irradiance ``E (N, 3)`` arriving there; the client's GI is ``albedo * E`` (docs/radiance.md).

:class:`GridEncoding` is the learned multi-resolution grid of instant-ngp (Mueller et al. 2022):
``L`` levels whose resolutions grow geometrically from ``base_resolution`` to
``max_resolution`` cells along the scene's longest axis (cells are cubes: shorter axes get
fewer). Each level is a table of ``F``-feature vectors at the grid's vertices, read by trilinear
interpolation of the 8 vertices around a point. A level whose vertices fit in ``2^log2_table``
entries is stored densely; a finer one shares ``2^log2_table`` entries through the spatial hash
``(x * 1 + y * 2654435761 + z * 805459861) mod 2^log2_table`` (a sum where instant-ngp uses XOR,
so that ONNX needs only Mul/Add/Mod and one Gather for all levels and corners). The concatenated
features of all levels and a spherical-harmonic polynomial of the normal feed a small MLP whose
output ``u`` is the log-irradiance ``log1p(E / scale)``.

:class:`ProbeVolume` is the classical peer: a regular 3D grid of probes, each holding the
coefficients of ``E(n)`` in the same normal basis (order 1: ``c0 + c . n``, the L1 spherical
harmonics of irradiance; order 2: 9 terms), interpolated trilinearly between the 8 probes around
the point; its coefficients are fitted by least squares (:func:`icbtool.radiance.fit_probes`).

Both shift the looked-up point by ``normal_offset`` along the normal (the "normal bias" of probe
systems: a point on one side of a thin wall then reads the vertices on its own side more).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from icbtool.radiance.data import Bounds, sh_terms

#: Hash primes per axis (instant-ngp's; the first is 1 so that neighbouring x stay coherent).
PRIMES: tuple[int, int, int] = (1, 2654435761, 805459861)

#: The 8 corners of a cell, bit 0 -> x, bit 1 -> y, bit 2 -> z.
CORNERS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], np.int64)


def sh_basis(normal: torch.Tensor, order: int) -> torch.Tensor:
    """(N, 3) unit normals -> (N, (order + 1)^2) basis (:func:`icbtool.radiance.data.sh_basis_np`,
    the same polynomials)."""
    x, y, z = normal[:, 0:1], normal[:, 1:2], normal[:, 2:3]
    cols = [torch.ones_like(x)]
    if order >= 1:
        cols += [x, y, z]
    if order >= 2:
        cols += [x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1]
    return torch.cat(cols, 1)


@dataclass(frozen=True)
class LevelLayout:
    """Where the vertices of each grid level live in one concatenated table.

    Attributes:
        cells: (L, 3) cells per axis of each level.
        strides: (L, 3) index = sum(vertex * stride) mod size (dense: row-major; hashed: primes).
        sizes: (L,) table entries of each level.
        offsets: (L,) first entry of each level in the concatenated table.
        hashed: (L,) whether the level is hashed.
    """

    cells: np.ndarray
    strides: np.ndarray
    sizes: np.ndarray
    offsets: np.ndarray
    hashed: np.ndarray

    @property
    def total(self) -> int:
        return int(self.sizes.sum())


def level_layout(extent: np.ndarray, resolutions: list[int], log2_table: int | None) -> LevelLayout:
    """Cells, strides and table sizes of grid levels over a box of ``extent``.

    Args:
        extent: (3,) box side lengths.
        resolutions: cells along the longest axis, per level.
        log2_table: hash table size exponent; None: every level dense (the probe volume).
    """
    rel = np.asarray(extent, np.float64) / float(np.max(extent))
    cells, strides, sizes, hashed = [], [], [], []
    for r in resolutions:
        c = np.maximum(1, np.ceil(r * rel - 1e-9)).astype(np.int64)
        v = c + 1
        dense = int(np.prod(v))
        if log2_table is None or dense <= 2**log2_table:
            strides.append([1, v[0], v[0] * v[1]])
            sizes.append(dense)
            hashed.append(False)
        else:
            strides.append(list(PRIMES))
            sizes.append(2**log2_table)
            hashed.append(True)
        cells.append(c)
    sizes_a = np.asarray(sizes, np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes_a)[:-1]]).astype(np.int64)
    return LevelLayout(
        np.asarray(cells, np.int64),
        np.asarray(strides, np.int64),
        sizes_a,
        offsets,
        np.asarray(hashed, bool),
    )


def corner_lookup(
    x: torch.Tensor,
    cells: torch.Tensor,
    strides: torch.Tensor,
    sizes: torch.Tensor,
    offsets: torch.Tensor,
    corners: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Table indices and trilinear weights of the 8 vertices around points, at every level.

    Both the dense index and the (sum) hash are linear in the vertex coordinates, so a corner's
    index is the cell's base index plus a per-level constant ``corner . stride`` (taken modulo
    the level's size): no (N, L, 8, 3) integer tensor is ever formed.

    Args:
        x: (N, 3) points normalised to [0, 1] per axis of the box (clamped here).
        cells: (L, 3) float cells per axis; strides, sizes, offsets: int64 :class:`LevelLayout`.
        corners: (8, 3) int64 :data:`CORNERS`.

    Returns:
        ``(index, weight)``: (N, L, 8) int64 rows of the concatenated table and (N, L, 8) float
        weights (summing to 1 over the 8 corners).
    """
    x = x.clamp(0.0, 1.0)
    pos = x[:, None, :] * cells[None]  # (N, L, 3)
    i0 = torch.minimum(torch.floor(pos), cells[None] - 1.0)
    frac = pos - i0
    i = i0.long()
    base = i[..., 0] * strides[:, 0] + i[..., 1] * strides[:, 1] + i[..., 2] * strides[:, 2]
    corner_step = (corners[None] * strides[:, None, :]).sum(-1)  # (L, 8), constant
    lin = torch.remainder(base[:, :, None] + corner_step[None], sizes[None, :, None])
    lin = lin + offsets[None, :, None]
    # corner c = x + 2 y + 4 z: an outer product with z slowest (no Gather, only Mul/Reshape)
    wx = torch.stack([1.0 - frac[..., 0], frac[..., 0]], -1)  # (N, L, 2)
    wy = torch.stack([1.0 - frac[..., 1], frac[..., 1]], -1)
    wz = torch.stack([1.0 - frac[..., 2], frac[..., 2]], -1)
    w = wz[..., :, None, None] * wy[..., None, :, None] * wx[..., None, None, :]
    return lin, w.reshape(w.shape[0], w.shape[1], 8)


def corner_lookup_np(x: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """numpy twin of :func:`corner_lookup` for one dense level (the probe fit).

    Args:
        x: (N, 3) points normalised to [0, 1] per axis.
        cells: (3,) int cells per axis (probes per axis - 1).

    Returns:
        (N, 8) int64 probe indices (x fastest) and (N, 8) float64 weights.
    """
    c = np.asarray(cells, np.float64)
    pos = np.clip(np.asarray(x, np.float64), 0.0, 1.0) * c
    i0 = np.minimum(np.floor(pos), c - 1.0)
    frac = pos - i0
    vert = i0.astype(np.int64)[:, None, :] + CORNERS[None]
    v = np.asarray(cells, np.int64) + 1
    idx = vert[..., 0] + v[0] * (vert[..., 1] + v[1] * vert[..., 2])
    w = np.where(CORNERS[None].astype(bool), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)
    return idx, w


class _Normaliser(nn.Module):
    """World point (+ normal offset) -> [0, 1]^3 in the model's box."""

    def __init__(self, bounds: Bounds, normal_offset: float) -> None:
        super().__init__()
        self.register_buffer("lo", torch.tensor(bounds.lo, dtype=torch.float32))
        self.register_buffer("inv_extent", torch.tensor(1.0 / bounds.extent, dtype=torch.float32))
        self.normal_offset = float(normal_offset)

    def forward(self, position: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        p = position + self.normal_offset * normal if self.normal_offset else position
        return (p - self.lo) * self.inv_extent


@dataclass(frozen=True)
class FieldSpec:
    """Shape of an :class:`IrradianceField` (saved with the model).

    Attributes:
        bounds: the box the grid covers (train surface pixels, padded).
        levels, features, log2_table, base_resolution, max_resolution: the grid (module doc).
        hidden, layers: MLP width and number of hidden layers.
        sh_order: order of the normal's basis fed to the MLP.
        normal_offset: lookup shift along the normal (scene units).
        scale: irradiance scale of the log output ``u = log1p(E / scale)``.
    """

    bounds: Bounds
    levels: int
    features: int
    log2_table: int
    base_resolution: int
    max_resolution: int
    hidden: int
    layers: int
    sh_order: int
    normal_offset: float
    scale: float

    def resolutions(self) -> list[int]:
        if self.levels == 1:
            return [self.max_resolution]
        b = math.exp(
            (math.log(self.max_resolution) - math.log(self.base_resolution)) / (self.levels - 1)
        )
        return [int(math.floor(self.base_resolution * b**lv + 1e-6)) for lv in range(self.levels)]

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["bounds"] = self.bounds.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FieldSpec:
        return cls(**{**d, "bounds": Bounds.from_dict(d["bounds"])})


class GridEncoding(nn.Module):
    """The learned multi-resolution grid (module doc): (N, 3) in [0, 1]^3 -> (N, L * F).

    Args:
        layout: the levels' :class:`LevelLayout`.
        features: features per vertex.
        generator: seeds the table's initialisation (uniform in +-1e-4, as instant-ngp).
    """

    def __init__(
        self, layout: LevelLayout, features: int, generator: torch.Generator | None = None
    ) -> None:
        super().__init__()
        self.levels, self.features = len(layout.sizes), int(features)
        t = torch.empty(layout.total, features).uniform_(-1e-4, 1e-4, generator=generator)
        self.table = nn.Parameter(t)
        self.register_buffer("cells", torch.tensor(layout.cells, dtype=torch.float32))
        self.register_buffer("strides", torch.tensor(layout.strides, dtype=torch.int64))
        self.register_buffer("sizes", torch.tensor(layout.sizes, dtype=torch.int64))
        self.register_buffer("offsets", torch.tensor(layout.offsets, dtype=torch.int64))
        self.register_buffer("corners", torch.tensor(CORNERS, dtype=torch.int64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        idx, w = corner_lookup(x, self.cells, self.strides, self.sizes, self.offsets, self.corners)
        f = self.table.t()[:, idx]  # (F, N, L, 8): one Gather, corners innermost
        out = (f * w[None]).sum(-1)  # (F, N, L): the weighted corner sum
        return out.permute(1, 2, 0).reshape(x.shape[0], self.levels * self.features)


class IrradianceField(nn.Module):
    """Grid encoding + normal basis + MLP -> irradiance (module doc).

    ``forward(position (N, 3), normal (N, 3)) -> E (N, 3)`` (>= 0); :meth:`log_irradiance` gives
    the raw output ``u`` that training fits.
    """

    def __init__(self, spec: FieldSpec, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.spec = spec
        layout = level_layout(spec.bounds.extent, spec.resolutions(), spec.log2_table)
        self.norm = _Normaliser(spec.bounds, spec.normal_offset)
        self.grid = GridEncoding(layout, spec.features, generator)
        width_in = spec.levels * spec.features + sh_terms(spec.sh_order)
        layers: list[nn.Module] = []
        w = width_in
        for _ in range(spec.layers):
            layers += [nn.Linear(w, spec.hidden), nn.ReLU()]
            w = spec.hidden
        layers.append(nn.Linear(w, 3))
        self.mlp = nn.Sequential(*layers)
        if generator is not None:  # seeded, independent of the global RNG
            for m in self.mlp:
                if isinstance(m, nn.Linear):
                    bound = 1.0 / math.sqrt(m.in_features)
                    nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5), generator=generator)
                    nn.init.uniform_(m.bias, -bound, bound, generator=generator)
        self.scale = float(spec.scale)
        self.hashed_levels = int(layout.hashed.sum())

    def log_irradiance(self, position: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        """(N, 3) raw output ``u = log1p(E / scale)`` (unclamped)."""
        x = self.norm(position, normal)
        h = torch.cat([self.grid(x), sh_basis(normal, self.spec.sh_order)], 1)
        return self.mlp(h)

    def forward(self, position: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        u = torch.relu(self.log_irradiance(position, normal))
        return self.scale * (torch.exp(u) - 1.0)


@dataclass(frozen=True)
class ProbeSpec:
    """Shape of a :class:`ProbeVolume` (saved with the model).

    Attributes:
        bounds: the box the probes span (probes at its corners and evenly in between).
        probes: (3,) probes per axis (>= 2 each).
        sh_order: order of each probe's irradiance basis (1: L1, 4 terms; 2: 9 terms).
        normal_offset: lookup shift along the normal (scene units).
    """

    bounds: Bounds
    probes: tuple[int, int, int]
    sh_order: int
    normal_offset: float

    @property
    def cells(self) -> np.ndarray:
        return np.asarray(self.probes, np.int64) - 1

    @property
    def count(self) -> int:
        return int(np.prod(self.probes))

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "bounds": self.bounds.to_dict(), "probes": list(self.probes)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ProbeSpec:
        return cls(
            Bounds.from_dict(d["bounds"]),
            tuple(int(v) for v in d["probes"]),  # type: ignore[arg-type]
            int(d["sh_order"]),
            float(d["normal_offset"]),
        )


class ProbeVolume(nn.Module):
    """Irradiance probes on a regular grid (module doc): ``forward(position, normal) -> E``.

    Args:
        spec: the probe layout.
        coefficients: (P, K, 3) per probe (x fastest, then y, then z), K basis terms per colour
            channel; zeros when None.
    """

    def __init__(self, spec: ProbeSpec, coefficients: np.ndarray | None = None) -> None:
        super().__init__()
        self.spec = spec
        k = sh_terms(spec.sh_order)
        c = np.zeros((spec.count, k, 3), np.float32) if coefficients is None else coefficients
        c = np.asarray(c, np.float32)
        if c.shape != (spec.count, k, 3):
            raise ValueError(f"probe coefficients must be {(spec.count, k, 3)}, got {c.shape}")
        self.coefficients = nn.Parameter(torch.from_numpy(c.copy()), requires_grad=False)
        v = np.asarray(spec.probes, np.int64)
        layout = LevelLayout(
            spec.cells[None],
            np.array([[1, v[0], v[0] * v[1]]], np.int64),
            np.array([spec.count], np.int64),
            np.zeros(1, np.int64),
            np.zeros(1, bool),
        )
        self.norm = _Normaliser(spec.bounds, spec.normal_offset)
        self.register_buffer("cells", torch.tensor(layout.cells, dtype=torch.float32))
        self.register_buffer("strides", torch.tensor(layout.strides, dtype=torch.int64))
        self.register_buffer("sizes", torch.tensor(layout.sizes, dtype=torch.int64))
        self.register_buffer("offsets", torch.tensor(layout.offsets, dtype=torch.int64))
        self.register_buffer("corners", torch.tensor(CORNERS, dtype=torch.int64))

    def forward(self, position: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        x = self.norm(position, normal)
        idx, w = corner_lookup(x, self.cells, self.strides, self.sizes, self.offsets, self.corners)
        k = self.coefficients.shape[1]
        c = self.coefficients.reshape(-1, k * 3)[idx[:, 0]]  # (N, 8, K * 3)
        c = torch.matmul(w[:, 0, None, :], c).reshape(-1, k, 3)  # (N, K, 3)
        b = sh_basis(normal, self.spec.sh_order)  # (N, K)
        return torch.relu(torch.matmul(b[:, None, :], c)[:, 0])


__all__ = [
    "CORNERS",
    "PRIMES",
    "FieldSpec",
    "GridEncoding",
    "IrradianceField",
    "LevelLayout",
    "ProbeSpec",
    "ProbeVolume",
    "corner_lookup",
    "corner_lookup_np",
    "level_layout",
    "sh_basis",
]
