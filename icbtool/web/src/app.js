// icbtool's browser client: the page served by `icbtool serve --web`.
// Connects with the token from the URL fragment (#token=...; never sent to the server in an
// HTTP request), streams the LPM levels coarse to fine, rasterizes the WRT-buffer, asks for GI
// with its camera and motion (the server places the prefetch camera), warps / combines / fills /
// blends, and shows the frame with an overlay. When the server offers a client model
// (scene_info.generator: a GAN generator or a world-space radiance model, ONNX), the page
// downloads it once, checks its SHA-256 and makes its GI with it in onnxruntime-web instead of
// asking (docs/protocol.md, section Client models). Fragment options: token, size (client image
// height = width, default 256), rtt (emulated round trip, ms), codec (the GI codec asked for,
// default f16m7-diff-zstd), model=0 (never use the served model), test=1 (no automatic loop:
// the tests drive window.icb).
import * as camera from "./camera.js";
import {CameraPath, resized} from "./camera.js";
import * as codec from "./codec.js";
import {CODECS, decodeReply} from "./codec.js";
import * as generator from "./generator.js";
import {ClientModel, OnnxGenerator, sha256Hex} from "./generator.js";
import * as lpm from "./lpm.js";
import {LevelCollector} from "./lpm.js";
import * as protocol from "./protocol.js";
import {ProtocolError, Session} from "./protocol.js";
import {WebRenderer} from "./render.js";

// the modules, for the tests (tests/test_web.py runs the protocol's test vectors through them)
globalThis.icbModules = {camera, codec, lpm, protocol, generator, OnnxGenerator, ClientModel};

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.hash.slice(1));
const token = params.get("token");
const SIZE = parseInt(params.get("size") || "256", 10);
const RTT = parseFloat(params.get("rtt") || "0");
const TEST = params.get("test") === "1";
const USE_MODEL = params.get("model") !== "0";
const GI_CODEC = params.get("codec") || CODECS[0];
const MODES = ["final", "DL", "GI", "holes"];

const state = {
  errors: [], levels: new Set(), level: -1, frames: 0, hits: 0, misses: 0, pending: 0,
  nextId: 0, replies: new Map(), last: {}, t0: performance.now(), firstFrameMs: null,
  mode: 0, playing: !TEST, pathT: 0, rxFrame: 0, model: null, generated: 0,
};

export function showError(msg) {
  state.errors.push(msg);
  const e = $("error");
  if (e) { e.textContent = msg; e.hidden = false; }
  console.warn(`icbtool: ${msg}`);  // a warning, not an error: tests count console errors
}

// ---------------------------------------------------------------- controls
class Controls {
  constructor(canvas) {
    this.mode = "orbit";
    this.keys = new Set();
    this.pose = null;        // world_from_cam (OpenCV axes)
    this.target = [0, 0, 0];
    this.speed = 1;
    canvas.addEventListener("pointerdown", (e) => { this.drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointerup", () => { this.drag = null; });
    canvas.addEventListener("pointermove", (e) => {
      if (!this.drag || !this.pose) return;
      const dx = e.clientX - this.drag[0], dy = e.clientY - this.drag[1];
      this.drag = [e.clientX, e.clientY];
      state.playing = false;
      this.rotate(-dx * 0.005, -dy * 0.005);
    });
    canvas.addEventListener("wheel", (e) => { e.preventDefault(); this.dolly(Math.sign(e.deltaY) * 0.1); }, {passive: false});
    addEventListener("keydown", (e) => this.key(e, true));
    addEventListener("keyup", (e) => this.key(e, false));
  }

  key(e, down) {
    const k = e.key.toLowerCase();
    if (down && "1234".includes(k)) { state.mode = parseInt(k, 10) - 1; return; }
    if (down && k === "p") { state.playing = !state.playing; return; }
    if (down && k === "o") { this.mode = this.mode === "orbit" ? "fly" : "orbit"; return; }
    if (down) this.keys.add(k); else this.keys.delete(k);
  }

  set(pose, bounds) {
    this.pose = pose.map((r) => r.slice());
    const c = [0, 1, 2].map((i) => 0.5 * (bounds[0][i] + bounds[1][i]));
    this.target = c;
    this.speed = 0.3 * Math.hypot(...bounds[1].map((x, i) => x - bounds[0][i]));
  }

  rotate(yaw, pitch) {  // about world up through the target (orbit) or the eye (fly)
    const p = this.pose;
    const pivot = this.mode === "orbit" ? this.target : [p[0][3], p[1][3], p[2][3]];
    const rot = (v, axis, a) => {  // Rodrigues
      const [x, y, z] = axis, c = Math.cos(a), s = Math.sin(a), d = x * v[0] + y * v[1] + z * v[2];
      return [v[0] * c + (y * v[2] - z * v[1]) * s + x * d * (1 - c),
              v[1] * c + (z * v[0] - x * v[2]) * s + y * d * (1 - c),
              v[2] * c + (x * v[1] - y * v[0]) * s + z * d * (1 - c)];
    };
    const right = [p[0][0], p[1][0], p[2][0]];
    for (const [axis, a] of [[[0, 1, 0], yaw], [right, pitch]]) {
      for (let c = 0; c < 3; c++) {
        const col = rot([p[0][c], p[1][c], p[2][c]], axis, a);
        for (let r = 0; r < 3; r++) p[r][c] = col[r];
      }
      const e = rot([p[0][3] - pivot[0], p[1][3] - pivot[1], p[2][3] - pivot[2]], axis, a);
      for (let r = 0; r < 3; r++) p[r][3] = pivot[r] + e[r];
    }
  }

  dolly(f) {
    const p = this.pose;
    for (let r = 0; r < 3; r++) p[r][3] += -f * this.speed * p[r][2];
    state.playing = false;
  }

  /** Move by held keys (WASD/QE) over dt seconds; returns the velocity in the camera frame. */
  update(dt) {
    const v = [0, 0, 0];
    const k = this.keys;
    if (k.has("w")) v[2] += 1; if (k.has("s")) v[2] -= 1;
    if (k.has("d")) v[0] += 1; if (k.has("a")) v[0] -= 1;
    if (k.has("q")) v[1] += 1; if (k.has("e")) v[1] -= 1;
    if (!this.pose || !v.some((x) => x)) return [0, 0, 0];
    state.playing = false;
    const vc = v.map((x) => x * this.speed);
    for (let r = 0; r < 3; r++) {
      this.pose[r][3] += dt * (this.pose[r][0] * vc[0] + this.pose[r][1] * vc[1] + this.pose[r][2] * vc[2]);
    }
    return vc;
  }
}

// ---------------------------------------------------------------- the client
class WebClient {
  async start() {
    if (!token) throw new ProtocolError("auth", "no token in the URL: open the exact link `icbtool serve --web` printed");
    if (!CODECS.includes(GI_CODEC)) throw new ProtocolError("bad_field", `codec=${GI_CODEC} in the URL is not one of ${CODECS.join(", ")}`);
    history.replaceState(null, "", location.pathname + (TEST ? "#test=1" : ""));  // token out of sight
    const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/`;
    this.session = new Session(url, token, {codecs: CODECS, rttMs: RTT});
    this.session.onClose = (why) => { if (why !== "closed by the client") showError(why); };
    const t0 = performance.now();
    const info = await this.session.connect();
    this.connectMs = performance.now() - t0;
    this.info = info.fields;
    const paths = info.payload.length ? JSON.parse(new TextDecoder().decode(info.payload)).paths : {};
    this.paths = Object.fromEntries(Object.entries(paths).map(([k, p]) => [k, new CameraPath(p)]));
    this.path = this.paths.test || Object.values(this.paths)[0] || null;
    this.collector = new LevelCollector();
    this.canvas = $("view");
    this.renderer = new WebRenderer(this.canvas, this.info);
    this.controls = new Controls(this.canvas);
    const cam0 = this.info.default_camera || this.info.camera;
    this.controls.set(cam0.world_from_cam, this.info.bounds);
    this.levelWaiters = [];
    this.session.onMessage = (m) => this.onMessage(m);
    const levels = this.info.lpm.levels.map((l) => l.level);
    this.levelTimes = {};
    // the coarsest level alone first: the first frame need not share the link and the main
    // thread with the finer levels; they follow after it (or 5 s after level 0 at most; in test
    // mode after the first step or requestFinerLevels())
    await this.session.send("lpm_request", {max_level: Math.min(...levels)});
    this.levelsOffered = levels;
    this.levelChain = Promise.resolve();
    this.modelReady = this.info.generator && USE_MODEL ? this.fetchModel() : Promise.resolve(null);
    this.modelReady.catch((e) => showError(`client model: ${e.message}`));
  }

  /** Ask for the served client model (every chunk), then for any chunk whose SHA-256 does not
   * match its header once more; resolves with the loaded ClientModel (also state.model). */
  async fetchModel() {
    const info = this.info.generator;
    this.modelPieces = new Array(info.chunks).fill(null);
    this.modelRetried = new Set();
    const done = new Promise((resolve, reject) => { this.modelWaiter = {resolve, reject}; });
    await this.session.send("generator_request", {});
    await done;
    const bytes = protocol.concat(...this.modelPieces);
    this.modelPieces = null;
    const model = await ClientModel.load(bytes, info);
    state.model = model;
    return model;
  }

  async onModelChunk(f, payload) {
    if (!this.modelPieces) return;
    if (f.count !== this.modelPieces.length) {
      this.modelWaiter.reject(new Error(`generator_chunk.count ${f.count}, scene_info.generator.chunks ${this.modelPieces.length}`));
      return;
    }
    if (await sha256Hex(payload) !== f.sha256) {
      if (this.modelRetried.has(f.index)) {
        this.modelWaiter.reject(new Error(`chunk ${f.index} failed its SHA-256 twice`));
        return;
      }
      this.modelRetried.add(f.index);
      await this.session.send("generator_request", {index: f.index});
      return;
    }
    this.modelPieces[f.index] = payload;
    if (this.modelPieces.every((p) => p !== null)) this.modelWaiter.resolve();
  }

  onMessage(m) {
    state.rxFrame += m.bytes;
    if (m.kind === "lpm_chunk") {
      this.collector.add(m.fields, m.payload);
    } else if (m.kind === "generator_chunk") {
      this.onModelChunk(m.fields, m.payload).catch((e) => showError(`client model: ${e.message}`));
    } else if (m.kind === "lpm_done") {
      const k = m.fields.level;
      this.levelTimes[k] = performance.now() - state.t0;
      if (k === Math.min(...this.levelsOffered) && !TEST) {  // GI may be slow: not forever
        setTimeout(() => this.requestFinerLevels(), 5000);
      }
      this.levelChain = this.levelChain.then(async () => {
        if (k > state.level) {
          await this.renderer.setLevel(this.collector.level(k));
          state.level = k;
        }
        state.levels.add(k);
        for (const w of this.levelWaiters.splice(0)) w();
      }).catch((e) => showError(`LPM level ${k}: ${e.message}`));
    } else if (m.kind === "gi_reply" || (m.kind === "error" && m.fields.ref !== null)) {
      const id = m.kind === "gi_reply" ? m.fields.id : m.fields.ref;
      const r = this.replies.get(id);
      if (r) { this.replies.delete(id); r.resolve(m); }
    } else if (m.kind === "error") {
      if (this.modelPieces && m.fields.message.startsWith("generator_request")) {
        this.modelWaiter.reject(new Error(`server error ${m.fields.code}: ${m.fields.message}`));
      }
      showError(`server error ${m.fields.code}: ${m.fields.message}`);
    }
  }

  get replies() { return state.replies; }

  /** Ask for the levels above the coarsest (once). */
  requestFinerLevels() {
    const lo = Math.min(...this.levelsOffered), hi = Math.max(...this.levelsOffered);
    if (this.finerRequested || hi === lo) return;
    this.finerRequested = true;
    this.session.send("lpm_request", {min_level: lo + 1, max_level: hi})
      .catch((e) => showError(`LPM request: ${e.message}`));
  }

  waitLevel(k = 0) {
    return new Promise((resolve) => {
      const check = () => (state.levels.has(k) ? resolve() : this.levelWaiters.push(check));
      check();
    });
  }

  /** Send a gi_request for `cam` with motion (v_t, v_r) at client time tS; resolves with the
   * decoded reply and the client-side latency split. */
  async requestGI(cam, vT, vR, tS, depthRange, seq = null) {
    const id = state.nextId++;
    if (seq === null) seq = id;
    const t0 = performance.now();
    const reply = new Promise((resolve) => state.replies.set(id, {resolve}));
    state.pending++;
    await this.session.send("gi_request", {
      id, codec: GI_CODEC, depth_codec: "f16-diff-zstd",
      request: {camera: cam, velocity_t: vT, velocity_r: vR, time_s: tS, seq, depth_range: depthRange},
    });
    const m = await reply;
    state.pending--;
    const tReply = performance.now();
    if (m.kind === "error") throw new ProtocolError(m.fields.code, `gi_request ${id}: ${m.fields.message}`);
    const parts = await decodeReply(m.fields, m.payload);
    const decodeMs = performance.now() - tReply;
    const requestMs = performance.now() - t0;
    const server = m.fields.timings_ms.server || 0;
    // transfer: from sending to the reply's arrival, less the server's time; the time from its
    // arrival to its handling here (main thread busy, decryption) is "wait", not the network's
    const arrived = m.arrivedMs ?? tReply;
    if (m.fields.cache_hit) state.hits++; else state.misses++;
    // an animated scene: a stale reference is shown marked (docs/dynamic.md)
    if (m.fields.stale === true) state.stale = (state.stale || 0) + 1;
    return {camera: m.fields.camera, parts, cacheHit: m.fields.cache_hit, bytes: m.bytes,
            stale: m.fields.stale === true, spp: m.fields.spp ?? null,
            timings: {request: requestMs, decode: decodeMs, server,
                      transfer: Math.max(0, arrived - t0 - server),
                      wait: Math.max(0, tReply - arrived),
                      render: m.fields.timings_ms.render || 0}};
  }

  /** The client's buffers at the last renderWRT, by name (icbtool's row order, H x W x C). */
  wrtMaps() {
    const r = this.renderer, [h, w] = r.size, n = h * w;
    const t = [0, 1, 2, 3].map((k) => r.read(r.gbuf, k));
    const rgb = (a) => { const o = new Float32Array(n * 3); for (let i = 0; i < n; i++) { o[3 * i] = a[4 * i]; o[3 * i + 1] = a[4 * i + 1]; o[3 * i + 2] = a[4 * i + 2]; } return o; };
    const depth = new Float32Array(n), mask = new Float32Array(n);
    for (let i = 0; i < n; i++) { depth[i] = t[2][4 * i + 3]; mask[i] = depth[i] > 0 ? 1 : 0; }
    const maps = {albedo: rgb(t[0]), normal_world: rgb(t[1]), position: rgb(t[2]), dl: rgb(t[3]), depth, mask};
    // camera-space normals (OpenCV axes): cam_from_world's rotation = world_from_cam's transposed
    const R = r.camera.world_from_cam, nw = maps.normal_world, nv = new Float32Array(n * 3);
    for (let i = 0; i < n; i++) {
      for (let c = 0; c < 3; c++) nv[3 * i + c] = R[0][c] * nw[3 * i] + R[1][c] * nw[3 * i + 1] + R[2][c] * nw[3 * i + 2];
    }
    maps.normal_view = nv;
    return {maps, h, w, surface: mask.some((v) => v > 0)};
  }

  /** The served model's GI of the current view as the reference (its own camera, depth and
   * mask: the warp is the identity, as icbtool.system.GeneratorSource); null when the client sees
   * no surface (then the server is asked, as the Python client does). */
  async generateGI(cam) {
    const t0 = performance.now();
    const {maps, h, w, surface} = this.wrtMaps();
    if (!surface) return null;
    const {gi, ms} = await state.model.generate(maps, h, w);
    this.renderer.setReference(cam, {gi: {data: gi, shape: [h, w, 3]},
                                     depth: {data: maps.depth, shape: [h, w, 1]},
                                     mask: {data: maps.mask, shape: [h, w, 1]}});
    state.generated++;
    return {generate: performance.now() - t0, model: ms};
  }

  /** One frame the way icbtool's Python loop makes it (pipeline.run_loop): the request for the
   * camera at t - latency, its reply awaited, then the frame at t; with the served model, its GI
   * of the view at t instead of the request. */
  async step({t, latency = 0.1, size = SIZE, seq = null}) {
    const path = this.path;
    const intr = resized(path.intrinsics, size, size);
    const cam = path.cameraAt(t, intr);
    const tReq = Math.max(t - latency, path.times[0]);
    const camReq = path.cameraAt(tReq, intr);
    const [vT, vR] = path.velocityCam(tReq);
    const r = this.renderer;
    let t0 = performance.now();
    r.renderWRT(cam);
    r.finish(r.gbuf);
    const rasterMs = performance.now() - t0;
    const gen = state.model ? await this.generateGI(cam) : null;
    let reply;
    if (gen) {
      reply = {camera: cam, cacheHit: false, bytes: 0, timings: {generate: gen.generate, model: gen.model}};
    } else {
      const dr = r.depthRange();
      reply = await this.requestGI(camReq, vT, vR, tReq, dr, seq);
      r.setReference(reply.camera, reply.parts);
    }
    t0 = performance.now();
    r.composite();
    r.finish();
    const warpMs = performance.now() - t0;
    r.mode = state.mode;
    r.display();
    state.frames++;
    this.requestFinerLevels();
    const holes = r.holeStats();
    const stats = {t, level: state.level, raster_ms: rasterMs, warp_ms: warpMs,
                   ...Object.fromEntries(Object.entries(reply.timings).map(([k, v]) => [`${k}_ms`, v])),
                   cache_hit: reply.cacheHit, bytes: reply.bytes, hole_ratio: holes.holes, camera: cam,
                   ref_camera: reply.camera};
    state.last = stats;
    overlay();
    return stats;
  }

  /** The interactive loop: path playback or the controls; GI requested continuously. */
  loop() {
    let last = performance.now();
    const frame = async () => {
      const now = performance.now();
      const dt = Math.min(0.1, (now - last) / 1e3);
      last = now;
      try {
        await this.tick(dt);
      } catch (e) {
        showError(e.message);
        if (e instanceof ProtocolError && ["auth", "crypto"].includes(e.code)) return;
      }
      requestAnimationFrame(frame);
    };
    requestAnimationFrame(frame);
  }

  async tick(dt) {
    if (state.level < 0) return;
    const r = this.renderer;
    const intr = resized(this.path ? this.path.intrinsics : this.info.camera, SIZE, SIZE);
    let cam, vT = [0, 0, 0], vR = [0, 0, 0];
    if (state.playing && this.path) {
      state.pathT += dt;
      if (state.pathT > this.path.times.at(-1)) state.pathT = this.path.times[0];
      cam = this.path.cameraAt(state.pathT, intr);
      [vT, vR] = this.path.velocityCam(state.pathT);
      this.controls.pose = cam.world_from_cam.map((x) => x.slice());
    } else {
      vT = this.controls.update(dt);
      cam = {...intr, world_from_cam: this.controls.pose.map((x) => x.slice())};
    }
    const t0 = performance.now();
    r.renderWRT(cam);
    r.finish(r.gbuf);
    const rasterMs = performance.now() - t0;
    const maxPending = this.info.max_pending || 4;
    const gen = state.model ? await this.generateGI(cam) : null;
    if (gen) {
      state.last.generate_ms = gen.generate;
    } else if (state.pending < Math.min(2, maxPending)) {  // keep a request in flight
      const dr = r.depthRange();
      const tS = performance.now() / 1e3;
      this.requestGI(cam, vT, vR, tS, dr).then((reply) => {
        r.setReference(reply.camera, reply.parts);
        Object.assign(state.last, Object.fromEntries(Object.entries(reply.timings).map(([k, v]) => [`${k}_ms`, v])));
        state.last.cache_hit = reply.cacheHit;
        state.last.bytes = reply.bytes;
      }).catch((e) => showError(e.message));
    }
    const t1 = performance.now();
    r.composite();
    r.mode = state.mode;
    r.display();
    r.finish();
    state.last.raster_ms = rasterMs;
    state.last.warp_ms = performance.now() - t1;
    // a whole-target read-back: every 8th frame only (it stalls the main thread)
    if (r.refs.length && state.frames % 8 === 0) state.last.hole_ratio = r.holeStats().holes;
    state.last.level = state.level;
    if (state.firstFrameMs === null && r.refs.length) {
      state.firstFrameMs = performance.now() - state.t0;
      this.requestFinerLevels();
    }
    state.frames++;
    if (state.frames % 4 === 0) overlay();
  }
}

function fmt(x, d = 1) { return x === undefined ? "-" : x.toFixed(d); }

function overlay() {
  const o = $("overlay");
  if (!o) return;
  const s = state.last;
  const r = client?.renderer;
  o.textContent = [
    `${MODES[state.mode]} | LPM level ${state.level} of ${(client?.levelsOffered?.length ?? 0) - 1} | ${r?.size?.[1]}x${r?.size?.[0]}`,
    `raster ${fmt(s.raster_ms)} | request ${fmt(s.request_ms)} (server ${fmt(s.server_ms)}, transfer ${fmt(s.transfer_ms)}, wait ${fmt(s.wait_ms)}) | decode ${fmt(s.decode_ms)} | warp ${fmt(s.warp_ms)} | generate ${fmt(s.generate_ms)} ms`,
    `${state.model ? `client model: ${state.model.kind} (${(state.model.info.bytes / 1024).toFixed(0)} KiB, ${state.generated} frames)` : client?.info?.generator ? "client model: downloading" : "client model: none offered"}`,
    `holes ${fmt(100 * (s.hole_ratio ?? 1))} % | cache hit ${state.hits} / miss ${state.misses} | ${fmt((s.bytes || 0) / 1024)} KiB/reply`,
    `${r?.glRenderer ?? ""}`,
    "drag: orbit | wheel: dolly | WASD QE: fly | O: orbit/fly | P: play path | 1-4: final/DL/GI/holes",
  ].join("\n");
}

let client = null;

async function main() {
  client = new WebClient();
  window.icb = {state, client, ready: null, showError, MODES};
  // test hooks: a float target in icbtool's row order (base64 of float32 H x W x 4), and the
  // WRT-buffer alone at a given camera
  const targets = (r) => ({albedo: [r.gbuf, 0], normal: [r.gbuf, 1], position: [r.gbuf, 2],
                           dl: [r.gbuf, 3], final: [r.final, 0]});
  window.icb.read = (name) => protocol.b64(new Uint8Array(client.renderer.read(...targets(client.renderer)[name]).buffer));
  window.icb.renderWRT = (cam) => {
    client.renderer.renderWRT(cam);
    client.renderer.finish(client.renderer.gbuf);
  };
  window.icb.ready = (async () => {
    await client.start();
    await client.waitLevel(0);
  })();
  try {
    await window.icb.ready;
  } catch (e) {
    showError(e instanceof ProtocolError ? `cannot start: ${e.detail}` : `cannot start: ${e.message}`);
    throw e;
  }
  overlay();
  if (!TEST) client.loop();
}

if (typeof document !== "undefined" && document.getElementById("view")) {
  main().catch(() => {});  // shown on the page by showError
}
