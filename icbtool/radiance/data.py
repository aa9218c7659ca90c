"""Surface pixels of a store's CRT-buffers as world-space samples of diffuse irradiance.

Every surface pixel of a record is one sample ``(position, normal) -> E`` of the scene's
indirect irradiance, with ``E = GI / albedo`` per channel (demodulation, docs/radiance.md: the GI
of a diffuse surface is its albedo times the irradiance arriving there). Where the albedo is
dark that division amplifies noise and is undefined at 0, so the target divides by the albedo
floored at ``albedo_floor`` and each channel carries a weight ``min(albedo / albedo_floor, 1)``:
1 on ordinary surfaces, falling to 0 on black ones, whose GI tells nothing about E.

numpy only (no torch): the probe volume, the coverage measures and the benchmarks use it too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Buffers a world-space model reads from a client or a record.
INPUTS: tuple[str, ...] = ("albedo", "normal_world", "position", "mask")


@dataclass(frozen=True)
class Bounds:
    """An axis-aligned box of world space (scene units).

    Attributes:
        lo: (3,) minimum corner.
        hi: (3,) maximum corner (> lo on every axis).
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, np.float64), np.asarray(self.hi, np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not np.isfinite([*lo, *hi]).all():
            raise ValueError(f"Bounds must be two finite 3-vectors, got {self.lo}, {self.hi}")
        if np.any(hi <= lo):
            raise ValueError(f"Bounds.hi must exceed Bounds.lo on every axis, got {lo}, {hi}")
        object.__setattr__(self, "lo", tuple(float(v) for v in lo))
        object.__setattr__(self, "hi", tuple(float(v) for v in hi))

    @property
    def extent(self) -> np.ndarray:
        """(3,) float64 side lengths."""
        return np.asarray(self.hi) - np.asarray(self.lo)

    @property
    def diagonal(self) -> float:
        return float(np.linalg.norm(self.extent))

    @classmethod
    def of_points(cls, points: np.ndarray, margin: float = 0.02) -> Bounds:
        """The box around (N, 3) points, grown by ``margin`` x its largest side on every side
        (a flat point set still gets a box of non-zero thickness)."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if len(p) == 0:
            raise ValueError("Bounds.of_points: no points")
        lo, hi = p.min(0), p.max(0)
        pad = margin * max(float((hi - lo).max()), 1e-6)
        return cls(tuple(lo - pad), tuple(hi + pad))  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        return {"lo": list(self.lo), "hi": list(self.hi)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Bounds:
        return cls(tuple(d["lo"]), tuple(d["hi"]))  # type: ignore[arg-type]


def demodulate(
    gi: np.ndarray, albedo: np.ndarray, albedo_floor: float
) -> tuple[np.ndarray, np.ndarray]:
    """Irradiance targets and their weights from GI and albedo (module doc).

    Args:
        gi: (..., 3) linear GI.
        albedo: (..., 3) albedo in [0, 1].
        albedo_floor: albedo below this is floored for the division and down-weighted.

    Returns:
        ``(E, weight)``: (..., 3) float32 ``gi / max(albedo, floor)`` and (..., 3) float32
        ``clip(albedo / floor, 0, 1)``.
    """
    a = np.asarray(albedo, np.float32)
    e = np.asarray(gi, np.float32) / np.maximum(a, np.float32(albedo_floor))
    w = np.clip(a / np.float32(albedo_floor), 0.0, 1.0).astype(np.float32)
    return e.astype(np.float32), w


@dataclass(frozen=True)
class PixelSamples:
    """Surface pixels of some records, flattened.

    Attributes:
        position: (N, 3) float32 world positions.
        normal: (N, 3) float32 unit world normals.
        albedo: (N, 3) float32.
        gi: (N, 3) float32 linear GI (the truth).
        view: (N,) int32 index of the record each pixel came from (into ``record_ids``).
        record_ids: the store records, in the order read.
    """

    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    gi: np.ndarray
    view: np.ndarray
    record_ids: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.position)

    def targets(self, albedo_floor: float) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) irradiance targets and (N, 3) weights (:func:`demodulate`)."""
        return demodulate(self.gi, self.albedo, albedo_floor)

    def subset(self, idx: np.ndarray) -> PixelSamples:
        return PixelSamples(
            self.position[idx],
            self.normal[idx],
            self.albedo[idx],
            self.gi[idx],
            self.view[idx],
            self.record_ids,
        )


def surface_maps(buffers: Any, where: str = "buffers") -> dict[str, np.ndarray]:
    """The maps a world-space model reads, checked: ``albedo``, ``normal_world``, ``position``
    ((H, W, 3) float32) and ``surface`` ((H, W) bool: mask > 0.5; all True without a mask).

    Args:
        buffers: a mapping of (H, W, C) arrays, a CRT-buffer or a raster result.
        where: names the buffers in error messages.

    Raises:
        ValueError: a missing or mis-shaped map, or NaN/Inf in a surface pixel's albedo, normal or
            position (background pixels are not read).
    """

    def fetch(name: str) -> Any:
        if isinstance(buffers, Mapping):
            return buffers.get(name)
        return getattr(buffers, name, None)

    out: dict[str, np.ndarray] = {}
    hw = None
    for n in ("albedo", "normal_world", "position"):
        a = fetch(n)
        if a is None:
            raise ValueError(f"{where} lacks the {n!r} map (a world-space model needs {INPUTS})")
        a = np.asarray(a, np.float32)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{where}.{n} must be (H, W, 3), got {a.shape}")
        if hw is None:
            hw = a.shape[:2]
        elif a.shape[:2] != hw:
            raise ValueError(f"{where}.{n} is {a.shape[:2]}, the other maps are {hw}")
        out[n] = a
    m = fetch("mask")
    if m is None:
        surface = np.ones(hw, bool)
    else:
        m = np.asarray(m, np.float32)
        if m.ndim == 3:
            m = m[..., 0]
        if m.shape != hw:
            raise ValueError(f"{where}.mask is {m.shape}, the other maps are {hw}")
        surface = m > 0.5
    for n in ("albedo", "normal_world", "position"):
        bad = ~np.isfinite(out[n][surface]).all(axis=1)
        if bad.any():
            ys, xs = np.nonzero(surface)
            raise ValueError(
                f"{where}.{n} holds NaN or Inf at {int(bad.sum())} surface pixel(s), the first "
                f"at (row {int(ys[bad][0])}, column {int(xs[bad][0])})"
            )
    out["surface"] = surface
    return out


def records_of_path(store: Any, path: str, scene: Any = None) -> list[int]:
    """Record ids tagged ``path`` (in path order) holding every buffer of :data:`INPUTS` + gi.

    Args:
        store: an open :class:`~icbtool.store.Store`.
        path: the camera-path tag (``meta.tags["path"]``, set by :func:`icbtool.bake.bake`).
        scene: a Scene, scene hash or name, or None (all scenes).
    """
    need = set(INPUTS) | {"gi"}
    out = []
    for info in store:
        m = info.meta
        if m.tags.get("path") != path or not need <= set(info.buffers):
            continue
        if scene is not None:
            if isinstance(scene, str):
                if scene not in (m.scene_hash, m.scene_name):
                    continue
            elif (m.scene_hash, m.light_hash) != (scene.content_hash, scene.light_hash):
                continue
        out.append((m.tags.get("index", 0), info.record_id))
    return [rid for _, rid in sorted(out)]


def pixels_from_records(
    store: Any,
    record_ids: list[int],
    max_pixels: int = 0,
    seed: int = 0,
) -> PixelSamples:
    """The surface pixels of some records (module doc).

    Args:
        store: an open store.
        record_ids: which records.
        max_pixels: keep at most this many pixels, drawn uniformly without replacement
            (0: all).
        seed: seed of that draw.

    Raises:
        ValueError: no records, no surface pixel in them, or a record whose albedo, normal or
            position holds NaN/Inf on a surface pixel (naming the record), or whose GI does.
    """
    if not record_ids:
        raise ValueError("no records to read pixels from (an empty camera path or store)")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("position", "normal", "albedo", "gi")}
    views = []
    for k, rid in enumerate(record_ids):
        rec = store.get(rid)
        where = f"store record {rid}"
        maps = surface_maps(rec, where)
        s = maps["surface"]
        gi = np.asarray(rec.gi, np.float32)[s]
        if not np.isfinite(gi).all():
            raise ValueError(f"{where}.gi holds NaN or Inf on surface pixels")
        parts["position"].append(maps["position"][s])
        parts["normal"].append(maps["normal_world"][s])
        parts["albedo"].append(maps["albedo"][s])
        parts["gi"].append(gi)
        views.append(np.full(int(s.sum()), k, np.int32))
    cat = {k: np.concatenate(v).astype(np.float32) for k, v in parts.items()}
    view = np.concatenate(views)
    if len(view) == 0:
        raise ValueError(f"records {record_ids[:5]}... hold no surface pixel (mask all 0)")
    out = PixelSamples(
        cat["position"], cat["normal"], cat["albedo"], cat["gi"], view, tuple(record_ids)
    )
    if max_pixels and len(out) > max_pixels:
        idx = np.sort(np.random.default_rng(seed).choice(len(out), max_pixels, replace=False))
        out = out.subset(idx)
    return out


def sh_basis_np(normal: np.ndarray, order: int) -> np.ndarray:
    """Real spherical-harmonic-like polynomial basis of unit normals (unnormalised).

    Args:
        normal: (N, 3).
        order: 0 (1 term), 1 (4 terms: 1, x, y, z) or 2 (9 terms: + xy, yz, xz, x^2 - y^2,
            3 z^2 - 1).

    Returns:
        (N, K) float64.
    """
    n = np.asarray(normal, np.float64)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    cols = [np.ones_like(x)]
    if order >= 1:
        cols += [x, y, z]
    if order >= 2:
        cols += [x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1]
    return np.stack(cols, 1)


def sh_terms(order: int) -> int:
    """Number of basis terms of :func:`sh_basis_np` for ``order``."""
    if order not in (0, 1, 2):
        raise ValueError(f"spherical-harmonic order must be 0, 1 or 2, got {order!r}")
    return (order + 1) ** 2


__all__ = [
    "INPUTS",
    "Bounds",
    "PixelSamples",
    "demodulate",
    "pixels_from_records",
    "records_of_path",
    "sh_basis_np",
    "sh_terms",
    "surface_maps",
]
