// GI and depth codecs (docs/protocol.md section 7; icbtool/net/codec.py): decode only.
// The zstd codecs: f32-zstd, f16-zstd, f16-diff-zstd, f16m7-diff-zstd (the default for GI).
// The PNG codecs (log-u16-png, rgbe-png) through a PNG decoder of our own (decodePNG: 8- and
// 16-bit samples as stored, no colour management, no premultiplied alpha; zlib through the
// browser's DecompressionStream), since a canvas or createImageBitmap clips 16-bit samples to 8.
import {decompress} from "fzstd";
import {crc32} from "./lpm.js";
import {ProtocolError} from "./protocol.js";

export const CODECS = ["f16m7-diff-zstd", "f16-diff-zstd", "f16-zstd", "f32-zstd", "log-u16-png", "rgbe-png"];
/** log-u16-png's range of log2 values (icbtool.net.codec LOG_MIN, LOG_MAX). */
export const LOG_MIN = -20, LOG_MAX = 20;
export const MAX_ELEMENTS = 64 * 2 ** 20;

function unzstd(data, expect, codec) {
  let raw;
  try {
    raw = decompress(data);
  } catch (e) {
    throw new ProtocolError("malformed", `${codec}: corrupt zstd data (${e.message})`);
  }
  if (raw.length !== expect) {
    throw new ProtocolError("malformed", `${codec}: ${raw.length} bytes, expected ${expect}`);
  }
  return raw;
}

/** Inverse byte shuffle: out[i*k + b] = in[b*n + i]. */
export function unshuffle(raw, k) {
  const n = raw.length / k;
  const out = new Uint8Array(raw.length);
  for (let b = 0; b < k; b++) {
    const base = b * n;
    for (let i = 0; i < n; i++) out[i * k + b] = raw[base + i];
  }
  return out;
}

const F16_TABLE = (() => {  // float16 bits -> float32, all 65536 values
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1;
    const e = (h >> 10) & 0x1f;
    const m = h & 0x3ff;
    if (e === 0) t[h] = s * m * 2 ** -24;
    else if (e === 31) t[h] = m ? NaN : s * Infinity;
    else t[h] = s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return t;
})();

function halfToFloat(u16) {
  const out = new Float32Array(u16.length);
  for (let i = 0; i < u16.length; i++) out[i] = F16_TABLE[u16[i]];
  return out;
}

function leU16(bytes) {  // little-endian uint16 (every browser is little-endian; check anyway)
  const out = new Uint16Array(bytes.length / 2);
  for (let i = 0; i < out.length; i++) out[i] = bytes[2 * i] | (bytes[2 * i + 1] << 8);
  return out;
}

/** Undo zigzag and the 2-D differences (cumsum along rows, then columns, mod 2^16). */
export function undiff2(z, shape) {
  const h = shape[0];
  const w = shape.length > 1 ? shape[1] : 1;
  const c = shape.slice(2).reduce((a, b) => a * b, 1);
  const u = new Uint16Array(z.length);
  for (let i = 0; i < z.length; i++) u[i] = ((z[i] >>> 1) ^ -(z[i] & 1)) & 0xffff;
  const row = w * c;
  for (let i = 1; i < h; i++) {        // axis 0
    const o = i * row;
    for (let k = 0; k < row; k++) u[o + k] = (u[o + k] + u[o - row + k]) & 0xffff;
  }
  for (let i = 0; i < h; i++) {        // axis 1
    const o = i * row;
    for (let j = 1; j < w; j++) {
      for (let ch = 0; ch < c; ch++) {
        const p = o + j * c + ch;
        u[p] = (u[p] + u[p - c]) & 0xffff;
      }
    }
  }
  return u;
}

// ------------------------------------------------------------------------------- PNG
const PNG_SIGNATURE = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];
const PNG_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4};  // colour type -> samples per pixel

async function inflate(bytes, codec) {
  try {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  } catch (e) {
    throw new ProtocolError("malformed", `${codec}: corrupt PNG (zlib: ${e.message})`);
  }
}

function paeth(a, b, c) {
  const p = a + b - c, pa = Math.abs(p - a), pb = Math.abs(p - b), pc = Math.abs(p - c);
  return pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
}

/**
 * Decode a PNG (non-interlaced; grey, grey + alpha, RGB or RGBA; 8 or 16 bits) to its samples as
 * stored: {height, width, channels, depth, samples: Uint8Array | Uint16Array (H * W * C)}.
 * Chunks are CRC-checked; anything else is a ProtocolError "malformed" naming `codec`.
 */
export async function decodePNG(data, codec = "png") {
  const bad = (why) => new ProtocolError("malformed", `${codec}: ${why}`);
  if (data.length < 8 || PNG_SIGNATURE.some((b, i) => data[i] !== b)) throw bad("not a PNG (bad signature)");
  const dv = new DataView(data.buffer, data.byteOffset, data.byteLength);
  let off = 8, ihdr = null, ended = false;
  const idat = [];
  while (off + 12 <= data.length && !ended) {
    const len = dv.getUint32(off), type = String.fromCharCode(...data.subarray(off + 4, off + 8));
    if (off + 12 + len > data.length) throw bad(`corrupt PNG (chunk ${type} beyond the data)`);
    const body = data.subarray(off + 8, off + 8 + len);
    if ((crc32(data.subarray(off + 4, off + 8 + len)) >>> 0) !== dv.getUint32(off + 8 + len)) throw bad(`corrupt PNG (chunk ${type}: CRC-32 mismatch)`);
    if (type === "IHDR") {
      const h = new DataView(body.buffer, body.byteOffset, body.byteLength);
      ihdr = {width: h.getUint32(0), height: h.getUint32(4), depth: body[8], colour: body[9], interlace: body[12]};
    } else if (type === "IDAT") idat.push(body);
    else if (type === "IEND") ended = true;
    off += 12 + len;
  }
  if (!ihdr || !ended || !idat.length) throw bad("corrupt PNG (IHDR, IDAT or IEND missing)");
  const {width, height, depth, colour, interlace} = ihdr;
  const channels = PNG_CHANNELS[colour];
  if (!channels || (depth !== 8 && depth !== 16) || interlace !== 0) {
    throw bad(`PNG colour type ${colour}, ${depth}-bit, interlace ${interlace} is not decoded (8/16-bit grey, grey + alpha, RGB, RGBA; not interlaced)`);
  }
  const n = width * height * channels;
  if (!(n >= 1 && n <= MAX_ELEMENTS)) throw bad(`PNG of ${width}x${height}x${channels} samples`);
  const raw = await inflate(idat.length === 1 ? idat[0] : new Uint8Array(await new Blob(idat).arrayBuffer()), codec);
  const bpp = channels * depth / 8, stride = width * bpp;
  if (raw.length !== height * (stride + 1)) throw bad(`corrupt PNG (${raw.length} bytes of scanlines, expected ${height * (stride + 1)})`);
  const img = new Uint8Array(height * stride);
  for (let y = 0; y < height; y++) {
    const f = raw[y * (stride + 1)], src = raw.subarray(y * (stride + 1) + 1, (y + 1) * (stride + 1));
    const o = y * stride, up = y > 0 ? o - stride : -1;
    for (let i = 0; i < stride; i++) {
      const a = i >= bpp ? img[o + i - bpp] : 0, b = up >= 0 ? img[up + i] : 0;
      const c = i >= bpp && up >= 0 ? img[up + i - bpp] : 0;
      let v;
      if (f === 0) v = src[i];
      else if (f === 1) v = src[i] + a;
      else if (f === 2) v = src[i] + b;
      else if (f === 3) v = src[i] + ((a + b) >> 1);
      else if (f === 4) v = src[i] + paeth(a, b, c);
      else throw bad(`corrupt PNG (filter type ${f} in row ${y})`);
      img[o + i] = v & 0xff;
    }
  }
  let samples = img;
  if (depth === 16) {  // big-endian in PNG
    samples = new Uint16Array(n);
    for (let i = 0; i < n; i++) samples[i] = (img[2 * i] << 8) | img[2 * i + 1];
  }
  return {height, width, channels, depth, samples};
}

let LOG_TABLE = null;  // log-u16-png code -> float32 value, all 65536 codes

function logValues(codes) {
  if (!LOG_TABLE) {
    LOG_TABLE = new Float32Array(65536);
    for (let c = 1; c < 65535; c++) LOG_TABLE[c] = 2 ** ((c - 1) / 65533 * (LOG_MAX - LOG_MIN) + LOG_MIN);
    LOG_TABLE[0] = 0;
    LOG_TABLE[65535] = Infinity;
  }
  const out = new Float32Array(codes.length);
  for (let i = 0; i < codes.length; i++) out[i] = LOG_TABLE[codes[i]];
  return out;
}

async function decodePNGPart(data, codec, shape) {
  const [h, w] = shape;
  const want = codec === "rgbe-png" ? 4 : shape.length === 2 ? 1 : shape[2];
  if (codec === "rgbe-png" && !(shape.length === 3 && shape[2] === 3)) {
    throw new ProtocolError("bad_field", `rgbe-png decodes (H, W, 3) arrays, not [${shape}]`);
  }
  if (codec === "log-u16-png" && !(shape.length === 2 || (shape.length === 3 && [1, 3, 4].includes(shape[2])))) {
    throw new ProtocolError("malformed", `log-u16-png: bad shape [${shape}]`);
  }
  const img = await decodePNG(data, codec);
  const depth = codec === "rgbe-png" ? 8 : 16;
  if (img.height !== h || img.width !== w || img.channels !== want || img.depth !== depth) {
    throw new ProtocolError("malformed", `${codec}: the PNG is ${img.depth}-bit ${img.height}x${img.width}x${img.channels}, expected ${depth}-bit ${h}x${w}x${want}`);
  }
  if (codec === "log-u16-png") return logValues(img.samples);
  const s = img.samples, out = new Float32Array(h * w * 3);
  for (let p = 0; p < h * w; p++) {
    const e = s[4 * p + 3], f = e > 0 ? 2 ** (e - 136) : 0;
    for (let c = 0; c < 3; c++) out[3 * p + c] = (s[4 * p + c] + 0.5) * f;
  }
  return out;
}

/**
 * Decode one part to a Float32Array of shape `shape` (C order); a Promise (the PNG codecs
 * inflate asynchronously).
 * @param {Uint8Array} data the part's encoded bytes
 * @param {string} codec one of CODECS
 * @param {number[]} shape e.g. [H, W, 3]
 */
export async function decodePart(data, codec, shape) {
  const n = shape.reduce((a, b) => a * b, 1);
  if (!(n >= 1 && n <= MAX_ELEMENTS)) throw new ProtocolError("malformed", `${codec}: bad shape ${shape}`);
  if (codec === "f32-zstd") {
    const raw = unshuffle(unzstd(data, 4 * n, codec), 4);
    return new Float32Array(raw.buffer, 0, n);
  }
  if (codec === "f16-zstd") return halfToFloat(leU16(unshuffle(unzstd(data, 2 * n, codec), 2)));
  if (codec === "f16-diff-zstd" || codec === "f16m7-diff-zstd") {
    const u = undiff2(leU16(unshuffle(unzstd(data, 2 * n, codec), 2)), shape);
    if (codec === "f16m7-diff-zstd") {
      for (let i = 0; i < n; i++) u[i] = (u[i] & 0x8000) | ((u[i] & 0x7fff) << 3);
    }
    return halfToFloat(u);
  }
  if (codec === "log-u16-png" || codec === "rgbe-png") return decodePNGPart(data, codec, shape);
  throw new ProtocolError("malformed", `codec ${codec} is not decoded by this client`);
}

/** All parts of a gi_reply: {gi, depth, mask: {data: Float32Array, shape}} (a Promise). */
export async function decodeReply(fields, payload) {
  const out = {};
  let off = 0;
  for (const p of fields.parts) {
    if (off + p.bytes > payload.length) {
      throw new ProtocolError("malformed", `gi_reply part ${p.name}: beyond the payload`);
    }
    out[p.name] = {data: await decodePart(payload.subarray(off, off + p.bytes), p.codec, p.shape),
                   shape: p.shape};
    off += p.bytes;
  }
  if (off !== payload.length) throw new ProtocolError("malformed", "gi_reply: payload longer than its parts");
  for (const k of ["gi", "depth", "mask"]) {
    if (!out[k]) throw new ProtocolError("bad_field", `gi_reply has no ${k} part`);
  }
  return out;
}
