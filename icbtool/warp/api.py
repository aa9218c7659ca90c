"""numpy API of :mod:`icbtool.warp`: warp HWC images between :class:`~icbtool.camera.Camera` s.

``icb.warp.backward`` (target depth known: the client has it), ``icb.warp.forward`` (splatting,
target depth unknown), ``icb.warp.combine`` (several references, per pixel) and
``icb.warp.inpaint`` (fill what is left, still reported in the masks). ``backward`` runs a fused
numba kernel (:mod:`icbtool.warp._numba`) by default, or the torch function
:func:`icbtool.warp.functional.warp_backward` under ``torch.inference_mode`` with
``WarpConfig(backend="torch")``; ``forward`` likewise runs a numba splatting kernel, or
:func:`~icbtool.warp.functional.warp_forward`.

Invalid depth: pixels whose mask is 0 are "no geometry" whatever their depth. Without a mask,
pixels with finite depth > 0 are geometry and the rest are not. With a mask, a pixel marked valid
whose depth is zero, negative or not finite is an error (ValueError naming the pixel count).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from icbtool.camera import Camera
from icbtool.imageio import HOLE_COLOURS  # re-exported: pictures of a WarpResult's holes

__all__ = [
    "HOLE_COLOURS",
    "ForwardWarpResult",
    "WarpConfig",
    "WarpResult",
    "backward",
    "combine",
    "forward",
    "inpaint",
    "inpaint_image",
]


@dataclass(frozen=True)
class WarpConfig:
    """Options of the numpy warps."""

    rel_depth_tol: float = 0.02
    """A bilinear tap passes the depth test if ``|z / z_tap - 1| <= rel_depth_tol``, with the
    tap's depth extrapolated to the sample along its own surface slope (see ``slope_limit``):
    surfaces 2 % apart in depth are told apart."""
    slope_limit: float = 0.25
    """Slope-aware depth test: inverse-depth slopes up to this (relative, per pixel) are
    surface slopes, larger ones are edges. 0: compare the raw tap depths (grazing surfaces then
    lose taps)."""
    soft_depth: float = 0.0
    """0: hard depth test. > 0: sigmoid test of this relative width (differentiable in torch)."""
    min_weight: float = 1e-3
    """A pixel whose passing bilinear weight is at most this counts as disoccluded."""
    splat: Literal["nearest", "footprint2"] = "nearest"
    """Forward warp footprint: the containing pixel, or the 2x2 pixels around the point."""
    dtype: Literal["float32", "float64"] = "float32"
    """Precision the inputs are read in (images and depths are cast to it). The torch backend
    also computes in it; the numba kernel always computes in float64 (scalar code: no slower)."""
    backend: Literal["auto", "numba", "torch"] = "auto"
    """Implementation of :func:`backward`: ``numba`` (the fused, non-differentiable kernel of
    :mod:`icbtool.warp._numba`, several times faster), ``torch`` (the differentiable
    :func:`~icbtool.warp.functional.warp_backward`, the reference), or ``auto`` = ``numba`` (the
    numpy API needs no gradients). Both give the same masks and images (to float rounding).
    Likewise for :func:`forward` (its numba kernel is single-threaded: splats collide)."""
    threads: int = 2
    """Threads of the numba backend (the target rows are split into this many ranges; small
    images use one)."""

    def __post_init__(self) -> None:
        if not self.rel_depth_tol > 0:
            raise ValueError(f"WarpConfig.rel_depth_tol must be > 0, got {self.rel_depth_tol}")
        if not self.soft_depth >= 0:
            raise ValueError(f"WarpConfig.soft_depth must be >= 0, got {self.soft_depth}")
        if not self.slope_limit >= 0:
            raise ValueError(f"WarpConfig.slope_limit must be >= 0, got {self.slope_limit}")
        if not 0 <= self.min_weight < 1:
            raise ValueError(f"WarpConfig.min_weight must be in [0, 1), got {self.min_weight}")
        if self.splat not in ("nearest", "footprint2"):
            raise ValueError(f"WarpConfig.splat must be nearest|footprint2, got {self.splat!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"WarpConfig.dtype must be float32|float64, got {self.dtype!r}")
        if self.backend not in ("auto", "numba", "torch"):
            raise ValueError(f"WarpConfig.backend must be auto|numba|torch, got {self.backend!r}")
        if (
            isinstance(self.threads, bool)
            or not isinstance(self.threads, (int, np.integer))
            or self.threads < 1
        ):
            raise ValueError(f"WarpConfig.threads must be an int >= 1, got {self.threads!r}")


@dataclass
class WarpResult:
    """A warped image with its hole masks, all at the target resolution (H, W).

    Attributes:
        image: (H, W, C) float32 warped image; 0 on holes unless inpainted.
        holes: (H, W) bool, ``outside | disoccluded | no_geometry``.
        outside: (H, W) bool, the target point is outside (or behind) every reference frustum.
        disoccluded: (H, W) bool, inside a reference frustum, but the reference saw another
            surface (or nothing) there.
        no_geometry: (H, W) bool, the target pixel has no geometry (mask 0 / invalid depth).
        weight: (H, W) float32, passing bilinear tap weight in [0, 1] (depth agreement).
        density: (H, W) float32, reference pixels per target pixel (< 1: magnified).
        source: (H, W) int16, index of the reference used per pixel (0 for a single warp),
            -1 on holes.
        inpainted: (H, W) bool, hole pixels filled by :func:`inpaint` (they stay in ``holes``).
    """

    image: np.ndarray
    holes: np.ndarray
    outside: np.ndarray
    disoccluded: np.ndarray
    no_geometry: np.ndarray
    weight: np.ndarray
    density: np.ndarray
    source: np.ndarray
    inpainted: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))

    def __post_init__(self) -> None:
        if self.inpainted.shape != self.holes.shape:
            self.inpainted = np.zeros(self.holes.shape, bool)

    @property
    def hole_ratio(self) -> float:
        """Fraction of target pixels WITH geometry that are holes (outside or disoccluded)."""
        geo = ~self.no_geometry
        n = int(geo.sum())
        return float((self.holes & geo).sum() / n) if n else 0.0


@dataclass
class ForwardWarpResult:
    """Result of :func:`forward`.

    Attributes:
        image: (H, W, C) float32 splatted image; 0 on holes.
        depth: (H, W, 1) float32 splatted target depth; 0 on holes.
        holes: (H, W) bool, target pixels that received no reference pixel.
    """

    image: np.ndarray
    depth: np.ndarray
    holes: np.ndarray


# --------------------------------------------------------------------------- helpers
def _hwc(x: np.ndarray, name: str, cam: Camera) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim != 3:
        raise ValueError(f"{name} must be (H, W, C), got shape {a.shape}")
    if a.shape[:2] != (cam.height, cam.width):
        raise ValueError(
            f"{name} is {a.shape[0]}x{a.shape[1]} but its camera is {cam.height}x{cam.width}"
        )
    return a


def _depth(x: np.ndarray, name: str, cam: Camera) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] != 1:
        raise ValueError(f"{name} must be (H, W, 1) (or (H, W)), got shape {np.shape(x)}")
    return _hwc(a, name, cam)


def _to_torch(a: np.ndarray | None, dtype):
    import torch

    if a is None:
        return None
    t = torch.from_numpy(np.ascontiguousarray(a))
    if t.dtype != torch.bool:
        t = t.to(dtype)
    return t.permute(2, 0, 1)[None]


def _torch_dtype(cfg: WarpConfig):
    import torch

    return torch.float32 if cfg.dtype == "float32" else torch.float64


def _mat(m: np.ndarray, dtype):
    import torch

    return torch.as_tensor(np.asarray(m, np.float64)).to(dtype)[None]


def _np_map(t) -> np.ndarray:
    return t[0, 0].cpu().numpy()


# --------------------------------------------------------------------------- public API
def backward(
    src_image: np.ndarray,
    src_depth: np.ndarray,
    src_cam: Camera,
    dst_depth: np.ndarray,
    dst_cam: Camera,
    src_mask: np.ndarray | None = None,
    dst_mask: np.ndarray | None = None,
    config: WarpConfig = WarpConfig(),  # noqa: B008 (frozen)
) -> WarpResult:
    """Backward-warp a reference image to a target camera whose depth is known.

    For every target pixel: lift with ``dst_depth`` and ``dst_cam``, project into ``src_cam``,
    sample ``src_image`` bilinearly with a per-tap depth test (see
    :mod:`icbtool.warp.functional`). The cameras may differ in pose, FOV, intrinsics and size.
    ``config.backend`` picks the implementation: the fused numba kernel (``auto``/``numba``,
    compiled on first use and cached on disk) or the torch reference (``torch``); they agree.

    Args:
        src_image: (Hs, Ws, C) reference image (e.g. a GI map).
        src_depth: (Hs, Ws, 1) reference view-space depth.
        src_cam: the reference camera (Hs x Ws).
        dst_depth: (Hd, Wd, 1) target view-space depth.
        dst_cam: the target camera (Hd x Wd).
        src_mask: optional (Hs, Ws, 1) or (Hs, Ws) geometry mask (> 0.5 = geometry).
        dst_mask: optional (Hd, Wd, 1) or (Hd, Wd) geometry mask.
        config: a :class:`WarpConfig`.

    Returns:
        A :class:`WarpResult` (image (Hd, Wd, C) float32 and (Hd, Wd) bool masks).

    Raises:
        ValueError: on shapes that do not match the cameras, or a mask marking pixels valid whose
            depth is zero, negative or not finite.
        ImportError: the numba backend was asked for (or ``auto``) and numba cannot be imported.
    """
    src_image = _hwc(src_image, "src_image", src_cam)
    src_depth = _depth(src_depth, "src_depth", src_cam)
    dst_depth = _depth(dst_depth, "dst_depth", dst_cam)
    src_mask = None if src_mask is None else _depth(src_mask, "src_mask", src_cam)
    dst_mask = None if dst_mask is None else _depth(dst_mask, "dst_mask", dst_cam)
    if not isinstance(config, WarpConfig):
        raise TypeError(f"config must be a WarpConfig, got {type(config).__name__}")
    if config.backend == "torch":
        return _backward_torch(
            src_image, src_depth, src_cam, dst_depth, dst_cam, src_mask, dst_mask, config
        )
    return _backward_numba(
        src_image, src_depth, src_cam, dst_depth, dst_cam, src_mask, dst_mask, config
    )


def _backward_torch(
    src_image, src_depth, src_cam, dst_depth, dst_cam, src_mask, dst_mask, config: WarpConfig
) -> WarpResult:
    """:func:`backward` through :func:`icbtool.warp.functional.warp_backward` (checked inputs)."""
    import torch

    from icbtool.warp.functional import warp_backward

    dt = _torch_dtype(config)
    with torch.inference_mode():
        out = warp_backward(
            _to_torch(src_image, dt),
            _to_torch(src_depth, dt),
            _to_torch(dst_depth, dt),
            _mat(src_cam.K, dt),
            _mat(dst_cam.K, dt),
            _mat(src_cam.cam_from_world @ dst_cam.world_from_cam, dt),
            _to_torch(src_mask, dt),
            _to_torch(dst_mask, dt),
            config.rel_depth_tol,
            config.soft_depth,
            config.min_weight,
            config.slope_limit,
        )
        holes = _np_map(out.holes)
        return WarpResult(
            image=out.image[0].permute(1, 2, 0).numpy().astype(np.float32),
            holes=holes,
            outside=_np_map(out.outside),
            disoccluded=_np_map(out.disoccluded),
            no_geometry=_np_map(out.no_geometry),
            weight=_np_map(out.weight).astype(np.float32),
            density=_np_map(out.density).astype(np.float32),
            source=np.where(holes, -1, 0).astype(np.int16),
        )


#: Target images with fewer pixels than this are warped on one thread (a split costs more).
_MIN_PIXELS_PER_THREAD = 16384
_POOL = None
_POOL_LOCK = threading.Lock()


def _pool(k: int):
    """A shared thread pool for the GIL-free numba kernels (as in icbtool.trace.tracer)."""
    from concurrent.futures import ThreadPoolExecutor

    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < k:
            _POOL = ThreadPoolExecutor(max_workers=k, thread_name_prefix="icb-warp")
        return _POOL


class _RowBlocks:
    """One kernel over the rows of an image in blocks, taken in turn by the calling thread and
    ``threads - 1`` pool threads (the kernels release the GIL). The caller waits only for the
    blocks, never for a pool thread that has not started: on a busy machine a woken thread can
    wait milliseconds for a core, and then the caller simply does more of the blocks."""

    def __init__(self, kernel, args: tuple, rows: int, block: int) -> None:
        self.kernel, self.args, self.rows, self.block = kernel, args, rows, block
        self.n_blocks = -(-rows // block)
        self._lock = threading.Lock()
        self._next = 0
        self._done = 0
        self._error: Exception | None = None
        self._finished = threading.Event()

    def work(self) -> None:
        while True:
            with self._lock:
                b = self._next
                self._next += 1
            if b >= self.n_blocks or self._finished.is_set():
                return
            lo = b * self.block
            try:
                self.kernel(*self.args, lo, min(lo + self.block, self.rows))
            except Exception as e:  # re-raised by run() in the calling thread
                with self._lock:
                    self._error = e
                self._finished.set()
                return
            with self._lock:
                self._done += 1
                if self._done == self.n_blocks:
                    self._finished.set()

    def run(self, threads: int) -> None:
        if threads > 1:
            pool = _pool(threads - 1)
            for _ in range(threads - 1):
                pool.submit(self.work)
        self.work()
        self._finished.wait()
        if self._error is not None:
            raise self._error


def _run_rows(kernel, args: tuple, shape: tuple[int, int], config: WarpConfig) -> None:
    """Run ``kernel(*args, row_lo, row_hi)`` over the rows of an (H, W) image on
    ``config.threads`` threads (one for small images), about 4 row blocks per thread."""
    h, w = shape
    k = max(1, min(config.threads, h, (h * w) // _MIN_PIXELS_PER_THREAD))
    if k == 1:
        kernel(*args, 0, h)
        return
    _RowBlocks(kernel, args, h, max(1, -(-h // (4 * k)))).run(k)


def _numba_kernels():
    import importlib

    try:
        return importlib.import_module("icbtool.warp._numba")
    except ImportError as e:  # numba is a dependency: a broken install, not a choice
        raise ImportError(
            "WarpConfig.backend='numba' (also the 'auto' choice of the numpy API) needs numba "
            f"({e}); install the project's requirements.lock, or pass WarpConfig(backend='torch')"
        ) from e


def _geometry_mask(depth2d: np.ndarray, mask: np.ndarray | None, name: str) -> np.ndarray:
    """(H, W) bool mask (> 0.5) checked against the depth, as functional._valid_mask."""
    m = mask[..., 0]
    m = m if m.dtype == np.bool_ else m > 0.5
    good = (depth2d > 0) & (depth2d < np.inf)
    bad = int(np.count_nonzero(m & ~good))
    if bad:
        raise ValueError(
            f"{name}_depth: {bad} pixel(s) marked valid by {name}_mask have zero, negative or "
            "non-finite depth"
        )
    return np.ascontiguousarray(m)


def _backward_numba(
    src_image, src_depth, src_cam, dst_depth, dst_cam, src_mask, dst_mask, config: WarpConfig
) -> WarpResult:
    """:func:`backward` through the fused numba kernel (checked inputs)."""
    kern = _numba_kernels()
    dt = np.dtype(config.dtype)
    img = np.ascontiguousarray(src_image, dt)
    sd = np.ascontiguousarray(src_depth, dt).reshape(src_cam.height, src_cam.width)
    dd = np.ascontiguousarray(dst_depth, dt).reshape(dst_cam.height, dst_cam.width)
    no_mask = np.zeros((0, 0), np.bool_)
    sm = no_mask if src_mask is None else _geometry_mask(sd, src_mask, "src")
    dm = no_mask if dst_mask is None else _geometry_mask(dd, dst_mask, "dst")
    # K_src R K_dst^-1 and K_src t in float64, as functional._pixel_transform
    src_from_dst = src_cam.cam_from_world @ dst_cam.world_from_cam
    k_src = np.asarray(src_cam.K, np.float64)
    k_dst = np.asarray(dst_cam.K, np.float64)
    m = np.ascontiguousarray(k_src @ src_from_dst[:3, :3] @ np.linalg.inv(k_dst))
    kt = np.ascontiguousarray(k_src @ src_from_dst[:3, 3])
    dens_num = math.sqrt(k_src[0, 0] * k_src[1, 1])
    dens_den = math.sqrt(k_dst[0, 0] * k_dst[1, 1])
    hd, wd = dst_cam.height, dst_cam.width
    image = np.empty((hd, wd, img.shape[2]), np.float32)
    masks = [np.empty((hd, wd), np.bool_) for _ in range(4)]
    weight = np.empty((hd, wd), np.float32)
    density = np.empty((hd, wd), np.float32)
    source = np.empty((hd, wd), np.int16)
    feats = np.empty((src_cam.height, src_cam.width, 3), np.float64)  # 1/z, d/dx, d/dy
    src_args = (sd, sm, src_mask is not None, float(config.slope_limit), feats)
    _run_rows(kern.source_rows, src_args, sd.shape, config)
    args = (
        img,
        feats,
        dd,
        dm,
        dst_mask is not None,
        m,
        kt,
        dens_num,
        dens_den,
        float(config.rel_depth_tol),
        float(config.soft_depth),
        float(config.min_weight),
        image,
        *masks,
        weight,
        density,
        source,
    )
    _run_rows(kern.backward_rows, args, dd.shape, config)
    return WarpResult(
        image=image,
        holes=masks[0],
        outside=masks[1],
        disoccluded=masks[2],
        no_geometry=masks[3],
        weight=weight,
        density=density,
        source=source,
    )


def forward(
    src_image: np.ndarray,
    src_depth: np.ndarray,
    src_cam: Camera,
    dst_cam: Camera,
    src_mask: np.ndarray | None = None,
    config: WarpConfig = WarpConfig(),  # noqa: B008 (frozen)
) -> ForwardWarpResult:
    """Forward-warp (splat with a z-buffer) a reference image into a target camera.

    Use it when the target depth is unknown; pixels that receive nothing are holes (cracks
    where the reference is magnified, disocclusions, and outside the reference frustum alike).

    Args:
        src_image: (Hs, Ws, C) reference image.
        src_depth: (Hs, Ws, 1) reference view-space depth.
        src_cam: reference camera.
        dst_cam: target camera (its size sets the output size).
        src_mask: optional (Hs, Ws, 1) or (Hs, Ws) geometry mask.
        config: ``config.splat`` chooses the footprint.

    Returns:
        A :class:`ForwardWarpResult` (image (Hd, Wd, C), depth (Hd, Wd, 1), holes (Hd, Wd)).
    """
    src_image = _hwc(src_image, "src_image", src_cam)
    src_depth = _depth(src_depth, "src_depth", src_cam)
    src_mask = None if src_mask is None else _depth(src_mask, "src_mask", src_cam)
    if not isinstance(config, WarpConfig):
        raise TypeError(f"config must be a WarpConfig, got {type(config).__name__}")
    if config.backend != "torch":
        return _forward_numba(src_image, src_depth, src_cam, dst_cam, src_mask, config)
    import torch

    from icbtool.warp.functional import warp_forward

    dt = _torch_dtype(config)
    with torch.inference_mode():
        out = warp_forward(
            _to_torch(src_image, dt),
            _to_torch(src_depth, dt),
            _mat(src_cam.K, dt),
            _mat(dst_cam.K, dt),
            _mat(dst_cam.cam_from_world @ src_cam.world_from_cam, dt),
            (dst_cam.height, dst_cam.width),
            _to_torch(src_mask, dt),
            config.splat,
        )
        return ForwardWarpResult(
            image=out.image[0].permute(1, 2, 0).numpy().astype(np.float32),
            depth=out.depth[0].permute(1, 2, 0).numpy().astype(np.float32),
            holes=_np_map(out.holes),
        )


def _forward_numba(src_image, src_depth, src_cam, dst_cam, src_mask, config) -> ForwardWarpResult:
    """:func:`forward` through the numba splatting kernel (checked inputs)."""
    kern = _numba_kernels()
    dt = np.dtype(config.dtype)
    img = np.ascontiguousarray(src_image, dt)
    sd = np.ascontiguousarray(src_depth, dt).reshape(src_cam.height, src_cam.width)
    sm = np.zeros((0, 0), np.bool_) if src_mask is None else _geometry_mask(sd, src_mask, "src")
    dst_from_src = dst_cam.cam_from_world @ src_cam.world_from_cam
    k_dst = np.asarray(dst_cam.K, np.float64)
    m = np.ascontiguousarray(k_dst @ dst_from_src[:3, :3] @ np.linalg.inv(src_cam.K))
    kt = np.ascontiguousarray(k_dst @ dst_from_src[:3, 3])
    hd, wd = dst_cam.height, dst_cam.width
    image = np.empty((hd, wd, img.shape[2]), np.float32)
    depth = np.empty((hd, wd), np.float32)
    holes = np.empty((hd, wd), np.bool_)
    zbuf = np.empty((hd, wd), np.float64)
    footprint2 = config.splat == "footprint2"
    kern.forward_splat(
        img, sd, sm, src_mask is not None, m, kt, footprint2, zbuf, image, depth, holes
    )
    return ForwardWarpResult(image=image, depth=depth[..., None], holes=holes)


def combine(results: Sequence[WarpResult]) -> WarpResult:
    """Merge warps of several references to one target, choosing a reference per pixel.

    Per pixel, among the references that are not holes, take the one with the highest score
    ``weight * min(density, 1)``: full depth agreement of the four taps first, then the least
    magnified (closest, densest) reference; ties go to the earlier reference in the list.
    A pixel is a hole only if it is one in every reference; its cause is ``outside`` if it is
    outside every reference frustum, else ``disoccluded`` (``no_geometry`` comes from the target).

    Args:
        results: warps of the references to the same target camera (same H, W, C).

    Returns:
        A :class:`WarpResult`; ``source`` tells which reference filled each pixel.
    """
    if len(results) == 0:
        raise ValueError("combine: need at least one WarpResult")
    shape = results[0].image.shape
    for i, r in enumerate(results):
        if not isinstance(r, WarpResult):
            raise TypeError(f"combine: results[{i}] is a {type(r).__name__}, not a WarpResult")
        if r.image.shape != shape:
            raise ValueError(f"combine: results[{i}] image is {r.image.shape}, results[0] {shape}")
    valid = np.stack([~r.holes for r in results])  # (R, H, W)
    score = np.stack([r.weight * np.minimum(r.density, 1.0) for r in results])
    score = np.where(valid, score + 1.0, 0.0)  # any valid beats every hole
    best = np.argmax(score, axis=0)
    any_valid = valid.any(0)
    take = best[None, ..., None]
    image = np.take_along_axis(np.stack([r.image for r in results]), take, 0)[0]
    image = np.where(any_valid[..., None], image, 0).astype(np.float32)

    def pick(name: str) -> np.ndarray:
        a = np.stack([getattr(r, name) for r in results])
        return np.take_along_axis(a, best[None], 0)[0]

    holes = ~any_valid
    no_geometry = results[0].no_geometry.copy()
    outside = holes & np.all(np.stack([r.outside for r in results]), 0)
    disoccluded = holes & ~outside & ~no_geometry
    return WarpResult(
        image=image,
        holes=holes,
        outside=outside,
        disoccluded=disoccluded,
        no_geometry=no_geometry,
        weight=np.where(holes, 0, pick("weight")).astype(np.float32),
        density=np.where(holes, 0, pick("density")).astype(np.float32),
        source=np.where(holes, -1, best).astype(np.int16),
    )


def inpaint_image(
    image: np.ndarray, mask: np.ndarray, radius: float = 3.0, method: str = "telea"
) -> np.ndarray:
    """Fill ``mask`` pixels of a float image with OpenCV's inpainting, channel by channel.

    Args:
        image: (H, W, C) float image (linear HDR is fine: done in float32).
        mask: (H, W) bool, pixels to fill.
        radius: neighbourhood radius in pixels.
        method: ``telea`` (cv2.INPAINT_TELEA) or ``ns`` (Navier-Stokes).

    Returns:
        (H, W, C) float32 image; pixels outside ``mask`` unchanged.
    """
    import cv2

    img = np.asarray(image, np.float32)
    if img.ndim != 3:
        raise ValueError(f"inpaint: image must be (H, W, C), got {img.shape}")
    m = np.asarray(mask, bool)
    if m.shape != img.shape[:2]:
        raise ValueError(f"inpaint: mask {m.shape} does not match image {img.shape[:2]}")
    if method not in ("telea", "ns"):
        raise ValueError(f"inpaint: method must be telea|ns, got {method!r}")
    if not m.any():
        return img.copy()
    flag = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
    m8 = m.astype(np.uint8) * 255
    out = np.empty_like(img)
    # OpenCV's float path extrapolates with gradients and overshoots (values far outside the
    # known range at edges): inpaint a 16-bit encoding of each channel's known range instead,
    # which also bounds the result to that range (16-bit steps on the filled pixels only).
    for ch in range(img.shape[2]):
        c = img[..., ch]
        known = c[~m]
        lo, hi = (float(known.min()), float(known.max())) if known.size else (0.0, 0.0)
        if hi <= lo:
            out[..., ch] = lo
            continue
        enc = np.round((np.clip(c, lo, hi) - lo) / (hi - lo) * 65535.0).astype(np.uint16)
        fill = cv2.inpaint(enc, m8, float(radius), flag)
        out[..., ch] = fill.astype(np.float32) / 65535.0 * (hi - lo) + lo
    out[~m] = img[~m]
    return out


def inpaint(
    result: WarpResult,
    depth: np.ndarray | None = None,
    radius: float = 3.0,
    method: str = "telea",
    fill_no_geometry: bool = False,
    rel_depth_gap: float = 0.05,
) -> WarpResult:
    """Fill the holes of a warp by inpainting; the masks still report them.

    Disocclusions reveal background, so with the target ``depth`` the fill is background-aware:
    known pixels near a hole that are more than ``rel_depth_gap`` nearer than the hole (the
    occluding foreground) are not used as sources (they are masked during the fill and restored
    after it). Without ``depth`` it is plain Telea/NS inpainting, which smears the foreground
    into disocclusions.

    Args:
        result: a :class:`WarpResult`.
        depth: optional (H, W, 1) or (H, W) target depth (as given to :func:`backward`).
        radius: inpainting radius in pixels.
        method: ``telea`` or ``ns``.
        fill_no_geometry: also fill pixels without geometry (background); default: only
            ``outside | disoccluded``.
        rel_depth_gap: relative depth gap that makes a known pixel foreground to a hole.

    Returns:
        A new :class:`WarpResult` with the filled image, ``inpainted`` set to the filled pixels
        and ``holes`` / ``outside`` / ``disoccluded`` unchanged.
    """
    fill = result.holes if fill_no_geometry else result.holes & ~result.no_geometry
    mask = fill.copy()
    if depth is not None:
        import cv2

        z = np.asarray(depth, np.float32).reshape(result.holes.shape)
        z = np.where(result.no_geometry, 0.0, np.nan_to_num(z)).astype(np.float32)
        k = 2 * int(math.ceil(radius)) + 3
        hole_z = cv2.dilate(np.where(fill, z, 0).astype(np.float32), np.ones((k, k), np.uint8))
        foreground = ~fill & ~result.no_geometry & (z < (1 - rel_depth_gap) * hole_z)
        mask |= foreground
    image = inpaint_image(result.image, mask, radius, method)
    image[~fill] = result.image[~fill]
    return replace(result, image=image, inpainted=fill.copy())
