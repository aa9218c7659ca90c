"""Configuration of the lightweight progressive mesh (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: Largest chunk any level may be cut into by default (bytes, header included).
DEFAULT_MAX_CHUNK_BYTES = 1 << 20


@dataclass(frozen=True)
class LPMConfig:
    """How :func:`icbtool.lpm.build` makes the levels of detail.

    Attributes:
        ratios: fraction of the triangles kept per level, coarse to fine, strictly increasing in
            (0, 1]; the last must be 1.0 (the finest level is the full mesh). Below about 0.05
            Sponza's arcades collapse into slabs (at 0.02: depth off by > 1 % on 40-75 % of the
            pixels), so the default starts there.
        budget: "global": the decimatable groups (not emissive, more than
            ``min_group_triangles``) go through ONE quadric queue to ``ratio`` of their
            triangles together, so the budget goes where the error is smallest (groups are
            welded apart, so materials stay exact); "per_group": each group is decimated alone
            to ``ratio`` of its own triangles (a complex group then loses as much as a flat one).
        texture_max: largest texture side (texels) per level, one per ratio; 0 keeps the
            texture's own size. A larger texture is shrunk with ``cv2.resize(INTER_AREA)`` (in
            linear light), aspect kept.
        texture_format: how textures travel: "png" (lossless 8-bit sRGB; the finest level's
            textures are then the input's exactly) or "jpeg" (Sponza at quality 90: texture
            bytes per default level 51 / 154 / 477 / 993 kB instead of PNG's 224 / 805 / 2444 /
            4847 kB, at a mean texel error of 0.9 / 255 on the full-size textures).
        jpeg_quality: JPEG quality (1-100) when ``texture_format == "jpeg"``.
        boundary_weight: open3d's quadric weight on boundary edges (material groups are
            welded apart, so their borders are boundaries). On Sponza (benchmarks.lpm_levels
            notes) 1 (open3d's default) gave lower surface and depth error than 10 or 100 at
            every ratio from 0.03 to 0.15, and about the same as 0.1.
        weld_tolerance: vertices of a material group closer than this fraction of the scene's
            bounding-box diagonal are welded before decimation (UV/normal seams split vertices;
            welding makes the group one connected surface for the decimator).
        min_group_triangles: a material group keeps at least this many triangles (or all it
            has): small groups (a few boxes, a relief) cost few bytes and lose their shape
            first, so they are kept whole; large groups are never decimated to nothing.
        normal_crease_deg: a transferred shading normal that differs from its decimated face's
            normal by more than this is replaced by the face normal (a hard edge that the
            decimation moved).
        max_chunk_bytes: the largest chunk :meth:`Level.to_chunks` writes (header included);
            big arrays and texture files are split into several chunks.
    """

    ratios: tuple[float, ...] = (0.05, 0.1, 0.25, 1.0)
    budget: Literal["global", "per_group"] = "global"
    texture_max: tuple[int, ...] = (128, 256, 512, 0)
    texture_format: Literal["png", "jpeg"] = "png"
    jpeg_quality: int = 90
    boundary_weight: float = 1.0
    weld_tolerance: float = 1e-6
    min_group_triangles: int = 64
    normal_crease_deg: float = 60.0
    max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES

    def __post_init__(self) -> None:
        r = tuple(float(x) for x in self.ratios)
        if not r:
            raise ValueError("LPMConfig.ratios must not be empty")
        if any(not (0.0 < x <= 1.0) for x in r):
            raise ValueError(f"LPMConfig.ratios must be in (0, 1], got {list(r)}")
        if any(b <= a for a, b in zip(r, r[1:])):
            raise ValueError(f"LPMConfig.ratios must increase strictly (coarse to fine), got {r}")
        if r[-1] != 1.0:
            raise ValueError(f"LPMConfig.ratios must end with 1.0 (the full mesh), got {r[-1]}")
        object.__setattr__(self, "ratios", r)
        tm = tuple(int(x) for x in self.texture_max)
        if len(tm) != len(r):
            raise ValueError(
                f"LPMConfig.texture_max needs one size per level ({len(r)}), got {len(tm)}"
            )
        if any(x < 0 for x in tm):
            raise ValueError(f"LPMConfig.texture_max must be >= 0 (0: keep), got {list(tm)}")
        object.__setattr__(self, "texture_max", tm)
        if self.budget not in ("global", "per_group"):
            raise ValueError(
                f"LPMConfig.budget must be 'global' or 'per_group', got {self.budget!r}"
            )
        if self.texture_format not in ("png", "jpeg"):
            raise ValueError(
                f"LPMConfig.texture_format must be 'png' or 'jpeg', got {self.texture_format!r}"
            )
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise ValueError(f"LPMConfig.jpeg_quality must be in [1, 100], got {self.jpeg_quality}")
        if not self.boundary_weight >= 0:
            raise ValueError(f"LPMConfig.boundary_weight must be >= 0, got {self.boundary_weight}")
        if not 0 <= self.weld_tolerance < 0.01:
            raise ValueError(
                f"LPMConfig.weld_tolerance must be in [0, 0.01), got {self.weld_tolerance}"
            )
        if int(self.min_group_triangles) < 1:
            raise ValueError(
                f"LPMConfig.min_group_triangles must be >= 1, got {self.min_group_triangles}"
            )
        if not 0 < self.normal_crease_deg <= 180:
            raise ValueError(
                f"LPMConfig.normal_crease_deg must be in (0, 180], got {self.normal_crease_deg}"
            )
        if int(self.max_chunk_bytes) < 4096:
            raise ValueError(
                f"LPMConfig.max_chunk_bytes must be >= 4096, got {self.max_chunk_bytes}"
            )

    @property
    def n_levels(self) -> int:
        return len(self.ratios)
