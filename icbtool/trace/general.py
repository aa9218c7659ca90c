"""The general path-tracing kernel: any BSDF of :mod:`icbtool.trace.bsdfs` at every vertex.

:func:`trace_paths_general` is used instead of :func:`icbtool.trace.kernels.trace_paths` only
when a scene has a material with a declared BSDF (:attr:`icbtool.scene.Material.bsdf`); a scene
of Lambertian materials keeps the tuned Lambert kernel. It takes the same parameter struct,
scratch outputs and per-pixel statistics, and reuses that module's inlined steps (camera ray,
samplers, Embree calls, hit frame, light and sky sampling, statistics), so images of the two
kernels share their sampling and their DL/GI split:

- next-event estimation at every non-delta vertex from each light type (suns, point/spot lights,
  emissive triangles, the sky or environment map), each light sample weighted against BSDF
  sampling by the power heuristic where the light has an area (emitters, sky); delta BSDFs
  (smooth conductor, dielectrics) skip it, and what their sampled direction finds counts fully;
- BSDF sampling (:func:`icbtool.trace.bsdfs.bsdf_sample`) continues the path; a ``mask`` lets
  the ray pass through (no vertex, the path's depth unchanged) with probability 1 - opacity;
- DL = emission seen + the first hit's light from the scene's direct lights (suns, point/spot,
  area lights), through the first hit's BSDF; everything else is GI (as the Lambert kernel).

Not done here (the Lambert kernel's performance features): ``gi_splits`` (one branch per
sample) and deferred texel loads.

numba's disk cache of a function is keyed on its own file only, but this kernel compiles in the
helpers of :mod:`icbtool.trace.kernels`, :mod:`icbtool.trace.bsdfs` and
:mod:`icbtool.trace.shapes`:
:func:`_drop_stale_cache` empties its cache when either file changed since it was written.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numba as nb
import numpy as np

from icbtool.trace import bsdfs as bs
from icbtool.trace import kernels as _kernels
from icbtool.trace import shapes as _shapes
from icbtool.trace.kernels import (
    _GOLD,
    _JIT,
    _U0,
    DIMS_PER_BOUNCE,
    EDGE_PAIR,
    LD_MAX_DEPTH,
    SAMPLER_SOBOL,
    SKY_NONE,
    SKY_PAIR0,
    _add_sample,
    _add_to,
    _address,
    _camera_ray,
    _closest,
    _emission_mis_weight,
    _emission_through_all,
    _emitter_pick,
    _eps,
    _hit_frame,
    _ld2,
    _log_ray,
    _mix,
    _sample_base,
    _sky,
    _sky_pdf,
    _sky_sample,
    _sobol2,
    _spot_falloff,
    _stack_words,
    _take_block,
    _tex_coords,
    _towards,
    _triangle_point,
    _u01,
    _visible_all,
    _zkey,
)
from icbtool.trace.shapes import shape_frame, shape_pdf, shape_sample

#: salts of the lobe choice and of a mask's pass-through decision (xor-ed into a dimension's)
_LOBE_SALT = np.uint64(0x632BE59BD9B4E019)
_MASK_SALT = np.uint64(0x85157AF5D2D2A4C3)
#: most mask pass-throughs of one path (a stack of masks cannot hang a path)
MAX_PASS = 64


@nb.njit(inline="always", **_JIT)
def _frame(n, t):
    """Orthonormal (s, t, n) about the unit n: s from the tangent t projected (Mitsuba's shading
    frame from dp/du) when it is usable, else Duff et al.'s basis (Mitsuba's
    ``coordinate_system``)."""
    n0, n1, n2 = n
    d = t[0] * n0 + t[1] * n1 + t[2] * n2
    s0 = t[0] - n0 * d
    s1 = t[1] - n1 * d
    s2 = t[2] - n2 * d
    ln = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
    if ln > 1e-12:
        s0 /= ln
        s1 /= ln
        s2 /= ln
    else:
        sign = 1.0 if n2 >= 0 else -1.0
        a = -1.0 / (sign + n2)
        b = n0 * n1 * a
        s0, s1, s2 = 1 + sign * n0 * n0 * a, sign * b, -sign * n0
    return (s0, s1, s2), (n1 * s2 - n2 * s1, n2 * s0 - n0 * s2, n0 * s1 - n1 * s0)


@nb.njit(inline="always", **_JIT)
def _to_local(s, t, n, x, y, z):
    return (
        s[0] * x + s[1] * y + s[2] * z,
        t[0] * x + t[1] * y + t[2] * z,
        n[0] * x + n[1] * y + n[2] * z,
    )


@nb.njit(inline="always", **_JIT)
def _to_world(s, t, n, v):
    return (
        s[0] * v[0] + t[0] * v[1] + n[0] * v[2],
        s[1] * v[0] + t[1] * v[1] + n[1] * v[2],
        s[2] * v[0] + t[2] * v[1] + n[2] * v[2],
    )


@nb.njit(inline="always", **_JIT)
def _offset(x, nf, eps, dx, dy, dz):
    """float32 origin of a ray leaving x along d: x moved eps along nf to d's side."""
    sg = eps if nf[0] * dx + nf[1] * dy + nf[2] * dz >= 0 else -eps
    return (
        np.float32(x[0] + nf[0] * sg),
        np.float32(x[1] + nf[1] * sg),
        np.float32(x[2] + nf[2] * sg),
    )


@nb.njit(inline="always", **_JIT)
def _light(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps, d, dist):
    """BSDF at a light direction d (world) and the offset shadow-ray origin and length:
    (f0, f1, f2, bsdf pdf, origin, tfar)."""
    s, t, n = fr
    wo_l = _to_local(s, t, n, d[0], d[1], d[2])
    f0, f1, f2, pb = bs.bsdf_eval(B, root, uu, vv, nearest, wi_l, wo_l, geo)
    so = _offset(x, nf, eps, d[0], d[1], d[2])
    return f0, f1, f2, pb, so


@nb.njit(inline="always", **_JIT)
def _geo(B, root, fr, face_t, face_b, fn, prim):
    """The local geometry a normal or bump map tilts the frame with (bsdfs.map_frame): dp/du,
    dp/dv and the geometric normal in the frame fr, and dp/du in world space; bsdfs.NO_GEO
    where the material has no map."""
    if not bs.has_map(B, root):
        return bs.NO_GEO
    s, t, n = fr
    du = (np.float64(face_t[prim, 0]), np.float64(face_t[prim, 1]), np.float64(face_t[prim, 2]))
    dv = (np.float64(face_b[prim, 0]), np.float64(face_b[prim, 1]), np.float64(face_b[prim, 2]))
    g = (np.float64(fn[prim, 0]), np.float64(fn[prim, 1]), np.float64(fn[prim, 2]))
    return (
        _to_local(s, t, n, du[0], du[1], du[2]),
        _to_local(s, t, n, dv[0], dv[1], dv[2]),
        _to_local(s, t, n, g[0], g[1], g[2]),
        du,
    )


@nb.njit(**_JIT)
def trace_paths_general(p, B, mat_root, face_t, face_b, out, acc, counts, log, part, queue, pix,
                        sid, bounds):  # fmt: skip
    """:func:`icbtool.trace.kernels.trace_paths` with any BSDF: one whole path per sample.

    Args:
        p: :data:`~icbtool.trace.kernels.TraceParams` (``sampling.splits`` is ignored).
        B: :data:`~icbtool.trace.bsdfs.BsdfParams`, the scene's BSDF nodes.
        mat_root: (M,) int64 root node of each material.
        face_t: (F, 3) float32 tangent (dp/du) per face, zeros where the face has no uvs.
        face_b: (F, 3) float32 dp/dv per face where the scene has a normal or bump map, else
            (1, 3) (never read).
        out, acc, counts, log, part, queue, pix, sid, bounds: as ``trace_paths``.
    """
    rtc, fn_isect, fn_occl = p.embree[0], p.embree[1], p.embree[2]
    cam = p.cam
    width, edge_extra = cam.width, cam.edge_extra
    sf = p.surf
    tri, fn, vn, face_mat, face_uv = sf.tri, sf.face_n, sf.vn, sf.face_mat, sf.face_uv
    mat_albedo, mat_emission = sf.mat_albedo, sf.mat_emission
    nearest, shading_normals, diag = sf.nearest, sf.shading_normals, sf.diag
    shp = sf.shapes  # analytic shapes: primitive n_tri + k (icbtool.trace.shapes)
    n_tri = tri.shape[0]
    suns, punct, face_light_pmf, face_area, face_is_area, emit_faces, emit_cdf = p.lights
    sky_kind, sky, env, rot, scale, frame, marg, cond, spdf, rows, phi0, mis = p.sky
    smp = p.sampling
    seed_mix, salts, pixseed0, sampler = smp.seed_mix, smp.salts, smp.pixseed, smp.sampler
    limit, rr_depth, want_aux, log2spp, zshift = (
        smp.limit, smp.rr_depth, smp.want_aux, smp.log2spp, smp.zshift,
    )  # fmt: skip
    direct, gi, first_hit, alb_out, nrm_out, _held = out
    sky_on = sky_kind != SKY_NONE
    sky_mis = mis != 0 and sky_on
    any_extra = len(edge_extra) > 0
    has_uv = face_uv.shape[0] == tri.shape[0]
    n_s = suns.shape[0]
    n_q = punct.shape[0]
    n_e = len(emit_faces)
    pw, pf = _stack_words()
    ray = (pw, pf, np.int64(0), _address(pw), p.embree[3])
    n_prim = 0
    n_bounce = 0
    n_shadow = 0
    row = part * 64
    n_blocks = len(bounds) - 1
    while True:
        blk = _take_block(queue)
        if blk >= n_blocks:
            break
        for s in range(bounds[blk], bounds[blk + 1]):
            direct[row, 0] = direct[row, 1] = direct[row, 2] = 0.0
            gi[row, 0] = gi[row, 1] = gi[row, 2] = 0.0
            first_hit[row] = False
            if want_aux:
                alb_out[row, 0] = alb_out[row, 1] = alb_out[row, 2] = 0.0
                nrm_out[row, 0] = nrm_out[row, 1] = nrm_out[row, 2] = 0.0
            pixel_seed = _mix(pixseed0 ^ (np.uint64(pix[s]) * _GOLD))
            base = _sample_base(seed_mix, pix[s], sid[s])
            pix_x = pix[s] % width
            pix_y = pix[s] // width
            zkey = _U0
            if zshift >= 0:
                zkey = _zkey(pix_x, pix_y, sid[s], log2spp, zshift)
            zk = (pixseed0, zkey, zshift)
            ox, oy, oz, dx, dy, dz = _camera_ray(
                cam, sampler, salts, pix[s], sid[s], pixel_seed, base, zk
            )
            w_seen = 1.0
            k_extra = edge_extra[pix[s]] if any_extra else 0
            if k_extra > 0:  # extra emission samples on an edge pixel (as trace_paths)
                w_seen = 1.0 / (k_extra + 1)
                for j in range(k_extra):
                    if sampler == SAMPLER_SOBOL:
                        jx, jy = _sobol2(pixel_seed, sid[s] * k_extra + j, EDGE_PAIR)
                    else:
                        bj = _mix(base + np.uint64(j + 1) * _GOLD)
                        jx = _u01(bj, salts[0])
                        jy = _u01(bj, salts[1])
                    le = _emission_through_all(
                        rtc, fn_isect, ray, log, cam,
                        np.float64(pix_x) + jx, np.float64(pix_y) + jy,
                        (fn, face_mat, mat_emission), (sky_kind, sky, env, rot, scale), shp,
                    )  # fmt: skip
                    n_prim += 1
                    direct[row, 0] += le[0] * w_seen
                    direct[row, 1] += le[1] * w_seen
                    direct[row, 2] += le[2] * w_seen
            t0 = 1.0
            t1 = 1.0
            t2 = 1.0
            pdf_prev = 0.0
            delta_prev = True  # what the camera ray finds counts fully
            from_first = False
            eta_path = 1.0  # relative IOR crossed so far (Mitsuba's eta: RR without 1/eta^2)
            depth = 1
            n_pass = 0
            while depth <= limit:
                _log_ray(log, 0 if depth == 1 else 2, ox, oy, oz, dx, dy, dz, np.float32(np.inf))
                th, prim, h_u, h_v = _closest(
                    rtc, fn_isect, ray, shp, n_tri, ox, oy, oz, dx, dy, dz
                )
                if depth == 1:
                    n_prim += 1
                else:
                    n_bounce += 1
                if prim < 0:  # the sky: direct for a camera ray, else gi (MIS-weighted)
                    if sky_on:
                        le = _sky(sky_kind, sky, env, rot, scale, dx, dy, dz)
                        if depth == 1:
                            direct[row, 0] += le[0] * w_seen
                            direct[row, 1] += le[1] * w_seen
                            direct[row, 2] += le[2] * w_seen
                        else:
                            w = 1.0
                            if sky_mis and not delta_prev:
                                psk = _sky_pdf(frame, spdf, rows, phi0, dx, dy, dz)
                                w = (
                                    pdf_prev
                                    * pdf_prev
                                    / max(pdf_prev * pdf_prev + psk * psk, 1e-300)
                                )
                            gi[row, 0] += le[0] * t0 * w
                            gi[row, 1] += le[1] * t1 * w
                            gi[row, 2] += le[2] * t2 * w
                    break
                on_shape = prim >= n_tri
                if on_shape:  # exact: point, normal; no uvs, the Duff frame (isotropic BSDFs)
                    x, bary, cos_o, front, nf, ns = shape_frame(
                        shp, prim - n_tri, np.float64(ox), np.float64(oy), np.float64(oz),
                        dx, dy, dz, th,
                    )  # fmt: skip
                else:
                    x, bary, cos_o, front, nf, ns = _hit_frame(
                        tri, fn, vn, shading_normals, prim, h_u, h_v, dx, dy, dz
                    )
                m = face_mat[prim]
                e0 = mat_emission[m, 0]
                e1 = mat_emission[m, 1]
                e2 = mat_emission[m, 2]
                if front and (e0 > 0 or e1 > 0 or e2 > 0):
                    if depth == 1:
                        direct[row, 0] += e0 * w_seen
                        direct[row, 1] += e1 * w_seen
                        direct[row, 2] += e2 * w_seen
                    else:
                        w = 1.0
                        if not delta_prev and on_shape:  # the density shape_sample used
                            pl = face_light_pmf[prim] * shape_pdf(
                                shp, prim - n_tri, np.float64(ox), np.float64(oy),
                                np.float64(oz), dx, dy, dz, th, cos_o,
                            )  # fmt: skip
                            w = pdf_prev * pdf_prev / max(pdf_prev * pdf_prev + pl * pl, 1e-300)
                        elif not delta_prev:
                            w = _emission_mis_weight(
                                face_light_pmf[prim], face_area[prim], th, cos_o, pdf_prev
                            )
                        _add_to(direct, gi, from_first and face_is_area[prim], row,
                                e0 * t0 * w, e1 * t1 * w, e2 * t2 * w)  # fmt: skip
                eps = _eps(x[0], x[1], x[2], th, diag)
                uu, vv = _tex_coords(face_uv, prim, bary) if has_uv and not on_shape else (0.0, 0.0)
                root = mat_root[m]
                dim0 = 2 + depth * DIMS_PER_BOUNCE
                if B.nt[root] == bs.MASK:  # pass through with probability 1 - opacity
                    a = bs.value1(B, root, 0, uu, vv, nearest)
                    um = _u01(base, salts[dim0 + 2] ^ _MASK_SALT ^ (np.uint64(n_pass) * _GOLD))
                    if um >= a and n_pass < MAX_PASS:
                        n_pass += 1
                        ox, oy, oz = _offset(x, nf, eps, dx, dy, dz)
                        delta_prev = True
                        continue
                    root = B.ni[root, 0]
                # the local shading frame: z = the shading normal on the face's front side
                sgn = 1.0 if front else -1.0
                n_sh = (ns[0] * sgn, ns[1] * sgn, ns[2] * sgn)
                tg = (0.0, 0.0, 0.0)
                if not on_shape:
                    tg = (np.float64(face_t[prim, 0]), np.float64(face_t[prim, 1]),
                          np.float64(face_t[prim, 2]))  # fmt: skip
                fr_s, fr_t = _frame(n_sh, tg)
                fr = (fr_s, fr_t, n_sh)
                wi_l = _to_local(fr_s, fr_t, n_sh, -dx, -dy, -dz)
                geo = bs.NO_GEO if on_shape else _geo(B, root, fr, face_t, face_b, fn, prim)
                if depth == 1:
                    first_hit[row] = True
                    if want_aux:
                        leaf = bs.leaf_of(B, root)
                        if B.nt[leaf] == bs.LAMBERT2 or B.nt[leaf] == bs.DIFFUSE:
                            al = bs.value(B, leaf, 0, uu, vv, nearest)
                        else:
                            al = (mat_albedo[m, 0], mat_albedo[m, 1], mat_albedo[m, 2])
                        alb_out[row, 0], alb_out[row, 1], alb_out[row, 2] = al
                        nrm_out[row, 0], nrm_out[row, 1], nrm_out[row, 2] = ns
                if depth >= limit:
                    break
                to_dl = depth == 1
                use_ld = sampler == SAMPLER_SOBOL and depth <= LD_MAX_DEPTH
                pair0 = 1 + 3 * depth
                if not bs.is_smooth(B, root):
                    n_shadow += _nee(
                        B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps, diag, t0, t1, t2,
                        to_dl, row, direct, gi, rtc, fn_occl, ray, log, shp, suns, n_s, punct,
                        n_q, tri, fn, face_mat, mat_emission, face_light_pmf, face_area,
                        face_is_area, emit_faces, emit_cdf, n_e, sky_mis, sky_kind, sky, env,
                        rot, scale, frame, marg, cond, spdf, rows, phi0, use_ld, pixel_seed,
                        sid[s], pair0, pixseed0, zkey, zshift, base, salts, dim0, depth,
                    )  # fmt: skip
                # ---- BSDF sampling
                if use_ld:
                    u1, u2 = _ld2(pixel_seed, sid[s], pair0, pixseed0, zkey, zshift)
                else:
                    u1 = _u01(base, salts[dim0])
                    u2 = _u01(base, salts[dim0 + 1])
                u0 = _u01(base, salts[dim0 + 5] ^ _LOBE_SALT)
                ok, wo_l, wgt, pdf, delta = bs.bsdf_sample(
                    B, root, uu, vv, nearest, wi_l, u0, u1, u2, geo
                )
                if not ok:
                    break
                f0 = t0 * wgt[0]
                f1 = t1 * wgt[1]
                f2 = t2 * wgt[2]
                if not (f0 > 0 or f1 > 0 or f2 > 0):
                    break
                if wo_l[2] * wi_l[2] < 0:  # transmitted: into or out of a dielectric
                    leaf = bs.leaf_of(B, root)
                    if B.nt[leaf] == bs.DIELECTRIC or B.nt[leaf] == bs.ROUGHDIELECTRIC:
                        e_rel = B.nf[leaf, 0]
                        eta_path = eta_path * e_rel if wi_l[2] > 0 else eta_path / e_rel
                if depth + 1 > rr_depth:
                    # the throughput carries 1 / eta^2 inside a denser medium: as Mitsuba, the
                    # survival probability leaves it out, or paths inside glass die young
                    q = min(max(f0, max(f1, f2)) * eta_path * eta_path, 0.95)
                    if not (_u01(base, salts[dim0 + 5]) < q):
                        break
                    f0 /= q
                    f1 /= q
                    f2 /= q
                wd = _to_world(fr_s, fr_t, n_sh, wo_l)
                ln = math.sqrt(wd[0] * wd[0] + wd[1] * wd[1] + wd[2] * wd[2])
                dx, dy, dz = wd[0] / ln, wd[1] / ln, wd[2] / ln
                ox, oy, oz = _offset(x, nf, eps, dx, dy, dz)
                t0, t1, t2 = f0, f1, f2
                pdf_prev = pdf
                delta_prev = delta
                from_first = depth == 1
                depth += 1
            _add_sample(acc, pix[s], direct, gi, first_hit, alb_out, nrm_out, row, want_aux)
    counts[0] += n_prim
    counts[1] += n_bounce
    counts[2] += n_shadow


@nb.njit(**_JIT)
def _nee(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps, diag, t0, t1, t2, to_dl, row, direct,
         gi, rtc, fn_occl, ray, log, shp, suns, n_s, punct, n_q, tri, fn, face_mat, mat_emission,
         face_light_pmf, face_area, face_is_area, emit_faces, emit_cdf, n_e, sky_mis, sky_kind,
         sky, env, rot, scale, frame, marg, cond, spdf, rows, phi0, use_ld, pixel_seed, sid_s,
         pair0, pixseed0, zkey, zshift, base, salts, dim0, depth):  # fmt: skip
    """Next-event estimation at one vertex: one shadow-tested sample of each sun, point and spot
    light, of the emissive triangles (by power) and of the sky, each through the vertex's BSDF
    (area lights MIS-weighted against BSDF sampling). Returns the shadow rays traced."""
    n_shadow = 0
    for j in range(n_s):  # directional lights (delta)
        d = (-suns[j, 0], -suns[j, 1], -suns[j, 2])
        f0, f1, f2, _, so = _light(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps, d, 0.0)
        if f0 > 0 or f1 > 0 or f2 > 0:
            n_shadow += 1
            if _visible_all(rtc, fn_occl, ray, log, shp, so, d[0], d[1], d[2], np.float32(np.inf)):
                _add_to(direct, gi, to_dl, row, t0 * f0 * suns[j, 3], t1 * f1 * suns[j, 4],
                        t2 * f2 * suns[j, 5])  # fmt: skip
    for j in range(n_q):  # point and spot lights (delta)
        w0, w1, w2, dist = _towards(x[0], x[1], x[2], punct[j, 0], punct[j, 1], punct[j, 2])
        if not dist > 0:
            continue
        fall = _spot_falloff(punct, j, w0, w1, w2)
        if not fall > 0:
            continue
        f0, f1, f2, _, so = _light(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps,
                                   (w0, w1, w2), dist)  # fmt: skip
        if f0 > 0 or f1 > 0 or f2 > 0:
            n_shadow += 1
            tf = np.float32(dist * (1 - 1e-5) - eps)
            if _visible_all(rtc, fn_occl, ray, log, shp, so, w0, w1, w2, tf):
                g = fall / (dist * dist)
                _add_to(direct, gi, to_dl, row, t0 * f0 * punct[j, 3] * g,
                        t1 * f1 * punct[j, 4] * g, t2 * f2 * punct[j, 5] * g)  # fmt: skip
    if n_e > 0:  # emissive triangles, by power; MIS with the BSDF
        if use_ld:
            ul, rb = _ld2(pixel_seed, sid_s, pair0 + 2, pixseed0, zkey, zshift)
            ra = 0.0
        else:
            ul = _u01(base, salts[dim0 + 2])
            ra = _u01(base, salts[dim0 + 3])
            rb = _u01(base, salts[dim0 + 4])
        lf, ra = _emitter_pick(emit_faces, emit_cdf, ul, ra, use_ld)
        if lf >= tri.shape[0]:  # an analytic emitter, drawn as Mitsuba draws it
            ok, w0, w1, w2, dist, pdf, y, _ = shape_sample(
                shp, lf - tri.shape[0], x[0], x[1], x[2], ra, rb
            )
            pl = face_light_pmf[lf] * pdf
        else:
            y = _triangle_point(tri, lf, ra, rb)
            w0, w1, w2, dist = _towards(x[0], x[1], x[2], y[0], y[1], y[2])
            cl = -(fn[lf, 0] * w0 + fn[lf, 1] * w1 + fn[lf, 2] * w2)
            ok = cl > 0
            pl = face_light_pmf[lf] / face_area[lf] * dist * dist / cl if ok else 0.0
        if ok and dist > 0:
            f0, f1, f2, pb, so = _light(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps,
                                        (w0, w1, w2), dist)  # fmt: skip
            if f0 > 0 or f1 > 0 or f2 > 0:
                g = pl / (pl * pl + pb * pb)  # w / pl, w = power heuristic
                n_shadow += 1
                eps_l = _eps(y[0], y[1], y[2], dist, diag)
                # aimed from the offset origin at y (see kernels._emitter_sample: along x -> y
                # the ray met a light seen at a grazing angle before y)
                s0, s1, s2, sdist = _towards(
                    np.float64(so[0]), np.float64(so[1]), np.float64(so[2]), y[0], y[1], y[2]
                )
                tf = np.float32(max(sdist - eps_l, 0.0))
                if _visible_all(rtc, fn_occl, ray, log, shp, so, s0, s1, s2, tf):
                    me = face_mat[lf]
                    _add_to(direct, gi, to_dl and face_is_area[lf], row,
                            t0 * f0 * mat_emission[me, 0] * g, t1 * f1 * mat_emission[me, 1] * g,
                            t2 * f2 * mat_emission[me, 2] * g)  # fmt: skip
    if sky_mis:  # the sky from its table; MIS with the BSDF; always gi
        if use_ld:
            us1, us2 = _ld2(pixel_seed, sid_s, SKY_PAIR0 + depth, pixseed0, zkey, zshift)
        else:
            us1 = _u01(base, salts[dim0 + 6])
            us2 = _u01(base, salts[dim0 + 7])
        w0, w1, w2, psk = _sky_sample(frame, marg, cond, spdf, rows, phi0, us1, us2)
        if psk > 0:
            f0, f1, f2, pb, so = _light(B, root, uu, vv, nearest, fr, wi_l, geo, x, nf, eps,
                                        (w0, w1, w2), 0.0)  # fmt: skip
            if f0 > 0 or f1 > 0 or f2 > 0:
                n_shadow += 1
                if _visible_all(rtc, fn_occl, ray, log, shp, so, w0, w1, w2, np.float32(np.inf)):
                    le = _sky(sky_kind, sky, env, rot, scale, w0, w1, w2)
                    g = psk / (psk * psk + pb * pb)
                    _add_to(direct, gi, False, row, t0 * f0 * le[0] * g, t1 * f1 * le[1] * g,
                            t2 * f2 * le[2] * g)  # fmt: skip
    return n_shadow


def _drop_stale_cache() -> None:
    """Empty the disk cache of the kernel and of :func:`_nee` when the modules whose helpers they
    compile in (kernels.py, bsdfs.py) differ from those they were cached with (a stamp file
    beside the cache); a read-only or missing cache is left alone."""
    try:
        deps = hashlib.sha256(
            b"".join(Path(m.__file__).read_bytes() for m in (_kernels, bs, _shapes))
        ).hexdigest()
        cache = trace_paths_general._cache
        stamp = Path(cache._cache_path) / "general_deps.sha256"
        if stamp.is_file() and stamp.read_text() == deps:
            return
        trace_paths_general._cache.flush()
        _nee._cache.flush()
        stamp.write_text(deps)
    except (OSError, AttributeError):  # pragma: no cover - read-only cache, other numba
        return


_drop_stale_cache()
