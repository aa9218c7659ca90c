// The ICB wire protocol, version 1, in the browser: docs/protocol.md section by section.
// Framing (section 1), value types (2), the handshake and sealed channels with WebCrypto (4),
// the message kinds (6, the same table as icbtool/net/protocol.py KINDS; tests/test_web.py
// checks that they agree) and the error codes (8). No DOM here: usable from a worker too.

export const PROTOCOL_VERSION = 1;
export const MAX_HEADER = 65536;
export const LABEL = "icbtool/net/v1";
export const CLIENT_TO_SERVER = new Uint8Array([0, 0, 0, 1]);
export const SERVER_TO_CLIENT = new Uint8Array([0, 0, 0, 2]);
const MAX_COUNTER = 2 ** 53 - 1;

// Section 6, top-level fields: name -> [type, required, nullable, byte length (base64/hex)].
export const KINDS = {
  hello: {sender: "client", sealed: false, payload: false, fields: {
    client: ["string", true, false], pub: ["base64", true, false, 32],
    nonce: ["base64", true, false, 32], codecs: ["array", true, false]}},
  welcome: {sender: "server", sealed: false, payload: false, fields: {
    session: ["string", true, false], pub: ["base64", true, false, 32],
    nonce: ["base64", true, false, 32], server: ["string", true, false]}},
  auth: {sender: "client", sealed: false, payload: false, fields: {
    mac: ["base64", true, false, 32]}},
  scene_info: {sender: "server", sealed: true, payload: true, fields: {
    name: ["string", true, false], bounds: ["array", true, false], lights: ["array", true, false],
    camera: ["object", true, false], lpm: ["object", true, false],
    generator: ["object", true, true], codecs: ["array", true, false],
    sky: ["object", false, true], up: ["array", false, false],
    default_camera: ["object", false, true], max_pending: ["integer", false, false],
    limits: ["object", false, false]}},
  lpm_request: {sender: "client", sealed: true, payload: false, fields: {
    max_level: ["integer", true, false], min_level: ["integer", false, false]}},
  lpm_chunk: {sender: "server", sealed: true, payload: true, fields: {
    level: ["integer", true, false], index: ["integer", true, false],
    count: ["integer", true, false], part: ["string", true, false],
    name: ["string", true, false], sha256: ["hex", true, false, 32]}},
  lpm_done: {sender: "server", sealed: true, payload: false, fields: {
    level: ["integer", true, false]}},
  gi_request: {sender: "client", sealed: true, payload: false, fields: {
    id: ["integer", true, false], request: ["object", true, false],
    codec: ["string", true, false], depth_codec: ["string", false, false]}},
  gi_reply: {sender: "server", sealed: true, payload: true, fields: {
    id: ["integer", true, false], camera: ["object", true, false],
    cache_hit: ["boolean", true, false], coalesced: ["boolean", false, false],
    stale: ["boolean", false, false], state: ["string", false, false],
    spp: ["integer", false, false], refining: ["boolean", false, false],
    timings_ms: ["object", true, false], parts: ["array", true, false]}},
  generator_request: {sender: "client", sealed: true, payload: false, fields: {
    index: ["integer", false, false]}},
  generator_chunk: {sender: "server", sealed: true, payload: true, fields: {
    index: ["integer", true, false], count: ["integer", true, false],
    sha256: ["hex", true, false, 32]}},
  error: {sender: "both", sealed: true, payload: false, fields: {
    code: ["string", true, false], message: ["string", true, false],
    ref: ["integer", true, true]}},
  bye: {sender: "both", sealed: true, payload: false, fields: {}},
};

export const ERROR_CODES = ["malformed", "version", "unknown_kind", "too_large", "bad_field",
  "auth", "crypto", "replay", "busy", "internal", "not_found"];

/** A protocol failure with its section-8 code (the page shows `message`). */
export class ProtocolError extends Error {
  constructor(code, message, ref = null) {
    super(`[${code}] ${message}`);
    this.code = code;
    this.detail = message;
    this.ref = ref;
  }
}

// ------------------------------------------------------------------------- value types (2)
const enc = new TextEncoder();
const dec = new TextDecoder("utf-8", {fatal: true});

export function b64(bytes) {
  let s = "";
  for (let i = 0; i < bytes.length; i += 0x8000) {
    s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  }
  return btoa(s);
}

export function unb64(s) {
  const bin = atob(s);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

export function hex(bytes) {
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

export function unhex(s) {
  if (s.length % 2 || /[^0-9a-f]/.test(s)) throw new Error(`not lowercase hex: ${s.slice(0, 16)}`);
  const out = new Uint8Array(s.length / 2);
  for (let i = 0; i < out.length; i++) out[i] = parseInt(s.substr(2 * i, 2), 16);
  return out;
}

export function concat(...parts) {
  const out = new Uint8Array(parts.reduce((n, p) => n + p.length, 0));
  let o = 0;
  for (const p of parts) { out.set(p, o); o += p.length; }
  return out;
}

function checkField(kind, name, spec, value) {
  const [type, , nullable, length] = spec;
  const bad = (why) => new ProtocolError("bad_field", `${kind}.${name}: ${why}`);
  if (value === null) {
    if (!nullable) throw bad("must not be null");
    return;
  }
  const ok = {
    string: typeof value === "string",
    integer: Number.isSafeInteger(value),
    number: typeof value === "number" && Number.isFinite(value),
    boolean: typeof value === "boolean",
    array: Array.isArray(value),
    object: typeof value === "object" && !Array.isArray(value),
    base64: typeof value === "string",
    hex: typeof value === "string",
  }[type];
  if (!ok) throw bad(`must be ${type}, got ${JSON.stringify(value).slice(0, 40)}`);
  if (type === "base64" && length !== undefined) {
    let n;
    try { n = unb64(value).length; } catch { throw bad("is not base64"); }
    if (n !== length) throw bad(`must decode to ${length} bytes, got ${n}`);
  }
  if (type === "hex" && length !== undefined && !new RegExp(`^[0-9a-f]{${2 * length}}$`).test(value)) {
    throw bad(`must be ${2 * length} lowercase hex digits`);
  }
}

/** Check a message against its kind's fields (section 6); throws ProtocolError. */
export function validate(kind, fields, payload) {
  const spec = KINDS[kind];
  if (!spec) throw new ProtocolError("unknown_kind", `unknown message kind ${JSON.stringify(kind)}`);
  for (const [name, f] of Object.entries(spec.fields)) {
    if (!(name in fields)) {
      if (f[1]) throw new ProtocolError("bad_field", `${kind}: missing field ${name}`);
      continue;
    }
    checkField(kind, name, f, fields[name]);
  }
  if (!spec.payload && payload.length) {
    throw new ProtocolError("bad_field", `${kind}: has no payload, got ${payload.length} bytes`);
  }
}

// ------------------------------------------------------------------------- framing (1)
/** The header bytes of a message (compact JSON with v and kind first). */
export function headerBytes(kind, fields, ctr = null) {
  const h = {v: PROTOCOL_VERSION, kind, ...fields};
  if (ctr !== null) h.ctr = ctr;
  return enc.encode(JSON.stringify(h));
}

export function frame(header, payload) {
  const out = new Uint8Array(4 + header.length + payload.length);
  new DataView(out.buffer).setUint32(0, header.length);  // big-endian
  out.set(header, 4);
  out.set(payload, 4 + header.length);
  return out;
}

/** Split a frame: {header bytes, header object, payload bytes}; throws ProtocolError. */
export function parseFrame(data) {
  const b = data instanceof Uint8Array ? data : new Uint8Array(data);
  if (b.length < 4) throw new ProtocolError("malformed", `frame of ${b.length} bytes is too short`);
  const n = new DataView(b.buffer, b.byteOffset, b.byteLength).getUint32(0);
  if (n > MAX_HEADER) throw new ProtocolError("too_large", `header of ${n} bytes`);
  if (4 + n > b.length) throw new ProtocolError("malformed", `header length ${n} beyond the data`);
  const headerB = b.subarray(4, 4 + n);
  let header;
  try { header = JSON.parse(dec.decode(headerB)); } catch (e) {
    throw new ProtocolError("malformed", `header is not UTF-8 JSON: ${e.message}`);
  }
  if (typeof header !== "object" || header === null || Array.isArray(header) ||
      !("v" in header) || !("kind" in header)) {
    throw new ProtocolError("malformed", "header is not an object with v and kind");
  }
  if (header.v !== PROTOCOL_VERSION) {
    throw new ProtocolError("version", `protocol version ${header.v}, this client speaks 1`);
  }
  if (!(header.kind in KINDS)) throw new ProtocolError("unknown_kind", `kind ${header.kind}`);
  return {headerB, header, payload: b.subarray(4 + n)};
}

function fieldsOf(header) {
  const f = {...header};
  delete f.v; delete f.kind; delete f.ctr;
  return f;
}

// ------------------------------------------------------------------------- crypto (4)
export function transcript(clientPub, clientNonce, serverPub, serverNonce, session) {
  return concat(enc.encode(LABEL), new Uint8Array([0]), clientPub, clientNonce, serverPub,
                serverNonce, enc.encode(session));
}

/** HMAC-SHA256(auth key, transcript) (section 4.2; the key from sessionKeyBytes). */
export async function authMac(authKey, tr) {
  const key = await crypto.subtle.importKey("raw", authKey,
                                            {name: "HMAC", hash: "SHA-256"}, false, ["sign"]);
  return new Uint8Array(await crypto.subtle.sign("HMAC", key, tr));
}

/** The raw 32-byte keys {c2s, s2c, auth} (section 4.2). */
export async function sessionKeyBytes(sharedSecret, token, tr) {
  if (sharedSecret.every((x) => x === 0)) {
    throw new ProtocolError("crypto", "X25519 shared secret is all zero (low-order key)");
  }
  const ikm = await crypto.subtle.importKey("raw", concat(sharedSecret, enc.encode(token)),
                                            "HKDF", false, ["deriveBits"]);
  const salt = new Uint8Array(await crypto.subtle.digest("SHA-256", tr));
  const derive = async (dir) => new Uint8Array(await crypto.subtle.deriveBits(
    {name: "HKDF", hash: "SHA-256", salt, info: enc.encode(`${LABEL} ${dir}`)}, ikm, 256));
  return {c2s: await derive("c2s"), s2c: await derive("s2c"), auth: await derive("auth")};
}

export async function x25519Shared(privateKey, peerPub) {
  const peer = await crypto.subtle.importKey("raw", peerPub, {name: "X25519"}, false, []);
  return new Uint8Array(await crypto.subtle.deriveBits({name: "X25519", public: peer},
                                                       privateKey, 256));
}

function gcmNonce(dirId, ctr) {
  const iv = new Uint8Array(12);
  iv.set(dirId, 0);
  new DataView(iv.buffer).setBigUint64(4, BigInt(ctr));
  return iv;
}

/** One direction of a sealed session (section 4.3): seal (send) or open (receive). */
export class Channel {
  static async create(rawKey, dirId) {
    const key = await crypto.subtle.importKey("raw", rawKey, "AES-GCM", false,
                                              ["encrypt", "decrypt"]);
    return new Channel(key, dirId);
  }

  constructor(key, dirId) {
    this.key = key;
    this.dirId = dirId;
    this.next = 0;       // sender: the next ctr
    this.last = -1;      // receiver: the last ctr accepted
  }

  async seal(kind, fields = {}, payload = new Uint8Array(0)) {
    validate(kind, fields, payload);
    if (this.next > MAX_COUNTER) throw new ProtocolError("crypto", "message counter exhausted");
    const ctr = this.next++;
    const header = headerBytes(kind, fields, ctr);
    const sealed = new Uint8Array(await crypto.subtle.encrypt(
      {name: "AES-GCM", iv: gcmNonce(this.dirId, ctr), additionalData: header, tagLength: 128},
      this.key, payload));
    return frame(header, sealed);
  }

  /** Open a received sealed frame: {kind, fields, payload}; throws ProtocolError. */
  async open(data) {
    const {headerB, header, payload} = parseFrame(data);
    const ctr = header.ctr;
    if (!Number.isSafeInteger(ctr) || ctr < 0) {
      throw new ProtocolError("crypto", `${header.kind} is not sealed (no ctr) after the handshake`);
    }
    if (ctr <= this.last) throw new ProtocolError("replay", `ctr ${ctr} <= ${this.last}`);
    let plain;
    try {
      plain = new Uint8Array(await crypto.subtle.decrypt(
        {name: "AES-GCM", iv: gcmNonce(this.dirId, ctr), additionalData: headerB, tagLength: 128},
        this.key, payload));
    } catch {
      throw new ProtocolError("crypto", `${header.kind} failed to authenticate (wrong token?)`);
    }
    this.last = ctr;
    const fields = fieldsOf(header);
    validate(header.kind, fields, plain);
    return {kind: header.kind, fields, payload: plain};
  }
}

/** A plain (handshake) frame. */
export function plainFrame(kind, fields) {
  validate(kind, fields, new Uint8Array(0));
  return frame(headerBytes(kind, fields), new Uint8Array(0));
}

export function openPlain(data) {
  const {header, payload} = parseFrame(data);
  if ("ctr" in header) throw new ProtocolError("crypto", `${header.kind} sealed during the handshake`);
  const fields = fieldsOf(header);
  validate(header.kind, fields, payload);
  return {kind: header.kind, fields, payload};
}

// ------------------------------------------------------------------------- session (3)
/**
 * A client session on a WebSocket: connect + handshake, then sealed messages.
 * `onMessage({kind, fields, payload, bytes})` gets every message after scene_info;
 * `onClose(reason)` once, with a readable reason.
 */
export class Session {
  constructor(url, token, {client = "icbtool-web/1", codecs = [], rttMs = 0} = {}) {
    this.url = url;
    this.delayMs = rttMs / 2;  // emulated network: half the round trip each way (net/shaper.py)
    this.token = token;
    this.client = client;
    this.codecs = codecs;
    this.onMessage = () => {};
    this.onClose = () => {};
    this.bytesReceived = {};
    this.bytesSent = {};
    this._queue = [];
    this._waiters = [];
    this._closed = null;
  }

  _count(table, kind, n) { table[kind] = (table[kind] || 0) + n; }

  _next(timeoutMs) {  // the next raw frame during the handshake
    if (this._queue.length) return Promise.resolve(this._queue.shift());
    if (this._closed) return Promise.reject(new Error(this._closed));
    return new Promise((resolve, reject) => {
      const t = setTimeout(() => reject(new Error(`no answer from ${this.url} in ${timeoutMs} ms`)),
                           timeoutMs);
      this._waiters.push({resolve: (x) => { clearTimeout(t); resolve(x); },
                          reject: (e) => { clearTimeout(t); reject(e); }});
    });
  }

  /** Connect and authenticate; resolves with {fields, payload} of scene_info. */
  async connect(timeoutMs = 20000) {
    if (!crypto.subtle || !("generateKey" in crypto.subtle)) {
      throw new ProtocolError("crypto", "this browser has no WebCrypto (needs a secure context: " +
                              "http://127.0.0.1 or https)");
    }
    let kp;
    try {
      kp = await crypto.subtle.generateKey({name: "X25519"}, true, ["deriveBits"]);
    } catch (e) {
      throw new ProtocolError("crypto", `this browser's WebCrypto has no X25519: ${e.message}`);
    }
    const pub = new Uint8Array(await crypto.subtle.exportKey("raw", kp.publicKey));
    const nonce = crypto.getRandomValues(new Uint8Array(32));
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    await new Promise((resolve, reject) => {
      ws.onopen = resolve;
      ws.onerror = () => reject(new Error(`cannot connect to ${this.url} (server gone?)`));
    });
    ws.onmessage = (ev) => {
      const b = new Uint8Array(ev.data);
      // arrival: when the event was made (before any wait for the main thread), plus the
      // emulated network delay; replies carry it as msg.arrivedMs (performance.now() clock)
      const at = (ev.timeStamp > 0 ? ev.timeStamp : performance.now()) + this.delayMs;
      if (this.delayMs > 0) setTimeout(() => this._onRaw(b, at), this.delayMs); else this._onRaw(b, at);
    };
    ws.onclose = (ev) => this._onWsClose(ev);
    ws.onerror = null;
    this._send(plainFrame("hello", {client: this.client, pub: b64(pub), nonce: b64(nonce),
                                    codecs: this.codecs}), "hello");
    const welcome = openPlain(await this._next(timeoutMs));
    if (welcome.kind === "error") throw new ProtocolError(welcome.fields.code, welcome.fields.message);
    if (welcome.kind !== "welcome") throw new ProtocolError("auth", `expected welcome, got ${welcome.kind}`);
    const w = welcome.fields;
    const tr = transcript(pub, nonce, unb64(w.pub), unb64(w.nonce), w.session);
    const shared = await x25519Shared(kp.privateKey, unb64(w.pub));
    const keys = await sessionKeyBytes(shared, this.token, tr);
    this.send_ = await Channel.create(keys.c2s, CLIENT_TO_SERVER);
    this.recv_ = await Channel.create(keys.s2c, SERVER_TO_CLIENT);
    this._send(plainFrame("auth", {mac: b64(await authMac(keys.auth, tr))}), "auth");
    this.session = w.session;
    this.server = w.server;
    const first = await this._next(timeoutMs);
    let msg;
    try {
      msg = await this.recv_.open(first);
    } catch (e) {  // a plain error: the server refused the token
      let plain = null;
      try { plain = openPlain(first); } catch { /* not plain either */ }
      if (plain && plain.kind === "error") {
        throw new ProtocolError(plain.fields.code, plain.fields.code === "auth"
          ? "the server refused the token (wrong or expired link?)" : plain.fields.message);
      }
      throw e;
    }
    if (msg.kind === "error") throw new ProtocolError(msg.fields.code, msg.fields.message);
    if (msg.kind !== "scene_info") throw new ProtocolError("bad_field", `expected scene_info, got ${msg.kind}`);
    this._count(this.bytesReceived, "scene_info", first.length);
    this._sealedMode = true;
    for (const f of this._queue.splice(0)) this._dispatch(f);
    return msg;
  }

  _send(bytes, kind) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN) {
      throw new Error(this._closed || "the connection is closed");
    }
    this._count(this.bytesSent, kind, bytes.length);
    if (this.delayMs > 0) {
      setTimeout(() => { if (this.ws.readyState === WebSocket.OPEN) this.ws.send(bytes); }, this.delayMs);
    } else {
      this.ws.send(bytes);
    }
  }

  async send(kind, fields = {}) {
    this._send(await this.send_.seal(kind, fields), kind);
  }

  _onRaw(bytes, arrivedMs = performance.now()) {
    if (!this._sealedMode) {
      const w = this._waiters.shift();
      if (w) w.resolve(bytes); else this._queue.push(bytes);
      return;
    }
    this._dispatch(bytes, arrivedMs);
  }

  _dispatch(bytes, arrivedMs) {
    // decrypt in arrival order: ctr must grow, so chain the opens
    this._opening = (this._opening || Promise.resolve()).then(async () => {
      let msg;
      try {
        msg = await this.recv_.open(bytes);
      } catch (e) {
        this.close(`protocol error from the server: ${e.message}`);
        return;
      }
      msg.bytes = bytes.length;
      msg.arrivedMs = arrivedMs;
      this._count(this.bytesReceived, msg.kind, bytes.length);
      try {
        this.onMessage(msg);
      } catch (e) {
        this.close(`client error handling ${msg.kind}: ${e.message}`);
      }
    });
  }

  _onWsClose(ev) {
    const why = ev.code === 1000 ? "the server closed the session"
      : `the connection to ${this.url} was lost (code ${ev.code}${ev.reason ? ": " + ev.reason : ""}; server gone?)`;
    if (!this._closed) this._closed = why;
    for (const w of this._waiters.splice(0)) w.reject(new Error(why));
    if (this._sealedMode) this.onClose(this._closed);  // during the handshake: connect() throws
  }

  close(reason = "closed by the client") {
    if (this._closed) return;
    this._closed = reason;
    try {
      if (this._sealedMode && this.ws.readyState === WebSocket.OPEN) {
        this.send("bye").finally(() => this.ws.close(1000));
      } else if (this.ws) {
        this.ws.close(1000);
      }
    } catch { /* already closed */ }
    this.onClose(reason);
  }
}
