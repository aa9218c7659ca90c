"""Where the path tracer's time goes: a per-stage profile in CPU seconds (one thread).

The tracer is one numba megakernel (:func:`icbtool.trace.kernels.trace_paths`), so its stages
cannot be timed from inside without changing it. They are timed here by replaying, on one thread
and in CPU seconds (``time.process_time``), the work of one render (the minimum of ``--repeats``
runs of each):

- ``render_cpu_s``: the whole render with ``threads=1``; ``trace_kernel_s``: its passes traced
  alone (the kernel on this thread, and the per-call buffers); ``accumulate_python``: the rest (the
  merge of samples into per-pixel statistics, its own kernel, and the driver's Python code), from
  each render's own clocks (its total minus its kernel calls; median of the renders).
- ``embree_intersect_primary`` / ``_bounce``, ``embree_occluded``: the render's own rays (recorded
  with ``render(..., ray_log=...)``, same seed) replayed through the tracer's one-ray Embree calls
  (``rtcIntersect1`` / ``rtcOccluded1``, :func:`~icbtool.trace.kernels.rtc_intersect_batch`), and
  through Embree's 8-ray packet calls (``rtcIntersect8`` / ``rtcOccluded8``, 8 consecutive rays of
  the log per packet; the packet layout is checked on known rays first, as icbtool.trace.rtc does
  for the one-ray layout). The same for the shadow rays of the paths' first vertices alone, in
  sample order (neighbouring pixels: coherent rays, as a wavefront would batch them).
- ``ray_generation``: the kernel's camera-ray helper (pixel sample, direction) for every sample.
- ``hit_frame``, ``textures``, ``light_sampling``, ``bsdf_sampling``, ``sampler``: the kernel's own
  inlined helpers run on the replayed hits of the intersect rays (one vertex per hit), in
  cumulative levels (hit point and normals; + texture lookup; + emitter / sun / sky light sample
  without its shadow ray; + cosine BSDF sample; + the Sobol random numbers a vertex draws): each
  stage is the difference between two levels. The Sobol level draws a vertex's numbers at every
  hit, though the kernel uses them for the first two vertices only (hashes deeper): an upper
  bound.
- ``unattributed``: the kernel's time minus all of the above: the megakernel's own control flow,
  per-sample bookkeeping and what the isolated replays do not see (cache and branch behaviour of
  interleaved stages).
- ``embree_ns_per_ray``: every kind of the render's rays, in ns per ray, through our one-ray
  calls and packets of 8 and 16, with the scene built robust and not (Mitsuba builds its scene
  without RTC_SCENE_FLAG_ROBUST), and through the peer's own Embree (Mitsuba's
  ``ray_intersect_preliminary`` / ``ray_test``, one thread, packets of its JIT's width): how much
  of the gap per sample the ray queries alone explain.
- ``mitsuba_llvm_ad_rgb``: the peer's render of the same scene and spp in process CPU seconds
  (all its threads: it parallelises itself), so the two compare per sample on a loaded machine.
- ``oidn_high`` / ``oidn_fast``: Open Image Denoise on the render's GI (only for denoised runs;
  its wall time on 2 threads, as the system uses it), when pyoidn is installed.

    .venv/bin/python -m benchmarks.trace_profile [--size 256] [--spp 8] [--scenes cornell_box]

Writes --out/profile.{json,png} (with the 1-minute load at start and end).
"""

from __future__ import annotations

import argparse
import ctypes
import os
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

import icbtool as icb
from benchmarks.common import add_out_argument
from benchmarks.trace_throughput import ray_log, sponza, write_profile_results
from icbtool.trace import TraceConfig
from icbtool.trace import kernels as K
from icbtool.trace.rtc import RtcScene, library
from icbtool.trace.tracer import Tracer, TraceStats

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"
PACKET = 8
_INVALID = np.uint32(0xFFFFFFFF)


# ------------------------------------------------------------------------------ Embree packets
@intrinsic
def _call4(typingctx, fn, a, b, c, d):
    """Call the C function at address ``fn`` with four pointer arguments (no result)."""
    sig = types.void(fn, a, b, c, d)

    def codegen(context, builder, signature, args):
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p, i8p])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(x, i8p) for x in args[1:]])
        return context.get_dummy_value()

    return sig, codegen


@nb.njit(nogil=True)
def _aligned(n):
    """(uint32 words, float32 view, first 64-byte aligned word, its address)."""
    buf = np.zeros(n + 16, np.uint32)
    addr = np.uint64(buf.ctypes.data)
    off = (np.uint64(64) - (addr & np.uint64(63))) & np.uint64(63)
    return buf, buf.view(np.float32), np.int64(off >> np.uint64(2)), addr + off


@nb.njit(nogil=True)
def _packet_batch(rtc, fn, occluded, o, d, tfar, t, prim, lo, hi, W=8):
    """Rays lo..hi-1 through rtcIntersectW (occluded=False: t, prim) or rtcOccludedW (t = -inf
    where blocked), W (8 or 16) consecutive rays per packet. RTCRayHitW as 32-bit words (W lanes
    each): org x/y/z 0-2, tnear 3, dir 4-6, time 7, tfar 8, mask 9, id 10, flags 11, Ng 12-14,
    u 15, v 16, primID 17, geomID 18."""
    w, f, k, addr = _aligned(W * 24)
    vw, _, vk, vaddr = _aligned(W)
    for i0 in range(lo, hi, W):
        n = min(W, hi - i0)
        for j in range(W):
            if j < n:
                i = i0 + j
                vw[vk + j] = _INVALID
                f[k + j] = o[i, 0]
                f[k + W + j] = o[i, 1]
                f[k + 2 * W + j] = o[i, 2]
                f[k + 3 * W + j] = 0.0
                f[k + 4 * W + j] = d[i, 0]
                f[k + 5 * W + j] = d[i, 1]
                f[k + 6 * W + j] = d[i, 2]
                f[k + 7 * W + j] = 0.0
                f[k + 8 * W + j] = tfar[i]
                w[k + 9 * W + j] = _INVALID
                w[k + 10 * W + j] = 0
                w[k + 11 * W + j] = 0
                w[k + 17 * W + j] = _INVALID
                w[k + 18 * W + j] = _INVALID
            else:
                vw[vk + j] = 0
        _call4(fn, vaddr, rtc, addr, np.uint64(0))
        for j in range(n):
            t[i0 + j] = f[k + 8 * W + j]
            if not occluded:
                g = w[k + 18 * W + j]
                prim[i0 + j] = -1 if g == _INVALID else np.int64(w[k + 17 * W + j])


def packet_fns(W: int = 8) -> tuple[int, int]:
    """Addresses of rtcIntersectW and rtcOccludedW (W = 8 or 16), checked on known rays (else
    RuntimeError)."""
    lib = library()
    fns = []
    for name in (f"rtcIntersect{W}", f"rtcOccluded{W}"):
        getattr(lib, name).restype = None
        fns.append(int(ctypes.cast(getattr(lib, name), ctypes.c_void_p).value))
    fi, fo = fns
    rs = RtcScene(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
    o = np.array([[0.25, 0.5, 2.0], [2.0, 2.0, 2.0], [0.1, 0.1, 3.0]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1], [0, 0, -1]], np.float32)
    tf = np.full(3, np.inf, np.float32)
    t, prim, t_occ = np.zeros(3, np.float32), np.zeros(3, np.int64), np.zeros(3, np.float32)
    _packet_batch(rs.ptr, fi, False, o, d, tf, t, prim, 0, 3, W)
    _packet_batch(rs.ptr, fo, True, o, d, tf, t_occ, prim[:0], 0, 3, W)
    ok = list(prim) == [0, -1, 0] and abs(t[0] - 2) < 1e-6 and abs(t[2] - 3) < 1e-6
    ok = ok and t_occ[0] == -np.inf and t_occ[1] == np.inf and t_occ[2] == -np.inf
    if not ok:
        raise RuntimeError(
            f"rtcIntersect{W}/rtcOccluded{W} layout check failed: {prim} {t} {t_occ}"
        )
    return fi, fo


# ------------------------------------------------------------------------------ stage replays
@nb.njit(nogil=True)
def _raygen(cam, sampling, pix, sid):
    salts, seed_mix, pixseed0, sampler = (
        sampling.salts,
        sampling.seed_mix,
        sampling.pixseed,
        sampling.sampler,
    )
    log2spp, zshift = sampling.log2spp, sampling.zshift
    acc = 0.0
    for s in range(len(pix)):
        pixel_seed = K._mix(pixseed0 ^ (np.uint64(pix[s]) * K._GOLD))
        base_s = K._sample_base(seed_mix, pix[s], sid[s])
        zkey = K._U0
        if zshift >= 0:
            zkey = K._zkey(pix[s] % cam.width, pix[s] // cam.width, sid[s], log2spp, zshift)
        ox, _, _, dx, dy, dz = K._camera_ray(
            cam, sampler, salts, pix[s], sid[s], pixel_seed, base_s, (pixseed0, zkey, zshift)
        )
        acc += ox + dx + dy + dz
    return acc


@nb.njit(nogil=True)
def _shade(p, level, d, prim, u, v, tt):
    """The kernel's per-vertex helpers on replayed hits, up to ``level`` (1: hit frame, 2: +
    textures, 3: + light sample, 4: + BSDF sample, 5: + Sobol numbers); returns a checksum."""
    tri, fn, vn, face_mat = p.surf.tri, p.surf.face_n, p.surf.vn, p.surf.face_mat
    face_uv, mat_albedo, shading_normals = p.surf.face_uv, p.surf.mat_albedo, p.surf.shading_normals
    tex, lut, tex_off, tex_hw = p.surf.tex_flat, p.surf.tex_lut, p.surf.tex_off, p.surf.tex_hw
    diag = p.surf.diag
    suns, punct, pmf, area, _, emit_faces, emit_cdf = p.lights
    sky_kind, _, _, _, _, frame, marg, cond, spdf, rows, phi0, mis = p.sky
    sky_mis = mis != 0 and sky_kind != K.SKY_NONE
    pixseed0, log2spp, zshift = p.sampling.pixseed, p.sampling.log2spp, p.sampling.zshift
    width = p.cam.width
    n_e = len(emit_faces)
    acc = 0.0
    for i in range(len(prim)):
        pr = prim[i]
        if pr < 0:
            continue
        dx, dy, dz = np.float64(d[i, 0]), np.float64(d[i, 1]), np.float64(d[i, 2])
        x, bary, cos_o, front, nf, ns = K._hit_frame(
            tri, fn, vn, shading_normals, pr, u[i], v[i], dx, dy, dz
        )
        acc += x[0] + ns[1] + cos_o
        if level < 2:
            continue
        m = face_mat[pr]
        al0 = mat_albedo[m, 0]
        if tex_off[m] >= 0:
            uu, vv = K._tex_coords(face_uv, pr, bary)
            p00, p01, p10, p11, ga, gb, gc, gd = K._bilinear_footprint(
                tex_off[m], tex_hw[m, 0], tex_hw[m, 1], uu, vv
            )
            al0 *= K._bilerp(tex, lut, p00, p01, p10, p11, ga, gb, gc, gd)
            al0 *= K._bilerp(tex, lut, p00 + 1, p01 + 1, p10 + 1, p11 + 1, ga, gb, gc, gd)
            al0 *= K._bilerp(tex, lut, p00 + 2, p01 + 2, p10 + 2, p11 + 2, ga, gb, gc, gd)
        acc += al0
        if level < 3:
            continue
        # stand-in uniform numbers below level 5 (a golden-ratio sequence)
        r0 = (i * 0.6180339887498949) % 1.0
        r1 = (i * 0.7548776662466927) % 1.0
        r2 = (i * 0.5698402909980532) % 1.0
        r3 = (i * 0.8191725133961645) % 1.0
        if level >= 5:
            ps = K._mix(pixseed0 ^ (np.uint64(i >> 3) * K._GOLD))
            sid = np.int64(i & 7)
            zkey = K._U0
            if zshift >= 0:
                px = (i >> 3) % (width * width)  # a pixel of the image (as the kernel's key)
                zkey = K._zkey(px % width, px // width, sid, log2spp, zshift)
            # the first vertex's two pairs, as the kernel: emitter (pick + point), bounce
            r0, r2 = K._ld2(ps, sid, 6, pixseed0, zkey, zshift)
            r3, r1 = K._ld2(ps, sid, 4, pixseed0, zkey, zshift)
        eps = K._eps(x[0], x[1], x[2], np.float64(tt[i]), diag)
        for j in range(suns.shape[0]):
            ok, wi0, wi1, wi2, c = K._sun_sample(suns[j, 0], suns[j, 1], suns[j, 2], nf, ns)
            acc += c
        for j in range(punct.shape[0]):
            ok, wi0, wi1, wi2, tf, ii, g = K._punctual_sample(punct, j, x, nf, ns, eps)
            acc += g
        if n_e > 0:
            lf, y = K._emitter_point(tri, emit_faces, emit_cdf, r0, 0.0, r2, True)
            nl = (fn[lf, 0], fn[lf, 1], fn[lf, 2])
            ok, wi0, wi1, wi2, tf, g = K._emitter_sample(
                y, nl, pmf[lf], area[lf], diag, x, nf, ns, eps
            )
            acc += g + tf
        if sky_mis:
            wi0, wi1, wi2, psk = K._sky_sample(frame, marg, cond, spdf, rows, phi0, r1, r2)
            ok, g = K._sky_light_weight(psk, wi0, wi1, wi2, nf, ns)
            acc += g
        if level < 4:
            continue
        wi0, wi1, wi2, pdf = K._cosine_sample(nf, ns, r3, r1)
        acc += wi0 + pdf
    return acc


def mitsuba_cpu(scene, cam, spp: int, repeats: int) -> dict:
    """Mitsuba 3 ``llvm_ad_rgb`` on the same scene and spp (as trace_time_error.py converts it):
    the fastest of ``repeats`` renders in process CPU seconds (all its threads) and wall seconds
    (after one untimed render that fills its kernel cache); {"unavailable": why} without it."""
    from benchmarks.trace_time_error import PeerMissingError, load_mitsuba, mitsuba_render

    try:
        load_mitsuba("llvm_ad_rgb")
    except PeerMissingError as e:
        return {"unavailable": str(e)}
    mitsuba_render(scene, cam, spp, seed=1)
    cpu, wall = np.inf, np.inf
    for _ in range(repeats):
        c0 = time.process_time()
        _, dt = mitsuba_render(scene, cam, spp, seed=1)
        cpu = min(cpu, time.process_time() - c0)
        wall = min(wall, dt)
    return {"render_cpu_s": cpu, "render_wall_s": wall, "spp": spp}


def record_with_first_shadow(scene, cam, cfg, capacity: int) -> tuple[dict, dict]:
    """:func:`trace_throughput.record`'s rays by kind, and the shadow rays of each path's first
    vertex (those between a camera ray and the path's first bounce ray), in sample order."""
    log, n = ray_log(scene, cam, cfg, capacity)
    kind = log["kind"][:n]
    # the kind of the last non-shadow ray before each ray (0 camera, 2 bounce)
    idx = np.where(kind != 1, np.arange(n), -1)
    last = np.maximum.accumulate(idx)
    first = (kind == 1) & (last >= 0) & (kind[np.maximum(last, 0)] == 0)
    by = {name: kind == k for name, k in (("primary", 0), ("bounce", 2), ("shadow", 1))}
    by["first_shadow"] = first
    out = {
        name: {k: np.ascontiguousarray(log[k][:n][m]) for k in ("o", "d", "tfar")}
        for name, m in by.items()
    }
    first_shadow = out.pop("first_shadow")
    return out, first_shadow


QUERIES = ("one_ray", "packet8", "packet16")


def _query(rs, fns: dict, q: str, occluded: bool, r: dict) -> None:
    """Rays ``r`` through one kind of Embree query ``q`` of :data:`QUERIES`."""
    n = len(r["tfar"])
    t, prim = np.empty(n, np.float32), np.empty(n, np.int64)
    if q == "one_ray" and occluded:
        blocked = np.empty(n, np.bool_)
        K.rtc_occluded_batch(rs.ptr, rs.fn_occluded, r["o"], r["d"], r["tfar"], blocked, 0, n)
    elif q == "one_ray":
        p32, u, v = np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32)
        K.rtc_intersect_batch(rs.ptr, rs.fn_intersect, r["o"], r["d"], t, p32, u, v, 0, n)
    else:
        W = int(q.removeprefix("packet"))
        fi, fo = fns[W]
        _packet_batch(rs.ptr, fo if occluded else fi, occluded, r["o"], r["d"], r["tfar"], t,
                      prim, 0, n, W)  # fmt: skip


def embree_variants(scene, rays: dict, repeats: int) -> dict:
    """ns per ray of each kind of the render's rays through: our one-ray calls, packets of 8 and
    16 (robust and not: Mitsuba builds its scene without RTC_SCENE_FLAG_ROBUST), and the peer's
    own Embree (``Scene.ray_intersect_preliminary`` / ``ray_test`` of Mitsuba ``llvm_ad_rgb`` on
    one thread, packets of its JIT's vector width, its kernel launch included) on the same rays.
    Tells how much of the gap to the peer per sample is the ray queries themselves."""
    out: dict = {}
    fns = {W: packet_fns(W) for W in (8, 16)}
    for robust in (True, False):
        rs = RtcScene.of(scene, robust=robust)
        tag = "robust" if robust else "not_robust"
        for kind in ("primary", "bounce", "shadow"):
            for q in QUERIES:
                cpu = cpu_min(partial(_query, rs, fns, q, kind == "shadow", rays[kind]), repeats)
                out[f"{tag}_{q}_{kind}"] = 1e9 * cpu / len(rays[kind]["tfar"])
    try:
        import drjit as dr

        from benchmarks.trace_time_error import PeerMissingError, load_mitsuba, to_mitsuba

        mi = load_mitsuba("llvm_ad_rgb")
    except (ImportError, PeerMissingError) as e:
        out["mitsuba_unavailable"] = str(e)
        return out
    cam = scene.default_camera.resized(8, 8)
    msc = mi.load_dict(to_mitsuba(scene, cam, 1))
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        for kind in ("primary", "bounce", "shadow"):
            r = rays[kind]
            n = len(r["tfar"])
            o = mi.Point3f(*[mi.Float(np.ascontiguousarray(r["o"][:, i])) for i in range(3)])
            d = mi.Vector3f(*[mi.Float(np.ascontiguousarray(r["d"][:, i])) for i in range(3)])
            ray = mi.Ray3f(o, d, mi.Float(np.minimum(r["tfar"], 3e38)), 0.0, [])

            def run(ray=ray, occ=kind == "shadow"):
                if occ:
                    dr.eval(msc.ray_test(ray))
                else:
                    pi = msc.ray_intersect_preliminary(ray)
                    dr.eval(pi.t, pi.prim_index)
                dr.sync_thread()

            run()  # compiles (kernel cache)
            out[f"mitsuba_{kind}"] = 1e9 * cpu_min(run, repeats) / n
    finally:
        dr.set_thread_count(threads)
    return out


def cpu_min(fn, repeats: int) -> float:
    """Fastest process CPU time of ``repeats`` calls of ``fn`` (single-threaded work)."""
    best = np.inf
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        best = min(best, time.process_time() - c0)
    return best


def profile(scene, cam, cfg: TraceConfig, repeats: int) -> dict:
    cfg1 = TraceConfig(**{**cfg.__dict__, "threads": 1})
    icb.trace.render(scene, cam, TraceConfig(spp=1))  # warm-up (JIT cache, scene data, BVH)
    # the kernel alone: the render's passes (spp_per_pass samples of every pixel) through the
    # tracer's trace(), which calls trace_paths on this thread (threads=1)
    tr = Tracer(scene, cam, cfg1, TraceStats())
    npix = cam.height * cam.width
    passes = []
    for a in range(0, cfg.spp, cfg.spp_per_pass):
        k = min(cfg.spp_per_pass, cfg.spp - a)
        passes.append(
            (
                np.repeat(np.arange(npix, dtype=np.int64), k),
                np.tile(np.arange(a, a + k, dtype=np.int64), npix),
            )
        )
    renders = []
    for _ in range(repeats):
        c0 = time.process_time()
        r = icb.trace.render(scene, cam, cfg1)
        renders.append((time.process_time() - c0, r))
    cpu_total, res = min(renders, key=lambda x: x[0])
    st = res.stats
    trace_s = cpu_min(lambda: [tr.trace(pp, ss) for pp, ss in passes], repeats)
    # the driver's share from each render's own clocks (its whole time minus its kernel calls),
    # not from the fastest render minus the fastest kernel run: on this VM one run of the same
    # work takes up to 25 % longer than the next, and that difference of two minima from
    # different minutes once came out as a fifth of the render
    driver_s = float(
        np.median([r.stats.time_s["total"] - r.stats.time_s["trace"] for _, r in renders])
    )
    rays, first_shadow = record_with_first_shadow(
        scene, cam, cfg1, capacity=int(st.total_rays * 1.05) + 1024
    )
    rs = RtcScene.of(scene, robust=cfg.robust)
    fi8, fo8 = packet_fns()
    stages: dict[str, float] = {}
    packets: dict[str, float] = {}
    hits = {}
    for kind in ("primary", "bounce"):
        r = rays[kind]
        n = len(r["tfar"])
        t, prim = np.empty(n, np.float32), np.empty(n, np.int32)
        u, v = np.empty(n, np.float32), np.empty(n, np.float32)
        stages[f"embree_intersect_{kind}"] = cpu_min(
            lambda r=r, n=n, t=t, prim=prim, u=u, v=v: K.rtc_intersect_batch(
                rs.ptr, rs.fn_intersect, r["o"], r["d"], t, prim, u, v, 0, n
            ),
            repeats,
        )
        hits[kind] = (r["d"], prim.copy(), u.copy(), v.copy(), t.copy())
        t8, p8 = np.empty(n, np.float32), np.empty(n, np.int64)
        packets[f"embree_intersect_{kind}"] = cpu_min(
            lambda r=r, n=n, t8=t8, p8=p8: _packet_batch(
                rs.ptr, fi8, False, r["o"], r["d"], r["tfar"], t8, p8, 0, n
            ),
            repeats,
        )
        if not np.array_equal(p8, prim.astype(np.int64)):
            raise RuntimeError(f"rtcIntersect8 and rtcIntersect1 disagree on {kind} rays")
    r = rays["shadow"]
    n = len(r["tfar"])
    blocked = np.empty(n, np.bool_)
    stages["embree_occluded"] = cpu_min(
        lambda: K.rtc_occluded_batch(
            rs.ptr, rs.fn_occluded, r["o"], r["d"], r["tfar"], blocked, 0, n
        ),
        repeats,
    )
    t8 = np.empty(n, np.float32)
    packets["embree_occluded"] = cpu_min(
        lambda: _packet_batch(
            rs.ptr, fo8, True, r["o"], r["d"], r["tfar"], t8, np.zeros(0, np.int64), 0, n
        ),
        repeats,
    )
    if not np.array_equal(t8 == -np.inf, blocked):
        raise RuntimeError("rtcOccluded8 and rtcOccluded1 disagree")
    # the first vertex's shadow rays alone, in sample order (neighbouring pixels: coherent), as
    # a wavefront that batched them would trace them
    r = first_shadow
    n = len(r["tfar"])
    blocked, t8 = np.empty(n, np.bool_), np.empty(n, np.float32)
    first = {
        "rays": n,
        "one_ray_s": cpu_min(
            lambda: K.rtc_occluded_batch(
                rs.ptr, rs.fn_occluded, r["o"], r["d"], r["tfar"], blocked, 0, n
            ),
            repeats,
        ),
        "packet8_s": cpu_min(
            lambda: _packet_batch(
                rs.ptr, fo8, True, r["o"], r["d"], r["tfar"], t8, np.zeros(0, np.int64), 0, n
            ),
            repeats,
        ),
    }
    first["packet8_over_one_ray"] = first["packet8_s"] / max(first["one_ray_s"], 1e-12)
    # ray generation: the camera-ray helper for every sample of the render
    prm = tr._params
    pix = np.concatenate([pp for pp, _ in passes])
    sid = np.concatenate([ss for _, ss in passes])
    c, s = prm.cam, prm.sampling
    stages["ray_generation"] = cpu_min(
        lambda: _raygen(c, s, pix, sid),
        repeats,
    )
    # per-vertex shading on the replayed hits (primary and bounce), cumulative levels
    d = np.concatenate([hits[k][0] for k in hits])
    prim = np.concatenate([hits[k][1] for k in hits])
    u = np.concatenate([hits[k][2] for k in hits])
    v = np.concatenate([hits[k][3] for k in hits])
    tt = np.concatenate([hits[k][4] for k in hits])
    levels = [
        cpu_min(lambda lv=lv: _shade(prm, lv, d, prim, u, v, tt), repeats) for lv in range(1, 6)
    ]
    names = ("hit_frame", "textures", "light_sampling", "bsdf_sampling", "sampler")
    prev = 0.0
    for name, lv in zip(names, levels, strict=True):
        stages[name] = max(lv - prev, 0.0)
        prev = lv
    stages["accumulate_python"] = max(driver_s, 0.0)
    attributed = sum(v for k, v in stages.items() if k != "accumulate_python")
    stages["unattributed"] = max(trace_s - attributed, 0.0)
    oidn = {}
    try:
        w = icb.trace.denoise(res.gi_raw, res.albedo, res.normal)  # loads the weights
        for q in ("high", "fast"):
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                w = icb.trace.denoise(res.gi_raw, res.albedo, res.normal, quality=q)
                best = min(best, time.perf_counter() - t0)
            oidn[f"oidn_{q}_wall_s"] = best
        del w
    except ImportError as e:
        oidn["unavailable"] = str(e)
    peer = mitsuba_cpu(scene, cam, cfg.spp, repeats)
    variants = embree_variants(scene, rays, repeats)
    # the sampler in the real kernel: whole renders with each (interleaved, fastest of repeats),
    # next to the replayed 'sampler' stage, which draws Sobol numbers at every vertex
    samplers = {"sobol": np.inf, "independent": np.inf}
    for _ in range(repeats):
        for name in samplers:
            c_s = replace(cfg1, sampler=name)
            c0 = time.process_time()
            icb.trace.render(scene, cam, c_s)
            samplers[name] = min(samplers[name], time.process_time() - c0)
    return {
        "mitsuba_llvm_ad_rgb": peer,
        "scene": scene.name,
        "size": [cam.height, cam.width],
        "triangles": scene.n_triangles,
        "spp": cfg.spp,
        "rays": st.rays,
        "render_cpu_s": cpu_total,
        "trace_kernel_s": trace_s,
        "stages_cpu_s": stages,
        "stage_shares_of_render": {k: v / cpu_total for k, v in stages.items()},
        "embree_packet8_cpu_s": packets,
        "embree_packet8_over_one_ray": {k: packets[k] / stages[k] for k in packets},
        "embree_first_vertex_shadow_rays": first,
        "embree_ns_per_ray": variants,
        "shade_levels_cpu_s": dict(zip(names, levels, strict=True)),
        "render_cpu_s_by_sampler": samplers,
        "oidn": oidn,
    }


COLORS = {
    "embree_intersect_primary": "#1f77b4",
    "embree_intersect_bounce": "#4a90d9",
    "embree_occluded": "#9cc3ec",
    "ray_generation": "#ff7f0e",
    "hit_frame": "#2ca02c",
    "textures": "#98df8a",
    "light_sampling": "#d62728",
    "bsdf_sampling": "#ff9896",
    "sampler": "#9467bd",
    "accumulate_python": "#8c564b",
    "unattributed": "#7f7f7f",
}


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 1.2 + 1.1 * len(rows)))
    for i, r in enumerate(rows):
        left = 0.0
        for k, col in COLORS.items():
            w = r["stages_cpu_s"].get(k, 0.0)
            ax.barh(i, w, left=left, color=col, label=k if i == 0 else None)
            left += w
        ax.text(left, i, f" {left:.2f} s", va="center", fontsize=8)
    ax.set_yticks(range(len(rows)), [f"{r['scene']}\n{r['spp']} spp" for r in rows])
    ax.set_xlabel("CPU seconds, one thread")
    ax.set_title(f"tracer per stage, {rows[0]['size'][1]}x{rows[0]['size'][0]} (replayed stages)")
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.35))
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument(
        "--robust",
        type=int,
        default=int(TraceConfig().robust),
        help="Embree robust mode (1/0; default: TraceConfig's)",
    )
    ap.add_argument("--out-name", default="profile")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    load_start = os.getloadavg()
    cfg = TraceConfig(spp=args.spp, spp_per_pass=4, max_depth=8, seed=0, robust=bool(args.robust))
    rows = []
    for name in args.scenes.split(","):
        scene = sponza() if name == "sponza" else getattr(icb.scene, name)()
        cam = scene.default_camera.resized(args.size, args.size)
        row = profile(scene, cam, cfg, args.repeats)
        print(name, f"render {row['render_cpu_s']:.3f} CPU s:")
        for k, v in row["stages_cpu_s"].items():
            print(f"  {k:26s} {v:7.3f} s  {100 * v / row['render_cpu_s']:5.1f} %")
        mi = row["mitsuba_llvm_ad_rgb"]
        if "render_cpu_s" in mi:
            print(f"  Mitsuba llvm_ad_rgb, same spp: {mi['render_cpu_s']:.3f} CPU s (all threads)")
        ratio = {k: round(v, 2) for k, v in row["embree_packet8_over_one_ray"].items()}
        print("  Embree packets of 8 / one ray:", ratio)
        fs = row["embree_first_vertex_shadow_rays"]
        print(
            f"  first-vertex shadow rays in sample order: packets {fs['packet8_over_one_ray']:.2f}x"
        )
        ns = row["embree_ns_per_ray"]
        for kind in ("primary", "bounce", "shadow"):
            ours = ", ".join(
                f"{tag} " + "/".join(f"{ns[f'{tag}_{q}_{kind}']:.0f}" for q in QUERIES)
                for tag in ("robust", "not_robust")
            )
            peer = ns.get(f"mitsuba_{kind}")
            peer_s = f"; Mitsuba's Embree {peer:.0f}" if peer is not None else ""
            print(f"  ns/ray {kind:7s} (1 ray/packet 8/packet 16): {ours}{peer_s}")
        rows.append(row)
    path, load_end = write_profile_results(args.out_name, cfg, args, load_start, rows, __doc__)
    plot(rows, OUT / f"{args.out_name}.png")
    print(f"wrote {path} (load {load_start[0]:.1f} -> {load_end[0]:.1f})")


if __name__ == "__main__":
    main()
