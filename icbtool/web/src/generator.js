// The GAN generator in onnxruntime-web (WebAssembly): an ONNX file exported by
// icbtool.gan.Generator.export_onnx (input "maps" (1, C, H, W) float32, output "gi_encoded"
// (1, 3, H, W) in [-1, 1]); threads where the page is cross-origin isolated (the server sends
// COOP/COEP headers), one thread otherwise.
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

export class OnnxGenerator {
  static async load(bytes) {
    configure();
    const session = await ort.InferenceSession.create(bytes, {executionProviders: ["wasm"]});
    return new OnnxGenerator(session);
  }

  constructor(session) {
    this.session = session;
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
