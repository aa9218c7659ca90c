"""A progressive wavefront path tracer: GI maps (full - DL) with Embree and numpy.

Light transport: two-sided Lambertian surfaces (textured albedo), one-sided emissive faces, a
directional sun, point and spot lights (delta lights: next-event estimation only), emissive
triangles (next-event estimation sampled by power, combined with BSDF sampling by multiple
importance sampling, power heuristic) and a sky (reached by cosine-weighted BSDF sampling, which
is a good importance function for a smooth sky; no sky light sampling, so no MIS is needed).

The DL/GI split (fixed system-wide): ``direct`` = emission of the first visible surface + direct
light at the first hit from the scene's directional, point, spot and *area* lights (the emissive
quads registered as :class:`~icbtool.scene.AreaLight`), shadowed. Everything else (sky light at the
first hit, light from other emissive geometry, all light that bounced at least once) is ``gi``.
Camera rays that miss: ``direct`` = sky radiance, ``gi`` = 0.

Depth convention (as Mitsuba's ``max_depth``): a path of ``k`` segments has depth ``k``; depth 1 is
an emitter seen directly, depth 2 direct lighting; ``max_depth = -1`` is unbounded (Russian
roulette ends paths; a hard cap of :data:`HARD_MAX_DEPTH` guards against hangs).

Determinism: every random number is a hash of (seed, pixel, sample index, dimension), so an image
depends on the seed and the config only, never on the number of threads or on timing (a time
budget changes how many samples are taken, not the samples themselves).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera
    from icbtool.scene import Scene
    from icbtool.trace.embree import EmbreeScene

log = logging.getLogger(__name__)

#: Upper bound on the path depth even with ``max_depth = -1`` (no hang on albedo-1 scenes).
HARD_MAX_DEPTH = 1024
_LUM = np.array([0.2126, 0.7152, 0.0722])


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
    pixel_jitter: bool = True
    """Box-filter pixels by jittering primary rays; False samples pixel centres (like a raster)."""
    shading_normals: bool = True
    """Use interpolated vertex normals for shading (False: flat geometric normals)."""
    texture_filter: Literal["bilinear", "nearest"] = "bilinear"
    """Texel lookup (textures repeat outside [0, 1])."""
    threads: int = 2
    """Threads for Embree queries (results do not depend on it)."""
    robust: bool = True
    """Embree robust (watertight) mode."""
    aux: bool = True
    """Compute the first-hit albedo and normal buffers (forced on by ``denoise``)."""

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ValueError:
            return ValueError(f"TraceConfig.{name} {why}, got {getattr(self, name)!r}")

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
    """Wall time per phase (setup, rng, primary, intersect, shadow, shade, accumulate, denoise)."""
    rays: dict[str, int] = field(default_factory=lambda: {"primary": 0, "bounce": 0, "shadow": 0})
    """Rays traced by kind."""
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
    error_history: list[tuple[float, int, float]] = field(default_factory=list)
    """(time_s, samples, rel_error) after each pass."""

    def add_time(self, phase: str, dt: float) -> None:
        self.time_s[phase] = self.time_s.get(phase, 0.0) + dt

    @property
    def total_rays(self) -> int:
        return int(sum(self.rays.values()))


@dataclass
class TraceResult:
    """The buffers of one traced view. All (H, W, C) float32, linear HDR.

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
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = 0x9E3779B97F4A7C15
_MASK64 = (1 << 64) - 1


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    x = x ^ (x >> np.uint64(30))
    x = x * _M1
    x = x ^ (x >> np.uint64(27))
    x = x * _M2
    return x ^ (x >> np.uint64(31))


def _mix_int(x: int) -> int:
    x &= _MASK64
    x ^= x >> 30
    x = (x * 0xBF58476D1CE4E5B9) & _MASK64
    x ^= x >> 27
    x = (x * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


class _Rng:
    """Counter-based uniforms: u = hash(seed, pixel, sample, dimension) in [0, 1)."""

    def __init__(self, seed: int, pixel: np.ndarray, sample: np.ndarray) -> None:
        self.seed = int(seed)
        key = (pixel.astype(np.uint64) << np.uint64(24)) ^ sample.astype(np.uint64)
        with np.errstate(over="ignore"):
            self.base = _mix(key * np.uint64(_GOLD) + np.uint64(_mix_int(self.seed)))

    def uniform(self, dim: int, idx: np.ndarray | None = None) -> np.ndarray:
        b = self.base if idx is None else self.base[idx]
        salt = np.uint64(_mix_int(self.seed * 0x632BE59BD9B4E019 + (dim + 1) * _GOLD))
        with np.errstate(over="ignore"):
            x = _mix(b ^ salt)
        return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


#: dimensions per bounce: 0-1 bsdf direction, 2 light pick, 3-4 point on light, 5 rr
_DIMS_PER_BOUNCE = 8


# ---------------------------------------------------------------------------------- scene data
class _SceneData:
    """Per-scene arrays the tracer needs (cached in ``scene._cache``)."""

    def __init__(self, scene: Scene) -> None:
        v = scene.vertices.astype(np.float64)
        f = scene.faces
        self.tri = v[f]  # (F, 3, 3)
        self.e1 = self.tri[:, 1] - self.tri[:, 0]
        self.e2 = self.tri[:, 2] - self.tri[:, 0]
        self.fn = scene.face_normals.astype(np.float64)
        self.vn = scene.normals.astype(np.float64)[f]  # (F, 3, 3)
        self.face_material = scene.face_material
        self.mat_albedo = np.stack([m.albedo for m in scene.materials]).astype(np.float64)
        self.mat_emission = np.stack([m.emission for m in scene.materials]).astype(np.float64)
        self.textures = {i: m.texture for i, m in enumerate(scene.materials) if m.is_textured}
        self.face_uv = None if scene.uvs is None else scene.uvs.astype(np.float64)[f]
        self.face_albedo = self.mat_albedo[self.face_material]
        self.face_emission = self.mat_emission[self.face_material]
        self.face_textured = np.array([m.is_textured for m in scene.materials])[self.face_material]
        b = scene.bounds
        self.extent = float(np.max(np.abs(b)))
        self.diag = max(scene.diagonal, 1e-30)
        # emitters: all emissive faces with positive area, sampled by power
        area = scene.face_areas
        power = area * (self.face_emission @ _LUM)
        emit = np.flatnonzero((power > 0) & np.isfinite(power))
        self.emit_faces = emit
        self.face_light_pmf = np.zeros(len(f))
        if len(emit):
            p = power[emit] / power[emit].sum()
            self.face_light_pmf[emit] = p
            self.emit_cdf = np.cumsum(p)
            self.emit_cdf[-1] = 1.0
        self.face_area = area
        # faces belonging to an AreaLight (their light is "direct"); others' light is GI
        self.face_is_area_light = np.zeros(len(f), bool)
        emissive = np.flatnonzero(np.any(self.face_emission > 0, axis=1))
        for light in scene.lights_of("area"):
            if len(emissive) == 0:
                break
            n = light.normal
            tol = 1e-4 * max(np.linalg.norm(light.edge_u) + np.linalg.norm(light.edge_v), 1e-30)
            pts = self.tri[emissive] - light.corner  # (E, 3, 3)
            on_plane = np.abs(pts @ n).max(1) <= tol
            gram = np.array(
                [
                    [light.edge_u @ light.edge_u, light.edge_u @ light.edge_v],
                    [light.edge_u @ light.edge_v, light.edge_v @ light.edge_v],
                ]
            )
            if abs(np.linalg.det(gram)) < 1e-300:
                continue
            st = np.linalg.solve(
                gram, np.stack([pts @ light.edge_u, pts @ light.edge_v], -1).reshape(-1, 2).T
            ).T.reshape(-1, 3, 2)
            inside = np.all((st >= -1e-3) & (st <= 1 + 1e-3), axis=(1, 2))
            self.face_is_area_light[emissive[on_plane & inside]] = True
        self.suns = scene.lights_of("directional")
        self.points = scene.lights_of("point")
        self.spots = scene.lights_of("spot")
        self.sky = scene.sky
        if self.sky is not None and self.sky.max_radiance <= 0:
            self.sky = None

    @classmethod
    def of(cls, scene: Scene) -> _SceneData:
        d = scene._cache.get("trace_data")
        if d is None:
            d = cls(scene)
            scene._cache["trace_data"] = d
        return d

    # ------------------------------------------------------------------ surface queries
    def texture_albedo(self, prim: np.ndarray, b1: np.ndarray, b2: np.ndarray, nearest: bool):
        """(N, 3) albedo at hits, material albedo times texture."""
        alb = self.face_albedo[prim].copy()
        if not self.textures:
            return alb
        tex_hits = np.flatnonzero(self.face_textured[prim])
        if len(tex_hits) == 0:
            return alb
        p = prim[tex_hits]
        w0 = (1 - b1[tex_hits] - b2[tex_hits])[:, None]
        uv = (
            w0 * self.face_uv[p, 0]
            + b1[tex_hits, None] * self.face_uv[p, 1]
            + b2[tex_hits, None] * self.face_uv[p, 2]
        )
        mats = self.face_material[p]
        for m, tex in self.textures.items():
            sel = np.flatnonzero(mats == m)
            if len(sel) == 0:
                continue
            h, w = tex.shape[:2]
            x = uv[sel, 0] * w - 0.5
            y = (1.0 - uv[sel, 1]) * h - 0.5
            if nearest:
                xi = np.floor(x + 0.5).astype(np.int64) % w
                yi = np.floor(y + 0.5).astype(np.int64) % h
                t = tex[yi, xi].astype(np.float64)
            else:
                x0, y0 = np.floor(x), np.floor(y)
                fx, fy = (x - x0)[:, None], (y - y0)[:, None]
                x0 = x0.astype(np.int64) % w
                y0 = y0.astype(np.int64) % h
                x1, y1 = (x0 + 1) % w, (y0 + 1) % h
                t = (1 - fy) * ((1 - fx) * tex[y0, x0] + fx * tex[y0, x1]) + fy * (
                    (1 - fx) * tex[y1, x0] + fx * tex[y1, x1]
                )
            alb[tex_hits[sel]] *= t
        return alb


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _normalize(a: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(a, axis=1, keepdims=True)
    ok = n > 1e-20
    return np.where(ok, a / np.where(ok, n, 1.0), fallback)


def _cosine_sample(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions about unit normals n (N, 3) (Duff et al. basis)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    bt = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    z = np.sqrt(np.maximum(0.0, 1 - u1))
    return (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * bt + z[:, None] * n


# ---------------------------------------------------------------------------------- tracer
class _Tracer:
    def __init__(self, scene: Scene, cam: Camera, cfg: TraceConfig, stats: TraceStats) -> None:
        from icbtool.trace.embree import EmbreeScene

        t0 = time.perf_counter()
        self.scene, self.cam, self.cfg, self.stats = scene, cam, cfg, stats
        self.es: EmbreeScene = EmbreeScene.from_scene(scene, robust=cfg.robust, threads=cfg.threads)
        self.sd = _SceneData.of(scene)
        sd = self.sd
        sk = stats.skipped
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
        if not (cfg.aux or cfg.denoise):
            sk.append("aux buffers (albedo, normal): not asked for")
        for s in sk:
            log.info("trace: skipped %s", s)
        stats.add_time("setup", time.perf_counter() - t0)

    def eps(self, p: np.ndarray, t: np.ndarray | float) -> np.ndarray:
        """Offset distance at points p (N, 3) reached by rays of length t (float32-safe)."""
        mag = np.abs(p).max(1)
        return 3e-5 * (mag + np.abs(t)) + 1e-6 * self.sd.diag

    # ------------------------------------------------------------------ one pass
    def trace(self, pix: np.ndarray, sid: np.ndarray):
        """Trace one sample for every (pixel, sample id) pair.

        Returns:
            direct, gi (P, 3); hit (P,) bool; albedo, normal (P, 3) or None.
        """
        cfg, sd, st = self.cfg, self.sd, self.stats
        P = len(pix)
        tt = time.perf_counter()
        rng = _Rng(cfg.seed, pix, sid)
        W = self.cam.width
        if cfg.pixel_jitter:
            jx, jy = rng.uniform(0), rng.uniform(1)
        else:
            jx = jy = np.full(P, 0.5)
        uv = np.stack([pix % W + jx, pix // W + jy], -1)
        o, d, _ = self.cam.rays(uv)
        st.add_time("rng", time.perf_counter() - tt)
        direct = np.zeros((P, 3))
        gi = np.zeros((P, 3))
        first_hit = np.zeros(P, bool)
        want_aux = cfg.aux or cfg.denoise
        alb_out = np.zeros((P, 3)) if want_aux else None
        nrm_out = np.zeros((P, 3)) if want_aux else None

        idx = np.arange(P)  # alive path -> sample
        thr = np.ones((P, 3))
        pdf_prev = np.zeros(P)  # solid-angle pdf of the bsdf sample that led here
        from_first = np.zeros(P, bool)  # the current ray left the first hit (for the DL split)
        limit = cfg.depth_limit
        for depth in range(1, limit + 1):  # ray segment number `depth` arrives at vertex `depth`
            if len(idx) == 0:
                break
            t0 = time.perf_counter()
            hits = self.es.intersect(o, d)
            st.rays["primary" if depth == 1 else "bounce"] += len(idx)
            st.add_time("intersect", time.perf_counter() - t0)
            t0 = time.perf_counter()
            hit = hits.hit
            # ---- misses: sky
            miss = np.flatnonzero(~hit)
            if len(miss) and sd.sky is not None:
                le = sd.sky.radiance(d[miss]).astype(np.float64) * thr[miss]
                if depth == 1:
                    direct[idx[miss]] += le
                else:
                    gi[idx[miss]] += le
            h = np.flatnonzero(hit)
            if len(h) == 0:
                st.add_time("shade", time.perf_counter() - t0)
                break
            idx, o, d, thr = idx[h], o[h], d[h], thr[h]
            pdf_prev, from_first = pdf_prev[h], from_first[h]
            prim = hits.prim[h]
            b1 = hits.u[h].astype(np.float64)
            b2 = hits.v[h].astype(np.float64)
            thit = hits.t[h].astype(np.float64)
            w0 = 1.0 - b1 - b2
            tri = sd.tri[prim]
            x = w0[:, None] * tri[:, 0] + b1[:, None] * tri[:, 1] + b2[:, None] * tri[:, 2]
            ng = sd.fn[prim]
            cos_o = -_dot(ng, d)
            degenerate = ~np.any(ng != 0, axis=1)
            ng = np.where(degenerate[:, None], -d, ng)
            cos_o = np.where(degenerate, 1.0, cos_o)
            front = cos_o > 0
            nf = np.where(front[:, None], ng, -ng)  # geometric normal facing the incoming ray
            if cfg.shading_normals:
                vn = sd.vn[prim]
                ns = _normalize(
                    w0[:, None] * vn[:, 0] + b1[:, None] * vn[:, 1] + b2[:, None] * vn[:, 2], nf
                )
                ns = np.where((_dot(ns, nf) < 0)[:, None], -ns, ns)
            else:
                ns = nf
            # ---- emission seen (one-sided)
            le_face = sd.face_emission[prim]
            em = np.flatnonzero(front & np.any(le_face > 0, axis=1))
            if len(em):
                le = le_face[em] * thr[em]
                if depth == 1:
                    direct[idx[em]] += le
                else:
                    pe = prim[em]
                    pl = (
                        sd.face_light_pmf[pe]
                        / np.maximum(sd.face_area[pe], 1e-300)
                        * thit[em] ** 2
                        / np.maximum(cos_o[em], 1e-12)
                    )
                    pb = pdf_prev[em]
                    w = np.where(pl > 0, pb * pb / np.maximum(pb * pb + pl * pl, 1e-300), 1.0)
                    le = le * w[:, None]
                    to_direct = from_first[em] & sd.face_is_area_light[pe]
                    direct[idx[em[to_direct]]] += le[to_direct]
                    gi[idx[em[~to_direct]]] += le[~to_direct]
            albedo = sd.texture_albedo(prim, b1, b2, cfg.texture_filter == "nearest")
            if depth == 1:
                first_hit[idx] = True
                if want_aux:
                    alb_out[idx] = albedo
                    nrm_out[idx] = ns
            if depth >= limit:
                st.add_time("shade", time.perf_counter() - t0)
                break
            # ---- survive: drop paths with zero throughput*albedo (exact, unbiased)
            fthr = thr * albedo  # throughput after a cosine-sampled Lambertian bounce
            alive = np.any(fthr > 0, axis=1)
            if not np.all(alive):
                keep = np.flatnonzero(alive)
                idx, o, d, thr, fthr, x, ng, nf, ns, albedo, thit = (
                    a[keep] for a in (idx, o, d, thr, fthr, x, ng, nf, ns, albedo, thit)
                )
            n = len(idx)
            if n == 0:
                st.add_time("shade", time.perf_counter() - t0)
                break
            eps = self.eps(x, thit)
            xo = x + nf * eps[:, None]  # origin offset to the incoming side
            dim0 = 2 + depth * _DIMS_PER_BOUNCE
            # ---- next-event estimation: gather shadow rays
            so, sdr, stf, sc, sdst = [], [], [], [], []  # origin, dir, tfar, contribution, dest
            to_dir = depth == 1
            f_over = thr * albedo / np.pi  # throughput * BRDF
            for sun in sd.suns:
                wi = np.broadcast_to(-sun.direction, (n, 3))
                c = np.minimum(_dot(ns, wi), 1.0)
                ok = np.flatnonzero((c > 0) & (_dot(nf, wi) > 0))
                if len(ok):
                    so.append(xo[ok])
                    sdr.append(wi[ok])
                    stf.append(np.full(len(ok), np.inf))
                    sc.append(f_over[ok] * sun.irradiance * c[ok, None])
                    sdst.append((ok, to_dir))
            for lt in [*sd.points, *sd.spots]:
                v = lt.position - x
                dist = np.linalg.norm(v, axis=1)
                wi = v / np.maximum(dist, 1e-300)[:, None]
                c = np.minimum(_dot(ns, wi), 1.0)
                inten = np.broadcast_to(lt.intensity, (n, 3))
                if lt.kind == "spot":
                    inten = (
                        inten
                        * lt.falloff(-_dot(wi, np.broadcast_to(lt.direction, (n, 3))))[:, None]
                    )
                ok = np.flatnonzero(
                    (c > 0) & (_dot(nf, wi) > 0) & (dist > 0) & np.any(inten > 0, axis=1)
                )
                if len(ok):
                    so.append(xo[ok])
                    sdr.append(wi[ok])
                    stf.append(dist[ok] * (1 - 1e-5) - eps[ok])
                    sc.append(f_over[ok] * inten[ok] * (c[ok] / dist[ok] ** 2)[:, None])
                    sdst.append((ok, to_dir))
            if len(sd.emit_faces):
                ul = rng.uniform(dim0 + 2, idx)
                k = np.minimum(
                    np.searchsorted(sd.emit_cdf, ul, side="right"), len(sd.emit_faces) - 1
                )
                lf = sd.emit_faces[k]
                r1 = np.sqrt(rng.uniform(dim0 + 3, idx))
                r2 = rng.uniform(dim0 + 4, idx)
                y = (
                    sd.tri[lf, 0]
                    + (r1 * (1 - r2))[:, None] * sd.e1[lf]
                    + (r1 * r2)[:, None] * sd.e2[lf]
                )
                v = y - x
                dist = np.linalg.norm(v, axis=1)
                wi = v / np.maximum(dist, 1e-300)[:, None]
                c = np.minimum(_dot(ns, wi), 1.0)
                cl = -_dot(sd.fn[lf], wi)
                ok = np.flatnonzero((c > 0) & (cl > 0) & (_dot(nf, wi) > 0) & (dist > 0))
                if len(ok):
                    pl = sd.face_light_pmf[lf[ok]] / sd.face_area[lf[ok]] * dist[ok] ** 2 / cl[ok]
                    pb = c[ok] / np.pi
                    w = pl * pl / (pl * pl + pb * pb)
                    contrib = f_over[ok] * sd.face_emission[lf[ok]] * (c[ok] * w / pl)[:, None]
                    eps_l = self.eps(y[ok], dist[ok])
                    is_dir = sd.face_is_area_light[lf[ok]] if to_dir else np.zeros(len(ok), bool)
                    so.append(xo[ok])
                    sdr.append(wi[ok])
                    stf.append(np.maximum(dist[ok] - eps[ok] - eps_l, 0.0))
                    sc.append(contrib)
                    sdst.append((ok, is_dir))
            st.add_time("shade", time.perf_counter() - t0)
            if so:
                t0 = time.perf_counter()
                blocked = self.es.occluded(
                    np.concatenate(so), np.concatenate(sdr), np.concatenate(stf)
                )
                st.rays["shadow"] += len(blocked)
                st.add_time("shadow", time.perf_counter() - t0)
                t0 = time.perf_counter()
                off = 0
                for contrib, (ok, is_dir) in zip(sc, sdst):
                    m = len(ok)
                    vis = ~blocked[off : off + m]
                    off += m
                    is_dir = np.broadcast_to(np.asarray(is_dir), (m,))
                    sel = vis & is_dir
                    direct[idx[ok[sel]]] += contrib[sel]
                    sel = vis & ~is_dir
                    gi[idx[ok[sel]]] += contrib[sel]
                st.add_time("shade", time.perf_counter() - t0)
            t0 = time.perf_counter()
            # ---- bounce: cosine-weighted about the shading normal
            wi = _cosine_sample(ns, rng.uniform(dim0, idx), rng.uniform(dim0 + 1, idx))
            below = _dot(wi, nf)
            wi = np.where((below <= 0)[:, None], wi - 2 * below[:, None] * nf, wi)
            wi = _normalize(wi, nf)
            pdf_prev = np.maximum(_dot(ns, wi), 1e-12) / np.pi
            thr = fthr
            if depth + 1 > cfg.rr_depth:  # Russian roulette for the next segment
                q = np.minimum(thr.max(1), 0.95)
                live = rng.uniform(dim0 + 5, idx) < q
                keep = np.flatnonzero(live)
                idx, thr, wi, pdf_prev, xo = (a[keep] for a in (idx, thr, wi, pdf_prev, xo))
                thr = thr / q[keep, None]
            o, d = xo, wi
            from_first = np.full(len(idx), depth == 1)
            st.add_time("shade", time.perf_counter() - t0)
        return direct, gi, first_hit, alb_out, nrm_out


# ---------------------------------------------------------------------------------- driver
class _Accum:
    """Per-pixel running mean and M2 (Welford/Chan) of C channels."""

    def __init__(self, npix: int, c: int) -> None:
        self.n = np.zeros(npix, np.int64)
        self.mean = np.zeros((npix, c))
        self.m2 = np.zeros((npix, c))

    def add(self, pix: np.ndarray, x: np.ndarray) -> None:
        """Merge a batch of samples x (P, C) of pixels pix (P,) (any number per pixel)."""
        npix = len(self.n)
        nb = np.bincount(pix, minlength=npix).astype(np.int64)
        c = x.shape[1]
        sb = np.stack([np.bincount(pix, x[:, i], minlength=npix) for i in range(c)], 1)
        has = nb > 0
        mb = np.zeros_like(sb)
        mb[has] = sb[has] / nb[has, None]
        dev = x - mb[pix]
        m2b = np.stack([np.bincount(pix, dev[:, i] ** 2, minlength=npix) for i in range(c)], 1)
        na = self.n
        ntot = na + nb
        delta = mb - self.mean
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(ntot > 0, nb / np.maximum(ntot, 1), 0.0)[:, None]
            self.mean = np.where(has[:, None], self.mean + delta * frac, self.mean)
            self.m2 = np.where(
                has[:, None], self.m2 + m2b + delta**2 * (na * frac[:, 0])[:, None], self.m2
            )
        self.n = ntot

    def var_of_mean(self) -> np.ndarray:
        n = self.n[:, None].astype(np.float64)
        return np.where(n > 1, self.m2 / np.maximum(n - 1, 1) / np.maximum(n, 1), 0.0)


def _rel_error(acc: _Accum, covered: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-pixel relative standard error of the GI luminance (channel 3) and its mean."""
    mean = np.abs(acc.mean[:, 3])
    se = np.sqrt(acc.var_of_mean()[:, 3])
    sel = covered & (acc.n > 0)
    if not sel.any():
        return np.zeros(len(mean)), 0.0
    floor = max(1e-2 * float(mean[sel].mean()), 1e-12)
    rel = se / np.maximum(mean, floor)
    rel = np.where(acc.n > 1, rel, np.inf)
    return rel, float(np.mean(np.where(sel, rel, 0.0)[sel]))


def render(scene: Scene, cam: Camera, config: TraceConfig | None = None) -> TraceResult:
    """Path trace one view progressively.

    Args:
        scene: the scene.
        cam: the camera (its height/width set the image size).
        config: :class:`TraceConfig` (default: ``TraceConfig()``).

    Returns:
        :class:`TraceResult` with (H, W, C) float32 buffers.

    Raises:
        ValueError: on a bad config or camera.
    """
    from icbtool.camera import Camera as _Camera
    from icbtool.scene import Scene as _Scene

    cfg = TraceConfig() if config is None else config
    if not isinstance(cfg, TraceConfig):
        raise ValueError(f"config must be a TraceConfig, got {type(cfg).__name__}")
    if not isinstance(scene, _Scene):
        raise ValueError(f"scene must be an icbtool Scene, got {type(scene).__name__}")
    if not isinstance(cam, _Camera):
        raise ValueError(f"cam must be an icbtool Camera, got {type(cam).__name__}")
    t_start = time.perf_counter()
    stats = TraceStats()
    tracer = _Tracer(scene, cam, cfg, stats)
    H, W = cam.height, cam.width
    npix = H * W
    acc_gi = _Accum(npix, 4)  # rgb + luminance
    acc_dir = _Accum(npix, 3)
    hit_sum = np.zeros(npix)
    want_aux = cfg.aux or cfg.denoise
    alb_sum = np.zeros((npix, 3)) if want_aux else None
    nrm_sum = np.zeros((npix, 3)) if want_aux else None
    active = np.arange(npix)
    n_skipped_pixels = 0
    while True:
        remaining = cfg.spp - acc_gi.n[active]
        active = active[remaining > 0]
        if len(active) == 0:
            stats.stop_reason = stats.stop_reason or "spp"
            break
        k = np.minimum(cfg.spp_per_pass, cfg.spp - acc_gi.n[active])
        pix = np.repeat(active, k)
        start = np.repeat(acc_gi.n[active], k)
        sid = start + (np.arange(len(pix)) - np.repeat(np.cumsum(k) - k, k))
        direct, gi, hit, alb, nrm = tracer.trace(pix, sid)
        t0 = time.perf_counter()
        lum = gi @ _LUM
        acc_gi.add(pix, np.concatenate([gi, lum[:, None]], 1))
        acc_dir.add(pix, direct)
        hit_sum += np.bincount(pix, hit.astype(np.float64), minlength=npix)
        if want_aux:
            for i in range(3):
                alb_sum[:, i] += np.bincount(pix, alb[:, i], minlength=npix)
                nrm_sum[:, i] += np.bincount(pix, nrm[:, i], minlength=npix)
        stats.passes += 1
        covered = hit_sum > 0.5 * np.maximum(acc_gi.n, 1)
        rel, mean_rel = _rel_error(acc_gi, covered)
        stats.rel_error = mean_rel
        elapsed = time.perf_counter() - t_start
        stats.error_history.append((elapsed, int(acc_gi.n.sum()), mean_rel))
        stats.add_time("accumulate", time.perf_counter() - t0)
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
    if n_skipped_pixels:
        stats.skipped.append(
            f"adaptive: {n_skipped_pixels} of {npix} pixels below the target error stopped early"
        )
    # ---- outputs
    n = np.maximum(acc_gi.n, 1)[:, None]
    gi = acc_gi.mean[:, :3].reshape(H, W, 3).astype(np.float32)
    direct = acc_dir.mean.reshape(H, W, 3).astype(np.float32)
    var = acc_gi.var_of_mean()[:, :3].reshape(H, W, 3).astype(np.float32)
    mask = (hit_sum / n[:, 0] > 0.5).reshape(H, W, 1).astype(np.float32)
    albedo = normal = None
    if want_aux:
        albedo = (alb_sum / n).reshape(H, W, 3).astype(np.float32)
        normal = _normalize(nrm_sum / n, np.zeros((1, 3))).reshape(H, W, 3).astype(np.float32)
    gi_raw = gi
    if cfg.denoise:
        t0 = time.perf_counter()
        gi = denoise(gi, albedo, normal)
        stats.add_time("denoise", time.perf_counter() - t0)
    stats.samples = int(acc_gi.n.sum())
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
        full=(direct + gi).astype(np.float32),
        variance=var,
        spp=acc_gi.n.reshape(H, W).astype(np.int32),
        mask=mask,
        albedo=albedo,
        normal=normal,
        gi_raw=gi_raw,
        stats=stats,
        config=cfg,
    )


def denoise(
    color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None
) -> np.ndarray:
    """Open Image Denoise (pyoidn, HDR) with optional first-hit albedo/normal aux buffers.

    Args:
        color: (H, W, 3) linear HDR, >= 0.
        albedo: (H, W, 3) in [0, 1] or None.
        normal: (H, W, 3) in [-1, 1] or None (needs albedo too).

    Returns:
        (H, W, 3) float32.
    """
    try:
        import pyoidn
    except ImportError as e:  # pragma: no cover
        raise ImportError(
            "denoising needs pyoidn: pip install pyoidn (see requirements.lock)"
        ) from e
    c = np.ascontiguousarray(np.maximum(color, 0), np.float32)
    a = None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32)
    nn = None if (normal is None or a is None) else np.ascontiguousarray(normal, np.float32)
    out = pyoidn.denoise(c, a, nn, hdr=True)
    return np.maximum(np.asarray(out, np.float32), 0.0)


def render_gi(scene: Scene, cam: Camera, spp: int = 64, seed: int = 0, **kwargs: Any) -> np.ndarray:
    """(H, W, 3) float32 linear HDR GI map (``render(...).gi``); kwargs go to TraceConfig."""
    return render(scene, cam, TraceConfig(spp=spp, seed=seed, **kwargs)).gi


__all__ = [
    "HARD_MAX_DEPTH",
    "TraceConfig",
    "TraceResult",
    "TraceStats",
    "denoise",
    "render",
    "render_gi",
]
