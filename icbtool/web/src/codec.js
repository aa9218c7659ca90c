// GI and depth codecs (docs/protocol.md section 7; icbtool/net/codec.py): decode only.
// The zstd codecs: f32-zstd, f16-zstd, f16-diff-zstd, f16m7-diff-zstd (the default for GI).
// The PNG codecs need a 16-bit PNG decoder and are not offered by this client (hello.codecs).
import {decompress} from "fzstd";
import {ProtocolError} from "./protocol.js";

export const CODECS = ["f16m7-diff-zstd", "f16-diff-zstd", "f16-zstd", "f32-zstd"];
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

/**
 * Decode one part to a Float32Array of shape `shape` (C order).
 * @param {Uint8Array} data the part's encoded bytes
 * @param {string} codec one of CODECS
 * @param {number[]} shape e.g. [H, W, 3]
 */
export function decodePart(data, codec, shape) {
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
  throw new ProtocolError("malformed", `codec ${codec} is not decoded by this client`);
}

/** All parts of a gi_reply: {gi, depth, mask: {data: Float32Array, shape}}, and bytes. */
export function decodeReply(fields, payload) {
  const out = {};
  let off = 0;
  for (const p of fields.parts) {
    if (off + p.bytes > payload.length) {
      throw new ProtocolError("malformed", `gi_reply part ${p.name}: beyond the payload`);
    }
    out[p.name] = {data: decodePart(payload.subarray(off, off + p.bytes), p.codec, p.shape),
                   shape: p.shape};
    off += p.bytes;
  }
  if (off !== payload.length) throw new ProtocolError("malformed", "gi_reply: payload longer than its parts");
  for (const k of ["gi", "depth", "mask"]) {
    if (!out[k]) throw new ProtocolError("bad_field", `gi_reply has no ${k} part`);
  }
  return out;
}
