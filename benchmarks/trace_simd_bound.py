"""How much a wavefront with SIMD shading could save the path tracer: a measured upper bound.

The tracer is one numba megakernel that follows one path at a time (icbtool.trace.kernels), so
its shading helpers run on scalar registers. A wavefront would trace a batch of paths one stage at
a time and keep each stage's per-path state in structure-of-arrays (SoA) form, where LLVM's loop
vectorizer can run 4 doubles per AVX2 instruction. Before such a rewrite (docs/design.md, section
8), this script measures what it could gain at most, on the hits of a real render:

- The render's own rays are recorded (``render(..., ray_log=...)``, as benchmarks/trace_profile.py
  does) and its camera and bounce rays replayed through Embree for their hits.
- On every hit, the shading math of one path vertex is timed two ways, with the same inputs and
  the same uniform numbers: (a) the kernel's own inlined helpers (``_hit_frame``, one emitter
  sample ``_emitter_point`` + ``_emitter_sample`` where the scene has emitters, one sun sample
  per directional light, ``_cosine_sample``) in one loop over the hits, one vertex at a time,
  their results summed (as the megakernel keeps them in registers); (b) a wavefront's stages over
  batches of 32 to 256 paths: a scalar gather of each hit's inputs into the batch's columns
  (face corners, vertex normals and the picked emitter face by index, and the ray, hit and
  uniform numbers a real wavefront would already hold there), then the same formulas written
  branch-free, one loop per group of outputs over 1D column views (LLVM's vectoriser refuses
  loops over 2D indexing, loops from an offset numba cannot prove non-negative, and loops over
  so many arrays that it would need "too many memory checks"). Both must agree to 1e-9 on every
  output (checked), and the script reports the packed AVX2 instructions (``ymm``) of each loop.
- What it leaves out, all of which a wavefront would also pay or keep: Embree (one ray per call
  either way; packets gain little on incoherent rays: trace_profile's packet rows), textures
  (random loads), the Sobol numbers (64-bit integer hashes, which AVX2 has no packed multiply for),
  the path's control flow, and handing each stage's state to the next and to Embree.

The bound: the share of the render in these stages (benchmarks/results/trace/profile.json: hit
frame, light and BSDF sampling) times (1 - 1 / speed-up) at the most favourable batch size is
the most this vectorisation could take off the render; the missed FLIP points of the Cornell box
need 15-25 % (docs/benchmarks.md, time against error).

    .venv/bin/python -m benchmarks.trace_simd_bound [--size 256] [--spp 8] [--scenes cornell_box] \
        [--batches 32,64,128,256]

Writes --out/simd_bound.json (with the 1-minute load at start and end).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numba as nb
import numpy as np

import icbtool as icb
from benchmarks.common import add_out_argument
from benchmarks.trace_throughput import ray_log, sponza, write_profile_results
from icbtool.trace import TraceConfig
from icbtool.trace import kernels as K
from icbtool.trace.rtc import RtcScene
from icbtool.trace.tracer import Tracer, TraceStats

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "trace"
#: outputs per vertex: point (3), nf (3), ns (3), light direction (3), light g, light tfar,
#: bounce direction (3), bounce pdf
N_OUT = 18


# ---------------------------------------------------------------------- (a) the kernel's helpers
@nb.njit(nogil=True)
def scalar_vertices(tri, fn, vn, suns, emit_faces, emit_cdf, pmf, area, diag, d, prim, u, v, tt,
                    rnd, out, store):  # fmt: skip
    """The megakernel's per-vertex helpers on each hit, one vertex at a time (AoS, as the kernel
    holds them). With ``store`` every result goes to ``out`` (N_OUT, n), for the check; without,
    into a returned checksum (as the kernel keeps them in registers), for the timing."""
    acc = 0.0
    n_e = len(emit_faces)
    for i in range(len(prim)):
        pr = prim[i]
        dx, dy, dz = np.float64(d[i, 0]), np.float64(d[i, 1]), np.float64(d[i, 2])
        x, bary, cos_o, front, nf, ns = K._hit_frame(tri, fn, vn, True, pr, u[i], v[i], dx, dy, dz)
        eps = K._eps(x[0], x[1], x[2], np.float64(tt[i]), diag)
        g = 0.0
        tf = np.float32(0.0)
        wi0 = wi1 = wi2 = 0.0
        for j in range(suns.shape[0]):
            ok, s0, s1, s2, c = K._sun_sample(suns[j, 0], suns[j, 1], suns[j, 2], nf, ns)
            g += c if ok else 0.0
        if n_e > 0:
            lf, y = K._emitter_point(tri, emit_faces, emit_cdf, rnd[0, i], 0.0, rnd[1, i], True)
            nl = (fn[lf, 0], fn[lf, 1], fn[lf, 2])
            ok, wi0, wi1, wi2, tf, ge = K._emitter_sample(
                y, nl, pmf[lf], area[lf], diag, x, nf, ns, eps
            )
            g += ge
        b0, b1, b2, pdf = K._cosine_sample(nf, ns, rnd[2, i], rnd[3, i])
        vals = (x[0], x[1], x[2], nf[0], nf[1], nf[2], ns[0], ns[1], ns[2],
                wi0, wi1, wi2, g, np.float64(tf), b0, b1, b2, pdf)  # fmt: skip
        if store:
            for k in range(N_OUT):
                out[k, i] = vals[k]
        else:
            for k in range(N_OUT):
                acc += vals[k]
    return acc


# --------------------------------------------------------------------- (b) SoA, branch-free
#: rows of a batch's input columns: hit face corners (0-8), vertex normals (9-17), geometric
#: normal (18-20), emitter face corners (21-29) and normal (30-32), its pick pmf (33), area (34)
#: and the pick's remainder (35), ray direction (36-38), barycentrics (39, 40), hit distance (41),
#: the emitter point's and the bounce's uniform numbers (42, 43, 44)
N_COLS = 45


@nb.njit(nogil=True)
def soa_gather(tri, fn, vn, emit_faces, emit_cdf, pmf, area, d, prim, u, v, tt, rnd, cols, lo):
    """Stage 1 (scalar: loads by index): the inputs of hits lo .. lo + B as the batch's columns
    ``cols`` (N_COLS, B), as a wavefront's queue would hold them."""
    n_e = len(emit_faces)
    for i in range(cols.shape[1]):
        j = lo + i
        pr = prim[j]
        for a in range(3):
            for b in range(3):
                cols[3 * a + b, i] = tri[pr, a, b]
                cols[9 + 3 * a + b, i] = vn[pr, a, b]
            cols[18 + a, i] = fn[pr, a]
            cols[36 + a, i] = d[j, a]
        if n_e > 0:
            k, r = K._cdf_pick(emit_cdf, 0, rnd[0, j])
            lf = emit_faces[k]
            for a in range(3):
                for b in range(3):
                    cols[21 + 3 * a + b, i] = tri[lf, a, b]
                cols[30 + a, i] = fn[lf, a]
            cols[33, i] = pmf[lf]
            cols[34, i] = area[lf]
            cols[35, i] = r
        cols[39, i] = u[j]
        cols[40, i] = v[j]
        cols[41, i] = tt[j]
        for a in range(3):
            cols[42 + a, i] = rnd[1 + a, j]


@nb.njit(nogil=True, error_model="numpy")
def soa_point(cols, diag, ob):
    """Stage 2a (vectorisable): the hit point (rows 0-2 of the batch's outputs ``ob``) and the
    vertex's ray offset (row 18). The frame takes three loops, not one: a loop over more arrays
    needs more run-time overlap checks than LLVM's vectoriser allows ("too many memory checks")."""
    t0, t1, t2, t3, t4, t5, t6, t7, t8 = (
        cols[0], cols[1], cols[2], cols[3], cols[4], cols[5], cols[6], cols[7], cols[8]
    )  # fmt: skip
    cu, cv, ct = cols[39], cols[40], cols[41]
    o0, o1, o2, oe = ob[0], ob[1], ob[2], ob[18]
    for i in range(len(cu)):
        b1 = cu[i]
        b2 = cv[i]
        w0 = 1.0 - b1 - b2
        x0 = w0 * t0[i] + b1 * t3[i] + b2 * t6[i]
        x1 = w0 * t1[i] + b1 * t4[i] + b2 * t7[i]
        x2 = w0 * t2[i] + b1 * t5[i] + b2 * t8[i]
        o0[i] = x0
        o1[i] = x1
        o2[i] = x2
        mag = max(abs(x0), max(abs(x1), abs(x2)))
        oe[i] = 3e-5 * (mag + abs(ct[i])) + 1e-6 * diag


@nb.njit(nogil=True, error_model="numpy")
def soa_face_normal(cols, ob):
    """Stage 2b (vectorisable): the geometric normal facing the ray (rows 3-5 of ``ob``)."""
    gg0, gg1, gg2, d0, d1, d2 = cols[18], cols[19], cols[20], cols[36], cols[37], cols[38]
    o3, o4, o5 = ob[3], ob[4], ob[5]
    for i in range(len(gg0)):
        g0 = gg0[i]
        g1 = gg1[i]
        g2 = gg2[i]
        dx = d0[i]
        dy = d1[i]
        dz = d2[i]
        degenerate = (g0 == 0) & (g1 == 0) & (g2 == 0)
        g0 = -dx if degenerate else g0
        g1 = -dy if degenerate else g1
        g2 = -dz if degenerate else g2
        cos_o = 1.0 if degenerate else -(g0 * dx + g1 * dy + g2 * dz)
        sg = 1.0 if cos_o > 0 else -1.0
        o3[i] = sg * g0
        o4[i] = sg * g1
        o5[i] = sg * g2


@nb.njit(nogil=True, error_model="numpy")
def soa_shading_normal(cols, ob):
    """Stage 2c (vectorisable): the interpolated shading normal on the geometric normal's side
    (rows 6-8 of ``ob``)."""
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = (
        cols[9], cols[10], cols[11], cols[12], cols[13], cols[14], cols[15], cols[16], cols[17]
    )  # fmt: skip
    cu, cv = cols[39], cols[40]
    o3, o4, o5, o6, o7, o8 = ob[3], ob[4], ob[5], ob[6], ob[7], ob[8]
    for i in range(len(cu)):
        b1 = cu[i]
        b2 = cv[i]
        w0 = 1.0 - b1 - b2
        nf0 = o3[i]
        nf1 = o4[i]
        nf2 = o5[i]
        a0 = w0 * m0[i] + b1 * m3[i] + b2 * m6[i]
        a1 = w0 * m1[i] + b1 * m4[i] + b2 * m7[i]
        a2 = w0 * m2[i] + b1 * m5[i] + b2 * m8[i]
        ln = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        okn = ln > 1e-20
        inv = 1.0 / (ln if okn else 1.0)
        ns0 = a0 * inv if okn else nf0
        ns1 = a1 * inv if okn else nf1
        ns2 = a2 * inv if okn else nf2
        flip = -1.0 if ns0 * nf0 + ns1 * nf1 + ns2 * nf2 < 0 else 1.0
        o6[i] = flip * ns0
        o7[i] = flip * ns1
        o8[i] = flip * ns2


@nb.njit(nogil=True, error_model="numpy")
def soa_suns(suns, ob):
    """Stage 3a (vectorisable): the directional lights' geometry terms (row 12 of ``ob``)."""
    o3, o4, o5, o6, o7, o8, o12 = ob[3], ob[4], ob[5], ob[6], ob[7], ob[8], ob[12]
    for i in range(len(o12)):
        o12[i] = 0.0
    for k in range(suns.shape[0]):
        s0 = -suns[k, 0]
        s1 = -suns[k, 1]
        s2 = -suns[k, 2]
        for i in range(len(o12)):
            c = min(o6[i] * s0 + o7[i] * s1 + o8[i] * s2, 1.0)
            ok = (c > 0) & (o3[i] * s0 + o4[i] * s1 + o5[i] * s2 > 0)
            o12[i] += c if ok else 0.0


@nb.njit(nogil=True, error_model="numpy")
def soa_emitter_point(cols, diag, ob):
    """Stage 3b (vectorisable): the point on the gathered emitter face (rows 21-23 of ``ob``),
    the direction to it (rows 9-11), its distance (row 19) and its ray offset (row 20)."""
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = (
        cols[21], cols[22], cols[23], cols[24], cols[25], cols[26], cols[27], cols[28], cols[29]
    )  # fmt: skip
    cr, crb = cols[35], cols[42]
    x0s, x1s, x2s = ob[0], ob[1], ob[2]
    o9, o10, o11, od, oel, oy0, oy1, oy2 = (
        ob[9], ob[10], ob[11], ob[19], ob[20], ob[21], ob[22], ob[23]
    )  # fmt: skip
    # two loops: in one, LLVM would need more run-time overlap checks between the 22 arrays
    # than it makes, and leaves the loop scalar
    for i in range(len(cr)):
        r1 = math.sqrt(cr[i])
        ca = r1 * (1 - crb[i])
        cb = r1 * crb[i]
        oy0[i] = e0[i] + ca * (e3[i] - e0[i]) + cb * (e6[i] - e0[i])
        oy1[i] = e1[i] + ca * (e4[i] - e1[i]) + cb * (e7[i] - e1[i])
        oy2[i] = e2[i] + ca * (e5[i] - e2[i]) + cb * (e8[i] - e2[i])
    for i in range(len(cr)):
        y0, y1, y2 = oy0[i], oy1[i], oy2[i]
        v0 = y0 - x0s[i]
        v1 = y1 - x1s[i]
        v2 = y2 - x2s[i]
        dist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        dd = max(dist, 1e-300)
        o9[i] = v0 / dd
        o10[i] = v1 / dd
        o11[i] = v2 / dd
        od[i] = dist
        mag = max(abs(y0), max(abs(y1), abs(y2)))
        oel[i] = 3e-5 * (mag + abs(dist)) + 1e-6 * diag


@nb.njit(nogil=True, error_model="numpy")
def soa_emitter_weight(cols, ob):
    """Stage 3c (vectorisable): the emitter sample's geometry times its MIS weight (added to
    row 12 of ``ob``), its shadow ray's direction from the offset origin (rows 9-11) and
    length (row 13)."""
    l0, l1, l2, cpmf, carea = cols[30], cols[31], cols[32], cols[33], cols[34]
    o3, o4, o5, o6, o7, o8 = ob[3], ob[4], ob[5], ob[6], ob[7], ob[8]
    o9, o10, o11, o12, o13, oe, od, oel = (
        ob[9], ob[10], ob[11], ob[12], ob[13], ob[18], ob[19], ob[20]
    )  # fmt: skip
    o0, o1, o2, oy0, oy1, oy2 = ob[0], ob[1], ob[2], ob[21], ob[22], ob[23]
    for i in range(len(l0)):
        wi0 = o9[i]
        wi1 = o10[i]
        wi2 = o11[i]
        dist = od[i]
        c = min(o6[i] * wi0 + o7[i] * wi1 + o8[i] * wi2, 1.0)
        cl = -(l0[i] * wi0 + l1[i] * wi1 + l2[i] * wi2)
        up = o3[i] * wi0 + o4[i] * wi1 + o5[i] * wi2
        ok = (c > 0) & (cl > 0) & (up > 0) & (dist > 0)
        pl = cpmf[i] / carea[i] * dist * dist / (cl if ok else 1.0)
        pb = c * K._INV_PI
        ge = c * pl / (pl * pl + pb * pb)
        v0 = oy0[i] - np.float64(np.float32(o0[i] + o3[i] * oe[i]))
        v1 = oy1[i] - np.float64(np.float32(o1[i] + o4[i] * oe[i]))
        v2 = oy2[i] - np.float64(np.float32(o2[i] + o5[i] * oe[i]))
        sdist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        sd = max(sdist, 1e-300)
        tf = np.float64(np.float32(max(sdist - oel[i], 0.0)))
        o9[i] = v0 / sd if ok else wi0
        o10[i] = v1 / sd if ok else wi1
        o11[i] = v2 / sd if ok else wi2
        o12[i] += ge if ok else 0.0
        o13[i] = tf if ok else 0.0


@nb.njit(nogil=True, error_model="numpy")
def soa_bounce(cols, ob):
    """Stage 3c (vectorisable): the cosine-weighted bounce (concentric map, quarter-angle
    polynomials) about the shading normal (rows 14-17 of ``ob``)."""
    q = 0.25 * math.pi
    cu1, cu2 = cols[43], cols[44]
    o3, o4, o5, o6, o7, o8 = ob[3], ob[4], ob[5], ob[6], ob[7], ob[8]
    o14, o15, o16, o17 = ob[14], ob[15], ob[16], ob[17]
    for i in range(len(cu1)):
        nf0 = o3[i]
        nf1 = o4[i]
        nf2 = o5[i]
        n0 = o6[i]
        n1 = o7[i]
        n2 = o8[i]
        a = 2.0 * cu1[i] - 1.0
        b = 2.0 * cu2[i] - 1.0
        big = abs(a) > abs(b)
        num = b if big else a
        den = a if big else b
        zero = (a == 0.0) & (b == 0.0)
        x = q * (num / (1.0 if zero else den))
        z = x * x
        s = K._S13 + z * (K._S15 + z * K._S17)
        s = K._S7 + z * (K._S9 + z * (K._S11 + z * s))
        s = x + x * z * (K._S3 + z * (K._S5 + z * s))
        cc = K._C12 + z * (K._C14 + z * K._C16)
        cc = K._C6 + z * (K._C8 + z * (K._C10 + z * cc))
        cc = 1.0 + z * (K._C2 + z * (K._C4 + z * cc))
        rc = a * cc if big else b * s
        rs = a * s if big else b * cc
        rc = 0.0 if zero else rc
        rs = 0.0 if zero else rs
        sign = 1.0 if n2 >= 0 else -1.0
        aa = -1.0 / (sign + n2)
        bb = n0 * n1 * aa
        zc = math.sqrt(max(0.0, 1 - (rc * rc + rs * rs)))
        w0 = rc * (1 + sign * n0 * n0 * aa) + rs * bb + zc * n0
        w1 = rc * (sign * bb) + rs * (sign + n1 * n1 * aa) + zc * n1
        w2 = rc * (-sign * n0) - rs * n1 + zc * n2
        below = min(w0 * nf0 + w1 * nf1 + w2 * nf2, 0.0)
        w0 -= 2 * below * nf0
        w1 -= 2 * below * nf1
        w2 -= 2 * below * nf2
        ln = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        okl = ln > 1e-20
        inv = 1.0 / (ln if okl else 1.0)
        w0 = w0 * inv if okl else nf0
        w1 = w1 * inv if okl else nf1
        w2 = w2 * inv if okl else nf2
        o14[i] = w0
        o15[i] = w1
        o16[i] = w2
        o17[i] = max(n0 * w0 + n1 * w1 + n2 * w2, 1e-12) * K._INV_PI


@nb.njit(nogil=True)
def soa_vertices(tri, fn, vn, suns, emit_faces, emit_cdf, pmf, area, diag, d, prim, u, v, tt, rnd,
                 out, cols, ob, level, store):  # fmt: skip
    """The SoA stages over the hits in batches of ``cols.shape[1]`` (a wavefront's queue: its
    scratch stays in cache), up to ``level`` (1 gather, 2 + frame, 3 + lights, 4 + bounce), each
    batch's results then copied to ``out`` (N_OUT, n) with ``store`` (for the check; a wavefront
    would hand them to its next stage instead)."""
    n = len(prim)
    B = cols.shape[1]
    has_e = len(emit_faces) > 0
    for lo in range(0, n - n % B, B):
        soa_gather(tri, fn, vn, emit_faces, emit_cdf, pmf, area, d, prim, u, v, tt, rnd, cols, lo)
        if level >= 2:
            soa_point(cols, diag, ob)
            soa_face_normal(cols, ob)
            soa_shading_normal(cols, ob)
        if level >= 3:
            soa_suns(suns, ob)
            if has_e:
                soa_emitter_point(cols, diag, ob)
                soa_emitter_weight(cols, ob)
        if level >= 4:
            soa_bounce(cols, ob)
        if store:
            out[:, lo : lo + B] = ob[:N_OUT]


STAGES = (soa_point, soa_face_normal, soa_shading_normal, soa_suns, soa_emitter_point,
          soa_emitter_weight, soa_bounce)  # fmt: skip


def packed_ymm(fn) -> int:
    """Packed AVX2 instructions (``ymm`` operands) in ``fn``'s compiled code: 0 = not vectorised."""
    return sum(asm.count("ymm") for asm in fn.inspect_asm().values())


def cpu_time(fn) -> float:
    """Process CPU seconds of one call of ``fn`` (single-threaded work)."""
    c0 = time.process_time()
    fn()
    return time.process_time() - c0


def hits_of(scene, cam, cfg) -> dict:
    """The render's camera and bounce rays (its ray log) and their Embree hits (misses dropped).
    Its first render also warms the kernels' cache and the scene data."""
    st = icb.trace.render(scene, cam, cfg).stats
    log, n = ray_log(scene, cam, cfg, capacity=int(st.total_rays * 1.05) + 1024)
    keep = log["kind"][:n] != 1  # camera (0) and bounce (2) rays
    o = np.ascontiguousarray(log["o"][:n][keep])
    d = np.ascontiguousarray(log["d"][:n][keep])
    m = len(d)
    rs = RtcScene.of(scene, robust=cfg.robust)
    t, prim = np.empty(m, np.float32), np.empty(m, np.int32)
    u, v = np.empty(m, np.float32), np.empty(m, np.float32)
    K.rtc_intersect_batch(rs.ptr, rs.fn_intersect, o, d, t, prim, u, v, 0, m)
    hit = prim >= 0
    return {"d": d[hit], "prim": prim[hit], "u": u[hit], "v": v[hit], "t": t[hit]}


def bound(
    scene,
    cam,
    cfg: TraceConfig,
    repeats: int,
    shading_share: float | None,
    batches=(32, 64, 128, 256),
) -> dict:
    """The scalar helpers against the SoA stages on one render's hits, for each batch size
    (interleaved rounds, the fastest of each); the bound takes the most favourable batch."""
    tr = Tracer(scene, cam, TraceConfig(**{**cfg.__dict__, "threads": 1}), TraceStats())
    p = tr._params
    sf = p.surf
    suns, _, pmf, area, _, emit_faces, emit_cdf = p.lights
    h = hits_of(scene, cam, cfg)
    step = int(np.lcm.reduce(batches))
    n = len(h["prim"]) - len(h["prim"]) % step  # whole batches of every size
    h = {k: np.ascontiguousarray(a[:n]) for k, a in h.items()}
    rnd = np.random.default_rng(0).random((4, n))
    tri, fn, vn, diag = sf.tri, sf.face_n, sf.vn, sf.diag
    a_out = np.zeros((N_OUT, n))
    args_a = (tri, fn, vn, suns, emit_faces, emit_cdf, pmf, area, diag, h["d"], h["prim"],
              h["u"], h["v"], h["t"], rnd, a_out)  # fmt: skip
    scalar_vertices(*args_a, True)
    args_b = {}
    diff = 0.0
    for batch in batches:
        b_out = np.zeros((N_OUT, n))
        args_b[batch] = (tri, fn, vn, suns, emit_faces, emit_cdf, pmf, area, diag, h["d"],
                         h["prim"], h["u"], h["v"], h["t"], rnd, b_out,
                         np.zeros((N_COLS, batch)), np.zeros((N_OUT + 6, batch)))  # fmt: skip
        soa_vertices(*args_b[batch], 4, True)
        if len(emit_faces) == 0:  # no emitter sample: the scalar loop leaves those at zero
            b_out[9:12] = 0.0
            b_out[13] = 0.0
        diff = max(diff, float(np.max(np.abs(a_out - b_out))))
    if not diff < 1e-9:
        raise RuntimeError(f"the SoA loops disagree with the kernel's helpers by {diff:g}")
    # interleaved rounds (the VM's speed drifts over minutes), the fastest of each
    t_scalar = np.inf
    levels = {b: [np.inf] * 4 for b in batches}
    for _ in range(repeats):
        t_scalar = min(t_scalar, cpu_time(lambda: scalar_vertices(*args_a, False)))
        for b in batches:
            for k in range(4):
                t = cpu_time(lambda b=b, k=k: soa_vertices(*args_b[b], k + 1, False))
                levels[b][k] = min(levels[b][k], t)
    by_batch = {}
    for b in batches:
        lv = levels[b]
        stages = dict(zip(("gather", "frame", "lights", "bounce"), np.diff([0.0, *lv])))
        by_batch[str(b)] = {
            "ns_per_vertex": {
                **{k: 1e9 * max(float(v), 0.0) / n for k, v in stages.items()},
                "total": 1e9 * lv[-1] / n,
            },
            "speedup": t_scalar / lv[-1],
            "speedup_without_gather": t_scalar / max(lv[-1] - lv[0], 1e-12),
        }
    packed = {f.__name__: packed_ymm(f) for f in STAGES}
    if not all(packed.values()):  # e.g. a numba or LLVM whose vectoriser gives up on a loop
        raise RuntimeError(f"a SoA stage compiled to scalar code (packed ymm counts {packed})")
    best = max(by_batch, key=lambda b: by_batch[b]["speedup"])
    row = {
        "vertices": n,
        "emitter_faces": int(len(emit_faces)),
        "suns": int(suns.shape[0]),
        "max_abs_difference": diff,
        "scalar_ns_per_vertex": 1e9 * t_scalar / n,
        "soa_by_batch": by_batch,
        "best_batch": int(best),
        "speedup_soa": by_batch[best]["speedup"],
        "speedup_soa_without_gather": by_batch[best]["speedup_without_gather"],
        "packed_ymm_instructions": packed,
    }
    if shading_share is not None:
        row["shading_share_of_render"] = shading_share
        row["render_saving_bound"] = shading_share * (1 - 1 / row["speedup_soa"])
    return row


def profile_shares() -> dict[str, float]:
    """Per scene, the share of the render in the stages this script vectorises (hit frame,
    light and BSDF sampling) from the last trace_profile.py run; {} without one."""
    path = OUT / "profile.json"
    if not path.is_file():
        return {}
    rows = json.loads(path.read_text())["results"]
    stages = ("hit_frame", "light_sampling", "bsdf_sampling")
    return {r["scene"]: sum(r["stage_shares_of_render"][s] for s in stages) for r in rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--scenes", default="cornell_box,sponza")
    ap.add_argument("--batches", default="32,64,128,256", help="paths per wavefront batch")
    ap.add_argument("--out-name", default="simd_bound")
    add_out_argument(ap, "trace")
    args = ap.parse_args()
    global OUT
    OUT = args.out
    load_start = os.getloadavg()
    cfg = TraceConfig(spp=args.spp, spp_per_pass=4, max_depth=8, seed=0)
    shares = profile_shares()
    batches = tuple(int(b) for b in args.batches.split(","))
    rows = []
    for name in args.scenes.split(","):
        scene = sponza() if name == "sponza" else getattr(icb.scene, name)()
        cam = scene.default_camera.resized(args.size, args.size)
        row = {
            "scene": name,
            **bound(scene, cam, cfg, args.repeats, shares.get(name), batches=batches),
        }
        print(
            f"{name}: {row['vertices']} vertices; kernel helpers "
            f"{row['scalar_ns_per_vertex']:.1f} ns per vertex; SoA by batch:"
        )
        for b, r in row["soa_by_batch"].items():
            ns = r["ns_per_vertex"]
            print(
                f"  {b:>4} paths: {ns['total']:.1f} ns (gather {ns['gather']:.1f}, frame "
                f"{ns['frame']:.1f}, lights {ns['lights']:.1f}, bounce {ns['bounce']:.1f}): "
                f"{r['speedup']:.2f}x ({r['speedup_without_gather']:.2f}x without the gather)"
            )
        print(f"  packed ymm instructions: {row['packed_ymm_instructions']}")
        if "render_saving_bound" in row:
            print(
                f"  shading share of the render {row['shading_share_of_render']:.2f}: "
                f"at most {100 * row['render_saving_bound']:.0f} % of the render"
            )
        rows.append(row)
    out, load_end = write_profile_results(args.out_name, cfg, args, load_start, rows, __doc__)
    print(f"wrote {out} (load {load_start[0]:.1f} -> {load_end[0]:.1f})")


if __name__ == "__main__":
    main()
