// Cameras (docs/protocol.md section 5): OpenCV axes, row-major world_from_cam, pixel centres at
// +0.5; their WebGL matrices; camera paths interpolated as icbtool.camera.CameraPath does
// (natural cubic spline of positions, slerp of rotations) with its velocities.

/** Column-major Float32Array(16) of a row-major 4x4 (array of rows). */
export function colMajor(m) {
  const out = new Float32Array(16);
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) out[c * 4 + r] = m[r][c];
  return out;
}

export function matmul(a, b) {
  const out = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]];
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[r][k] * b[k][c];
    out[r][c] = s;
  }
  return out;
}

/** Inverse of a rigid 4x4 (rotation + translation). */
export function rigidInverse(m) {
  const out = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]];
  for (let r = 0; r < 3; r++) {
    for (let c = 0; c < 3; c++) out[r][c] = m[c][r];
    out[r][3] = -(m[0][r] * m[0][3] + m[1][r] * m[1][3] + m[2][r] * m[2][3]);
  }
  return out;
}

export const position = (cam) => [0, 1, 2].map((r) => cam.world_from_cam[r][3]);
export const forward = (cam) => [0, 1, 2].map((r) => cam.world_from_cam[r][2]);

/** GL view matrix (row-major): inverse of world_from_cam * diag(1, -1, -1, 1). */
export function glView(cam) {
  const w = cam.world_from_cam.map((row) => [row[0], -row[1], -row[2], row[3]]);
  return rigidInverse(w);
}

/** GL projection (row-major) from the intrinsics, section 5. */
export function glProjection(cam, near, far) {
  const {fx, fy, cx, cy, width, height} = cam;
  return [
    [2 * fx / width, 0, 1 - 2 * cx / width, 0],
    [0, 2 * fy / height, 2 * cy / height - 1, 0],
    [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
    [0, 0, -1, 0],
  ];
}

/** Near/far planes enclosing the scene bounds (icbtool.raster.renderer.camera_near_far). */
export function nearFar(cam, bounds) {
  const lo = bounds[0], hi = bounds[1];
  const d = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  const pad = Math.max(1e-3 * d, 1e-6);
  const b0 = lo.map((x) => x - pad), b1 = hi.map((x) => x + pad);
  const p = position(cam), f = forward(cam);
  let zmax = -Infinity;
  for (const x of [b0[0], b1[0]]) for (const y of [b0[1], b1[1]]) for (const z of [b0[2], b1[2]]) {
    zmax = Math.max(zmax, (x - p[0]) * f[0] + (y - p[1]) * f[1] + (z - p[2]) * f[2]);
  }
  const closest = p.map((v, i) => Math.min(Math.max(v, b0[i]), b1[i]));
  const dist = Math.hypot(...closest.map((v, i) => v - p[i]));
  let far = zmax * 1.01;
  if (far <= 0) far = 2 * dist + 1;
  return [Math.max(far * 1e-3, 0.5 * dist), far];
}

/** The same pose through intrinsics scaled to height x width (Camera.resized). */
export function resized(cam, height, width) {
  const sx = width / cam.width, sy = height / cam.height;
  return {height, width, fx: cam.fx * sx, fy: cam.fy * sy, cx: cam.cx * sx, cy: cam.cy * sy,
          world_from_cam: cam.world_from_cam.map((r) => r.slice())};
}

// ---------------------------------------------------------------- rotations as quaternions
function matToQuat(m) {  // [x, y, z, w]
  const t = m[0][0] + m[1][1] + m[2][2];
  let q;
  if (t > 0) {
    const s = Math.sqrt(t + 1) * 2;
    q = [(m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s, s / 4];
  } else if (m[0][0] > m[1][1] && m[0][0] > m[2][2]) {
    const s = Math.sqrt(1 + m[0][0] - m[1][1] - m[2][2]) * 2;
    q = [s / 4, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s, (m[2][1] - m[1][2]) / s];
  } else if (m[1][1] > m[2][2]) {
    const s = Math.sqrt(1 + m[1][1] - m[0][0] - m[2][2]) * 2;
    q = [(m[0][1] + m[1][0]) / s, s / 4, (m[1][2] + m[2][1]) / s, (m[0][2] - m[2][0]) / s];
  } else {
    const s = Math.sqrt(1 + m[2][2] - m[0][0] - m[1][1]) * 2;
    q = [(m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4, (m[1][0] - m[0][1]) / s];
  }
  const n = Math.hypot(...q);
  return q.map((x) => x / n);
}

function quatToMat([x, y, z, w]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
}

function slerp(a, b, t) {  // scipy's Slerp: the shortest arc
  let d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
  if (d < 0) { b = b.map((x) => -x); d = -d; }
  if (d > 0.9999999) return a.map((x, i) => x + t * (b[i] - x));
  const th = Math.acos(Math.min(d, 1));
  const s = Math.sin(th);
  const wa = Math.sin((1 - t) * th) / s, wb = Math.sin(t * th) / s;
  return a.map((x, i) => wa * x + wb * b[i]);
}

function rotvec(m) {  // axis * angle of a 3x3 rotation
  const q = matToQuat(m);
  const s = Math.hypot(q[0], q[1], q[2]);
  if (s < 1e-12) return [2 * q[0], 2 * q[1], 2 * q[2]];
  const ang = 2 * Math.atan2(s, q[3]);
  const a = ang > Math.PI ? ang - 2 * Math.PI : ang;
  return [q[0] / s * a, q[1] / s * a, q[2] / s * a];
}

/** Natural cubic spline through (t_i, y_i), second derivatives at the knots. */
function naturalSpline(t, y) {
  const n = t.length;
  const m = new Float64Array(n);
  if (n < 3) return m;
  const a = new Float64Array(n), b = new Float64Array(n), c = new Float64Array(n),
        d = new Float64Array(n);
  b[0] = 1; b[n - 1] = 1;
  for (let i = 1; i < n - 1; i++) {
    const h0 = t[i] - t[i - 1], h1 = t[i + 1] - t[i];
    a[i] = h0; b[i] = 2 * (h0 + h1); c[i] = h1;
    d[i] = 6 * ((y[i + 1] - y[i]) / h1 - (y[i] - y[i - 1]) / h0);
  }
  for (let i = 1; i < n; i++) {  // Thomas algorithm
    const w = a[i] / b[i - 1];
    b[i] -= w * c[i - 1];
    d[i] -= w * d[i - 1];
  }
  m[n - 1] = d[n - 1] / b[n - 1];
  for (let i = n - 2; i >= 0; i--) m[i] = (d[i] - c[i] * m[i + 1]) / b[i];
  return m;
}

/** A camera path from scene_info's payload ({name, times, world_from_cam, intrinsics}). */
export class CameraPath {
  constructor(p) {
    this.name = p.name;
    this.times = p.times;
    this.poses = p.world_from_cam;
    this.intrinsics = p.intrinsics;
    this.quats = this.poses.map((m) => matToQuat(m));
    for (let i = 1; i < this.quats.length; i++) {  // keep neighbours on one hemisphere
      const a = this.quats[i - 1], b = this.quats[i];
      if (a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0) this.quats[i] = b.map((x) => -x);
    }
    this.m2 = [0, 1, 2].map((k) => naturalSpline(this.times, this.poses.map((m) => m[k][3])));
  }

  get duration() { return this.times[this.times.length - 1] - this.times[0]; }

  _seg(t) {
    const ts = this.times;
    t = Math.min(Math.max(t, ts[0]), ts[ts.length - 1]);
    let i = 0;
    while (i < ts.length - 2 && t > ts[i + 1]) i++;
    return [i, t];
  }

  _pos(t, deriv = 0) {
    const [i, tt] = this._seg(t);
    const ts = this.times, h = ts[i + 1] - ts[i];
    const A = (ts[i + 1] - tt) / h, B = (tt - ts[i]) / h;
    return [0, 1, 2].map((k) => {
      const y0 = this.poses[i][k][3], y1 = this.poses[i + 1][k][3];
      const m0 = this.m2[k][i], m1 = this.m2[k][i + 1];
      if (deriv) return (y1 - y0) / h - (3 * A * A - 1) / 6 * h * m0 + (3 * B * B - 1) / 6 * h * m1;
      return A * y0 + B * y1 + ((A ** 3 - A) * m0 + (B ** 3 - B) * m1) * h * h / 6;
    });
  }

  _rot(t) {
    const [i, tt] = this._seg(t);
    const ts = this.times;
    return quatToMat(slerp(this.quats[i], this.quats[i + 1], (tt - ts[i]) / (ts[i + 1] - ts[i])));
  }

  poseAt(t) {
    if (this.times.length === 1) return this.poses[0].map((r) => r.slice());
    const r = this._rot(t), p = this._pos(t);
    return [[...r[0], p[0]], [...r[1], p[1]], [...r[2], p[2]], [0, 0, 0, 1]];
  }

  /** The camera at time t with intrinsics `intr` (default: the path's). */
  cameraAt(t, intr = this.intrinsics) {
    const {height, width, fx, fy, cx, cy} = intr;
    return {height, width, fx, fy, cx, cy, world_from_cam: this.poseAt(t)};
  }

  /** [velocity_t in the camera frame, velocity_r (pitch, yaw, roll rates)] at t. */
  velocityCam(t) {
    if (this.times.length === 1) return [[0, 0, 0], [0, 0, 0]];
    const ts = this.times;
    t = Math.min(Math.max(t, ts[0]), ts[ts.length - 1]);
    const v = this._pos(t, 1);
    const h = 1e-3 * Math.max(this.duration / Math.max(ts.length - 1, 1), 1e-6);
    const t0 = Math.max(t - h, ts[0]), t1 = Math.min(t + h, ts[ts.length - 1]);
    const r0 = this._rot(t0), r1 = this._rot(t1);
    const rel = [0, 1, 2].map((i) => [0, 1, 2].map((j) => (
      r0[0][i] * r1[0][j] + r0[1][i] * r1[1][j] + r0[2][i] * r1[2][j])));  // r0^T r1
    const w = rotvec(rel).map((x) => x / (t1 - t0));
    const r = this._rot(t);
    const vc = [0, 1, 2].map((i) => r[0][i] * v[0] + r[1][i] * v[1] + r[2][i] * v[2]);
    return [vc, w];
  }
}
