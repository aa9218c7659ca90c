"""What a level of detail costs: geometric error against the full mesh, the texture error of
the transferred uvs, and the effect on the client's WRT-buffer and on warping.

* :func:`geometric_error`: points sampled uniformly by area on each surface (seeded), their
  exact distance to the other surface (:class:`~icbtool.lpm.closest.ClosestPointQuery`: open3d's
  candidate refined by exact point-triangle distances), both ways; RMS and Hausdorff (max) as
  fractions of the full mesh's bounding-box diagonal. The symmetric RMS is over both sample
  sets, the symmetric Hausdorff the larger of the two one-sided maxima.
* :func:`uv_error`: points sampled on the level's textured faces; the texel their level uv
  addresses against the texel the full mesh's uv addresses at the nearest full-mesh point of the
  same material, both in the FULL-resolution texture (so only the uv transfer is measured, not
  the texture shrink): mean absolute difference on the display scale (0-255) and the median uv
  distance in texels.
* :func:`client_error`: DL, depth and albedo rasterized from the level and from the full mesh
  at the same cameras: depth relative error ``|z_lvl - z_full| / z_full`` (median, p95) on pixels
  both see, the fraction of pixels (either sees) whose depth is off by more than 1 % or that only
  one sees, and DL and albedo SSIM (display scale, one exposure from the full DL).
* :func:`warp_error`: a reference GI map (path traced on the full mesh at a reference camera)
  backward-warped to the client camera once with the full mesh's client depth and once with the
  level's: SSIM between the two warps and each one's hole ratio.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera
    from icbtool.raster import RasterBuffers, RasterConfig
    from icbtool.scene import Scene


def sample_surface(
    scene: Scene, n: int, seed: int = 0, faces: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` points uniform by area on ``scene`` (or on its faces ``faces``).

    Returns:
        points (n, 3) float64, face index (n,) int64, barycentric weights (n, 3) float64.
    """
    rng = np.random.default_rng(seed)
    idx = np.arange(len(scene.faces)) if faces is None else np.asarray(faces, np.int64)
    area = scene.face_areas[idx]
    if len(idx) == 0 or area.sum() <= 0:
        raise ValueError(f"scene '{scene.name}': no surface area to sample")
    f = idx[rng.choice(len(idx), size=n, p=area / area.sum())]
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    tri = scene.vertices[scene.faces[f]].astype(np.float64)
    return (w[:, :, None] * tri).sum(1), f, w


def _distance(scene: Scene, points: np.ndarray, faces: np.ndarray | None = None) -> np.ndarray:
    """(N,) exact distance of ``points`` to ``scene`` (or to its faces ``faces``)."""
    from icbtool.lpm.closest import ClosestPointQuery

    f = scene.faces if faces is None else scene.faces[faces]
    return ClosestPointQuery(scene.vertices, f).query(points).distance


def geometric_error(
    level: Scene, full: Scene, n_samples: int = 200_000, seed: int = 0
) -> dict[str, float]:
    """Symmetric surface distance between ``level`` and ``full`` (see the module docstring).

    Args:
        level: the level's scene.
        full: the full scene.
        n_samples: points sampled on each surface.
        seed: sampling seed.

    Returns:
        ``rms``, ``hausdorff`` (symmetric), ``rms_level_to_full``, ``rms_full_to_level``,
        ``max_level_to_full``, ``max_full_to_level``, all as fractions of ``full.diagonal``;
        ``diagonal`` (scene units), ``n_samples``.
    """
    diag = max(full.diagonal, 1e-30)
    pl, _, _ = sample_surface(level, n_samples, seed)
    pf, _, _ = sample_surface(full, n_samples, seed + 1)
    d_lf = _distance(full, pl) / diag
    d_fl = _distance(level, pf) / diag
    both = np.concatenate([d_lf, d_fl])
    return {
        "rms": float(np.sqrt(np.mean(both**2))),
        "hausdorff": float(max(d_lf.max(), d_fl.max())),
        "rms_level_to_full": float(np.sqrt(np.mean(d_lf**2))),
        "rms_full_to_level": float(np.sqrt(np.mean(d_fl**2))),
        "max_level_to_full": float(d_lf.max()),
        "max_full_to_level": float(d_fl.max()),
        "diagonal": float(diag),
        "n_samples": int(n_samples),
    }


def _texel(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest texel (repeat wrap) of ``texture`` (h, w, 3) at ``uv`` (N, 2); v up."""
    h, w = texture.shape[:2]
    col = np.floor(np.mod(uv[:, 0], 1.0) * w).astype(np.int64).clip(0, w - 1)
    row = np.floor((1.0 - np.mod(uv[:, 1], 1.0)) * h).astype(np.int64).clip(0, h - 1)
    return texture[row, col]


def uv_error(level: Scene, full: Scene, n_samples: int = 50_000, seed: int = 0) -> dict[str, Any]:
    """How well the level's uvs address the full mesh's texels (see the module docstring).

    Returns:
        ``mean_abs_255`` (mean |difference| of the display-encoded texel, 0-255),
        ``median_texel_distance``, ``p95_texel_distance`` and ``n_samples`` over all textured
        materials; NaN values when nothing is textured.
    """
    from icbtool.imageio import to_display
    from icbtool.lpm.closest import ClosestPointQuery

    nan = {
        "mean_abs_255": float("nan"),
        "median_texel_distance": float("nan"),
        "p95_texel_distance": float("nan"),
        "n_samples": 0,
    }
    if level.uvs is None or full.uvs is None:
        return nan
    textured = [m for m, mat in enumerate(full.materials) if mat.texture is not None]
    lf = np.flatnonzero(np.isin(level.face_material, textured))
    if len(lf) == 0:
        return nan
    p, f, w = sample_surface(level, n_samples, seed, faces=lf)
    uv_l = (w[:, :, None] * level.uvs[level.faces[f]].astype(np.float64)).sum(1)
    diffs, dists = [], []
    for m in textured:
        sel = level.face_material[f] == m
        ff = np.flatnonzero(full.face_material == m)
        if not sel.any() or len(ff) == 0:
            continue
        r = ClosestPointQuery(full.vertices, full.faces[ff]).query(p[sel])
        fid, wf = ff[r.face], r.weights
        uv_f = (wf[:, :, None] * full.uvs[full.faces[fid]].astype(np.float64)).sum(1)
        tex = full.materials[m].texture
        a = to_display(_texel(tex, uv_l[sel])[None]).astype(np.float64)
        c = to_display(_texel(tex, uv_f)[None]).astype(np.float64)
        diffs.append(np.abs(a - c).mean(-1).ravel())
        h, wd = tex.shape[:2]
        d = uv_l[sel] - uv_f
        d -= np.round(d)  # repeat wrap: uv u and u + 1 address the same texel
        dists.append(np.hypot(d[:, 0] * wd, d[:, 1] * h))
    if not diffs:
        return nan
    dd, ds = np.concatenate(diffs), np.concatenate(dists)
    return {
        "mean_abs_255": float(dd.mean()),
        "median_texel_distance": float(np.median(ds)),
        "p95_texel_distance": float(np.percentile(ds, 95)),
        "n_samples": int(len(dd)),
    }


def render_views(
    scene: Scene, cameras: Sequence[Camera], config: RasterConfig | None = None
) -> list[RasterBuffers]:
    """DL, depth and albedo of ``scene`` at ``cameras`` (one GL context for all)."""
    from icbtool.raster import Rasterizer

    with Rasterizer(scene, config) as r:
        return [r.render(c, ("dl", "depth", "albedo")) for c in cameras]


def compare_views(level: RasterBuffers, full: RasterBuffers, exposure: float) -> dict[str, float]:
    """Depth and image errors of one camera's level render against the full render."""
    from icbtool.metrics import ssim

    vl, vf = level.valid, full.valid
    both = vl & vf
    either = vl | vf
    zl, zf = level.depth[..., 0], full.depth[..., 0]
    rel = np.abs(zl - zf) / np.maximum(np.abs(zf), 1e-12)
    bad = (both & (rel > 0.01)) | (either & ~both)
    r = rel[both] if both.any() else np.array([np.nan])
    return {
        "depth_rel_median": float(np.median(r)),
        "depth_rel_p95": float(np.percentile(r, 95)),
        "depth_bad_fraction": float(bad.sum() / max(int(either.sum()), 1)),
        "mask_mismatch_fraction": float((either & ~both).sum() / max(int(either.sum()), 1)),
        "dl_ssim": ssim(level.dl, full.dl, exposure),
        "albedo_ssim": ssim(level.albedo, full.albedo, 1.0),
    }


def client_error(
    level: Scene,
    full: Scene,
    cameras: Sequence[Camera],
    config: RasterConfig | None = None,
    full_views: list[RasterBuffers] | None = None,
) -> dict[str, Any]:
    """Client-side effect of a level: see the module docstring.

    Args:
        level, full: the two scenes.
        cameras: the client cameras.
        config: raster options.
        full_views: the full mesh's renders at ``cameras`` (from :func:`render_views`), reused
            across levels; rendered when None.

    Returns:
        ``per_camera`` (list of :func:`compare_views` dicts) and the mean of each value.
    """
    from icbtool.imageio import auto_exposure

    fv = full_views if full_views is not None else render_views(full, cameras, config)
    lv = render_views(level, cameras, config)
    rows = []
    for a, b in zip(lv, fv):
        exp = auto_exposure(b.dl, b.valid)
        rows.append(compare_views(a, b, exp))
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}
    return {"per_camera": rows, **mean}


def warp_error(
    level_views: Sequence[RasterBuffers],
    full_views: Sequence[RasterBuffers],
    references: Sequence[tuple[np.ndarray, RasterBuffers]],
) -> dict[str, Any]:
    """Warp each reference GI to its client camera with the full and the level's client depth.

    Args:
        level_views: the level's renders at the client cameras (depth needed).
        full_views: the full mesh's renders at the client cameras.
        references: per client camera, (GI map (H, W, 3) at the reference camera, the full
            mesh's render at the reference camera (depth and camera needed)).

    Returns:
        ``ssim`` (mean over cameras, warp with level depth vs with full depth),
        ``holes_level`` and ``holes_full`` (mean hole ratio), ``per_camera``.
    """
    from icbtool import warp
    from icbtool.imageio import auto_exposure
    from icbtool.metrics import ssim

    rows = []
    for lv, fv, (gi, ref) in zip(level_views, full_views, references):
        args = (gi, ref.depth, ref.camera)
        wf = warp.backward(*args, fv.depth, fv.camera, ref.mask, fv.mask)
        wl = warp.backward(*args, lv.depth, lv.camera, ref.mask, lv.mask)
        exp = auto_exposure(gi, ref.valid)
        rows.append(
            {
                "ssim": ssim(wl.image, wf.image, exp),
                "holes_level": wl.hole_ratio,
                "holes_full": wf.hole_ratio,
            }
        )
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    return {"per_camera": rows, **mean}


__all__ = [
    "client_error",
    "compare_views",
    "geometric_error",
    "render_views",
    "sample_surface",
    "uv_error",
    "warp_error",
]
