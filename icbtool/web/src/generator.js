// The served client model in onnxruntime-web (WebAssembly; docs/protocol.md section Client
// models): threads where the page is cross-origin isolated (the server sends COOP/COEP
// headers), one thread otherwise.
//
// OnnxGenerator runs an ONNX file as is (input "maps" (1, C, H, W) float32, output "gi_encoded").
// ClientModel follows a scene_info.generator announcement exactly as icbtool's Python client does
// (icbtool/net/client_model.py ServedModel): a "gan" model gets its inputs normalised by the
// announced rules, stacked in the announced order and padded to the size multiple by edge
// replication; its output goes through the HDR curve and times the albedo when demodulated. A
// "radiance" model gets the surface pixels' world positions and normals and its irradiance is
// multiplied by the albedo. Buffers are icbtool's row order: H x W x C Float32Arrays.
import * as ort from "onnxruntime-web/wasm";

let configured = false;

function configure() {
  if (configured) return;
  ort.env.wasm.wasmPaths = new URL("./", import.meta.url).href;  // the bundle folder
  ort.env.wasm.numThreads = globalThis.crossOriginIsolated ?
    Math.max(1, Math.min(4, navigator.hardwareConcurrency || 1)) : 1;
  ort.env.wasm.proxy = false;
  configured = true;
}

async function session(bytes) {
  configure();
  return ort.InferenceSession.create(bytes, {executionProviders: ["wasm"]});
}

export class OnnxGenerator {
  static async load(bytes) {
    return new OnnxGenerator(await session(bytes));
  }

  constructor(s) {
    this.session = s;
    this.threads = ort.env.wasm.numThreads;
  }

  /** Run on encoded maps: Float32Array (C * H * W) -> Float32Array (3 * H * W), and ms. */
  async run(maps, channels, height, width) {
    const t0 = performance.now();
    const x = new ort.Tensor("float32", maps, [1, channels, height, width]);
    const out = await this.session.run({maps: x});
    const y = out.gi_encoded;
    return {data: y.data, dims: y.dims, ms: performance.now() - t0};
  }
}

/** Channels of the client buffers a model may read (docs/protocol.md, Client models). */
export const CHANNELS = {dl: 3, albedo: 3, normal_world: 3, normal_view: 3, depth: 1, position: 3, mask: 1};
/** How a gan model's input buffer is normalised (icbtool/net/client_model.py GAN_MAP_RULES). */
export const GAN_MAP_RULES = {dl: "hdr", albedo: "unit", mask: "unit", normal_world: "identity",
                              normal_view: "identity", depth: "depth", position: "position"};

/** The mapping of one value of buffer `name`, channel `c`, by its rule with the announced
 * encoding `e` (docs/protocol.md, Client models). */
export function mapRule(name, c, e) {
  const hdr = e.hdr, norm = Math.log1p(hdr.max_value / hdr.scale);
  return {
    hdr: (v) => 2 * Math.log1p(Math.min(Math.max(v, 0), hdr.max_value) / hdr.scale) / norm - 1,
    unit: (v) => 2 * v - 1,
    identity: (v) => v,
    depth: (v) => 2 * v / e.depth_max - 1,
    position: (v) => (v - e.position_center[c]) / e.position_half_extent,
  }[GAN_MAP_RULES[name]];
}

/** A gan model's output value y -> linear radiance (before the albedo). */
export function decodeOutput(y, e) {
  const hdr = e.hdr, norm = Math.log1p(hdr.max_value / hdr.scale);
  return Math.fround(hdr.scale * Math.expm1((Math.min(Math.max(y, -1), 1) + 1) * 0.5 * norm));
}

/** SHA-256 of bytes as lowercase hex (WebCrypto). */
export async function sha256Hex(bytes) {
  const d = new Uint8Array(await crypto.subtle.digest("SHA-256", bytes));
  return Array.from(d, (b) => b.toString(16).padStart(2, "0")).join("");
}

export class ClientModel {
  /** The model of `info` (scene_info.generator) from its file, checked against info's size and
   * SHA-256 (a mismatch throws: the file is not used). */
  static async load(bytes, info) {
    if (bytes.length !== info.bytes) throw new Error(`client model: ${bytes.length} bytes, scene_info.generator says ${info.bytes}`);
    const got = await sha256Hex(bytes);
    if (got !== info.sha256) throw new Error(`client model: SHA-256 ${got}, scene_info.generator says ${info.sha256}`);
    if (!["gan", "radiance"].includes(info.kind)) throw new Error(`client model kind ${info.kind} is not gan or radiance`);
    if ((info.format || "onnx") !== "onnx") throw new Error(`client model format ${info.format} is not onnx`);
    const bad = info.inputs.filter((n) => !(n in CHANNELS));
    if (bad.length) throw new Error(`client model reads ${bad}, which this page does not render`);
    return new ClientModel(await session(bytes), info);
  }

  constructor(s, info) {
    this.session = s;
    this.info = info;
    this.kind = info.kind;
    this.threads = ort.env.wasm.numThreads;
    // the buffers generate() reads (a radiance model also needs albedo and the mask)
    this.needs = info.kind === "gan" ? [...new Set([...info.inputs, ...(info.demodulated ? ["albedo"] : [])])]
                                     : ["albedo", "normal_world", "position", "mask"];
  }

  /** GI from the client's buffers `maps` ({name: Float32Array H * W * C}) of an h x w view:
   * {gi: Float32Array H * W * 3 (linear), ms (model run only)}. */
  async generate(maps, h, w) {
    for (const n of this.needs) {
      if (!maps[n] || maps[n].length !== h * w * CHANNELS[n]) throw new Error(`client model: buffer ${n} missing or not ${h}x${w}x${CHANNELS[n]}`);
    }
    return this.kind === "gan" ? this._gan(maps, h, w) : this._radiance(maps, h, w);
  }

  async _gan(maps, h, w) {
    const info = this.info, e = info.encoding, m = info.size_multiple || 1;
    const H = Math.ceil(h / m) * m, W = Math.ceil(w / m) * m;  // padded by edge replication
    const nc = info.inputs.reduce((s, n) => s + CHANNELS[n], 0);
    const x = new Float32Array(nc * H * W);
    let ch = 0;
    for (const name of info.inputs) {
      const a = maps[name], k = CHANNELS[name];
      for (let c = 0; c < k; c++, ch++) {
        const f = mapRule(name, c, e);
        const plane = ch * H * W;
        for (let i = 0; i < H; i++) {
          const si = Math.min(i, h - 1);
          for (let j = 0; j < W; j++) {
            const v = a[(si * w + Math.min(j, w - 1)) * k + c];
            if (!Number.isFinite(v)) throw new Error(`client model: buffer ${name} holds NaN or Inf`);
            x[plane + i * W + j] = f(v);
          }
        }
      }
    }
    const t0 = performance.now();
    const out = await this.session.run({maps: new ort.Tensor("float32", x, [1, nc, H, W])});
    const ms = performance.now() - t0;
    const y = out.gi_encoded.data;
    const gi = new Float32Array(h * w * 3);
    const albedo = info.demodulated ? maps.albedo : null;
    for (let c = 0; c < 3; c++) {
      for (let i = 0; i < h; i++) {
        for (let j = 0; j < w; j++) {
          const p = (i * w + j) * 3 + c;
          const g = decodeOutput(y[(c * H + i) * W + j], e);
          gi[p] = albedo ? g * albedo[p] : g;
        }
      }
    }
    return {gi, ms};
  }

  async _radiance(maps, h, w) {
    const mask = maps.mask, n = h * w;
    const idx = [];
    for (let i = 0; i < n; i++) if (mask[i] > 0.5) idx.push(i);
    const gi = new Float32Array(n * 3);
    if (!idx.length) return {gi, ms: 0};
    const pos = new Float32Array(idx.length * 3), nrm = new Float32Array(idx.length * 3);
    idx.forEach((p, k) => {
      for (let c = 0; c < 3; c++) {
        pos[3 * k + c] = maps.position[3 * p + c];
        nrm[3 * k + c] = maps.normal_world[3 * p + c];
      }
    });
    const t0 = performance.now();
    const out = await this.session.run({
      position: new ort.Tensor("float32", pos, [idx.length, 3]),
      normal: new ort.Tensor("float32", nrm, [idx.length, 3]),
    });
    const ms = performance.now() - t0;
    const e = out.irradiance.data;
    idx.forEach((p, k) => {
      for (let c = 0; c < 3; c++) gi[3 * p + c] = maps.albedo[3 * p + c] * e[3 * k + c];
    });
    return {gi, ms};
  }
}
