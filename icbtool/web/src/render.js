// The client's GPU work in three.js / WebGL2: LPM levels as three.js geometry, the WRT-buffer
// (albedo, normal, position + depth, DL) in one multiple-render-target pass with shadow maps,
// the 3D warp of reference GI maps, combine, hole filling, blend and display (shaders/*.glsl).
import * as THREE from "three";
import backgroundFrag from "../shaders/background.frag";
import blendFrag from "../shaders/blend.frag";
import combineFrag from "../shaders/combine.frag";
import depthFrag from "../shaders/depth.frag";
import depthVert from "../shaders/depth.vert";
import displayFrag from "../shaders/display.frag";
import fillFrag from "../shaders/fill.frag";
import gbufferFrag from "../shaders/gbuffer.frag";
import gbufferVert from "../shaders/gbuffer.vert";
import screenVert from "../shaders/screen.vert";
import warpFrag from "../shaders/warp.frag";
import {colMajor, glProjection, glView, matmul, nearFar, rigidInverse} from "./camera.js";

/** icbtool.raster.RasterConfig defaults the browser follows. */
export const RASTER = {
  shadowMapSize: 2048, areaShadowMapSize: 512, areaSamples: 4, depthBiasSlope: 1.5,
  depthBiasUnits: 2.0, normalOffset: 1.5, areaOffset: 2.0, penumbraSamples: 2,
  maxFrustumHalfAngleDeg: 60.0, textureSize: 512,
};
/** icbtool.warp.WarpConfig / inpaint defaults. */
export const WARP = {relDepthTol: 0.02, minWeight: 1e-3, relDepthGap: 0.05};

export class UnsupportedBrowser extends Error {}

// ---------------------------------------------------------------- shadow views (raster/renderer.py)
const sub = (a, b) => a.map((x, i) => x - b[i]);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => { const n = norm(a); return a.map((x) => x / n); };

function boundsPad(bounds) {
  const pad = Math.max(1e-3 * norm(sub(bounds[1], bounds[0])), 1e-6);
  return [bounds[0].map((x) => x - pad), bounds[1].map((x) => x + pad)];
}

function corners([lo, hi]) {
  const out = [];
  for (const x of [lo[0], hi[0]]) for (const y of [lo[1], hi[1]]) for (const z of [lo[2], hi[2]]) out.push([x, y, z]);
  return out;
}

function glLook(eye, fwd, up) {
  const z = unit(fwd).map((v) => -v);
  let x = cross(up, z);
  if (norm(x) < 1e-6) x = cross(Math.abs(z[0]) < 0.9 ? [1, 0, 0] : [0, 0, 1], z);
  x = unit(x);
  const y = cross(z, x);
  const m = [[...x, 0], [...y, 0], [...z, 0], [0, 0, 0, 1]];
  for (let r = 0; r < 3; r++) m[r][3] = -dot(m[r].slice(0, 3), eye);
  return m;
}

function perspective(halfDeg, near, far) {
  const f = 1 / Math.tan(halfDeg * Math.PI / 180);
  return [[f, 0, 0, 0], [0, f, 0, 0],
          [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)], [0, 0, -1, 0]];
}

function ortho(lo, hi) {
  const p = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
  p[0][0] = 2 / (hi[0] - lo[0]); p[1][1] = 2 / (hi[1] - lo[1]); p[2][2] = -2 / (hi[2] - lo[2]);
  p[0][3] = -(hi[0] + lo[0]) / (hi[0] - lo[0]);
  p[1][3] = -(hi[1] + lo[1]) / (hi[1] - lo[1]);
  p[2][3] = -(hi[2] + lo[2]) / (hi[2] - lo[2]);
  return p;
}

const apply = (m, p) => [0, 1, 2].map((r) => m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);

export function directionalView(direction, bounds, res) {
  const b = boundsPad(bounds);
  const centre = b[0].map((x, i) => 0.5 * (x + b[1][i]));
  const view = glLook(centre, direction, [0, 1, 0]);
  const c = corners(b).map((p) => apply(view, p));
  const lo = [Math.min(...c.map((p) => p[0])), Math.min(...c.map((p) => p[1])), Math.min(...c.map((p) => -p[2]))];
  const hi = [Math.max(...c.map((p) => p[0])), Math.max(...c.map((p) => p[1])), Math.max(...c.map((p) => -p[2]))];
  return [matmul(ortho(lo, hi), view), Math.max(hi[0] - lo[0], hi[1] - lo[1]) / res];
}

export function perspectiveView(eye, fwd, halfDeg, bounds, res, up = [0, 1, 0]) {
  const b = boundsPad(bounds);
  const far = Math.max(...corners(b).map((p) => norm(sub(p, eye)))) * 1.01 + 1e-6;
  let near = Math.max(1e-3 * norm(sub(b[1], b[0])), far * 1e-5);
  near = Math.min(near, 0.5 * far);
  return [matmul(perspective(halfDeg, near, far), glLook(eye, fwd, up)),
          2 * Math.tan(halfDeg * Math.PI / 180) / res];
}

const CUBE = [[[1, 0, 0], [0, 1, 0]], [[-1, 0, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 1]],
              [[0, -1, 0], [0, 0, 1]], [[0, 0, 1], [0, 1, 0]], [[0, 0, -1], [0, 1, 0]]];

export function areaVertices(l) {
  const c = l.corner, u = l.edge_u, v = l.edge_v;
  const add = (...xs) => [0, 1, 2].map((i) => xs.reduce((s, x) => s + x[i], 0));
  return l.shape === "triangle" ? [c, add(c, u), add(c, v)] : [c, add(c, u), add(c, u, v), add(c, v)];
}

export function areaSamplePoints(l, k) {
  const st = [];
  if (l.shape === "parallelogram") {
    for (let j = 0; j < k; j++) for (let i = 0; i < k; i++) st.push([(i + 0.5) / k, (j + 0.5) / k]);
  } else {
    for (let j = 0; j < k; j++) {
      for (let i = 0; i < k - j; i++) st.push([(i + 1 / 3) / k, (j + 1 / 3) / k]);
      for (let i = 0; i < k - j - 1; i++) st.push([(i + 2 / 3) / k, (j + 2 / 3) / k]);
    }
  }
  return st.map(([a, b]) => [0, 1, 2].map((i) => l.corner[i] + a * l.edge_u[i] + b * l.edge_v[i]));
}

/** Shadow views of the lights: {sharp: [[m, texel]], area: [[m, texel, samplePos]]}. */
export function shadowViews(lights, bounds, cfg = RASTER) {
  const of = (k) => lights.filter((l) => l.kind === k);
  const sharp = [];
  for (const l of of("directional")) sharp.push(directionalView(l.direction, bounds, cfg.shadowMapSize));
  for (const l of of("point")) {
    for (const [f, up] of CUBE) sharp.push(perspectiveView(l.position, f, 45, bounds, cfg.shadowMapSize, up));
  }
  for (const l of of("spot")) {
    sharp.push(perspectiveView(l.position, l.direction, Math.min(l.outer_deg + 1, 89), bounds, cfg.shadowMapSize));
  }
  const area = [];
  const cs = corners(boundsPad(bounds));
  for (const l of of("area")) {
    const n = unit(cross(l.edge_u, l.edge_v));
    for (const s of areaSamplePoints(l, cfg.areaSamples)) {
      const mind = Math.min(...cs.map((p) => dot(unit(sub(p, s)), n)));
      const ang = Math.acos(Math.min(Math.max(mind, -1), 1)) * 180 / Math.PI;
      const [m, texel] = perspectiveView(s, n, Math.min(ang + 1, cfg.maxFrustumHalfAngleDeg), bounds,
                                         cfg.areaShadowMapSize);
      area.push([m, texel, s]);
    }
  }
  return {sharp, area};
}

// ---------------------------------------------------------------- materials and geometry
async function decodeTexture(t, size) {
  const blob = new Blob([t.bytes], {type: t.format === "jpeg" ? "image/jpeg" : "image/png"});
  const bmp = await createImageBitmap(blob, {colorSpaceConversion: "none", premultiplyAlpha: "none",
                                             resizeWidth: size, resizeHeight: size,
                                             resizeQuality: "high"});
  const cv = new OffscreenCanvas(size, size);
  const ctx = cv.getContext("2d", {colorSpace: "srgb"});
  ctx.drawImage(bmp, 0, 0);
  return ctx.getImageData(0, 0, size, size).data;
}

/** three.js geometry of an assembled level (de-indexed: one vertex per face corner). */
export function levelGeometry(level) {
  const {vertices, normals, uvs, faces, face_material: fm} = level.arrays;
  const nf = faces.length / 3;
  const pos = new Float32Array(9 * nf), nrm = new Float32Array(9 * nf), ng = new Float32Array(9 * nf);
  const uv = new Float32Array(6 * nf), mat = new Float32Array(3 * nf);
  for (let f = 0; f < nf; f++) {
    const i = [faces[3 * f], faces[3 * f + 1], faces[3 * f + 2]];
    const p = i.map((k) => [vertices[3 * k], vertices[3 * k + 1], vertices[3 * k + 2]]);
    let g = cross(sub(p[1], p[0]), sub(p[2], p[0]));
    const l = norm(g);
    g = l > 0 ? g.map((x) => x / l) : [0, 0, 1];
    for (let c = 0; c < 3; c++) {
      const o = 9 * f + 3 * c;
      for (let a = 0; a < 3; a++) {
        pos[o + a] = p[c][a];
        nrm[o + a] = normals[3 * i[c] + a];
        ng[o + a] = g[a];
      }
      if (uvs) { uv[6 * f + 2 * c] = uvs[2 * i[c]]; uv[6 * f + 2 * c + 1] = uvs[2 * i[c] + 1]; }
      mat[3 * f + c] = fm[f];
    }
  }
  const geo = new THREE.BufferGeometry();
  geo.setAttribute("position", new THREE.BufferAttribute(pos, 3));
  geo.setAttribute("normal", new THREE.BufferAttribute(nrm, 3));
  geo.setAttribute("uv", new THREE.BufferAttribute(uv, 2));
  geo.setAttribute("face_normal", new THREE.BufferAttribute(ng, 3));
  geo.setAttribute("material", new THREE.BufferAttribute(mat, 1));
  return geo;
}

function floatTarget(w, h, count = 1, depth = false) {
  const rt = new THREE.WebGLRenderTarget(w, h, {
    count, type: THREE.FloatType, format: THREE.RGBAFormat, minFilter: THREE.NearestFilter,
    magFilter: THREE.NearestFilter, depthBuffer: depth, stencilBuffer: false,
    generateMipmaps: false,
  });
  return rt;
}

function raw(vertex, fragment, uniforms = {}, defines = {}) {
  return new THREE.RawShaderMaterial({vertexShader: vertex, fragmentShader: fragment, uniforms,
                                      defines, glslVersion: THREE.GLSL3, depthTest: false,
                                      depthWrite: false});
}

// ---------------------------------------------------------------- the renderer
export class WebRenderer {
  /**
   * @param {HTMLCanvasElement} canvas shows the frames (its size: the client image)
   * @param {object} info scene_info fields (lights, sky, bounds)
   */
  constructor(canvas, info, {giWeight = 1.0} = {}) {
    const gl = canvas.getContext("webgl2", {antialias: false, preserveDrawingBuffer: true,
                                            depth: false, alpha: false});
    if (!gl) throw new UnsupportedBrowser("this browser has no WebGL2 (a GPU or SwiftShader is needed)");
    if (!gl.getExtension("EXT_color_buffer_float")) {
      throw new UnsupportedBrowser("WebGL2 without EXT_color_buffer_float: float G-buffers unavailable");
    }
    if (gl.getParameter(gl.MAX_DRAW_BUFFERS) < 4) {
      throw new UnsupportedBrowser("WebGL2 with fewer than 4 draw buffers: no G-buffer pass");
    }
    const dbg = gl.getExtension("WEBGL_debug_renderer_info");
    this.glRenderer = dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    this.gl = gl;
    this.canvas = canvas;
    this.three = new THREE.WebGLRenderer({canvas, context: gl, antialias: false});
    this.three.autoClear = false;
    this.three.debug.checkShaderErrors = true;
    this.info = info;
    this.giWeight = giWeight;
    this.cam3 = new THREE.Camera();
    this.screen = new THREE.BufferGeometry();
    this.screen.setAttribute("position", new THREE.BufferAttribute(new Float32Array(9), 3));
    this.passes = {};
    this.level = null;
    this.refs = [];     // [{camera, gi texture, depth texture}] current first
    this.mode = 0;
    this.exposure = 1.0;
    this.size = [0, 0];
  }

  _pass(name, frag, uniforms) {
    if (!this.passes[name]) {
      const mesh = new THREE.Mesh(this.screen, raw(screenVert, frag, uniforms));
      mesh.frustumCulled = false;
      const scene = new THREE.Scene();
      scene.add(mesh);
      this.passes[name] = {scene, uniforms: mesh.material.uniforms};
    }
    return this.passes[name];
  }

  _run(name, frag, target, values) {
    const p = this._pass(name, frag, Object.fromEntries(Object.keys(values).map((k) => [k, {value: null}])));
    for (const [k, v] of Object.entries(values)) p.uniforms[k].value = v;
    this.three.setRenderTarget(target);
    this.three.render(p.scene, this.cam3);
  }

  resize(height, width) {
    if (this.size[0] === height && this.size[1] === width) return;
    this.size = [height, width];
    this.canvas.width = width;
    this.canvas.height = height;
    this.three.setSize(width, height, false);
    for (const k of ["gbuf", "warpA", "warpB", "combined", "fillA", "fillB", "final"]) {
      if (this[k]) this[k].dispose();
    }
    this.gbuf = floatTarget(width, height, 4, true);
    for (const k of ["warpA", "warpB", "combined", "fillA", "fillB", "final"]) this[k] = floatTarget(width, height);
  }

  /** Swap in an assembled LPM level (geometry, materials, textures; shadow maps redone). */
  async setLevel(level) {
    const mats = level.manifest.materials;
    const texIdx = [];
    const layers = [];
    const tsize = RASTER.textureSize;  // every texture resized to one square size, as icbtool.raster
    for (let i = 0; i < mats.length; i++) {
      if (level.textures[i]) {
        texIdx.push(layers.length);
        layers.push(await decodeTexture(level.textures[i], tsize));
      } else texIdx.push(-1);
    }
    const mdata = new Float32Array(2 * 4 * mats.length);
    mats.forEach((m, i) => {
      mdata.set([...m.albedo, texIdx[i]], 8 * i);
      mdata.set([...m.emission, 0], 8 * i + 4);
    });
    const matTex = new THREE.DataTexture(mdata, 2, mats.length, THREE.RGBAFormat, THREE.FloatType);
    matTex.needsUpdate = true;
    let texArray = null;
    if (layers.length) {
      const all = new Uint8Array(tsize * tsize * 4 * layers.length);
      layers.forEach((l, i) => all.set(l, i * tsize * tsize * 4));
      texArray = new THREE.DataArrayTexture(all, tsize, tsize, layers.length);
      texArray.colorSpace = THREE.SRGBColorSpace;
      texArray.wrapS = texArray.wrapT = THREE.RepeatWrapping;
      texArray.minFilter = THREE.LinearMipmapLinearFilter;
      texArray.magFilter = THREE.LinearFilter;
      texArray.generateMipmaps = true;
      texArray.needsUpdate = true;
    }
    const geo = levelGeometry(level);
    if (this.level) this.level.dispose();
    this.level = {geo, matTex, texArray, dispose: () => { geo.dispose(); matTex.dispose(); texArray?.dispose(); this._freeShadows(); }};
    this._buildShadows(geo);
    this._buildGbufferMaterial();
    this.levelIndex = level.level;
  }

  _freeShadows() {
    for (const a of ["sharpAtlas", "areaAtlas"]) {
      if (this[a]) { this[a].rt.depthTexture.dispose(); this[a].rt.dispose(); this[a] = null; }
    }
    if (this.viewsTex) { this.viewsTex.dispose(); this.viewsTex = null; }
  }

  _atlas(views, res) {
    const maxSize = this.gl.getParameter(this.gl.MAX_TEXTURE_SIZE);
    const cols = Math.ceil(Math.sqrt(views.length));
    if (cols * res > maxSize) res = Math.floor(maxSize / cols);  // stated in docs/guide/web-client.md
    const size = cols * res;
    const depth = new THREE.DepthTexture(size, size, THREE.UnsignedIntType);
    depth.compareFunction = THREE.LessEqualCompare;
    depth.minFilter = depth.magFilter = THREE.LinearFilter;  // bilinear PCF
    const rt = new THREE.WebGLRenderTarget(size, size, {depthTexture: depth, depthBuffer: true,
                                                        type: THREE.UnsignedByteType});
    return {rt, cols, res};
  }

  _buildShadows(geo) {
    const {sharp, area} = shadowViews(this.info.lights, this.info.bounds);
    this.shadow = {sharp, area};
    const all = [...sharp.map(([m, t]) => [m, t, [0, 0, 0]]), ...area];
    if (!all.length) return;
    const rows = new Float32Array(all.length * 5 * 4);
    all.forEach(([m, texel, s], i) => {
      rows.set(colMajor(m), i * 20);
      rows.set([...s, texel], i * 20 + 16);
    });
    this.viewsTex = new THREE.DataTexture(rows, 5, all.length, THREE.RGBAFormat, THREE.FloatType);
    this.viewsTex.needsUpdate = true;
    const mat = new THREE.RawShaderMaterial({
      vertexShader: depthVert, fragmentShader: depthFrag, glslVersion: THREE.GLSL3,
      uniforms: {u_clip_from_world: {value: new THREE.Matrix4()}}, colorWrite: false,
      polygonOffset: true, polygonOffsetFactor: RASTER.depthBiasSlope,
      polygonOffsetUnits: RASTER.depthBiasUnits, side: THREE.DoubleSide,
    });
    const mesh = new THREE.Mesh(geo, mat);
    mesh.frustumCulled = false;
    const scene = new THREE.Scene();
    scene.add(mesh);
    const draw = (views, res) => {
      const atlas = this._atlas(views, res);
      this.three.setRenderTarget(atlas.rt);
      this.three.setClearColor(0x000000, 0);
      atlas.rt.scissorTest = false;
      this.three.clear(true, true, false);
      views.forEach(([m], i) => {
        const x = (i % atlas.cols) * atlas.res, y = Math.floor(i / atlas.cols) * atlas.res;
        atlas.rt.viewport.set(x, y, atlas.res, atlas.res);
        atlas.rt.scissor.set(x, y, atlas.res, atlas.res);
        atlas.rt.scissorTest = true;
        this.three.setRenderTarget(atlas.rt);
        mat.uniforms.u_clip_from_world.value.fromArray(colMajor(m));
        this.three.render(scene, this.cam3);
      });
      atlas.rt.scissorTest = false;
      atlas.rt.viewport.set(0, 0, atlas.rt.width, atlas.rt.height);
      return atlas;
    };
    if (sharp.length) this.sharpAtlas = draw(sharp, RASTER.shadowMapSize);
    if (area.length) this.areaAtlas = draw(area, RASTER.areaShadowMapSize);
    mat.dispose();
  }

  _buildGbufferMaterial() {
    const lights = this.info.lights;
    const of = (k) => lights.filter((l) => l.kind === k);
    const [dir, point, spot, area] = ["directional", "point", "spot", "area"].map(of);
    const defines = {N_DIR: dir.length, N_POINT: point.length, N_SPOT: spot.length,
                     N_AREA: area.length, AREA_K: RASTER.areaSamples, AREA_SUB: 1};
    if (this.viewsTex) { defines.SHADOWS = 1; defines.AREA_SUB = RASTER.penumbraSamples; }
    if (this.level.texArray) defines.HAS_TEX = 1;
    const v3 = (a) => new THREE.Vector3(...a);
    const u = {
      u_clip_from_world: {value: new THREE.Matrix4()}, u_cam_pos: {value: new THREE.Vector3()},
      u_cam_forward: {value: new THREE.Vector3()}, u_materials: {value: this.level.matTex},
      u_textures: {value: this.level.texArray}, u_views: {value: this.viewsTex},
      u_normal_offset: {value: RASTER.normalOffset}, u_area_offset: {value: RASTER.areaOffset},
    };
    if (this.sharpAtlas) {
      u.u_sharp = {value: this.sharpAtlas.rt.depthTexture};
      u.u_sharp_grid = {value: new THREE.Vector2(this.sharpAtlas.cols, this.sharpAtlas.res)};
    }
    if (this.areaAtlas) {
      u.u_area = {value: this.areaAtlas.rt.depthTexture};
      u.u_area_grid = {value: new THREE.Vector2(this.areaAtlas.cols, this.areaAtlas.res)};
      u.u_area_view0 = {value: this.shadow.sharp.length};
    }
    if (dir.length) {
      u.u_dir_dir = {value: dir.map((l) => v3(l.direction))};
      u.u_dir_E = {value: dir.map((l) => v3(l.irradiance))};
    }
    if (point.length) {
      u.u_point_pos = {value: point.map((l) => v3(l.position))};
      u.u_point_I = {value: point.map((l) => v3(l.intensity))};
    }
    if (spot.length) {
      u.u_spot_pos = {value: spot.map((l) => v3(l.position))};
      u.u_spot_dir = {value: spot.map((l) => v3(unit(l.direction)))};
      u.u_spot_I = {value: spot.map((l) => v3(l.intensity))};
      u.u_spot_cos = {value: spot.map((l) => new THREE.Vector2(Math.cos(l.inner_deg * Math.PI / 180),
                                                               Math.cos(l.outer_deg * Math.PI / 180)))};
    }
    if (area.length) {
      u.u_area_v = {value: area.flatMap((l) => { const v = areaVertices(l); if (v.length === 3) v.push(v[2]); return v.map(v3); })};
      u.u_area_L = {value: area.map((l) => v3(l.radiance))};
    }
    const mat = new THREE.RawShaderMaterial({
      vertexShader: gbufferVert, fragmentShader: gbufferFrag, glslVersion: THREE.GLSL3,
      uniforms: u, defines, side: THREE.DoubleSide, depthTest: true, depthWrite: true,
    });
    if (this.gMesh) this.gMesh.material.dispose();
    this.gMesh = new THREE.Mesh(this.level.geo, mat);
    this.gMesh.frustumCulled = false;
    this.gScene = new THREE.Scene();
    this.gScene.add(this.gMesh);
  }

  /** Rasterize the WRT-buffer at `cam` (docs/protocol.md camera object). */
  renderWRT(cam) {
    this.resize(cam.height, cam.width);
    const [near, far] = nearFar(cam, this.info.bounds);
    const clip = matmul(glProjection(cam, near, far), glView(cam));
    const w = cam.world_from_cam;
    const sky = this.info.sky;
    this.three.setRenderTarget(this.gbuf);
    this.three.setClearColor(0x000000, 0);
    this.three.clear(true, true, false);
    this._run("background", backgroundFrag, this.gbuf, {
      u_height: cam.height, u_intrinsics: new THREE.Vector4(cam.fx, cam.fy, cam.cx, cam.cy),
      u_world_from_cam: new THREE.Matrix3().set(w[0][0], w[0][1], w[0][2], w[1][0], w[1][1], w[1][2],
                                                w[2][0], w[2][1], w[2][2]),
      u_sky: sky ? (sky.kind === "gradient" ? 2 : 1) : 0,
      u_zenith: new THREE.Vector3(...(sky?.zenith || [0, 0, 0])),
      u_horizon: new THREE.Vector3(...(sky?.horizon || [0, 0, 0])),
      u_ground: new THREE.Vector3(...(sky?.ground || [0, 0, 0])),
      u_up: new THREE.Vector3(...(sky?.up || [0, 1, 0])),
    });
    const u = this.gMesh.material.uniforms;
    u.u_clip_from_world.value.fromArray(colMajor(clip));
    u.u_cam_pos.value.set(w[0][3], w[1][3], w[2][3]);
    u.u_cam_forward.value.set(w[0][2], w[1][2], w[2][2]);
    this.three.setRenderTarget(this.gbuf);
    this.three.render(this.gScene, this.cam3);
    this.camera = cam;
  }

  /** Upload a decoded gi_reply as the current reference (the previous one is kept). */
  setReference(camera, parts) {
    const [h, w] = parts.gi.shape;
    const rgba = new Float32Array(h * w * 4);
    const g = parts.gi.data;
    for (let i = 0; i < h * w; i++) {
      rgba[4 * i] = g[3 * i]; rgba[4 * i + 1] = g[3 * i + 1]; rgba[4 * i + 2] = g[3 * i + 2]; rgba[4 * i + 3] = 1;
    }
    const z = new Float32Array(h * w);
    const d = parts.depth.data, m = parts.mask.data;
    for (let i = 0; i < h * w; i++) z[i] = m[i] > 0.5 && Number.isFinite(d[i]) && d[i] > 0 ? d[i] : 0;
    const tex = (data, fmt) => {
      const t = new THREE.DataTexture(data, w, h, fmt, THREE.FloatType);
      t.minFilter = t.magFilter = THREE.NearestFilter;
      t.needsUpdate = true;
      return t;
    };
    const ref = {camera, gi: tex(rgba, THREE.RGBAFormat), depth: tex(z, THREE.RedFormat)};
    const old = this.refs.splice(1);
    for (const r of old) { r.gi.dispose(); r.depth.dispose(); }
    this.refs.unshift(ref);
  }

  _warp(ref, target) {
    const c = ref.camera, cam = this.camera;
    this._run("warp", warpFrag, target, {
      u_pos: this.gbuf.textures[2], u_ref_gi: ref.gi, u_ref_depth: ref.depth,
      u_ref_from_world: new THREE.Matrix4().fromArray(colMajor(rigidInverse(c.world_from_cam))),
      u_ref_K: new THREE.Vector4(c.fx, c.fy, c.cx, c.cy),
      u_dst_K: new THREE.Vector4(cam.fx, cam.fy, cam.cx, cam.cy),
      u_rel_tol: WARP.relDepthTol, u_min_weight: WARP.minWeight,
    });
  }

  /** Warp the references, combine, fill the holes, blend (after renderWRT). */
  composite() {
    if (!this.refs.length) {
      this._run("blend", blendFrag, this.final, {u_dl: this.gbuf.textures[3], u_gi: this.combined.texture, u_gi_weight: 0});
      return;
    }
    this._warp(this.refs[0], this.warpA);
    let combined = this.warpA;
    if (this.refs.length > 1) {
      this._warp(this.refs[1], this.warpB);
      this._run("combine", combineFrag, this.combined, {u_a: this.warpA.texture, u_b: this.warpB.texture});
      combined = this.combined;
    }
    this.holesTarget = combined;
    const steps = Math.min(32, Math.max(8, Math.ceil(Math.max(...this.size) / 8)));
    let src = combined;
    for (let i = 0; i < steps; i++) {
      const dst = i % 2 ? this.fillB : this.fillA;
      this._run("fill", fillFrag, dst, {u_gi: src.texture, u_pos: this.gbuf.textures[2], u_rel_gap: WARP.relDepthGap});
      src = dst;
    }
    this.filled = src;
    this._run("blend", blendFrag, this.final, {u_dl: this.gbuf.textures[3], u_gi: src.texture, u_gi_weight: this.giWeight});
  }

  /** Show final / DL / GI / holes on the canvas (mode 0-3). */
  display() {
    const gi = this.filled || this.combined;
    this._run("display", displayFrag, null, {
      u_final: this.final.texture, u_dl: this.gbuf.textures[3], u_gi: gi.texture,
      u_holes: (this.holesTarget || this.combined).texture, u_mode: this.mode, u_exposure: this.exposure,
    });
  }

  /** Read a float target back in icbtool's row order: Float32Array(H * W * 4). */
  read(target, index = 0) {
    const [h, w] = this.size;
    const buf = new Float32Array(h * w * 4);
    this.three.readRenderTargetPixels(target, 0, 0, w, h, buf, undefined, index);
    const out = new Float32Array(h * w * 4);
    for (let r = 0; r < h; r++) out.set(buf.subarray((h - 1 - r) * w * 4, (h - r) * w * 4), r * w * 4);
    return out;
  }

  /** (near, far) view depths the client sees (prefetch.depth_range_from_depth), or null. */
  depthRange() {
    const p = this.read(this.gbuf, 2);
    let lo = Infinity, hi = -Infinity;
    for (let i = 3; i < p.length; i += 4) if (p[i] > 0) { lo = Math.min(lo, p[i]); hi = Math.max(hi, p[i]); }
    if (!(hi > 0)) return null;
    return [Math.max(lo, 1e-3), Math.max(hi, lo * (1 + 1e-9))];
  }

  /** Hole fractions of the last composite (before filling) over the client's geometry. */
  holeStats() {
    if (!this.holesTarget) return {holes: 1, outside: 0, disoccluded: 0};
    const c = this.read(this.holesTarget);
    let n = 0, out = 0, dis = 0;
    for (let i = 3; i < c.length; i += 4) {
      if (c[i] === -3) continue;
      n++;
      if (c[i] === -1) out++; else if (c[i] === -2) dis++;
    }
    return {holes: n ? (out + dis) / n : 0, outside: n ? out / n : 0, disoccluded: n ? dis / n : 0};
  }

  /** Wait for the GPU: a 1-pixel read-back of the last target (gl.finish alone does not
   * block under ANGLE), so stage times are real. */
  finish(target = this.final) {
    if (target) this.three.readRenderTargetPixels(target, 0, 0, 1, 1, new Float32Array(4));
  }
}
