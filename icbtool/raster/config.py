"""Configuration and result types of the rasterizer (no OpenGL import here)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera

from icbtool.buffers import BUFFERS, CHANNELS, RASTER_BUFFERS, check_names

#: Every buffer the rasterizer can produce, with its channel count (see :mod:`icbtool.buffers`).
BUFFER_CHANNELS: dict[str, int] = {n: CHANNELS[n] for n in RASTER_BUFFERS}
BUFFER_NAMES: tuple[str, ...] = RASTER_BUFFERS

#: How each buffer is previewed by :func:`icbtool.imageio.preview`.
PREVIEW_KIND: dict[str, str] = {n: BUFFERS[n].preview for n in RASTER_BUFFERS}


def check_buffers(buffers: tuple[str, ...] | list[str] | str | None) -> tuple[str, ...]:
    """Validate a buffer selection; None means all. Returns them in canonical order.

    Raises:
        ValueError: for an empty selection or an unknown name.
    """
    if buffers is None:
        return BUFFER_NAMES
    if isinstance(buffers, str):
        buffers = [b.strip() for b in buffers.split(",") if b.strip()]
    names = set(buffers)
    check_names(list(names), BUFFER_NAMES, "raster")
    if not names:
        raise ValueError(f"no raster buffer requested; choose from {list(BUFFER_NAMES)}")
    return tuple(b for b in BUFFER_NAMES if b in names)


@dataclass(frozen=True)
class RasterConfig:
    """How :class:`icbtool.raster.Rasterizer` renders.

    Attributes:
        backend: OpenGL backend. "auto": $ICBTOOL_GL_BACKEND (read when the context is created)
            if set, else the first that works of egl, osmesa (the error names each failure).
        shadow_map_size: resolution (texels per side) of the shadow map of each directional light,
            of each of the 6 cube faces of a point light and of each spot light.
        area_shadow_map_size: resolution of the shadow map of each area-light sample point (area
            shadows are soft, so a coarser map is enough).
        area_samples: k: each area light's visibility is estimated from k x k stratified points
            (cell centres, deterministic); its unshadowed irradiance is exact (polygon formula).
        shadows: render shadows at all (False: lights are unoccluded; for debugging/speed).
        pcf: filter shadow lookups with the hardware 2x2 bilinear comparison (soft 1-texel edge).
        depth_bias_slope: glPolygonOffset factor in the shadow pass (slope-scaled depth bias).
        depth_bias_units: glPolygonOffset units in the shadow pass (constant depth bias).
        normal_offset: receiver offset along its geometric normal at the shadow lookups of
            directional, point and spot lights, in shadow-map texels (scaled by the sine of the
            light's incidence angle).
        area_offset: receiver offset towards the light sample at the shadow lookups of area
            lights, in shadow-map texels (scaled by the tangent of the incidence angle, at most
            8). Along the ray, unlike a normal offset, which displaces soft shadows on receivers
            at grazing incidence (with it the Cornell box's penumbrae were 2-3.5 % too dark
            against the tracer's direct light; see docs/client.md).
        penumbra_samples: s: pixels in an area light's penumbra (some of its shadow samples
            hidden, some not) are shaded again at s x s stratified points of the pixel's
            footprint on its face's plane and box-filtered, the tracer's pixel filter where one
            point per pixel is biased (a penumbra's profile is curved); 1: pixel centres.
        glossy_area_samples: n: the glossy BSDFs (:mod:`icbtool.raster.glossy`) integrate each
            area light by the midpoint rule at n x n points of the polygon (unshadowed, then
            times its visibility fraction); the Lambertian materials keep the exact polygon
            formula. More points resolve sharper lobes (alpha well below the light's angular
            size over n) at n^2 BSDF evaluations per glossy pixel and light.
        max_frustum_half_angle_deg: half-angle cap of the perspective shadow frusta of area-light
            samples (a frustum is fitted to the scene bounds, then capped: a wider one wastes
            resolution); receivers farther off the light's axis count as unshadowed (they get at
            most cos(cap) of the on-axis emission). Spot frusta cover the outer cone (<= 89 deg).
        texture_size: textured materials are resized to this square size (texels) to share one
            GL_TEXTURE_2D_ARRAY (stored as sRGB8 of the linear texture, decoded by GL; mipmapped).
        near: camera near plane (scene units); None: from the scene bounds and the camera.
        far: camera far plane; None: from the scene bounds and the camera.
        cache_shadow_maps: lights and geometry are fixed for a Rasterizer, so render the shadow
            maps once (first frame that needs them) and reuse them; False: every frame.
        dl_supersample: k: ``dl`` is shaded at k x k stratified points per pixel (the same view
            rendered at k times the resolution, box-filtered down), the tracer's pixel filter
            (``TraceConfig.pixel_jitter``); the other buffers stay one sample at the pixel
            centre. 1: dl at pixel centres. On McGuire's Cornell box (128^2, against the
            tracer's direct light) k = 2 lowers the blurred relative RMSE about twofold for about
            4x the dl cost (docs/benchmarks.md, "Client DL accuracy").
        depth_prepass: draw depth first, then the visibility pass with GL_EQUAL. The renderer is
            deferred (every pixel is shaded once by a full-screen resolve pass whatever the
            overdraw), so this only repeats the vertex work: off by default; kept for
            experiments.
    """

    backend: Literal["auto", "osmesa", "egl"] = "auto"
    shadow_map_size: int = 2048
    area_shadow_map_size: int = 512
    area_samples: int = 4
    shadows: bool = True
    pcf: bool = True
    depth_bias_slope: float = 1.5
    depth_bias_units: float = 2.0
    normal_offset: float = 1.5
    area_offset: float = 2.0
    penumbra_samples: int = 2
    glossy_area_samples: int = 8
    max_frustum_half_angle_deg: float = 60.0
    texture_size: int = 512
    near: float | None = None
    far: float | None = None
    cache_shadow_maps: bool = True
    depth_prepass: bool = False
    dl_supersample: int = 1

    def __post_init__(self) -> None:
        if self.backend not in ("auto", "osmesa", "egl"):
            raise ValueError(
                f"RasterConfig.backend must be 'auto', 'osmesa' or 'egl', got {self.backend!r}"
            )
        for name, lo, hi in (
            ("shadow_map_size", 16, 16384),
            ("area_shadow_map_size", 16, 16384),
            ("area_samples", 1, 8),
            ("texture_size", 1, 8192),
            ("dl_supersample", 1, 8),
            ("penumbra_samples", 1, 8),
            ("glossy_area_samples", 1, 32),
        ):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(
                    f"RasterConfig.{name} must be an integer in [{lo}, {hi}], got {v!r}"
                )
        for name in ("depth_bias_slope", "depth_bias_units", "normal_offset", "area_offset"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"RasterConfig.{name} must be finite and >= 0, got {v!r}")
        if not 1.0 <= self.max_frustum_half_angle_deg <= 89.0:
            raise ValueError(
                "RasterConfig.max_frustum_half_angle_deg must be in [1, 89], got "
                f"{self.max_frustum_half_angle_deg!r}"
            )
        if self.near is not None and not (np.isfinite(self.near) and self.near > 0):
            raise ValueError(f"RasterConfig.near must be > 0 or None, got {self.near!r}")
        if self.far is not None and not np.isfinite(self.far):
            raise ValueError(f"RasterConfig.far must be finite or None, got {self.far!r}")
        if self.near is not None and self.far is not None and not self.near < self.far:
            raise ValueError(f"RasterConfig needs near < far, got {self.near} >= {self.far}")


@dataclass(eq=False)
class RasterBuffers:
    """What one raster pass produced. Buffers not requested are None (mask is always there).

    Attributes:
        camera: the camera rendered.
        mask: (H, W, 1) float32, 1 where a surface was hit, 0 for background.
        dl: (H, W, 3) float32 direct lighting (emission seen + shadowed direct light; sky radiance
            on background pixels).
        albedo: (H, W, 3) float32 linear diffuse albedo (texture x factor); 0 on background.
        normal_world: (H, W, 3) float32 unit shading normals, world space (facing the camera).
        normal_view: (H, W, 3) float32 the same in camera space (OpenCV axes).
        depth: (H, W, 1) float32 view-space z.
        position: (H, W, 3) float32 world positions.
        timings: milliseconds per stage ("shadow" (first frame), "visibility", "resolve",
            "draw" (both passes), "readback", "total").
    """

    camera: Camera
    mask: np.ndarray
    dl: np.ndarray | None = None
    albedo: np.ndarray | None = None
    normal_world: np.ndarray | None = None
    normal_view: np.ndarray | None = None
    depth: np.ndarray | None = None
    position: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels that hit a surface."""
        return self.mask[..., 0] > 0.5

    @property
    def names(self) -> tuple[str, ...]:
        """The buffers present (not None), in canonical order."""
        return tuple(n for n in BUFFER_NAMES if getattr(self, n) is not None)

    def as_dict(self) -> dict[str, np.ndarray]:
        """The present buffers by name."""
        return {n: getattr(self, n) for n in self.names}
