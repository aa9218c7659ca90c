"""Analytic shapes in the path tracer: exact spheres, disks and cylinders (hooks for the kernels).

A scene's :class:`~icbtool.scene.types.AnalyticShape` s reach the kernels as one float64 table
(:func:`pack_shapes`, (S, :data:`SHAPE_COLS`)); Embree holds only the triangles (the shapes'
tessellations are left out of its scene). These small inlined helpers are all a kernel needs:

* :func:`shapes_intersect` and :func:`shapes_occluded`: the nearest shape hit of a ray before
  ``tmax``, or whether any lies on a segment; a kernel keeps the nearer of that and Embree's hit
  (a scene without shapes pays one comparison: S = 0 skips the loop);
* :func:`shape_frame`: the hit point, ``cos_o``, front/back and normals, as the triangle
  kernel's ``_hit_frame`` returns them (barycentrics (1, 0, 0): the materials are untextured);
* :func:`shape_sample` and :func:`shape_pdf`: an emitter sample and its solid-angle density as
  Mitsuba 3 draws them (a sphere: uniform in the cone of directions it subtends, from outside;
  uniform by area from inside; a disk (concentric map) and a cylinder: uniform by area), so that
  a kernel combines it with BSDF sampling by MIS with the density it really used.

The signatures of these five are stable: kernels other than ``trace_paths`` call them too.
Every ray quantity is float64; origins may be the kernels' float32 offset points. A hit needs
``t > 0``: kernels offset their origins off the surface (as for triangles), and the float64
solutions are far more precise than that offset.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba as nb
import numpy as np

_JIT = dict(cache=True, nogil=True, error_model="numpy", boundscheck=False)
_PI = math.pi

SHAPE_SPHERE = 1
SHAPE_DISK = 2
SHAPE_CYLINDER = 3
_KIND = {"sphere": SHAPE_SPHERE, "disk": SHAPE_DISK, "cylinder": SHAPE_CYLINDER}

#: Columns of the shape table: kind (0), side (+1, or -1 flipped: 1), material (2), centre or
#: p0 (3-5), unit axis: a disk's normal, a cylinder's axis (6-8), radius (9), cylinder length
#: (10), area (11), disk local axes ex, ey (12-17) and their dual rows ax, ay (18-23; local x =
#: (p - centre) . ax), a unit frame perpendicular to the axis e1, e2 (24-29).
SHAPE_COLS = 30


def pack_shapes(shapes: Sequence) -> np.ndarray:
    """The kernels' shape table (S, :data:`SHAPE_COLS`) float64 of AnalyticShape s (S may be 0)."""
    out = np.zeros((len(shapes), SHAPE_COLS), np.float64)
    for i, sh in enumerate(shapes):
        m = np.asarray(sh.world_from_local, np.float64)
        lin, c = m[:3, :3], m[:3, 3]
        ex, ey, ez = lin[:, 0], lin[:, 1], lin[:, 2]
        row = out[i]
        row[0] = _KIND[sh.kind]
        row[1] = -1.0 if sh.flip_normals else 1.0
        row[2] = sh.material
        row[3:6] = c
        row[11] = sh.area
        if sh.kind == "disk":
            n = np.linalg.inv(lin).T @ np.array([0.0, 0.0, 1.0])  # normals: inverse transpose
            n /= np.linalg.norm(n)
            row[6:9] = n
            row[9] = np.linalg.norm(ex)
            row[12:15], row[15:18] = ex, ey
            # dual basis in the plane: (p - c) = x ex + y ey  =>  x = (p - c) . ax
            inv = np.linalg.pinv(np.stack([ex, ey], 1))  # (2, 3)
            row[18:21], row[21:24] = inv[0], inv[1]
        elif sh.kind == "cylinder":
            length = float(np.linalg.norm(ez))
            row[6:9] = ez / length
            row[9] = np.linalg.norm(ex)
            row[10] = length
        else:
            row[9] = np.linalg.norm(ex)
        axis = row[6:9] if sh.kind != "sphere" else np.array([0.0, 0.0, 1.0])
        e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        row[24:27] = e1
        row[27:30] = np.cross(axis, e1)
    return np.ascontiguousarray(out)


# ------------------------------------------------------------------------------ intersection
@nb.njit(inline="always", **_JIT)
def _shape_hit(shp, k, ox, oy, oz, dx, dy, dz, tmax):
    """Distance along the unit ray to shape k's first surface point with 0 < t < tmax (inf:
    none). Spheres and cylinders are hit from either side."""
    kind = shp[k, 0]
    cx = ox - shp[k, 3]
    cy = oy - shp[k, 4]
    cz = oz - shp[k, 5]
    if kind == SHAPE_SPHERE:
        # Mitsuba's robust form: solve from the point of the ray nearest the centre
        r = shp[k, 9]
        tp = -(cx * dx + cy * dy + cz * dz)
        px = cx + tp * dx
        py = cy + tp * dy
        pz = cz + tp * dz
        h2 = r * r - (px * px + py * py + pz * pz)
        if h2 < 0:
            return np.inf
        h = math.sqrt(h2)
        t = tp - h
        if not t > 0:
            t = tp + h
        return t if (t > 0 and t < tmax) else np.inf
    if kind == SHAPE_DISK:
        nx = shp[k, 6]
        ny = shp[k, 7]
        nz = shp[k, 8]
        dn = dx * nx + dy * ny + dz * nz
        if dn == 0:
            return np.inf
        t = -(cx * nx + cy * ny + cz * nz) / dn
        if not (t > 0 and t < tmax):
            return np.inf
        qx = cx + t * dx
        qy = cy + t * dy
        qz = cz + t * dz
        lx = qx * shp[k, 18] + qy * shp[k, 19] + qz * shp[k, 20]
        ly = qx * shp[k, 21] + qy * shp[k, 22] + qz * shp[k, 23]
        return t if lx * lx + ly * ly <= 1.0 else np.inf
    # cylinder: |(o + t d - p0) - ((o + t d - p0) . a) a| = r, 0 <= (o + t d - p0) . a <= L
    ax = shp[k, 6]
    ay = shp[k, 7]
    az = shp[k, 8]
    r = shp[k, 9]
    length = shp[k, 10]
    oa = cx * ax + cy * ay + cz * az
    da = dx * ax + dy * ay + dz * az
    px = cx - oa * ax
    py = cy - oa * ay
    pz = cz - oa * az
    qx = dx - da * ax
    qy = dy - da * ay
    qz = dz - da * az
    a = qx * qx + qy * qy + qz * qz
    if a <= 1e-300:
        return np.inf
    tp = -(px * qx + py * qy + pz * qz) / a  # the ray's point nearest the axis (as the sphere)
    sx = px + tp * qx
    sy = py + tp * qy
    sz = pz + tp * qz
    h2 = (r * r - (sx * sx + sy * sy + sz * sz)) / a
    if h2 < 0:
        return np.inf
    h = math.sqrt(h2)
    t = tp - h
    z = oa + t * da
    if not (t > 0 and t < tmax and z >= 0 and z <= length):
        t = tp + h
        z = oa + t * da
        if not (t > 0 and t < tmax and z >= 0 and z <= length):
            return np.inf
    return t


@nb.njit(inline="always", **_JIT)
def shapes_intersect(shp, ox, oy, oz, dx, dy, dz, tmax):
    """The nearest shape hit of the unit ray with 0 < t < tmax: (t, shape index), (tmax, -1)
    when none. A kernel passes Embree's hit distance (inf: a miss) as ``tmax`` and keeps the
    shape's hit when the index is >= 0."""
    best = tmax
    kb = -1
    for k in range(shp.shape[0]):
        t = _shape_hit(shp, k, ox, oy, oz, dx, dy, dz, best)
        if t < best:
            best = t
            kb = k
    return best, kb


@nb.njit(inline="always", **_JIT)
def shapes_occluded(shp, ox, oy, oz, dx, dy, dz, tmax):
    """Whether a shape lies on the unit ray's segment 0 < t < tmax."""
    for k in range(shp.shape[0]):
        if _shape_hit(shp, k, ox, oy, oz, dx, dy, dz, tmax) < tmax:
            return True
    return False


@nb.njit(inline="always", **_JIT)
def _shape_point_normal(shp, k, qx, qy, qz):
    """A point near shape k's surface projected onto it, and the outward (unflipped) unit
    normal there: ((x0, x1, x2), (n0, n1, n2))."""
    kind = shp[k, 0]
    cx = shp[k, 3]
    cy = shp[k, 4]
    cz = shp[k, 5]
    vx = qx - cx
    vy = qy - cy
    vz = qz - cz
    if kind == SHAPE_SPHERE:
        ln = math.sqrt(vx * vx + vy * vy + vz * vz)
        if ln > 0:
            n0, n1, n2 = vx / ln, vy / ln, vz / ln
        else:
            n0, n1, n2 = 0.0, 0.0, 1.0
        r = shp[k, 9]
        return (cx + r * n0, cy + r * n1, cz + r * n2), (n0, n1, n2)
    ax = shp[k, 6]
    ay = shp[k, 7]
    az = shp[k, 8]
    va = vx * ax + vy * ay + vz * az
    if kind == SHAPE_DISK:
        return (qx - va * ax, qy - va * ay, qz - va * az), (ax, ay, az)
    rx = vx - va * ax
    ry = vy - va * ay
    rz = vz - va * az
    ln = math.sqrt(rx * rx + ry * ry + rz * rz)
    if ln > 0:
        n0, n1, n2 = rx / ln, ry / ln, rz / ln
    else:
        n0, n1, n2 = shp[k, 24], shp[k, 25], shp[k, 26]
    r = shp[k, 9]
    return (
        (cx + va * ax + r * n0, cy + va * ay + r * n1, cz + va * az + r * n2),
        (n0, n1, n2),
    )


@nb.njit(inline="always", **_JIT)
def shape_frame(shp, k, ox, oy, oz, dx, dy, dz, t):
    """Where the unit ray hit shape k at distance t, as ``_hit_frame`` of the triangle kernel:
    (point, barycentrics (1, 0, 0), cos_o (normal . -ray; the normal flipped with
    ``flip_normals``), front, forward-facing normal nf, shading normal ns = nf)."""
    x, n = _shape_point_normal(shp, k, ox + t * dx, oy + t * dy, oz + t * dz)
    side = shp[k, 1]
    g0 = side * n[0]
    g1 = side * n[1]
    g2 = side * n[2]
    cos_o = -(g0 * dx + g1 * dy + g2 * dz)
    front = cos_o > 0
    if front:
        nf = (g0, g1, g2)
    else:
        nf = (-g0, -g1, -g2)
    return x, (1.0, 0.0, 0.0), cos_o, front, nf, nf


# ------------------------------------------------------------------------------ emitter sampling
@nb.njit(inline="always", **_JIT)
def _disk_point(u1, u2):
    """Shirley and Chiu's concentric map of [0, 1)^2 onto the unit disk (Mitsuba's disk)."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    if a == 0.0 and b == 0.0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        phi = (0.25 * _PI) * (b / a)
        return a * math.cos(phi), a * math.sin(phi)
    phi = 0.5 * _PI - (0.25 * _PI) * (a / b)
    return b * math.cos(phi), b * math.sin(phi)


@nb.njit(inline="always", **_JIT)
def _one_minus_cos_max(sin2):
    """1 - cos(theta_max) for sin^2(theta_max) = sin2, without cancellation."""
    return sin2 / (1.0 + math.sqrt(max(1.0 - sin2, 0.0)))


@nb.njit(inline="always", **_JIT)
def shape_sample(shp, k, px, py, pz, u1, u2):
    """A point on emitter shape k drawn for the reference point p (Mitsuba 3's
    ``sample_direction``): (usable, unit direction p -> y, distance, solid-angle density,
    the point y, cos at the emitter (its emitting normal . -direction)).

    A sphere seen from outside: uniform in the cone it subtends (every point drawn faces p);
    from inside, and disks and cylinders: uniform by area, density ``dist^2 / (area cl)``.
    Unusable (False): the point's emitting side faces away from p (a one-sided emitter seen
    from behind), or a zero distance."""
    kind = shp[k, 0]
    side = shp[k, 1]
    cx = shp[k, 3]
    cy = shp[k, 4]
    cz = shp[k, 5]
    r = shp[k, 9]
    cone = False
    pdf_cone = 0.0
    if kind == SHAPE_SPHERE:
        wx = cx - px
        wy = cy - py
        wz = cz - pz
        dc2 = wx * wx + wy * wy + wz * wz
        if dc2 > r * r * (1.0 + 1e-9):
            cone = True
            inv_dc = 1.0 / math.sqrt(dc2)
            sin2_max = r * r / dc2
            om = _one_minus_cos_max(sin2_max)
            pdf_cone = 1.0 / (2.0 * _PI * om)
            # cos(theta) = 1 - u1 (1 - cos_max): sin^2 = u1 om (2 - u1 om), no cancellation
            s = u1 * om
            sin2 = s * (2.0 - s)
            cos_t = 1.0 - s
            inv_sin_max = 1.0 / math.sqrt(sin2_max)
            # the angle alpha at the centre between -w and the point (Mitsuba; akalin.com)
            cos_a = sin2 * inv_sin_max + cos_t * math.sqrt(max(1.0 - sin2 * inv_sin_max**2, 0.0))
            sin_a = math.sqrt(max(1.0 - cos_a * cos_a, 0.0))
            phi = 2.0 * _PI * u2
            lx = math.cos(phi) * sin_a
            ly = math.sin(phi) * sin_a
            # frame about z = -w / |w| (Duff et al.)
            z0 = -wx * inv_dc
            z1 = -wy * inv_dc
            z2 = -wz * inv_dc
            sg = 1.0 if z2 >= 0 else -1.0
            a = -1.0 / (sg + z2)
            b = z0 * z1 * a
            n0 = lx * (1 + sg * z0 * z0 * a) + ly * b + cos_a * z0
            n1 = lx * (sg * b) + ly * (sg + z1 * z1 * a) + cos_a * z1
            n2 = lx * (-sg * z0) + ly * (-z1) + cos_a * z2
        else:  # inside: uniform on the sphere
            zz = 1.0 - 2.0 * u1
            rr = math.sqrt(max(1.0 - zz * zz, 0.0))
            phi = 2.0 * _PI * u2
            n0 = rr * math.cos(phi)
            n1 = rr * math.sin(phi)
            n2 = zz
        y0 = cx + r * n0
        y1 = cy + r * n1
        y2 = cz + r * n2
    elif kind == SHAPE_DISK:
        lx, ly = _disk_point(u1, u2)
        y0 = cx + lx * shp[k, 12] + ly * shp[k, 15]
        y1 = cy + lx * shp[k, 13] + ly * shp[k, 16]
        y2 = cz + lx * shp[k, 14] + ly * shp[k, 17]
        n0 = shp[k, 6]
        n1 = shp[k, 7]
        n2 = shp[k, 8]
    else:
        phi = 2.0 * _PI * u2
        cp = math.cos(phi)
        sp = math.sin(phi)
        n0 = cp * shp[k, 24] + sp * shp[k, 27]
        n1 = cp * shp[k, 25] + sp * shp[k, 28]
        n2 = cp * shp[k, 26] + sp * shp[k, 29]
        z = u1 * shp[k, 10]
        y0 = cx + z * shp[k, 6] + r * n0
        y1 = cy + z * shp[k, 7] + r * n1
        y2 = cz + z * shp[k, 8] + r * n2
    vx = y0 - px
    vy = y1 - py
    vz = y2 - pz
    dist = math.sqrt(vx * vx + vy * vy + vz * vz)
    if not dist > 0:
        return False, 0.0, 0.0, 1.0, 0.0, 0.0, (y0, y1, y2), 0.0
    wi0 = vx / dist
    wi1 = vy / dist
    wi2 = vz / dist
    cl = -side * (n0 * wi0 + n1 * wi1 + n2 * wi2)
    if cone:
        pdf = pdf_cone
    else:
        pdf = dist * dist / (shp[k, 11] * max(abs(cl), 1e-300))
    return cl > 0, wi0, wi1, wi2, dist, pdf, (y0, y1, y2), cl


@nb.njit(inline="always", **_JIT)
def shape_pdf(shp, k, px, py, pz, dx, dy, dz, dist, cos_o):
    """Solid-angle density with which :func:`shape_sample` draws the direction (dx, dy, dz)
    from p, given that it reaches shape k at distance ``dist`` with ``|cos_o|`` at the shape
    (Mitsuba 3's ``pdf_direction``)."""
    if shp[k, 0] == SHAPE_SPHERE:
        wx = shp[k, 3] - px
        wy = shp[k, 4] - py
        wz = shp[k, 5] - pz
        dc2 = wx * wx + wy * wy + wz * wz
        r = shp[k, 9]
        if dc2 > r * r * (1.0 + 1e-9):
            return 1.0 / (2.0 * _PI * _one_minus_cos_max(r * r / dc2))
    return dist * dist / (shp[k, 11] * max(abs(cos_o), 1e-300))


# ------------------------------------------------------------------------------ batch wrappers
@nb.njit(**_JIT)
def intersect_batch(shp, o, d, tmax, t_out, k_out):
    """:func:`shapes_intersect` of rays o, d (N, 3) float64 (d unit) into t_out, k_out (tests)."""
    for i in range(len(o)):
        t, k = shapes_intersect(shp, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tmax[i])
        t_out[i] = t
        k_out[i] = k


@nb.njit(**_JIT)
def sample_batch(shp, k, p, u, d_out, dist_out, pdf_out, ok_out, y_out):
    """:func:`shape_sample` of shape k for points p (N, 3) and uniforms u (N, 2) (tests)."""
    for i in range(len(p)):
        ok, w0, w1, w2, dist, pdf, y, _ = shape_sample(
            shp, k, p[i, 0], p[i, 1], p[i, 2], u[i, 0], u[i, 1]
        )
        d_out[i, 0] = w0
        d_out[i, 1] = w1
        d_out[i, 2] = w2
        dist_out[i] = dist
        pdf_out[i] = pdf
        ok_out[i] = ok
        y_out[i, 0] = y[0]
        y_out[i, 1] = y[1]
        y_out[i, 2] = y[2]


@nb.njit(**_JIT)
def pdf_batch(shp, k, p, d, dist, cos_o, out):
    """:func:`shape_pdf` of shape k for points p, directions d (N, 3), distances and cosines."""
    for i in range(len(p)):
        out[i] = shape_pdf(
            shp, k, p[i, 0], p[i, 1], p[i, 2], d[i, 0], d[i, 1], d[i, 2], dist[i], cos_o[i]
        )


__all__ = [
    "SHAPE_COLS",
    "SHAPE_CYLINDER",
    "SHAPE_DISK",
    "SHAPE_SPHERE",
    "pack_shapes",
    "shape_frame",
    "shape_pdf",
    "shape_sample",
    "shapes_intersect",
    "shapes_occluded",
]
