"""A progressive path tracer for GI maps (full - DL): numba kernels that call Embree directly.

Each pass traces one or more samples for a set of pixels. One numba kernel
(:func:`icbtool.trace.kernels.trace_paths`) follows each sample's whole path, calling Embree 4's
``rtcIntersect1``/``rtcOccluded1`` itself (:mod:`icbtool.trace.rtc`), so no Python runs per depth
or per ray batch; ``threads`` Python threads run it on interleaved blocks of whole pixels (it
releases the GIL), and it adds every sample to its pixel's running statistics as the sample ends.
The driver here reads those statistics between passes and decides when to stop. The kernels are
compiled on first use and cached on disk (numba ``cache=True``): once per machine (or per change
of ``kernels.py``); a new process then only loads the cache (both times are measured by
``python -m benchmarks.trace_compile``: docs/benchmarks.md).

Light transport: two-sided Lambertian surfaces (textured albedo), one-sided emissive faces, a
directional sun, point and spot lights (delta lights: next-event estimation only), emissive
triangles (next-event estimation sampled by power, combined with BSDF sampling by multiple
importance sampling, power heuristic) and a sky, uniform, gradient or a lat-long environment map
(one light sample per vertex drawn from a table of its luminance, :class:`SkyTable`, combined
with BSDF sampling by MIS; or BSDF sampling alone for a smooth sky, see
``TraceConfig.sky_sampling``).

The DL/GI split (fixed system-wide): ``direct`` = emission of the first visible surface + direct
light at the first hit from the scene's directional, point, spot and *area* lights (the emissive
faces lying in an :class:`~icbtool.scene.AreaLight`: its quad or triangle, or a mesh emitter
promoted by :func:`icbtool.scene.emitters.promote_emitters`), shadowed. Everything else (sky
light at the first hit, light from other emissive geometry, all light that bounced at least
once) is ``gi``.
Camera rays that miss: ``direct`` = sky radiance, ``gi`` = 0.

Cameras (:class:`~icbtool.camera.Camera`, as Mitsuba 3's sensors): a pinhole's rays start at its
centre; a thin lens's (``aperture_radius > 0``) from a point of its aperture disk drawn from a
lens sample of its own (two dimensions, or one Sobol pair, that nothing else uses), aimed at the
focus plane; an orthographic camera's parallel to its axis from its image plane; all of them, and
a pinhole with a ``near_clip``, from where they cross the near clip plane. The rest of the ICB
pipeline renders :meth:`~icbtool.camera.Camera.pinhole` of a camera.

Depth convention (as Mitsuba's ``max_depth``): a path of ``k`` segments has depth ``k``; depth 1 is
an emitter seen directly, depth 2 direct lighting; ``max_depth = -1`` is unbounded (Russian
roulette ends paths; a hard cap of :data:`HARD_MAX_DEPTH` guards against hangs).

Determinism: every random number is a function of (seed, pixel, sample index, dimension), so an
image depends on the seed and the config only, never on the number of threads or on timing (a
time budget changes how many samples are taken, not the samples themselves). ``sampler='sobol'``
stratifies each pixel's samples (pixel area, BSDF direction and point on the light for the first
vertices) with shuffled Owen-scrambled Sobol points; it stays unbiased, and the per-pixel variance
estimate (``variance``, adaptive sampling, target error) becomes conservative (it assumes
independent samples). The default ``sampler='zsobol'`` takes the same points from one sequence
in screen-space Z (Morton) order, so that every aligned 2^k x 2^k block of pixels is stratified
too and the pixels' errors form blue noise (the ZSobol sampler of pbrt-v4; Ahmed and Wonka 2020,
"Screen-space blue-noise diffusion of Monte Carlo sampling error via hierarchical ordering of
pixels"). ``sampler='independent'`` draws every dimension from its own hash (the random numbers
of the earlier numpy tracer).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from icbtool.trace.texels import encode_texels

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera
    from icbtool.scene import Scene

log = logging.getLogger(__name__)

#: Upper bound on the path depth even with ``max_depth = -1`` (no hang on albedo-1 scenes).
HARD_MAX_DEPTH = 1024
#: ``sky_sampling='auto'`` samples the sky (MIS) when its peak/mean luminance exceeds this.
SKY_MIS_PEAK = 2.5
#: Samples traced per kernel call: a pass over a large image is split into calls of this many
#: (the split changes nothing: every pixel's samples are added in sample order).
MAX_SAMPLES_PER_CALL = 1 << 20
#: Upper bound on ``TraceConfig.edge_samples``.
MAX_EDGE_SAMPLES = 64
#: upper bound of TraceConfig.gi_splits
MAX_GI_SPLITS = 16
#: A pixel gets ``edge_samples`` when the emission seen through its four corners differs by more
#: than this fraction of the brightest of them (luminance): a light's or the sky's outline, not
#: a smooth sky gradient or an environment map's texels of similar brightness.
EDGE_CONTRAST = 0.2
#: Where emission can come from anywhere on screen (a sky), edge pixels are looked for in blocks
#: of this many pixels a side first (coarse to fine).
EDGE_BLOCK = 4
_LUM = np.array([0.2126, 0.7152, 0.0722])

#: Open Image Denoise quality settings (``TraceConfig.denoise_quality`` and the configs that
#: pass it on: LoopConfig, BakeConfig, the CLI).
DenoiseQuality = Literal["high", "balanced", "fast"]
DENOISE_QUALITIES: tuple[str, ...] = ("high", "balanced", "fast")


def check_denoise_quality(value: object, name: str) -> None:
    """Raise ValueError naming ``name`` unless ``value`` is one of :data:`DENOISE_QUALITIES`."""
    if value not in DENOISE_QUALITIES:
        allowed = ", ".join(repr(q) for q in DENOISE_QUALITIES)
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


# ---------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class TraceConfig:
    """How to trace a GI map."""

    spp: int = 64
    """Maximum samples per pixel (fewer if a time budget or target error stops first)."""
    seed: int = 0
    """Seed of the counter-based random numbers (same seed + config = same image)."""
    max_depth: int = 8
    """Longest path in segments (1: emitters seen, 2: direct light, ...); -1 = unbounded."""
    rr_depth: int = 4
    """Russian roulette (throughput-based) starts at this depth."""
    spp_per_pass: int = 4
    """Samples per pixel added per progressive pass."""
    time_budget_s: float | None = None
    """Stop after the pass that exceeds this wall time (at least one pass is always traced)."""
    target_error: float | None = None
    """Stop when the mean relative standard error of the GI luminance drops below this."""
    adaptive: bool = False
    """After ``adaptive_min_passes`` passes, sample only pixels whose error is above target."""
    adaptive_min_passes: int = 2
    """Passes over every pixel before adaptive sampling starts."""
    denoise: bool = False
    """Denoise ``gi`` (and ``full``) with Open Image Denoise using the first-hit albedo/normal."""
    denoise_quality: DenoiseQuality = "high"
    """OIDN's quality setting. 'fast' takes about half the time of 'high' on the CPU for about
    the same error; 'balanced' gave the same images as 'high' on the scenes measured
    (docs/benchmarks.md, "Denoising")."""
    pixel_jitter: bool = True
    """Box-filter pixels by jittering primary rays; False samples pixel centres (like a raster)."""
    shading_normals: bool = True
    """Use interpolated vertex normals for shading (False: flat geometric normals)."""
    texture_filter: Literal["bilinear", "nearest"] = "bilinear"
    """Texel lookup (textures repeat outside [0, 1])."""
    threads: int = 2
    """Threads for Embree queries (results do not depend on it)."""
    robust: bool = False
    """Embree's robust (watertight) traversal. Off by default, as in Mitsuba 3: it costs a
    share of Embree's time per ray, and the rays a path tracer shoots hardly ever slip through
    an edge without it (same-seed renders differ far inside the noise; docs/design.md, section
    8, and `benchmarks.embree_robust`). Turn it on for rays aimed exactly at shared edges or
    vertices, which slip through far more often without it."""
    aux: bool = True
    """Compute the first-hit albedo and normal buffers (forced on by ``denoise``)."""
    sky_sampling: Literal["auto", "mis", "bsdf"] = "auto"
    """How paths find the sky: 'mis' adds one sky light sample per vertex (importance-sampled
    from a table of the sky's luminance) combined with BSDF sampling by MIS (power heuristic);
    'bsdf' relies on cosine BSDF sampling alone; 'auto' uses 'mis' only for a peaked sky (the
    brightest direction more than :data:`SKY_MIS_PEAK` times the sky's mean luminance). A smooth
    sky is found by cosine sampling as well as by a light sample, which would only add a shadow
    ray per vertex for almost no less variance; on a strongly peaked sky MIS cuts the GI
    variance by far more than it costs."""
    sampler: Literal["zsobol", "sobol", "independent"] = "zsobol"
    """Random numbers: 'zsobol' (Owen-scrambled Sobol pairs for the pixel area, BSDF and light
    dimensions, indexed in screen-space Z order so that neighbouring pixels share one stratified
    point set: a pixel's error is as with 'sobol', but neighbouring pixels' errors are negatively
    correlated, blue noise that the eye, FLIP and a denoiser average away; docs/design.md,
    section 8), 'sobol' (the same points, shuffled per pixel: white noise across pixels) or
    'independent' (a hash per dimension). All are unbiased."""
    gi_splits: int = 1
    """Branches of every path after its first vertex (1: none). Each sample's camera ray, first
    hit and direct light there are shared by ``gi_splits`` independent continuations (bounce
    direction and all that follows), each weighted 1 / gi_splits: the GI gets that many
    samples for less than that many paths' cost (docs/design.md, section 8). ``spp`` still
    counts camera rays."""
    edge_samples: int = 8
    """Extra camera rays per sample, for the emission seen directly only, on the pixels that an
    emitter's or the sky's edge crosses (0: none). A pixel half on a light is otherwise its
    worst: one sample sees the light or not, and at a few spp those few pixels hold most of
    the image's squared error. The pixels are found once per render, before any sample, by
    comparing the emission seen through each pixel's four corners (deterministic, so the
    estimate stays unbiased); their emission term becomes the mean over this sample's own
    camera ray and the extras, which cost a closest hit each and no shading (docs/design.md,
    section 8). Needs ``pixel_jitter``."""

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ValueError:
            return ValueError(f"TraceConfig.{name} {why}, got {getattr(self, name)!r}")

        if (
            not isinstance(self.edge_samples, (int, np.integer))
            or isinstance(self.edge_samples, bool)
            or not 0 <= self.edge_samples <= MAX_EDGE_SAMPLES
        ):
            raise bad("edge_samples", f"must be an integer in [0, {MAX_EDGE_SAMPLES}]")
        for name in ("spp", "spp_per_pass", "threads", "adaptive_min_passes"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise bad(name, "must be an integer >= 1")
        if not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**63:
            raise bad("seed", "must be an integer in [0, 2**63)")
        if not isinstance(self.max_depth, (int, np.integer)) or (
            self.max_depth < 1 and self.max_depth != -1
        ):
            raise bad("max_depth", "must be an integer >= 1 or -1 (unbounded)")
        if not isinstance(self.rr_depth, (int, np.integer)) or self.rr_depth < 1:
            raise bad("rr_depth", "must be an integer >= 1")
        if self.time_budget_s is not None and not (self.time_budget_s > 0):
            raise bad("time_budget_s", "must be > 0 or None")
        if self.target_error is not None and not (self.target_error > 0):
            raise bad("target_error", "must be > 0 or None")
        if self.texture_filter not in ("bilinear", "nearest"):
            raise bad("texture_filter", "must be 'bilinear' or 'nearest'")
        if (
            not isinstance(self.gi_splits, (int, np.integer))
            or isinstance(self.gi_splits, bool)
            or not 1 <= self.gi_splits <= MAX_GI_SPLITS
        ):
            raise bad("gi_splits", f"must be an integer in [1, {MAX_GI_SPLITS}]")
        if self.sampler not in ("sobol", "zsobol", "independent"):
            raise bad("sampler", "must be 'sobol', 'zsobol' or 'independent'")
        check_denoise_quality(self.denoise_quality, "TraceConfig.denoise_quality")
        if self.sky_sampling not in ("auto", "mis", "bsdf"):
            raise bad("sky_sampling", "must be 'auto', 'mis' or 'bsdf'")
        if self.adaptive and self.target_error is None:
            raise ValueError("TraceConfig.adaptive needs a target_error (the per-pixel threshold)")

    @property
    def depth_limit(self) -> int:
        return HARD_MAX_DEPTH if self.max_depth == -1 else min(self.max_depth, HARD_MAX_DEPTH)


# ---------------------------------------------------------------------------------- results
@dataclass
class TraceStats:
    """What a render cost and what it skipped."""

    time_s: dict[str, float] = field(default_factory=dict)
    """Wall time per phase: setup, trace (paths: Embree, shading and the per-pixel statistics),
    accumulate (the error estimate between passes and the output buffers), denoise."""
    rays: dict[str, int] = field(
        default_factory=lambda: {"primary": 0, "bounce": 0, "shadow": 0, "edge_probe": 0}
    )
    """Rays traced by kind: a path's camera rays (its own and its extra edge samples', see
    ``TraceConfig.edge_samples``), bounce and shadow rays, and the rays through pixel corners
    that look for edge pixels before the first sample."""
    passes: int = 0
    """Progressive passes traced."""
    samples: int = 0
    """Total path samples (sum of the spp map)."""
    stop_reason: str = ""
    """Why sampling stopped: 'spp', 'time_budget', 'target_error' or 'converged'."""
    rel_error: float = float("nan")
    """Final mean relative standard error of the GI luminance (over covered pixels)."""
    skipped: list[str] = field(default_factory=list)
    """Work the scene or config did not need, and why."""
    edge_pixels: int = 0
    """Pixels that got ``TraceConfig.edge_samples`` (an emitter's or the sky's edge crosses
    them)."""
    error_history: list[tuple[float, int, float]] = field(default_factory=list)
    """(time_s, samples, rel_error) after each pass."""

    def add_time(self, phase: str, dt: float) -> None:
        self.time_s[phase] = self.time_s.get(phase, 0.0) + dt

    @property
    def total_rays(self) -> int:
        return int(sum(self.rays.values()))


@dataclass
class TraceResult:
    """The buffers of one traced view. All (H, W, C) float32, linear HDR; the float32 buffers
    of :func:`render` are views of one allocation (fewer page faults), so keeping one keeps
    them all.

    Attributes:
        gi: (H, W, 3) global illumination = full - direct (denoised if ``config.denoise``).
        direct: (H, W, 3) the raster-DL equivalent (emission seen + shadowed sun/point/spot/area).
        full: (H, W, 3) direct + gi.
        variance: (H, W, 3) variance of the per-pixel mean of the (raw) gi estimate.
        spp: (H, W) int32 samples per pixel.
        mask: (H, W, 1) 1 where the pixel sees geometry (majority of its samples), else 0.
        albedo: (H, W, 3) first-hit albedo (mean over samples; 0 on background), or None.
        normal: (H, W, 3) first-hit world shading normal facing the camera, or None.
        gi_raw: (H, W, 3) the undenoised gi (the same array as ``gi`` without denoising).
        stats: :class:`TraceStats`.
        config: the :class:`TraceConfig` used.
    """

    gi: np.ndarray
    direct: np.ndarray
    full: np.ndarray
    variance: np.ndarray
    spp: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray | None
    normal: np.ndarray | None
    gi_raw: np.ndarray
    stats: TraceStats
    config: TraceConfig


# ---------------------------------------------------------------------------------- rng
_GOLD = 0x9E3779B97F4A7C15
_MASK64 = (1 << 64) - 1


def _mix_int(x: int) -> int:
    """splitmix64 finaliser on a Python int (the kernels use the same on uint64)."""
    x &= _MASK64
    x ^= x >> 30
    x = (x * 0xBF58476D1CE4E5B9) & _MASK64
    x ^= x >> 27
    x = (x * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


#: dimensions per bounce of the independent sampler: 0-1 bsdf direction, 2 light pick,
#: 3-4 point on light, 5 rr
_DIMS_PER_BOUNCE = 8


def _salts(seed: int, n_dims: int) -> np.ndarray:
    """(n_dims,) uint64 per-dimension salts of the independent sampler."""
    return np.array(
        [_mix_int(int(seed) * 0x632BE59BD9B4E019 + (dim + 1) * _GOLD) for dim in range(n_dims)],
        np.uint64,
    )


def _paint_boxes(grid: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Add 1 to ``grid[y0:y1 + 1, x0:x1 + 1]`` for each box (lo = (x0, y0), hi = (x1, y1), both
    (B, 2) inclusive grid indices): a 2D difference array, O(B + grid size) whatever B is."""
    if len(lo) == 0:
        return
    x0, y0 = lo.min(0)  # work in the boxes' bounding box only
    x1, y1 = hi.max(0)
    lo = lo - (x0, y0)
    hi = hi - (x0, y0)
    diff = np.zeros((y1 - y0 + 2, x1 - x0 + 2), np.int64)
    np.add.at(diff, (lo[:, 1], lo[:, 0]), 1)
    np.add.at(diff, (lo[:, 1], hi[:, 0] + 1), -1)
    np.add.at(diff, (hi[:, 1] + 1, lo[:, 0]), -1)
    np.add.at(diff, (hi[:, 1] + 1, hi[:, 0] + 1), 1)
    grid[y0 : y1 + 1, x0 : x1 + 1] += diff.cumsum(0).cumsum(1)[:-1, :-1].astype(grid.dtype)


def _contrast_edges(corners: np.ndarray) -> np.ndarray:
    """Cells (J - 1, I - 1) of a grid of corner luminances (J, I) whose four corners differ by
    more than :data:`EDGE_CONTRAST` of the brightest (False where a corner is NaN)."""
    a, b, c, d = corners[:-1, :-1], corners[:-1, 1:], corners[1:, :-1], corners[1:, 1:]
    hi = np.maximum(np.maximum(a, b), np.maximum(c, d))  # NaN where a corner is NaN
    lo = np.minimum(np.minimum(a, b), np.minimum(c, d))
    with np.errstate(invalid="ignore"):
        return (hi > 0) & (hi - lo > EDGE_CONTRAST * hi)


# ---------------------------------------------------------------------------------- sky
def _piecewise_2d(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A piecewise-constant 2D distribution over the cells of ``v`` (R, C) (non-negative, sum >
    0): the cell probabilities, the rows' marginal CDF (R,) and each row's conditional CDF
    (R, C) (uniform in an empty row)."""
    p = v / v.sum()
    marg = p.sum(1)
    marg_cdf = np.cumsum(marg)
    marg_cdf /= marg_cdf[-1]
    cond = np.where(marg[:, None] > 0, p / np.maximum(marg[:, None], 1e-300), 1.0 / v.shape[1])
    cond_cdf = np.cumsum(cond, axis=1)
    cond_cdf /= cond_cdf[:, -1:]
    return p, marg_cdf, cond_cdf


@dataclass(frozen=True)
class SkyTable:
    """A piecewise-constant importance function over the sphere, proportional to a sky's luminance.

    Cells are equal in ``c = d . up`` (rows, from -1 to 1) and in the azimuth ``phi`` (columns,
    about ``up`` from ``t1`` towards ``t2``), so every cell covers the same solid angle
    ``4 pi / (nc * nphi)``. Skies that do not depend on the azimuth (uniform, gradient) get one
    column. Sampling inverts the marginal (rows) and conditional (columns) CDFs, reusing the
    remainder of each uniform number for the position within the cell; ``pdf`` is exact for it.

    An environment map (``Sky.kind == 'envmap'``) gets the table of its own texel grid
    (:meth:`of_envmap`): rows are the latitude bands between its texel rows (equal in the polar
    angle, ``rows == 1``), columns the azimuth bands between its texel columns (starting at
    ``phi0``), each cell weighted by its mean luminance times its solid angle (the sin(theta)
    Jacobian of the lat-long parametrisation, integrated over the band).

    Attributes:
        frame: (3, 3) rows t1, t2, up.
        marg_cdf: (nc,) CDF over rows (last = 1).
        cond_cdf: (nc, nphi) CDF over columns per row (last = 1).
        pdf: (nc, nphi) density per unit solid angle of a direction in each cell.
        rows: 0: rows equal in c = d . up, from c = -1 up; 1: equal in the polar angle, from
            the pole along ``up`` down.
        phi0: azimuth where the first column starts.
    """

    frame: np.ndarray
    marg_cdf: np.ndarray
    cond_cdf: np.ndarray
    pdf: np.ndarray
    rows: int = 0
    phi0: float = 0.0

    @staticmethod
    def empty() -> SkyTable:
        return SkyTable(np.eye(3), np.ones(1), np.ones((1, 1)), np.zeros((1, 1)))

    @staticmethod
    def of(sky: Any, nc: int = 256, nphi: int | None = None, supersample: int = 4) -> SkyTable:
        """The table of ``sky`` (``sky.radiance(dirs)``, ``sky.up``, ``sky.kind``)."""
        if sky.kind == "envmap":
            return SkyTable.of_envmap(sky.envmap, sky.world_from_map)
        up = np.asarray(sky.up, np.float64)
        up = up / np.linalg.norm(up)
        a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t1 = np.cross(up, a)
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(up, t1)
        if nphi is None:
            nphi = 1 if sky.kind in ("uniform", "gradient") else 2 * nc
        ss = supersample
        c = -1.0 + (np.arange(nc * ss) + 0.5) / (nc * ss) * 2.0
        ph = (np.arange(nphi * ss) + 0.5) / (nphi * ss) * 2.0 * np.pi
        C, PH = np.meshgrid(c, ph, indexing="ij")
        sn = np.sqrt(np.maximum(0.0, 1.0 - C * C))
        dirs = (sn * np.cos(PH))[..., None] * t1 + (sn * np.sin(PH))[..., None] * t2
        dirs += C[..., None] * up
        lum = np.asarray(sky.radiance(dirs), np.float64) @ _LUM
        v = np.maximum(lum, 0.0).reshape(nc, ss, nphi, ss).mean(axis=(1, 3))
        if not v.sum() > 0:
            return SkyTable.empty()
        p, marg_cdf, cond_cdf = _piecewise_2d(v)
        pdf = p / (4.0 * np.pi / (nc * nphi))
        return SkyTable(
            np.ascontiguousarray(np.stack([t1, t2, up])),
            np.ascontiguousarray(marg_cdf),
            np.ascontiguousarray(cond_cdf),
            np.ascontiguousarray(pdf),
        )

    @staticmethod
    def of_envmap(envmap: np.ndarray, world_from_map: np.ndarray) -> SkyTable:
        """The table of a lat-long map (H, W, 3) in Mitsuba's convention (see
        :class:`icbtool.scene.Sky`): (H - 1) x W cells between texel centres."""
        from icbtool.scene.types import envmap_periodic

        m = envmap_periodic(envmap).astype(np.float64) @ _LUM  # (H, W + 1)
        h, w = m.shape[0], m.shape[1] - 1
        cell = 0.25 * (m[:-1, :-1] + m[:-1, 1:] + m[1:, :-1] + m[1:, 1:])  # (H - 1, W)
        th = np.arange(h) * (np.pi / (h - 1))
        band = np.cos(th[:-1]) - np.cos(th[1:])  # (H - 1,) solid angle / (2 pi) of each row
        solid = band[:, None] * (2.0 * np.pi / w)
        v = np.maximum(cell, 0.0) * solid
        r = np.asarray(world_from_map, np.float64)
        frame = np.ascontiguousarray(np.stack([-r[:, 2], r[:, 0], r[:, 1]]))
        if not v.sum() > 0:
            return SkyTable.empty()
        p, marg_cdf, cond_cdf = _piecewise_2d(v)
        pdf = p / solid
        return SkyTable(
            frame,
            np.ascontiguousarray(marg_cdf),
            np.ascontiguousarray(cond_cdf),
            np.ascontiguousarray(pdf),
            rows=1,
            phi0=float(np.pi / w),
        )

    def params(self, sky: Any = None, mis: bool = False) -> Any:
        """The kernels' :data:`~icbtool.trace.kernels.SkyParams` of this table and ``sky`` (an
        :class:`icbtool.scene.Sky` or None)."""
        K = _kernels()
        kind, rad = K.SKY_NONE, np.zeros((4, 3))
        env, rot, scale = np.zeros((3, 2, 3), np.float32), np.eye(3), 1.0
        if sky is not None:
            kind = {"uniform": K.SKY_UNIFORM, "gradient": K.SKY_GRADIENT}.get(
                sky.kind, K.SKY_ENVMAP
            )
            if sky.kind == "envmap":
                from icbtool.scene.types import envmap_periodic

                env = envmap_periodic(sky.envmap)
                # a writeable copy: the Sky's own array is read-only, and numba types a
                # read-only array apart (a second ~45 s compile of trace_paths)
                rot = np.array(sky.world_from_map, np.float64, order="C")
                scale = float(sky.envmap_scale)
            else:
                rad = np.array([sky.zenith, sky.horizon, sky.ground, sky.up], np.float64)
        return K.SkyParams(
            kind,
            rad,
            env,
            rot,
            scale,
            np.ascontiguousarray(self.frame, np.float64),
            np.ascontiguousarray(self.marg_cdf[None], np.float64),
            np.ascontiguousarray(self.cond_cdf, np.float64),
            np.ascontiguousarray(self.pdf, np.float64),
            int(self.rows),
            float(self.phi0),
            int(bool(mis)),
        )

    @property
    def peak(self) -> float:
        """Brightest cell's luminance over the mean over the sphere (1 = uniform)."""
        return float(self.pdf.max() * 4.0 * np.pi)

    def sample(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Directions (N, 3) and their pdf (N,) for uniform numbers u (N, 2) (as the kernels)."""
        u = np.ascontiguousarray(u, np.float64)
        d = np.empty((len(u), 3))
        pdf = np.empty(len(u))
        _kernels().sky_sample_batch(self.params(), u, d, pdf)
        return d, pdf

    def pdf_of(self, d: np.ndarray) -> np.ndarray:
        """Density (N,) of unit directions d (N, 3) (as the kernels evaluate it for MIS)."""
        d = np.ascontiguousarray(d, np.float64)
        out = np.empty(len(d))
        _kernels().sky_pdf_batch(self.params(), d, out)
        return out


# ---------------------------------------------------------------------------------- scene data
class _SceneData:
    """Per-scene arrays the tracer needs (cached: :mod:`icbtool.scene.derived`)."""

    def __init__(self, scene: Scene) -> None:
        f = scene.faces
        self.face_material = scene.face_material
        self.mat_albedo = np.stack([m.albedo for m in scene.materials]).astype(np.float64)
        self.mat_emission = np.stack([m.emission for m in scene.materials]).astype(np.float64)
        self.textures = {i: m.texture for i, m in enumerate(scene.materials) if m.is_textured}
        self.diag = max(scene.diagonal, 1e-30)
        # analytic shapes (icbtool.trace.shapes): primitive F + k; their tessellations are left
        # out of Embree's scene and of the emitters. The general (BSDF) kernel shades an exact
        # shape without uvs and in the Duff frame of its normal: where a shape's BSDF needs
        # them (a texture, a normal or bump map, anisotropy) the tessellations are traced
        from icbtool.scene.emitters import light_faces
        from icbtool.trace.shapes import pack_shapes

        shapes = tuple(scene.shapes)
        if any(_needs_surface_frame(scene.materials[sh.material].bsdf) for sh in shapes):
            shapes = ()
        self.shapes = shapes
        F, S = len(f), len(shapes)
        self.shape_table = pack_shapes(shapes)
        tess = np.zeros(F, bool)
        for sh in shapes:
            tess[sh.faces[0] : sh.faces[1]] = True
        # emitters: all emissive faces with positive area and emissive shapes, sampled by power
        # (the per-face emission is a temporary: 24 bytes a face the kernels never read)
        face_power = scene.face_areas * (self.mat_emission[self.face_material] @ _LUM)
        power = np.concatenate(
            [face_power, [sh.area * (self.mat_emission[sh.material] @ _LUM) for sh in shapes]]
        )
        power[:F][tess] = 0.0
        area = np.concatenate([scene.face_areas, [sh.area for sh in shapes]])
        emit = np.flatnonzero((power > 0) & np.isfinite(power))
        self.emit_faces = emit
        # emissive faces the camera can see (the edge probes' screen boxes): tessellations too
        self.seen_emit_faces = np.flatnonzero((face_power > 0) & np.isfinite(face_power))
        self.face_light_pmf = np.zeros(F + S)  # float64, contiguous
        if len(emit):
            p = power[emit] / power[emit].sum()
            self.face_light_pmf[emit] = p
            self.emit_cdf = np.cumsum(p)
            self.emit_cdf[-1] = 1.0
        self.face_area = np.ascontiguousarray(area, np.float64)
        # faces belonging to an AreaLight (their light is "direct"); others' light is GI; a
        # shape's light is direct when its tessellation is (the raster's DL has it then)
        lf = np.asarray(light_faces(scene))
        self.face_is_area_light = np.concatenate(
            [lf, [bool(lf[sh.faces[0] : sh.faces[1]].all()) for sh in shapes]]
        ).astype(bool)
        self.suns = scene.lights_of("directional")
        self.points = scene.lights_of("point")
        self.spots = scene.lights_of("spot")
        self.sky = scene.sky
        if self.sky is not None and self.sky.max_radiance <= 0:
            self.sky = None

        self._pack(scene)

    def _pack(self, scene: Scene) -> None:
        """Contiguous arrays for the numba kernels."""
        F = len(scene.faces)
        self.k_face_mat = np.ascontiguousarray(
            np.concatenate([self.face_material, [sh.material for sh in self.shapes]]), np.int64
        )
        # per-face geometry as the scene stores it (float32: half the memory the kernel reads at
        # random); albedo and emission per material (a tiny, cached table)
        f = scene.faces
        self.k_tri = np.ascontiguousarray(scene.vertices[f], np.float32)
        self.k_fn = np.ascontiguousarray(scene.face_normals, np.float32)
        self.k_vn = np.ascontiguousarray(scene.normals[f], np.float32)
        self.k_mat_albedo = np.ascontiguousarray(self.mat_albedo, np.float64)
        self.k_mat_emission = np.ascontiguousarray(self.mat_emission, np.float64)
        has_uv = scene.uvs is not None
        self.k_face_uv = (
            np.ascontiguousarray(scene.uvs[f], np.float32)
            if has_uv
            else np.zeros((1, 3, 2), np.float32)
        )
        M = len(scene.materials)
        general = any(m.bsdf is not None for m in scene.materials)
        self.k_tex_off = np.full(M, -1, np.int64)
        self.k_tex_hw = np.ones((M, 2), np.int64)
        chunks, off, at = [], 0, {}
        for m, tex in self.textures.items():
            if not has_uv or general:
                # no uvs: the texture cannot be looked up (the material albedo is used); the
                # general kernel reads its own texels (BsdfParams), never these
                continue
            if id(tex) not in at:  # materials sharing one texture array share its texels
                t = np.ascontiguousarray(tex, np.float32)
                at[id(tex)] = off
                chunks.append(t.reshape(-1))
                off += t.size
            self.k_tex_off[m] = at[id(tex)]
            self.k_tex_hw[m] = tex.shape[:2]
        self.k_tex, self.k_tex_lut = encode_texels(chunks)
        self.k_face_is_area = np.ascontiguousarray(self.face_is_area_light, np.bool_)
        self.k_emit_faces = np.ascontiguousarray(self.emit_faces, np.int64)
        self.k_emit_cdf = (
            np.ascontiguousarray(self.emit_cdf, np.float64) if len(self.emit_faces) else np.ones(1)
        )
        self.k_suns = np.array(
            [[*s.direction, *s.irradiance] for s in self.suns], np.float64
        ).reshape(-1, 6)
        rows = []
        for lt in [*self.points, *self.spots]:
            if lt.kind == "spot" and lt.profile == "linear":  # angles (radians), kind 2
                a_in, a_out = math.radians(lt.inner_deg), math.radians(lt.outer_deg)
                rows.append([*lt.position, *lt.intensity, *lt.direction, a_in, a_out, 2.0])
            elif lt.kind == "spot":
                c_in = math.cos(math.radians(lt.inner_deg))
                c_out = math.cos(math.radians(lt.outer_deg))
                rows.append([*lt.position, *lt.intensity, *lt.direction, c_in, c_out, 1.0])
            else:
                rows.append([*lt.position, *lt.intensity, 0, 0, 0, 1, 0, 0.0])
        self.k_punct = np.array(rows, np.float64).reshape(-1, 12)
        self.k_sky_table = SkyTable.empty() if self.sky is None else SkyTable.of(self.sky)
        # the kernels' sky parameters (an envmap's periodic copy made once per scene)
        self.k_sky_params = self.k_sky_table.params(self.sky)
        assert self.k_tri.shape == (F, 3, 3)
        # declared BSDFs (icbtool.scene.bsdf): the general kernel's node table, else None
        self.general = None
        if general:
            self.general = _general_data(scene, self.k_face_uv if has_uv else None)

    @classmethod
    def of(cls, scene: Scene) -> _SceneData:
        from icbtool.scene.derived import derived

        def build() -> _SceneData:
            t0 = time.perf_counter()
            sd = cls(scene)
            log.info(
                "scene '%s': tracer arrays packed in %.1f s", scene.name, time.perf_counter() - t0
            )
            return sd

        return derived(scene, "trace_data", build)


def _needs_surface_frame(b: Any) -> bool:
    """Whether a declared BSDF reads uvs or the tangent frame: a texture, a normal or bump map,
    or anisotropic roughness anywhere in it (None: a Lambert material, which does not)."""
    import dataclasses

    from icbtool.scene.bsdf import MAPPED_TYPES, Bitmap, Checkerboard

    if b is None:
        return False
    if isinstance(b, (*MAPPED_TYPES, Bitmap, Checkerboard)):
        return True
    if getattr(b, "alpha_u", None) is not None and b.alpha_u != b.alpha_v:
        return True
    if not dataclasses.is_dataclass(b):
        return False
    return any(_needs_surface_frame(getattr(b, f.name)) for f in dataclasses.fields(b))


@dataclass(frozen=True)
class _General:
    """What the general (BSDF) kernel reads beyond the Lambert kernel's parameters."""

    params: Any  # icbtool.trace.bsdfs.BsdfParams
    mat_root: np.ndarray  # (M,) int64
    face_t: np.ndarray  # (F, 3) float32 dp/du
    face_b: np.ndarray  # (F, 3) float32 dp/dv where the scene has a normal or bump map, else (1, 3)
    kinds: list[str]  # the BSDF plugins present

    @property
    def kernel_args(self) -> tuple:
        return self.params, self.mat_root, self.face_t, self.face_b


def _general_data(scene: Scene, face_uv: np.ndarray | None) -> _General:
    """The general kernel's BSDF table and per-face tangents: dp/du (Mitsuba's shading frame)
    where a face has uvs, and dp/dv too where the scene has a normal or bump map (a face whose
    uvs are degenerate takes Mitsuba's fallback, the two axes of ``coordinate_system`` of its
    normal). A scene without uvs cannot look maps up: they are dropped, with a warning."""
    from icbtool.scene.bsdf import MAPPED_TYPES
    from icbtool.trace.bsdfs import pack

    def mapped(b: Any) -> bool:
        if isinstance(b, MAPPED_TYPES):
            return True
        kids = [getattr(b, k, None) for k in ("front", "back", "bsdf", "bsdf0", "bsdf1")]
        return any(mapped(k) for k in kids if k is not None)

    maps = any(m.bsdf is not None and mapped(m.bsdf) for m in scene.materials)
    if maps and face_uv is None:
        log.warning(
            "scene '%s': normal/bump maps need texture coordinates and the scene has none: "
            "their nested BSDFs are traced without them",
            scene.name,
        )
    table = pack(scene.materials, maps=face_uv is not None)
    F = len(scene.faces)
    face_t = np.zeros((F, 3), np.float32)
    face_b = np.zeros((F if maps and face_uv is not None else 1, 3), np.float32)
    if face_uv is not None:
        for s in range(0, F, TANGENT_CHUNK):  # float64 temporaries for one chunk at a time
            e = min(s + TANGENT_CHUNK, F)
            _face_tangents(
                scene.vertices[scene.faces[s:e]],
                face_uv[s:e],
                scene.face_normals[s:e],
                face_t[s:e],
                face_b[s:e] if len(face_b) == F else None,
            )
    return _General(table.params, table.mat_root, np.ascontiguousarray(face_t), face_b, table.kinds)


#: Faces whose tangents are computed at once (their float64 temporaries: about 350 bytes a face).
TANGENT_CHUNK = 1 << 16


def _face_tangents(
    tri: np.ndarray,
    uv: np.ndarray,
    fn: np.ndarray,
    out_t: np.ndarray,
    out_b: np.ndarray | None,
) -> None:
    """Per-face dp/du (and dp/dv) of faces, computed in float64, written into float32 arrays.

    Args:
        tri: (N, 3, 3) corners.
        uv: (N, 3, 2) texture coordinates (OpenGL's v: flipped to Mitsuba's here).
        fn: (N, 3) unit face normals (the fallback frame of a face with degenerate uvs).
        out_t: (N, 3) float32, receives dp/du (zeros where the uvs are degenerate, unless
            ``out_b`` is given: then the first axis of the normal's ``coordinate_system``).
        out_b: (N, 3) float32 receiving dp/dv (else its fallback), or None.
    """
    p = tri.astype(np.float64)
    uv = uv.astype(np.float64)  # a copy
    uv[:, :, 1] = 1.0 - uv[:, :, 1]  # Mitsuba's v
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    ok = np.abs(det) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None]
    dpdu = (d2[:, 1:2] * e1 - d1[:, 1:2] * e2) * inv
    if out_b is None:
        out_t[:] = np.where(ok[:, None], dpdu, 0.0)
        return
    dpdv = (d1[:, 0:1] * e2 - d2[:, 0:1] * e1) * inv
    s, t = _coordinate_system(np.asarray(fn, np.float64))
    out_t[:] = np.where(ok[:, None], dpdu, s)
    out_b[:] = np.where(ok[:, None], dpdv, t)


def _coordinate_system(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's ``coordinate_system`` (Duff et al. 2017) of unit normals (N, 3): (s, t)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([n[:, 0] ** 2 * a * sign + 1, b * sign, -n[:, 0] * sign], 1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return s, t


# ---------------------------------------------------------------------------------- tracer
def _z_layout(cfg: TraceConfig, width: int, height: int) -> tuple[int, int]:
    """(log2 of the sample slots per pixel, shift) of the Z sampler's 32-bit sample key
    (Morton code of the pixel, then the sample index); shift -1 (per-pixel Sobol points) when
    the sampler is not 'zsobol' or the key would not fit in 32 bits."""
    log2spp = max(int(cfg.spp) - 1, 0).bit_length()
    nbits = max(max(int(width), int(height)) - 1, 0).bit_length()
    log2split = _log2_splits(cfg)
    used = 2 * nbits + log2spp + log2split
    if cfg.sampler != "zsobol" or used > 32:
        return log2spp, -1
    return log2spp, 32 - used + log2split


def _camera_kind(cam: Camera) -> int:
    """The kernels' camera kind (``CAM_*`` of :mod:`icbtool.trace.kernels`) of ``cam``."""
    K = _kernels()
    if cam.projection == "orthographic":
        return K.CAM_ORTHOGRAPHIC
    return K.CAM_PINHOLE if cam.is_pinhole else K.CAM_PERSPECTIVE


def _log2_splits(cfg: TraceConfig) -> int:
    """Bits of a branch's slot within its sample (``gi_splits`` rounded up to a power of 2)."""
    return (int(cfg.gi_splits) - 1).bit_length()


class Tracer:
    """One scene prepared for one camera: Embree's scene, the packed arrays, the kernel chosen
    (Lambert or general), the pixel statistics. :func:`render` builds one and drives its
    passes; profiling code builds one to time the kernel's stages."""

    def __init__(self, scene: Scene, cam: Camera, cfg: TraceConfig, stats: TraceStats) -> None:
        from icbtool.trace.rtc import RtcScene

        t0 = time.perf_counter()
        self.scene, self.cam, self.cfg, self.stats = scene, cam, cfg, stats
        self.sd = _SceneData.of(scene)
        self.rtc = RtcScene.of(scene, robust=cfg.robust, skip_shapes=len(self.sd.shapes) > 0)
        sd = self.sd
        sk = stats.skipped
        if sd.general is None:
            sk.append("general BSDF kernel: every material is Lambertian (the Lambert kernel)")
        else:
            sk.append(
                "Lambert kernel: declared BSDFs (" + ", ".join(sd.general.kinds) + ") need the "
                "general kernel (no gi_splits, no deferred texel loads)"
            )
        if not sd.textures:
            sk.append("texture lookups: no textured material")
        if not sd.suns:
            sk.append("sun sampling: no directional light")
        if not sd.points:
            sk.append("point light sampling: no point light")
        if not sd.spots:
            sk.append("spot light sampling: no spot light")
        if len(sd.emit_faces) == 0:
            sk.append("emitter sampling: no emissive triangle with positive area")
        if sd.sky is None:
            sk.append("sky: none (black environment)")
        mode = cfg.sky_sampling
        if mode == "auto" and sd.sky is not None:
            peak = sd.k_sky_table.peak
            mode = "mis" if peak > SKY_MIS_PEAK else "bsdf"
            if mode == "bsdf":
                sk.append(
                    f"sky light sampling: smooth sky (peak/mean luminance {peak:.2f} <= "
                    f"{SKY_MIS_PEAK}): cosine BSDF sampling finds it as well"
                )
        elif mode == "bsdf" and sd.sky is not None:
            sk.append("sky light sampling: sky_sampling='bsdf'")
        self.sky_mis = mode == "mis" and sd.sky is not None
        if not (cfg.aux or cfg.denoise):
            sk.append("aux buffers (albedo, normal): not asked for")
        for s in sk:
            log.info("trace: skipped %s", s)
        self._ws = _take_workspace()
        self.acc = self._pixel_stats()
        n_dims = 2 + (cfg.depth_limit + 1) * _DIMS_PER_BOUNCE
        self._salts = _salts(cfg.seed, n_dims)
        self._seed_mix = np.uint64(_mix_int(int(cfg.seed)))
        self._pixseed = np.uint64(_mix_int(int(cfg.seed) ^ 0x5851F42D4C957F2D))
        self._params = self._kernel_params()
        stats.add_time("setup", time.perf_counter() - t0)
        t0 = time.perf_counter()
        extra = self._edge_extra()
        if extra is not None:
            self._params = self._params._replace(cam=self._params.cam._replace(edge_extra=extra))
        stats.add_time("edges", time.perf_counter() - t0)

    def _emission_at(self, pts: np.ndarray) -> np.ndarray:
        """Luminance (N,) of the emission seen through the image points ``pts`` (N, 2) (x, y in
        pixels), on the render's threads; counted in ``stats.rays['edge_probe']``."""
        pts = np.ascontiguousarray(pts, np.float64)
        out = np.empty(len(pts), np.float64)
        _in_parts(_kernels().emission_at, (self._params, _LUM, pts, out), len(pts),
                  self.cfg.threads, 1024)  # fmt: skip
        self.stats.rays["edge_probe"] += len(pts)
        return out

    def _edge_extra(self) -> np.ndarray | None:
        """Per-pixel extra emission samples (N,) int32: ``TraceConfig.edge_samples`` on the pixels
        whose four corners see emission differing by more than :data:`EDGE_CONTRAST`, or None
        when no pixel gets any (``stats.skipped`` says why none were looked for).

        Which pixel corners are probed: every corner of each emissive face's screen box (so a
        light seen as a thin sliver is found), and, where emission can come from anywhere on
        screen (a sky, or an emissive face reaching behind the camera), the corners of blocks
        of :data:`EDGE_BLOCK` pixels first, then every corner of the blocks whose corners
        differ. A sky's outline that enters and leaves a block between two of its corners is
        missed there (those pixels keep one emission sample per sample: the image stays
        unbiased, only less smooth).
        """
        cfg, st, sd, cam = self.cfg, self.stats, self.sd, self.cam
        if cfg.edge_samples == 0:
            st.skipped.append("edge samples: edge_samples=0")
            return None
        if not cfg.pixel_jitter:
            st.skipped.append("edge samples: pixel_jitter=False (every sample sees the centre)")
            return None
        if cam.aperture_radius > 0:
            st.skipped.append("edge samples: a thin lens (the edges are blurred, not sharp)")
            return None
        H, W = cam.height, cam.width
        probe = np.zeros((H + 1, W + 1), np.int32)  # corners to probe (> 0), painted by boxes
        anywhere = sd.sky is not None
        if len(sd.seen_emit_faces):
            uv, z = cam.project(self.scene.vertices[self.scene.faces[sd.seen_emit_faces]])
            front = (z > 0).all(1)
            anywhere |= bool(((z > 0).any(1) & ~front).any())  # a face crossing the camera plane
            uv = uv[front]
            if len(uv):
                lo = np.clip(np.floor(uv.min(1)).astype(np.int64) - 1, 0, [W, H])
                hi = np.clip(np.ceil(uv.max(1)).astype(np.int64) + 1, 0, [W, H])
                keep = (hi > lo).all(1)
                _paint_boxes(probe, lo[keep], hi[keep])
        if anywhere:
            cx = np.unique(np.r_[np.arange(0, W, EDGE_BLOCK), W])
            cy = np.unique(np.r_[np.arange(0, H, EDGE_BLOCK), H])
            gx, gy = np.meshgrid(cx, cy)
            coarse = self._emission_at(np.stack([gx.ravel(), gy.ravel()], 1))
            blocks = np.argwhere(_contrast_edges(coarse.reshape(len(cy), len(cx))))
            lo = np.stack([cx[blocks[:, 1]], cy[blocks[:, 0]]], 1)
            hi = np.stack([cx[blocks[:, 1] + 1], cy[blocks[:, 0] + 1]], 1)
            _paint_boxes(probe, lo, hi)
        if not probe.any():
            st.skipped.append("edge samples: no emitter or sky in view")
            return None
        ys, xs = np.nonzero(probe)
        y0, y1, x0, x1 = ys.min(), ys.max(), xs.min(), xs.max()
        corners = np.full((y1 - y0 + 1, x1 - x0 + 1), np.nan)
        corners[ys - y0, xs - x0] = self._emission_at(np.stack([xs, ys], 1))
        edge = _contrast_edges(corners)  # pixels y0 .. y1 - 1, x0 .. x1 - 1
        st.edge_pixels = int(edge.sum())
        if st.edge_pixels == 0:
            return None
        extra = np.zeros((H, W), np.int32)
        extra[y0:y1, x0:x1][edge] = cfg.edge_samples
        return extra.reshape(-1)

    def _kernel_params(self) -> Any:
        """The kernels' :data:`~icbtool.trace.kernels.TraceParams` (fixed for a render)."""
        K = _kernels()
        cfg, sd, cam, rs = self.cfg, self.sd, self.cam, self.rtc
        sampler = K.SAMPLER_INDEPENDENT if cfg.sampler == "independent" else K.SAMPLER_SOBOL
        log2spp, zshift = _z_layout(cfg, cam.width, cam.height)
        return K.TraceParams(
            K.EmbreeFns(rs.ptr, rs.fn_intersect, rs.fn_occluded, rs.prim_map),
            K.View(
                np.array([cam.fx, cam.fy, cam.cx, cam.cy], np.float64),
                np.ascontiguousarray(cam.world_from_cam[:3, :3], np.float64),
                np.ascontiguousarray(cam.position, np.float64),
                int(cam.width),
                int(bool(cfg.pixel_jitter)),
                np.zeros(0, np.int32),  # edge_extra: set by _edge_extra
                _camera_kind(cam),
                np.array([cam.aperture_radius, cam.focus_distance, cam.near_clip], np.float64),
            ),
            K.Surfaces(
                sd.k_tri,
                sd.k_fn,
                sd.k_vn,
                sd.k_face_mat,
                sd.k_face_uv,
                sd.k_mat_albedo,
                sd.k_mat_emission,
                sd.k_tex,
                sd.k_tex_lut,
                sd.k_tex_off,
                sd.k_tex_hw,
                int(cfg.texture_filter == "nearest"),
                int(bool(cfg.shading_normals)),
                float(sd.diag),
                sd.shape_table,
            ),
            K.Lights(
                sd.k_suns,
                sd.k_punct,
                sd.face_light_pmf,
                sd.face_area,
                sd.k_face_is_area,
                sd.k_emit_faces,
                sd.k_emit_cdf[None],  # (1, E): a one-row CDF
            ),
            sd.k_sky_params._replace(mis=int(self.sky_mis)),
            K.Sampling(
                self._seed_mix,
                self._salts,
                self._pixseed,
                sampler,
                int(cfg.depth_limit),
                int(cfg.rr_depth),
                int(bool(cfg.aux or cfg.denoise)),
                log2spp,
                zshift,
                int(cfg.gi_splits),
                _log2_splits(cfg),
            ),
        )

    def _pixel_stats(self) -> Any:
        """Per-pixel statistics (:data:`~icbtool.trace.kernels.PixelStats`, workspace buffers)
        for the kernel to add samples to: the counts zeroed, the rest as the workspace left them
        (a pixel's first sample sets them, and a pixel without samples is never read)."""
        K = _kernels()
        ws, npix = self._ws, self.cam.height * self.cam.width
        n_aux = npix if (self.cfg.aux or self.cfg.denoise) else 1
        return K.PixelStats(
            _LUM,
            ws.zeros("acc_n", (npix,), np.int64),
            ws.get("acc_gi_mean", (npix, 4), np.float64),  # rgb + luminance
            ws.get("acc_gi_m2", (npix, 4), np.float64),
            ws.get("acc_dir_mean", (npix, 3), np.float64),
            ws.get("acc_dir_m2", (npix, 3), np.float64),
            ws.get("hit_sum", (npix,), np.float64),
            ws.get("alb_sum", (n_aux, 3), np.float64),
            ws.get("nrm_sum", (n_aux, 3), np.float64),
        )

    # ------------------------------------------------------------------ one pass
    def trace(self, pix: np.ndarray, sid: np.ndarray, ray_log: dict | None = None) -> None:
        """Trace one path for every (pixel, sample id) pair and add it to ``self.acc``.

        Args:
            pix, sid: (P,) pixel index (row-major, non-decreasing: a pixel's samples together)
                and sample index.
            ray_log: see :func:`render` (forces one thread).

        Raises:
            ValueError: ``pix`` is not sorted (two threads could then update one pixel).
        """
        K = _kernels()
        cfg, st = self.cfg, self.stats
        P = len(pix)
        pix = np.ascontiguousarray(pix, np.int64)
        sid = np.ascontiguousarray(sid, np.int64)
        if P > 1 and not bool((pix[1:] >= pix[:-1]).all()):
            raise ValueError("trace: pixel indices must be non-decreasing (samples by pixel)")
        # blocks of about BLOCK samples, each boundary moved on to the next pixel's first sample
        cut = np.searchsorted(pix, pix[np.arange(K.BLOCK, P, K.BLOCK) - 1], side="right")
        bounds = np.unique(np.concatenate([[0], cut, [P]])).astype(np.int64)
        n_blocks = len(bounds) - 1
        parts = 1 if ray_log is not None else max(1, min(cfg.threads, n_blocks))
        ws = self._ws
        want_aux = cfg.aux or cfg.denoise
        # one scratch row per part (the kernel zeroes it as each sample starts)
        rows = parts * K.ROW_STRIDE
        direct = ws.get("direct", (rows, 3), np.float64)
        gi = ws.get("gi", (rows, 3), np.float64)
        first_hit = ws.get("first_hit", (rows,), np.bool_)
        alb_out = ws.get("alb", (rows if want_aux else 1, 3), np.float64)
        nrm_out = ws.get("nrm", (rows if want_aux else 1, 3), np.float64)
        rl = ray_log_buffers(1) if ray_log is None else ray_log  # capacity 1: logging off
        log = (rl["o"], rl["d"], rl["tfar"], rl["kind"], rl["n"])
        counts = np.zeros((parts, 3), np.int64)
        queue = np.zeros(1, np.int64)  # the next block: the parts take blocks from it
        held = ws.get("held", (rows, 14), np.float64)
        out = K.Outputs(direct, gi, first_hit, alb_out, nrm_out, held)
        prm, acc = self._params, self.acc
        gen = self.sd.general
        if gen is None:
            kernel, extra = K.trace_paths, ()
        else:
            from icbtool.trace.general import trace_paths_general

            kernel, extra = trace_paths_general, gen.kernel_args
        t0 = time.perf_counter()
        if parts == 1:
            kernel(prm, *extra, out, acc, counts[0], log, 0, queue, pix, sid, bounds)
        else:
            pool = _pool(parts)
            futs = [
                pool.submit(
                    kernel, prm, *extra, out, acc, counts[i], log, i, queue, pix, sid, bounds
                )
                for i in range(parts)
            ]
            # on Ctrl-C the parts take no further block (each finishes the one it holds)
            _wait_parts(futs, stop=lambda: queue.fill(n_blocks))
        st.add_time("trace", time.perf_counter() - t0)
        c = counts.sum(0)
        st.rays["primary"] += int(c[0])
        st.rays["bounce"] += int(c[1])
        st.rays["shadow"] += int(c[2])


def _note_first_use(kernel: Any) -> None:
    """Say (once, as a warning) that the tracer's kernels are being compiled when ``kernel`` (a
    numba dispatcher) has nothing compiled in this process and nothing valid in numba's disk
    cache: the first render after an install or an update of the kernels then takes minutes
    (docs/benchmarks.md gives the measured time), which would otherwise look like a hang."""
    if kernel.signatures:
        return  # compiled or loaded in this process already
    try:  # numba's cache index for the kernel: empty when missing or made for other source
        cached = bool(kernel._cache._cache_file._load_index())
    except Exception:  # pragma: no cover - a numba without these internals: say nothing
        return
    if not cached:
        log.warning(
            "compiling the path tracer's kernels (numba): a few minutes on 2 cores, once per "
            "install or update of icbtool (`python -m icbtool.trace.warm` compiles both kernels "
            "at once); later runs load them from numba's cache"
        )


def _kernels():
    """The numba kernels module (imported on first use: numba is a heavy import)."""
    from icbtool.trace import kernels

    return kernels


class _Workspace:
    """Reusable buffers: fresh allocations page-fault on first touch, which costs about as much
    as a 1-spp pass's shading; ``get`` returns a C-contiguous view of a buffer grown as needed."""

    def __init__(self) -> None:
        self._bufs: dict[str, np.ndarray] = {}
        self._layouts: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        n = int(np.prod(shape))
        b = self._bufs.get(name)
        if b is None or b.size < n or b.dtype != np.dtype(dtype):
            b = np.empty(max(n, 1), dtype)
            self._bufs[name] = b
        return b[:n].reshape(shape)

    def zeros(self, name: str, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        a = self.get(name, shape, dtype)
        a.fill(0)
        return a

    def pass_samples(
        self, active: np.ndarray, npix: int, k: int, first: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """(pix, sid) of a pass that gives each pixel of ``active`` (sorted) its samples
        ``first .. first + k - 1``, pixel by pixel. A pass over the whole image keeps its pixel
        indices and in-pixel offsets here, built once per (image size, k): building them every
        pass (numpy repeats and page faults) was a measurable share of a low-spp render."""

        def layout(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Each pixel k times, and the in-pixel offsets 0 .. k - 1 beside them."""
            return np.repeat(pixels, k), np.tile(np.arange(k, dtype=np.int64), len(pixels))

        if len(active) != npix:
            pix, off = layout(active.astype(np.int64, copy=False))
            return pix, off + first
        key = (npix, k)
        if key not in self._layouts:
            if len(self._layouts) >= 4:
                self._layouts.clear()
            self._layouts[key] = layout(np.arange(npix, dtype=np.int64))
        pix, off = self._layouts[key]
        sid = self.get("sid", off.shape, np.int64)
        np.add(off, first, out=sid)
        return pix, sid

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self._bufs.values()) + sum(
            a.nbytes + b.nbytes for a, b in self._layouts.values()
        )


#: Workspaces kept between renders (a render takes one, or makes one, and gives it back).
_WS_FREE: list[_Workspace] = []
_WS_LOCK = threading.Lock()
#: Workspaces larger than this are not kept after a render.
_WS_KEEP_BYTES = 512 * 2**20


def _take_workspace() -> _Workspace:
    with _WS_LOCK:
        return _WS_FREE.pop() if _WS_FREE else _Workspace()


def _give_workspace(ws: _Workspace) -> None:
    with _WS_LOCK:
        if ws.nbytes <= _WS_KEEP_BYTES and len(_WS_FREE) < 2:
            _WS_FREE.append(ws)


def release_workspaces() -> int:
    """Drop the workspaces kept between renders (a server calls it after each render: the
    memory is worth more than the page faults of the next render). Returns the bytes dropped."""
    with _WS_LOCK:
        n = sum(ws.nbytes for ws in _WS_FREE)
        _WS_FREE.clear()
    return n


_POOL: ThreadPoolExecutor | None = None


def _pool(k: int) -> ThreadPoolExecutor:
    """A shared thread pool for the GIL-free kernels."""
    global _POOL
    if _POOL is None or _POOL._max_workers < k:
        _POOL = ThreadPoolExecutor(max_workers=k, thread_name_prefix="icb-trace")
    return _POOL


def _in_parts(
    kernel: Callable[..., None], args: tuple, n: int, threads: int, min_part: int
) -> None:
    """``kernel(*args, lo, hi)`` over [0, n) in up to ``threads`` contiguous parts of at least
    ``min_part`` items each, on the shared pool (the kernels release the GIL)."""
    parts = max(1, min(threads, n // min_part))
    if parts == 1:
        kernel(*args, 0, n)
        return
    cuts = np.linspace(0, n, parts + 1).astype(np.int64)
    pool = _pool(parts)
    _wait_parts([pool.submit(kernel, *args, int(a), int(b)) for a, b in zip(cuts, cuts[1:])])


def _wait_parts(futs: list[Future], stop: Callable[[], None] | None = None) -> None:
    """Wait for the parts of one kernel call on the pool, and re-raise the first error.

    A Ctrl-C raises KeyboardInterrupt here, in the waiting main thread, while the parts still
    run native code (numba, Embree) on this call's buffers and on the Embree scene. Unwinding
    then would free the scene under them (``Scene.__del__`` releases it), and they crash the
    process as it exits (exit 139 after "interrupted"). So the interrupt waits: ``stop()`` tells
    the parts to take no more work, every part returns, and only then does it propagate. A
    second Ctrl-C during that wait (milliseconds: one block per part) does not cut it short.

    Args:
        futs: the parts' futures.
        stop: makes the running parts return early (None: they run to the end of their part).

    Raises:
        KeyboardInterrupt: the wait was interrupted (raised after every part has returned).
        Exception: the first part's error.
    """
    try:
        for f in futs:
            f.result()
    except KeyboardInterrupt:
        if stop is not None:
            stop()
        while not all(f.done() for f in futs):
            try:
                wait(futs)
            except KeyboardInterrupt:  # Ctrl-C again: the parts are already stopping
                continue
        raise


# ---------------------------------------------------------------------------------- driver
def ray_log_buffers(capacity: int) -> dict[str, np.ndarray]:
    """Empty buffers for :func:`render`'s ``ray_log`` that hold the first ``capacity`` rays.

    Returns:
        {"o", "d": (capacity, 3) float32, "tfar": (capacity,) float32, "kind": (capacity,) int8,
        "n": (1,) int64 zero}.
    """
    return {
        "o": np.zeros((capacity, 3), np.float32),
        "d": np.zeros((capacity, 3), np.float32),
        "tfar": np.zeros(capacity, np.float32),
        "kind": np.zeros(capacity, np.int8),
        "n": np.zeros(1, np.int64),
    }


def _output_buffers(H: int, W: int, want_aux: bool) -> tuple[np.ndarray, ...]:
    """A render's float32 outputs: gi, direct, full, variance (H, W, 3), mask (H, W, 1) and,
    with ``want_aux``, albedo and normal (H, W, 3) (else None), as views of one block. One
    allocation of 4 MiB or more gets huge pages from numpy, so writing it first costs few page
    faults (the paired A/B: docs/benchmarks.md, tracer speed changes)."""
    npix = H * W
    n3 = 6 if want_aux else 4
    block = np.empty(npix * (3 * n3 + 1), np.float32)
    views = [block[i * 3 * npix : (i + 1) * 3 * npix].reshape(H, W, 3) for i in range(n3)]
    mask = block[n3 * 3 * npix :].reshape(H, W, 1)
    gi, direct, full, var = views[:4]
    albedo, normal = (views[4], views[5]) if want_aux else (None, None)
    return gi, direct, full, var, mask, albedo, normal


def render(
    scene: Scene,
    cam: Camera,
    config: TraceConfig | None = None,
    *,
    ray_log: dict[str, np.ndarray] | None = None,
    progress: bool | Callable[[TraceStats], None] = False,
) -> TraceResult:
    """Path trace one view progressively.

    Args:
        scene: the scene.
        cam: the camera (its height/width set the image size).
        config: :class:`TraceConfig` (default: ``TraceConfig()``, with the scene's
            ``max_depth`` when its file gives one, e.g. a Mitsuba integrator's).
        ray_log: for benchmarks: {"o", "d": (C, 3) float32, "tfar": (C,) float32, "kind": (C,)
            int8, "n": (1,) int64} (:func:`ray_log_buffers`) receives the first C rays traced,
            in order (kind 0: camera ray, 1: shadow ray, 2: bounce ray), with ``n`` counting
            them; it makes the render single-threaded.
        progress: True shows a progress bar (mean spp, relative error) on stderr; a callable
            is called with the :class:`TraceStats` after every pass (``stats.error_history[-1]``
            is (seconds, samples, relative error) so far).

    Returns:
        :class:`TraceResult` with (H, W, C) float32 buffers.

    Raises:
        ValueError: on a bad config or camera.
    """
    from icbtool.camera import Camera as _Camera
    from icbtool.scene import Scene as _Scene

    if config is None:
        depth = getattr(scene, "max_depth", None)
        cfg = TraceConfig() if depth is None else TraceConfig(max_depth=depth)
    else:
        cfg = config
    if not isinstance(cfg, TraceConfig):
        raise ValueError(f"config must be a TraceConfig, got {type(cfg).__name__}")
    if not isinstance(scene, _Scene):
        raise ValueError(f"scene must be an icbtool Scene, got {type(scene).__name__}")
    if not isinstance(cam, _Camera):
        raise ValueError(f"cam must be an icbtool Camera, got {type(cam).__name__}")
    t_start = time.perf_counter()
    _note_first_use(_kernels().trace_paths)  # before the edge probes compile their kernel too
    stats = TraceStats()
    tracer = Tracer(scene, cam, cfg, stats)
    H, W = cam.height, cam.width
    npix = H * W
    K = _kernels()
    ws = tracer._ws
    acc = tracer.acc
    want_aux = cfg.aux or cfg.denoise
    rel = ws.get("rel", (npix,), np.float64)
    active = np.arange(npix)
    n_skipped_pixels = 0
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=cfg.spp, desc=f"trace {W}x{H}", unit="spp", leave=False)
    n_done = 0  # every pass gives each active pixel k samples: they all have n_done
    while True:
        if n_done >= cfg.spp:
            stats.stop_reason = stats.stop_reason or "spp"
            break
        k = min(cfg.spp_per_pass, cfg.spp - n_done)
        pix, sid = ws.pass_samples(active, npix, k, n_done)
        n_done += k
        # a pass is traced in calls of at most MAX_SAMPLES_PER_CALL samples; each pixel's samples
        # are added in the same order, so the split changes nothing
        for a in range(0, len(pix), MAX_SAMPLES_PER_CALL):
            tracer.trace(
                pix[a : a + MAX_SAMPLES_PER_CALL], sid[a : a + MAX_SAMPLES_PER_CALL], ray_log
            )
        t0 = time.perf_counter()
        stats.passes += 1
        mean_rel = float(K.rel_error_lum(acc.n, acc.mean_g, acc.m2_g, acc.hit_sum, rel))
        stats.rel_error = mean_rel
        elapsed = time.perf_counter() - t_start
        stats.error_history.append((elapsed, int(acc.n.sum()), mean_rel))
        stats.add_time("accumulate", time.perf_counter() - t0)
        if bar is not None:
            bar.n = round(stats.error_history[-1][1] / npix, 2)
            bar.set_postfix(rel_err=f"{mean_rel:.4f}", refresh=True)
        elif callable(progress):
            progress(stats)
        if cfg.target_error is not None and mean_rel <= cfg.target_error and stats.passes >= 2:
            stats.stop_reason = "target_error"
            break
        if cfg.time_budget_s is not None and elapsed >= cfg.time_budget_s:
            stats.stop_reason = "time_budget"
            break
        if cfg.adaptive and stats.passes >= cfg.adaptive_min_passes:
            need = rel > cfg.target_error
            n_skipped_pixels = int(npix - need.sum())
            active = np.flatnonzero(need)
            if len(active) == 0:
                stats.stop_reason = "converged"
                break
    if bar is not None:
        bar.close()
    if n_skipped_pixels:
        stats.skipped.append(
            f"adaptive: {n_skipped_pixels} of {npix} pixels below the target error stopped early"
        )
    # ---- outputs
    t0 = time.perf_counter()
    gi, direct, full, var, mask, albedo, normal = _output_buffers(H, W, want_aux)
    finish_args = (
        acc.n,
        acc.mean_g,
        acc.m2_g,
        acc.mean_d,
        acc.hit_sum,
        acc.alb_sum,
        acc.nrm_sum,
        want_aux,
        gi.reshape(npix, 3),
        direct.reshape(npix, 3),
        var.reshape(npix, 3),
        mask.reshape(npix),
        (albedo if want_aux else gi).reshape(npix, 3),
        (normal if want_aux else gi).reshape(npix, 3),
    )
    _in_parts(K.finish, finish_args, npix, cfg.threads, 4096)
    spp = acc.n.reshape(H, W).astype(np.int32)
    stats.samples = int(acc.n.sum())
    _give_workspace(ws)  # (lost on an exception: then it is simply garbage)
    stats.add_time("accumulate", time.perf_counter() - t0)
    gi_raw = gi
    if cfg.denoise:
        t0 = time.perf_counter()
        gi = denoise(gi, albedo, normal, quality=cfg.denoise_quality)
        stats.add_time("denoise", time.perf_counter() - t0)
    stats.time_s["total"] = time.perf_counter() - t_start
    log.info(
        "trace: %dx%d, %d passes, %.1f spp mean, %.2f s, %.2f Mrays/s, rel.err %.4f (%s)",
        W,
        H,
        stats.passes,
        stats.samples / npix,
        stats.time_s["total"],
        stats.total_rays / max(stats.time_s["total"], 1e-9) / 1e6,
        stats.rel_error,
        stats.stop_reason,
    )
    return TraceResult(
        gi=gi,
        direct=direct,
        full=np.add(direct, gi, out=full),
        variance=var,
        spp=spp,
        mask=mask,
        albedo=albedo,
        normal=normal,
        gi_raw=gi_raw,
        stats=stats,
        config=cfg,
    )


def denoise_inputs(
    color: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The images :func:`denoise` hands Open Image Denoise: contiguous float32 colour clamped at
    zero, albedo clipped to [0, 1], and the normal only beside an albedo (OIDN's rule)."""
    c = np.ascontiguousarray(np.maximum(color, 0), np.float32)
    a = None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32)
    nn = None if (normal is None or a is None) else np.ascontiguousarray(normal, np.float32)
    return c, a, nn


def denoise(
    color: np.ndarray,
    albedo: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    quality: DenoiseQuality = "high",
) -> np.ndarray:
    """Open Image Denoise (pyoidn, HDR) with optional first-hit albedo/normal aux buffers.

    Args:
        color: (H, W, 3) linear HDR, >= 0.
        albedo: (H, W, 3) in [0, 1] or None.
        normal: (H, W, 3) in [-1, 1] or None (needs albedo too).
        quality: OIDN's quality setting (see ``TraceConfig.denoise_quality``).

    Returns:
        (H, W, 3) float32.

    Raises:
        icbtool.optional.MissingOptionalDependency: pyoidn is not installed (the message says
            ``pip install ".[denoise]"`` in the checkout).
    """
    from icbtool.optional import require

    pyoidn = require("pyoidn", "denoising (Open Image Denoise)")
    c, a, nn = denoise_inputs(color, albedo, normal)
    check_denoise_quality(quality, "denoise quality")
    out = pyoidn.denoise(c, a, nn, hdr=True, quality=quality)
    return np.maximum(np.asarray(out, np.float32), 0.0)


def release_denoiser() -> bool:
    """Free Open Image Denoise's device and filter that pyoidn keeps for the life of the process
    (with scratch buffers sized for the last image: about 600 MB at 1024^2); the next
    :func:`denoise` makes them again (at no measurable cost beside the denoising itself).

    Returns:
        True when pyoidn held resources that were released.
    """
    import sys

    mod = sys.modules.get("pyoidn.denoise")  # not imported: nothing was denoised
    owner = getattr(mod, "_denoiser", None)
    if owner is None or not getattr(owner, "_resources", None):
        return False
    owner.close()
    return True


def render_gi(scene: Scene, cam: Camera, spp: int = 64, seed: int = 0, **kwargs: Any) -> np.ndarray:
    """(H, W, 3) float32 linear HDR GI map (``render(...).gi``); kwargs go to TraceConfig."""
    return render(scene, cam, TraceConfig(spp=spp, seed=seed, **kwargs)).gi


__all__ = [
    "HARD_MAX_DEPTH",
    "SKY_MIS_PEAK",
    "SkyTable",
    "TraceConfig",
    "TraceResult",
    "TraceStats",
    "Tracer",
    "denoise",
    "render",
    "render_gi",
]
