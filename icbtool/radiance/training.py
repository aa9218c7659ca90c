"""Training a world-space irradiance model from a store's CRT-buffers, resumable.

``train(store, config, out_dir)`` fits :class:`RadianceConfig` (the multi-resolution grid + MLP,
Adam on random batches of the train path's surface pixels) or :class:`ProbeConfig` (the probe
volume, one weighted least-squares solve) and evaluates the GI ``albedo * E`` on whole views of
the evaluation paths (SSIM / MSE on the display scale, :mod:`icbtool.metrics`).

A run directory holds:

- ``config.json``: the resolved config, the model's shape, the records used, versions, machine;
- ``radiance.pt``: what :meth:`icbtool.radiance.RadianceModel.load` reads;
- ``checkpoints/last.pt`` (grid): model, optimiser, sampler RNG, step, evaluations and elapsed
  seconds; written atomically, never after a non-finite loss;
- ``evals.csv`` / ``evals.json``: every evaluation (iteration, path, views, SSIM, MSE, seconds);
- ``samples/<path>_NNNNNN.png``: prediction | truth | |difference| of each path's first view.

Resuming (``resume=True``) continues the grid's training from the checkpoint: a run stopped at a
checkpoint and resumed ends with the same weights as an uninterrupted one (same machine and
threads); the ``seconds`` column goes on from the stopped run's elapsed time.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from icbtool.metrics import mse as mse_metric
from icbtool.metrics import ssim as ssim_metric
from icbtool.provenance import run_info, write_json
from icbtool.radiance.data import (
    Bounds,
    PixelSamples,
    pixels_from_records,
    records_of_path,
    sh_basis_np,
    surface_maps,
)
from icbtool.radiance.model import MODEL_FILE, RadianceModel, save_model
from icbtool.radiance.models import (
    FieldSpec,
    IrradianceField,
    ProbeSpec,
    ProbeVolume,
    corner_lookup_np,
)
from icbtool.runs import atomic_save, sample_png, scene_key, write_evals


class RadianceDivergedError(RuntimeError):
    """The loss became NaN/Inf or exceeded ``divergence_limit``; the last checkpoint is kept."""


def _check_int(cls: str, name: str, v: Any, lo: int = 1) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or v < lo:
        raise ValueError(f"{cls}.{name} must be an integer >= {lo}, got {v!r}")


def _check_float(cls: str, name: str, v: Any, lo: float = 0.0, strict: bool = False) -> None:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if not ok or v < lo or (strict and v == lo):
        rel = ">" if strict else ">="
        raise ValueError(f"{cls}.{name} must be a finite number {rel} {lo}, got {v!r}")


def _check_common(cfg: Any) -> None:
    cls = type(cfg).__name__
    _check_float(cls, "albedo_floor", cfg.albedo_floor, 0.0, strict=True)
    _check_float(cls, "display_exposure", cfg.display_exposure, 0.0, strict=True)
    _check_float(cls, "normal_offset", cfg.normal_offset)
    _check_int(cls, "max_train_pixels", cfg.max_train_pixels, 0)
    _check_int(cls, "eval_views", cfg.eval_views, 0)
    _check_int(cls, "seed", cfg.seed, 0)
    tp = (cfg.train_paths,) if isinstance(cfg.train_paths, str) else tuple(cfg.train_paths)
    if not tp or not all(isinstance(p, str) and p for p in tp) or len(set(tp)) != len(tp):
        raise ValueError(f"{cls}.train_paths must be distinct path names, got {cfg.train_paths!r}")
    object.__setattr__(cfg, "train_paths", tp)
    paths = tuple(cfg.eval_paths)
    if not all(isinstance(p, str) and p for p in paths) or len(set(paths)) != len(paths):
        raise ValueError(f"{cls}.eval_paths must be distinct path names, got {cfg.eval_paths!r}")
    object.__setattr__(cfg, "eval_paths", paths)
    if cfg.sh_order not in (0, 1, 2):
        raise ValueError(f"{cls}.sh_order must be 0, 1 or 2, got {cfg.sh_order!r}")


class _ConfigIO:
    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)  # type: ignore[call-overload]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Any:
        names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}")
        tup = {k: tuple(v) for k, v in d.items() if isinstance(v, list)}
        return cls(**{**d, **tup})


@dataclass(frozen=True)
class _FitConfig(_ConfigIO):
    """The fields every world-space model's fit shares (what it learns from, how it is scored)."""

    albedo_floor: float = 0.05
    """Demodulation floor: targets are GI / max(albedo, floor), weighted by min(albedo/floor, 1)."""
    train_paths: tuple[str, ...] = ("train",)
    """Camera-path tags of the training records (e.g. the train path and views baked to cover
    what it missed)."""
    eval_paths: tuple[str, ...] = ("test",)
    """Camera-path tags evaluated (whole views: SSIM/MSE of albedo * E against the GI)."""
    eval_views: int = 0
    """At most this many views per evaluation path (the first ones; 0: all)."""
    display_exposure: float = 1.0
    """Exposure of the display transform of the metrics."""
    seed: int = 0
    """Seed of the initialisation (if any) and of the pixel draws."""


@dataclass(frozen=True)
class RadianceConfig(_FitConfig):
    """The multi-resolution grid + MLP model and its training (written to ``config.json``)."""

    levels: int = 12
    """Grid levels (resolutions grow geometrically from base_resolution to max_resolution)."""
    features: int = 2
    """Features per grid vertex."""
    log2_table: int = 16
    """Entries per level are at most 2^log2_table; finer levels are hashed into that many."""
    base_resolution: int = 8
    """Cells of the coarsest level along the scene's longest axis."""
    max_resolution: int = 512
    """Cells of the finest level along the scene's longest axis."""
    hidden: int = 64
    """Width of the MLP's hidden layers."""
    layers: int = 2
    """Hidden layers of the MLP."""
    sh_order: int = 2
    """Order of the normal's polynomial basis fed to the MLP (0, 1 or 2: 1, 4 or 9 terms)."""
    normal_offset: float = 0.0
    """Look the grid up this many finest-level cells along the normal (0: at the surface)."""
    iterations: int = 3000
    """Adam steps (a resumed run may raise it; the learning-rate schedule follows it)."""
    batch_size: int = 16384
    """Surface pixels per step, drawn uniformly with replacement from the train path."""
    lr: float = 1e-2
    """Initial Adam learning rate."""
    lr_decay: float = 0.1
    """The learning rate decays exponentially to lr * lr_decay at the last iteration."""
    betas: tuple[float, float] = (0.9, 0.99)
    """Adam betas (instant-ngp's)."""
    eps: float = 1e-15
    """Adam epsilon (tiny, as instant-ngp: rarely touched hash entries still move)."""
    loss: Literal["l2", "l1"] = "l2"
    """Loss on the log-irradiance log1p(E / scale), weighted per channel by the albedo."""
    max_train_pixels: int = 0
    """Keep at most this many train pixels (a seeded uniform draw; 0: all)."""
    eval_every: int = 500
    """Evaluate every this many iterations (and at the end)."""
    checkpoint_every: int = 500
    """Checkpoint every this many iterations (and at the end)."""
    divergence_limit: float = 1e6
    """A loss above this stops training (as does NaN/Inf)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Where to train."""

    def __post_init__(self) -> None:
        c = "RadianceConfig"
        for n in ("levels", "features", "base_resolution", "max_resolution", "hidden",
                  "iterations", "batch_size", "eval_every", "checkpoint_every"):  # fmt: skip
            _check_int(c, n, getattr(self, n))
        _check_int(c, "layers", self.layers, 0)
        _check_int(c, "log2_table", self.log2_table, 4)
        if self.log2_table > 24:
            raise ValueError(f"{c}.log2_table must be <= 24, got {self.log2_table}")
        if self.max_resolution < self.base_resolution:
            raise ValueError(
                f"{c}.max_resolution ({self.max_resolution}) must be >= base_resolution "
                f"({self.base_resolution})"
            )
        _check_float(c, "lr", self.lr, 0.0, strict=True)
        _check_float(c, "lr_decay", self.lr_decay, 0.0, strict=True)
        _check_float(c, "eps", self.eps, 0.0, strict=True)
        _check_float(c, "divergence_limit", self.divergence_limit, 0.0, strict=True)
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ValueError(f"{c}.betas must be two numbers in [0, 1), got {self.betas}")
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))
        if self.loss not in ("l2", "l1"):
            raise ValueError(f"{c}.loss must be 'l2' or 'l1', got {self.loss!r}")
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"{c}.device must be 'cpu' or 'cuda', got {self.device!r}")
        _check_common(self)


@dataclass(frozen=True)
class ProbeConfig(_FitConfig):
    """The irradiance probe volume and its least-squares fit (written to ``config.json``)."""

    resolution: int = 24
    """Probes along the scene's longest axis (shorter axes: proportionally fewer, >= 2)."""
    sh_order: int = 1
    """Each probe's irradiance basis in the normal: 1 (L1: c0 + c . n) or 2 (9 terms)."""
    smoothness: float = 1e-3
    """Weight of the squared second differences of the coefficients between neighbouring probes
    (per probe) against the weighted mean squared irradiance error (per pixel); it also fills
    probes that no train pixel reaches. Its null space holds every trilinear field."""
    normal_offset: float = 0.25
    """Look the probes up this many probe spacings along the normal (light-leak bias)."""
    max_train_pixels: int = 300_000
    """Fit on at most this many train pixels (a seeded uniform draw; 0: all)."""
    cg_rtol: float = 1e-6
    """Conjugate gradients stop at this relative residual of the normal equations."""
    cg_maxiter: int = 2000
    """...or after this many iterations (a warning then gives the residual reached)."""

    def __post_init__(self) -> None:
        _check_int("ProbeConfig", "resolution", self.resolution, 2)
        _check_float("ProbeConfig", "smoothness", self.smoothness)
        _check_float("ProbeConfig", "cg_rtol", self.cg_rtol, 0.0, strict=True)
        _check_int("ProbeConfig", "cg_maxiter", self.cg_maxiter)
        _check_common(self)


@dataclass
class RadianceResult:
    """What :func:`train` did.

    Attributes:
        run_dir: the run directory.
        steps: iterations done (0 for a probe volume).
        evals: every evaluation row (dicts of :data:`EVAL_COLUMNS`).
        seconds: elapsed time of the whole run, resumed parts included.
    """

    run_dir: Path
    steps: int
    evals: list[dict[str, Any]]
    seconds: float

    def last(self, path: str) -> dict[str, Any] | None:
        """The latest evaluation row of ``path``."""
        rows = [r for r in self.evals if r["path"] == path]
        return rows[-1] if rows else None


EVAL_COLUMNS = ("iteration", "path", "views", "ssim", "mse", "seconds")


# ------------------------------------------------------------------------------ evaluation
@dataclass
class EvalView:
    """One view of an evaluation path, in memory."""

    record_id: int
    surface: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    gi: np.ndarray


def load_views(store: Any, record_ids: list[int]) -> list[EvalView]:
    """Whole views (surface pixels and the GI truth) of some records."""
    out = []
    for rid in record_ids:
        rec = store.get(rid)
        m = surface_maps(rec, f"store record {rid}")
        s = m["surface"]
        out.append(
            EvalView(
                rid,
                s,
                m["position"][s],
                m["normal_world"][s],
                m["albedo"],
                np.asarray(rec.gi, np.float32),
            )
        )
    return out


def predict_view(model: RadianceModel, v: EvalView) -> np.ndarray:
    """(H, W, 3) GI of ``model`` at a view."""
    gi = np.zeros_like(v.gi)
    if v.surface.any():
        gi[v.surface] = v.albedo[v.surface] * model.irradiance(v.position, v.normal)
    return gi


def evaluate_views(
    model: RadianceModel, views: list[EvalView], exposure: float
) -> tuple[dict[str, float], np.ndarray | None]:
    """Mean SSIM / MSE (display scale 0-255) of ``model`` over views.

    Returns:
        (``{"views", "ssim", "mse"}``, (H, W, 3) prediction of the first view or None).
    """
    s, m, first = [], [], None
    for v in views:
        pred = predict_view(model, v)
        s.append(ssim_metric(pred, v.gi, exposure))
        m.append(mse_metric(pred, v.gi, exposure))
        if first is None:
            first = pred
    return {"views": len(views), "ssim": float(np.mean(s)), "mse": float(np.mean(m))}, first


def _eval_sets(store: Any, cfg: Any, scene: Any) -> dict[str, list[int]]:
    out = {}
    for p in cfg.eval_paths:
        ids = records_of_path(store, p, scene)
        if not ids:
            raise ValueError(
                f"the store has no records on the evaluation path {p!r} (with albedo, "
                "normal_world, position, mask and gi); bake it or change eval_paths"
            )
        out[p] = ids[: cfg.eval_views] if cfg.eval_views else ids
    return out


def _train_samples(store: Any, cfg: Any, scene: Any) -> PixelSamples:
    ids = []
    for path in cfg.train_paths:
        got = records_of_path(store, path, scene)
        if not got:
            raise ValueError(
                f"the store has no records on the train path {path!r} (with albedo, "
                f"normal_world, position, mask and gi); bake it first (icbtool bake ... --path "
                f"{path})"
            )
        ids += got
    return pixels_from_records(store, ids, cfg.max_train_pixels, cfg.seed)


# ------------------------------------------------------------------------------ probes
def probe_spec(bounds: Bounds, cfg: ProbeConfig) -> ProbeSpec:
    """Probe counts per axis (cubic-ish spacing) and the normal offset in scene units."""
    ext = bounds.extent
    probes = np.maximum(2, np.ceil((cfg.resolution - 1) * ext / ext.max() - 1e-9) + 1)
    probes = tuple(int(v) for v in probes)
    spacing = float(np.min(ext / (np.asarray(probes) - 1)))
    return ProbeSpec(bounds, probes, cfg.sh_order, cfg.normal_offset * spacing)  # type: ignore


def _second_differences(probes: tuple[int, int, int]) -> Any:
    """Sparse (R, P) operator of the second differences along each axis of a probe grid."""
    import scipy.sparse as sp

    nx, ny, nz = probes
    ops = []
    eye = [sp.identity(n, format="csr") for n in (nx, ny, nz)]
    for axis, n in enumerate((nx, ny, nz)):
        if n < 3:
            continue
        d = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n), format="csr")
        mats = [d if a == axis else eye[a] for a in range(3)]
        # index = x + nx * (y + ny * z): kron(z, kron(y, x))
        ops.append(sp.kron(mats[2], sp.kron(mats[1], mats[0], format="csr"), format="csr"))
    if not ops:
        return sp.csr_matrix((0, nx * ny * nz))
    return sp.vstack(ops, format="csr")


#: Probe fits with at most this many unknowns (probes x basis terms) are solved directly.
DIRECT_UNKNOWNS = 8000


def fit_probe_volume(
    samples: PixelSamples,
    spec: ProbeSpec,
    albedo_floor: float,
    smoothness: float,
    cg_rtol: float = 1e-6,
    cg_maxiter: int = 2000,
) -> np.ndarray:
    """Least-squares probe coefficients (module doc of :mod:`icbtool.radiance.models`).

    Minimises, per colour channel ``c``, ``sum_i w_ic (E(p_i, n_i) - e_ic)^2 / sum_i w_ic +
    smoothness * |D x_c|^2 / P`` (``D``: second differences between neighbouring probes, ``P``
    probes) over the coefficients ``x_c``, with ``E`` the trilinear interpolation of the probes'
    bases, ``e`` the demodulated targets and ``w`` their weights (:func:`demodulate`). The normal
    equations (plus a 1e-9 relative ridge) are solved directly (sparse LU) up to
    :data:`DIRECT_UNKNOWNS` unknowns, above that by Jacobi-preconditioned conjugate gradients to
    relative residual ``cg_rtol`` (a direct solve of a 3D probe grid fills in: 16^3 probes x 4
    took over a minute; CG's iterations are cheap but converge slowly where only the smoothness
    term reaches).

    Returns:
        (P, K, 3) float32 coefficients.

    Raises:
        ValueError: no samples.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import LinearOperator, cg, spsolve

    if len(samples) == 0:
        raise ValueError("no train pixels to fit the probe volume on")
    e, w = samples.targets(albedo_floor)
    b = spec.bounds
    p = samples.position.astype(np.float64) + spec.normal_offset * samples.normal
    x = (p - np.asarray(b.lo)) / b.extent
    idx, tw = corner_lookup_np(x, spec.cells)  # (N, 8)
    basis = sh_basis_np(samples.normal, spec.sh_order)  # (N, K)
    n, k, pc = len(samples), basis.shape[1], spec.count
    vals = (tw[:, :, None] * basis[:, None, :]).reshape(n, -1)
    cols = (idx[:, :, None] * k + np.arange(k)[None, None, :]).reshape(n, -1)
    rows = np.repeat(np.arange(n), 8 * k)
    a = sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(n, pc * k))
    d = sp.kron(_second_differences(spec.probes), sp.identity(k), format="csr")
    reg = (smoothness / pc) * (d.T @ d)
    out = np.zeros((pc, k, 3), np.float64)
    for c in range(3):
        wc = w[:, c].astype(np.float64)
        tot = wc.sum()
        if tot <= 0:
            continue  # a channel with no usable pixel: zero irradiance
        wa = a.multiply(wc[:, None] / tot).tocsr()
        m = (a.T @ wa + reg).tocsr()
        diag = m.diagonal()
        ridge = 1e-9 * max(float(diag.mean()), 1e-30)
        m = m + sp.identity(pc * k, format="csr") * ridge
        rhs = wa.T @ e[:, c].astype(np.float64)
        if pc * k <= DIRECT_UNKNOWNS:
            out[:, :, c] = spsolve(m.tocsc(), rhs).reshape(pc, k)
            continue
        inv = 1.0 / (diag + ridge)
        pre = LinearOperator(m.shape, matvec=lambda v, inv=inv: v * inv)
        sol, info = cg(m, rhs, rtol=cg_rtol, maxiter=cg_maxiter, M=pre)
        if info > 0:
            res = float(np.linalg.norm(m @ sol - rhs) / max(np.linalg.norm(rhs), 1e-300))
            warnings.warn(
                f"probe fit, channel {c}: conjugate gradients stopped after {cg_maxiter} "
                f"iterations at relative residual {res:.2e} (asked {cg_rtol:g})",
                stacklevel=2,
            )
        out[:, :, c] = sol.reshape(pc, k)
    return out.astype(np.float32)


def _fit_probes_run(
    store: Any, cfg: ProbeConfig, run_dir: Path, scene: Any, progress: bool
) -> RadianceResult:
    t0 = time.perf_counter()
    samples = _train_samples(store, cfg, scene)
    eval_ids = _eval_sets(store, cfg, scene)
    bounds = Bounds.of_points(samples.position)
    spec = probe_spec(bounds, cfg)
    coef = fit_probe_volume(
        samples, spec, cfg.albedo_floor, cfg.smoothness, cfg.cg_rtol, cfg.cg_maxiter
    )
    module = ProbeVolume(spec, coef)
    fit_s = time.perf_counter() - t0
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "samples").mkdir(exist_ok=True)
    write_json(
        run_dir / "config.json",
        {
            "kind": "probes",
            "probe_config": cfg.to_dict(),
            "spec": spec.to_dict(),
            "scene": scene_key(scene),
            "store": str(getattr(store, "root", store)),
            "train_records": list(samples.record_ids),
            "train_pixels": len(samples),
            "eval_records": eval_ids,
            "fit_seconds": fit_s,
            "run": run_info(),
        },
    )
    save_model(run_dir / MODEL_FILE, "probes", module, {"config": cfg.to_dict(), "step": 0})
    model = RadianceModel(module, "probes")
    evals = []
    for path, ids in eval_ids.items():
        views = load_views(store, ids)
        m, first = evaluate_views(model, views, cfg.display_exposure)
        evals.append({"iteration": 0, "path": path, **m, "seconds": time.perf_counter() - t0})
        if first is not None:
            sample_png(
                run_dir / "samples" / f"{path}_000000.png", first, views[0].gi,
                cfg.display_exposure,
            )  # fmt: skip
        if progress:
            print(f"probes: {path} ({m['views']} views): SSIM {m['ssim']:.4f}  MSE {m['mse']:.1f}")
    write_evals(run_dir, evals, EVAL_COLUMNS)
    return RadianceResult(run_dir, 0, evals, time.perf_counter() - t0)


# ------------------------------------------------------------------------------ grid
def field_spec(bounds: Bounds, cfg: RadianceConfig, scale: float) -> FieldSpec:
    """The grid model's shape; the normal offset in scene units (finest cells)."""
    cell = float(bounds.extent.max()) / cfg.max_resolution
    return FieldSpec(
        bounds,
        cfg.levels,
        cfg.features,
        cfg.log2_table,
        cfg.base_resolution,
        cfg.max_resolution,
        cfg.hidden,
        cfg.layers,
        cfg.sh_order,
        cfg.normal_offset * cell,
        scale,
    )


def train(
    store: Any,
    config: RadianceConfig | ProbeConfig,
    out_dir: str | os.PathLike,
    scene: Any = None,
    resume: bool = False,
    progress: bool = True,
    stop_at: int | None = None,
) -> RadianceResult:
    """Fit a world-space irradiance model on a store's train path; evaluate on other paths.

    Args:
        store: an open :class:`~icbtool.store.Store` whose records are tagged with every
            ``config.train_paths`` and ``config.eval_paths`` (:func:`icbtool.bake.bake`).
        config: :class:`RadianceConfig` (grid + MLP, trained) or :class:`ProbeConfig` (probe
            volume, one least-squares fit).
        out_dir: the run directory (module doc).
        scene: which scene's records (Scene, hash or name; None: all).
        resume: continue the grid's training from ``out_dir/checkpoints/last.pt`` (the config
            must match except ``iterations``); without a checkpoint it starts from scratch.
        progress: show a progress bar and print evaluations.
        stop_at: (grid) stop after this iteration with a checkpoint, as if the run had been
            killed there: ``resume=True`` later continues the same plan (``iterations`` and its
            learning-rate schedule unchanged). For working in time slices.

    Returns:
        The :class:`RadianceResult`.

    Raises:
        ValueError: no train or evaluation records, no surface pixels, NaN/Inf in a record's
            maps, a run already in ``out_dir`` without ``resume``, a config differing from the
            resumed run's.
        RadianceDivergedError: a loss became non-finite or exceeded ``divergence_limit``.
    """
    run_dir = Path(out_dir)
    if isinstance(config, ProbeConfig):
        if (run_dir / MODEL_FILE).exists() and not resume:
            raise ValueError(f"{run_dir} already holds a model: choose another output directory")
        return _fit_probes_run(store, config, run_dir, scene, progress)
    if not isinstance(config, RadianceConfig):
        raise TypeError(f"config must be a RadianceConfig or ProbeConfig, got {type(config)}")
    if stop_at is not None and (
        isinstance(stop_at, bool) or int(stop_at) != stop_at or stop_at < 1
    ):
        raise ValueError(f"stop_at must be an integer >= 1 or None, got {stop_at!r}")
    return _train_grid(store, config, run_dir, scene, resume, progress, stop_at)


def _train_grid(
    store: Any,
    cfg: RadianceConfig,
    run_dir: Path,
    scene: Any,
    resume: bool,
    progress: bool,
    stop_at: int | None,
) -> RadianceResult:
    t0 = time.perf_counter()
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("RadianceConfig.device is 'cuda' but torch sees no CUDA device here")
    device = torch.device(cfg.device)
    ckpt_path = run_dir / "checkpoints" / "last.pt"
    cfg_path = run_dir / "config.json"
    if ckpt_path.exists() and not resume:
        raise ValueError(
            f"{run_dir} already holds a run: resume it (resume=True) or choose another directory"
        )
    if resume and ckpt_path.exists() and cfg_path.exists():
        old = RadianceConfig.from_dict(json.loads(cfg_path.read_text())["radiance_config"])
        if replace(old, iterations=cfg.iterations) != cfg:
            diff = {
                k: (v, cfg.to_dict()[k])
                for k, v in old.to_dict().items()
                if k != "iterations" and cfg.to_dict()[k] != v
            }
            raise ValueError(f"cannot resume {run_dir}: config differs (old, new): {diff}")

    samples = _train_samples(store, cfg, scene)
    eval_ids = _eval_sets(store, cfg, scene)
    views = {p: load_views(store, ids) for p, ids in eval_ids.items()}
    e, w = samples.targets(cfg.albedo_floor)
    pos_ok = w.sum(1) > 0
    scale = float(np.median(e[pos_ok])) if pos_ok.any() else 1.0
    scale = max(scale, 1e-6)
    bounds = Bounds.of_points(samples.position)
    spec = field_spec(bounds, cfg, scale)
    gen = torch.Generator().manual_seed(cfg.seed)
    module = IrradianceField(spec, gen).to(device).train()
    opt = torch.optim.Adam(module.parameters(), lr=cfg.lr, betas=cfg.betas, eps=cfg.eps)
    rng = np.random.default_rng(cfg.seed)
    step, evals, elapsed0 = 0, [], 0.0
    if resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=device, weights_only=False)
        module.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        rng.bit_generator.state = ck["rng"]
        step, evals, elapsed0 = int(ck["step"]), list(ck["evals"]), float(ck["seconds"])
    ckpt_path.parent.mkdir(parents=True, exist_ok=True)
    (run_dir / "samples").mkdir(exist_ok=True)
    write_json(
        cfg_path,
        {
            "kind": "grid",
            "radiance_config": cfg.to_dict(),
            "spec": spec.to_dict(),
            "scene": scene_key(scene),
            "store": str(getattr(store, "root", store)),
            "train_records": list(samples.record_ids),
            "train_pixels": len(samples),
            "eval_records": eval_ids,
            "parameters": int(sum(p.numel() for p in module.parameters())),
            "hashed_levels": module.hashed_levels,
            "run": run_info(),
        },
    )
    pos_t = torch.from_numpy(samples.position).to(device)
    nrm_t = torch.from_numpy(samples.normal).to(device)
    u_t = torch.from_numpy(np.log1p(np.maximum(e, 0.0) / scale).astype(np.float32)).to(device)
    w_t = torch.from_numpy(w).to(device)

    def elapsed() -> float:
        return elapsed0 + time.perf_counter() - t0

    def save() -> None:
        atomic_save(
            {
                "step": step,
                "model": module.state_dict(),
                "opt": opt.state_dict(),
                "rng": rng.bit_generator.state,
                "evals": evals,
                "seconds": elapsed(),
            },
            ckpt_path,
        )
        save_model(run_dir / MODEL_FILE, "grid", module, {"config": cfg.to_dict(), "step": step})

    def evaluate() -> None:
        model = RadianceModel(module, "grid", cfg.device)
        for path, vs in views.items():
            m, first = evaluate_views(model, vs, cfg.display_exposure)
            evals.append({"iteration": step, "path": path, **m, "seconds": elapsed()})
            if first is not None:
                sample_png(
                    run_dir / "samples" / f"{path}_{step:06d}.png", first, vs[0].gi,
                    cfg.display_exposure,
                )  # fmt: skip
            if progress:
                bar.write(
                    f"iteration {step}: {path} ({m['views']} views) SSIM {m['ssim']:.4f}  "
                    f"MSE {m['mse']:.1f}"
                )
        module.train()
        write_evals(run_dir, evals, EVAL_COLUMNS)

    from tqdm import tqdm

    bar = tqdm(total=cfg.iterations, initial=step, disable=not progress, desc="radiance")
    n = len(samples)
    end = cfg.iterations if stop_at is None else min(cfg.iterations, int(stop_at))
    try:
        while step < end:
            lr = cfg.lr * cfg.lr_decay ** (step / cfg.iterations)
            for g in opt.param_groups:
                g["lr"] = lr
            idx = torch.from_numpy(rng.integers(0, n, cfg.batch_size)).to(device)
            u = module.log_irradiance(pos_t[idx], nrm_t[idx])
            d = u - u_t[idx]
            err = d * d if cfg.loss == "l2" else d.abs()
            wb = w_t[idx]
            loss = (err * wb).sum() / wb.sum().clamp_min(1e-12)
            lv = float(loss.detach())
            if not math.isfinite(lv) or lv > cfg.divergence_limit:
                raise RadianceDivergedError(
                    f"training diverged at iteration {step + 1}: loss {lv}; the last good "
                    f"checkpoint is kept ({ckpt_path if ckpt_path.exists() else 'none yet'}). "
                    "Lower RadianceConfig.lr or check the data."
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            bar.update(1)
            bar.set_postfix(loss=f"{lv:.4g}", lr=f"{lr:.2g}")
            if step % cfg.eval_every == 0 or step == cfg.iterations:
                evaluate()
            if step % cfg.checkpoint_every == 0 or step in (cfg.iterations, end):
                save()
    finally:
        bar.close()
    if not (run_dir / MODEL_FILE).exists():  # nothing ran (resumed at its end)
        save()
    return RadianceResult(run_dir, step, evals, elapsed())


__all__ = [
    "EVAL_COLUMNS",
    "ProbeConfig",
    "RadianceConfig",
    "RadianceDivergedError",
    "RadianceResult",
    "evaluate_views",
    "fit_probe_volume",
    "load_views",
    "predict_view",
    "train",
]
