// LPM levels from lpm_chunk payloads (docs/lpm.md "Chunk layout"): parse, check, assemble.
// A level is complete when its materials chunk and every chunk its manifest lists are here.

const dec = new TextDecoder("utf-8", {fatal: true});

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

/** CRC-32 (zlib, IEEE polynomial) of bytes. */
export function crc32(bytes) {
  let c = 0xffffffff;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

/** One chunk file: {header, payload}; throws Error naming the chunk. */
export function parseChunk(name, data) {
  const what = `LPM chunk '${name}'`;
  if (data.length < 8 || String.fromCharCode(...data.subarray(0, 4)) !== "ICBL") {
    throw new Error(`${what}: no ICBL magic`);
  }
  const hlen = new DataView(data.buffer, data.byteOffset, data.byteLength).getUint32(4, true);
  if (hlen > 65536 || 8 + hlen > data.length) throw new Error(`${what}: bad header length ${hlen}`);
  const header = JSON.parse(dec.decode(data.subarray(8, 8 + hlen)));
  if (header.v !== 1) throw new Error(`${what}: format version ${header.v}, expected 1`);
  if (header.name !== name) throw new Error(`${what}: header names '${header.name}'`);
  const payload = data.subarray(8 + hlen);
  if (payload.length !== header.size) {
    throw new Error(`${what}: payload ${payload.length} bytes, header says ${header.size} (truncated)`);
  }
  if (crc32(payload) !== header.crc32) throw new Error(`${what}: CRC-32 mismatch (corrupt payload)`);
  return {header, payload};
}

const COLS = {vertices: 3, normals: 3, uvs: 2, faces: 3, face_material: 1};

/** Collects the lpm_chunk messages of the levels; `level(k)` assembles a complete one. */
export class LevelCollector {
  constructor() {
    this.files = new Map();  // level -> Map(name -> [chunk payloads by index])
    this.done = new Set();
  }

  add(fields, payload) {
    if (!this.files.has(fields.level)) this.files.set(fields.level, new Map());
    const files = this.files.get(fields.level);
    if (!files.has(fields.name)) files.set(fields.name, []);
    files.get(fields.name).push({index: fields.index, bytes: payload.slice()});
  }

  /** Assemble level k: {level, manifest, arrays, textures: [{bytes, format} or null]}. */
  level(k) {
    const files = this.files.get(k);
    if (!files) throw new Error(`LPM level ${k}: no chunks received`);
    const whole = new Map();
    for (const [name, parts] of files) {
      parts.sort((a, b) => a.index - b.index);
      const n = parts.reduce((s, p) => s + p.bytes.length, 0);
      const buf = new Uint8Array(n);
      let o = 0;
      for (const p of parts) { buf.set(p.bytes, o); o += p.bytes.length; }
      whole.set(name, parseChunk(name, buf));
    }
    const mname = `L${k}/materials`;
    if (!whole.has(mname)) throw new Error(`LPM level ${k}: no materials chunk`);
    const manifest = JSON.parse(dec.decode(whole.get(mname).payload));
    const missing = manifest.chunks.filter((c) => !whole.has(c));
    if (missing.length) throw new Error(`LPM level ${k} lacks ${missing.length} chunk(s): ${missing.slice(0, 3)}`);
    const arrays = {};
    const textures = manifest.materials.map(() => null);
    for (const name of manifest.chunks) {
      const {header, payload} = whole.get(name);
      if (header.part === "geometry") {
        const [rows, cols] = [header.shape[0], COLS[header.array]];
        if (!cols) throw new Error(`LPM chunk '${name}': unknown array ${header.array}`);
        const Typed = header.dtype === "<f4" ? Float32Array : header.dtype === "<i4" ? Int32Array : null;
        if (!Typed) throw new Error(`LPM chunk '${name}': dtype ${header.dtype}`);
        if (!arrays[header.array]) arrays[header.array] = new Typed(rows * cols);
        if (payload.length !== header.rows * cols * 4 || header.row0 + header.rows > rows) {
          throw new Error(`LPM chunk '${name}': rows ${header.row0}+${header.rows} do not fit`);
        }
        const src = new Typed(payload.slice().buffer);
        arrays[header.array].set(src, header.row0 * cols);
      } else if (header.part === "texture") {
        const t = textures[header.material] ||
          (textures[header.material] = {bytes: new Uint8Array(header.total), format: header.format});
        t.bytes.set(payload, header.offset);
      }
    }
    for (const a of ["vertices", "normals", "faces", "face_material"]) {
      if (!arrays[a]) throw new Error(`LPM level ${k}: no ${a} array`);
    }
    return {level: k, manifest, arrays, textures};
  }
}
