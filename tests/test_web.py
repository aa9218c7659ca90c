"""The browser client (icbtool/web) in Debian's headless chromium, driven by Playwright.

One server (icbtool.net.Server with ``web=True``, the Cornell box) serves the page and the
protocol on one port; the page is opened at :func:`icbtool.net.web.page_url` and driven through
its test hooks (``window.icb``, ``window.icbModules``). Checked: the protocol's test vectors
(docs/protocol.md section 10) and kinds table in JavaScript, codec and LPM decoding equal to the
Python implementation, handshake + every LPM level + frames without console errors, the wrong
token's error on the page, the WebGL2 G-buffers and DL against icbtool.raster, final frames
against the Python client's (SSIM), the onnxruntime-web generator against onnxruntime.

Every wait is bounded (Playwright timeouts, client timeouts); nothing asserts a wall-clock time.
Needs the bundle (``make web``) and chromium (``make install`` installs both): a missing one
FAILS with the fix in the message.
"""

from __future__ import annotations

import base64
import json
import os
import re
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("websockets")
pytest.importorskip("cryptography")
pytest.importorskip("zstandard")

from icbtool import metrics, raster, system  # noqa: E402
from icbtool import scene as sc  # noqa: E402
from icbtool.net import codec, protocol, web  # noqa: E402
from icbtool.net.server import Server, ServerConfig  # noqa: E402

pytestmark = [pytest.mark.web, pytest.mark.network, pytest.mark.gl]

TOKEN = "web-test-token-0123456789abcdef-0123456789abcdef"
SIZE = 128  # client image (small: SwiftShader renders on the CPU)
CLOUD = system.CloudConfig(spp=4, denoise=False, max_depth=3)
T_MS = 120_000  # every browser wait
REPO = Path(__file__).resolve().parent.parent

#: Tolerances of the browser's WRT-buffer against icbtool.raster (same camera, Cornell box,
#: 128 x 128). The browser rasterizes forward (perspective-correct interpolation), icbtool
#: resolves exact ray-plane barycentrics; its shadow maps are 24-bit (icbtool: 32-bit float)
#: and tiled in an atlas. Silhouette pixels may see a different face: counted, not compared.
TOL = {
    "mask_agree": 0.995,  # fraction of pixels with the same coverage
    "depth_rel_p99": 2e-3,  # relative view-depth error, 99th percentile
    "normal_deg_p99": 0.5,  # angle between shading normals, 99th percentile
    "albedo_off_frac": 0.01,  # pixels whose albedo differs by > 1e-3
    "dl_rel_mean": 0.03,  # |DL difference| mean / DL mean
    "dl_p99": 0.05,  # |DL difference| 99th percentile (the DL mean is ~0.03)
    "ssim_final": 0.95,  # final frames vs the Python client's (display scale, valid padding)
    "onnx_max_abs": 1e-4,  # generator output (tanh range [-1, 1]) vs onnxruntime in Python
    "model_rel": 1e-5,  # served model's GI, same buffers: |browser - Python| / max |Python GI|
}


def _need_browser() -> None:
    try:
        web.check_bundle()
    except web.WebBundleMissing as e:
        pytest.fail(str(e))
    if not Path(web.CHROMIUM).is_file():
        pytest.fail(f"{web.CHROMIUM} is missing: `make install` installs Debian's chromium")
    try:
        import playwright  # noqa: F401
    except ImportError:
        pytest.fail("playwright is missing: `make install` (requirements.lock) installs it")


@pytest.fixture(scope="module")
def scene():
    return sc.PROCEDURAL["cornell_box"]()


@pytest.fixture(scope="module")
def server(scene, tmp_path_factory):
    _need_browser()
    srv = Server(scene, tmp_path_factory.mktemp("store"), TOKEN, ServerConfig(web=True), CLOUD)
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def browser():
    _need_browser()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(
            executable_path=web.CHROMIUM, args=list(web.HEADLESS_CHROMIUM_ARGS), headless=True
        )
        yield b
        b.close()


class Page:
    """A page of the client with its console messages and page errors collected."""

    def __init__(self, browser, url: str) -> None:
        # bypass_csp: Playwright's polling predicates are evaluated strings, which the page's
        # Content-Security-Policy (no 'unsafe-eval') would refuse
        self.page = browser.new_page(viewport={"width": 560, "height": 720}, bypass_csp=True)
        self.page.set_default_timeout(T_MS)
        self.console: list[tuple[str, str]] = []
        self.page.on("console", lambda m: self.console.append((m.type, m.text)))
        self.page.on("pageerror", lambda e: self.console.append(("pageerror", str(e))))
        self.page.goto(url)

    def js(self, expr: str, arg=None):
        return self.page.evaluate(expr, arg)

    def errors(self) -> list[str]:
        return [f"{k}: {t}" for k, t in self.console if k in ("error", "pageerror")]

    def ready(self) -> None:
        self.page.wait_for_function("window.icb && window.icb.ready")
        self.js("window.icb.ready")

    def read(self, name: str) -> np.ndarray:
        b = base64.b64decode(self.js("(n) => window.icb.read(n)", name))
        return np.frombuffer(b, np.float32).reshape(SIZE, SIZE, 4)

    def close(self) -> None:
        self.page.close()


def _open(browser, server, token: str = TOKEN, extra: str = "&test=1") -> Page:
    size = "" if "size=" in extra else f"&size={SIZE}"
    return Page(browser, web.page_url(server.url, token) + f"{size}{extra}")


@pytest.fixture
def page(browser, server):
    p = _open(browser, server)
    p.ready()
    yield p
    p.close()


def _vectors() -> dict:
    text = (REPO / "docs" / "protocol.md").read_text()
    m = re.search(r"<!-- BEGIN TEST VECTORS -->\s*```json\n(.*?)```", text, re.S)
    assert m, "docs/protocol.md has no test vectors block"
    return json.loads(m.group(1))


# ---------------------------------------------------------------- the page and its server
def test_page_files_are_served_with_isolation_headers_and_nothing_else(server):
    base = f"http://127.0.0.1:{server.port}"
    with urllib.request.urlopen(base + "/", timeout=30) as r:
        assert r.status == 200
        assert b"bundle/app.js" in r.read()
        assert r.headers["Cross-Origin-Opener-Policy"] == "same-origin"
        assert r.headers["Cross-Origin-Embedder-Policy"] == "require-corp"
        assert "script-src 'self'" in r.headers["Content-Security-Policy"]
    with urllib.request.urlopen(base + "/bundle/ort-wasm-simd-threaded.wasm", timeout=30) as r:
        assert r.headers["Content-Type"] == "application/wasm"
        assert r.read(4) == b"\0asm"
    for bad in ("/../setup.cfg", "/bundle/../../net/web.py", "/icbtool/net/web.py", "/x"):
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(base + bad, timeout=30)
        assert e.value.code == 404, bad


def test_page_url_keeps_the_token_in_the_fragment():
    u = web.page_url("ws://127.0.0.1:8765", "a b/c#d")
    assert u == "http://127.0.0.1:8765/#token=a%20b%2Fc%23d"
    with pytest.raises(ValueError, match="not a ws"):
        web.page_url("http://x", "t")


def test_protocol_test_vectors_and_kinds_in_javascript(page):
    v = _vectors()
    got = page.js(
        """async (v) => {
      const P = window.icbModules.protocol;
      const h = P.unhex, b64u = (b) => P.b64(b).replace(/\\+/g, "-").replace(/\\//g, "_")
                                               .replace(/=+$/, "");
      const priv = await crypto.subtle.importKey("jwk", {kty: "OKP", crv: "X25519",
          d: b64u(h(v.client_private)), x: b64u(h(v.client_pub))}, {name: "X25519"}, true,
          ["deriveBits"]);
      const tr = P.transcript(h(v.client_pub), h(v.client_nonce), h(v.server_pub),
                              h(v.server_nonce), v.session);
      const shared = await P.x25519Shared(priv, h(v.server_pub));
      const keys = await P.sessionKeyBytes(shared, v.token, tr);
      const ch = await P.Channel.create(keys.c2s, P.CLIENT_TO_SERVER);
      const m = v.first_client_message;
      const frame = await ch.seal(m.kind, m.fields);
      // and the server's direction: open what a server with key_s2c seals
      const s = await P.Channel.create(keys.s2c, P.SERVER_TO_CLIENT);
      const r = await P.Channel.create(keys.s2c, P.SERVER_TO_CLIENT);
      const opened = await r.open(await s.seal("lpm_done", {level: 3}));
      let replay = null;
      try { await r.open(await new P.Channel(s.key, P.SERVER_TO_CLIENT).seal("bye")); }
      catch (e) { replay = e.code; }
      return {transcript: P.hex(tr), shared_secret: P.hex(shared),
              auth_key: P.hex(keys.auth), mac: P.hex(await P.authMac(keys.auth, tr)),
              key_c2s: P.hex(keys.c2s),
              key_s2c: P.hex(keys.s2c), frame: P.hex(frame), opened, replay,
              kinds: P.KINDS, errors: P.ERROR_CODES};
    }""",
        v,
    )
    for k in ("transcript", "shared_secret", "auth_key", "mac", "key_c2s", "key_s2c"):
        assert got[k] == v[k], k
    assert got["frame"] == v["first_client_message"]["frame"]
    assert got["opened"]["kind"] == "lpm_done" and got["opened"]["fields"] == {"level": 3}
    assert got["replay"] == "replay"
    # the kinds table mirrors icbtool.net.protocol.KINDS field by field
    assert set(got["kinds"]) == set(protocol.KINDS)
    for kind, spec in protocol.KINDS.items():
        js = got["kinds"][kind]
        assert (js["sender"], js["sealed"], js["payload"]) == (
            spec.sender,
            spec.sealed,
            spec.payload is not None,
        ), kind
        want = {
            f.name: [f.type, f.required, f.nullable]
            + ([f.length] if f.length and f.type in ("base64", "hex") else [])
            for f in spec.fields
        }
        assert js["fields"] == want, kind
    assert sorted(got["errors"]) == sorted(protocol.ERROR_CODES)
    assert not page.errors()


def test_client_model_vectors_in_javascript(page):
    """docs/protocol.md section 10's client-model vectors through generator.js's rules."""
    from test_net_protocol import client_model_vectors

    v = client_model_vectors()
    got = page.js(
        """(v) => {
          const G = window.icbModules.generator, enc = {};
          for (const [name, x] of Object.entries(v.inputs)) {
            enc[name] = x.map((val, c) => Math.fround(G.mapRule(name, c, v.encoding)(val)));
          }
          return {encoded: enc, decoded: v.outputs.map((y) => G.decodeOutput(y, v.encoding))};
        }""",
        v,
    )
    for name, want in v["encoded"].items():
        np.testing.assert_allclose(got["encoded"][name], want, rtol=0, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(got["decoded"], v["decoded"], rtol=1e-6, atol=0)
    assert not page.errors()


def test_codecs_and_lpm_chunks_decode_like_python(page, scene):
    rng = np.random.default_rng(3)
    gi = (rng.gamma(1.0, 0.3, (12, 17, 3)) * np.array([1, 10, 1000])).astype(np.float32)
    gi[0, 0] = [0.0, 65504.0 * 4, 1e-7]  # zero, beyond float16, subnormal
    depth = rng.uniform(0.5, 9.0, (12, 17, 1)).astype(np.float32)
    depth[2:4, 5:9] = np.inf
    depth[0, :3] = 0.0
    every_code = codec.log_values(np.arange(65536, dtype=np.uint16)).reshape(256, 256, 1)
    cases = []
    for name in ("f16m7-diff-zstd", "f16-diff-zstd", "f16-zstd", "f32-zstd", "log-u16-png"):
        for a in (gi, depth):
            data = codec.encode(a, name)
            cases.append((name, a, base64.b64encode(data).decode()))
    cases.append(
        (
            "log-u16-png",
            every_code,
            base64.b64encode(codec.encode(every_code, "log-u16-png")).decode(),
        )
    )
    grey = depth[..., 0]  # a [H, W] part: a grey PNG too
    cases.append(
        ("log-u16-png", grey, base64.b64encode(codec.encode(grey, "log-u16-png")).decode())
    )
    for a in (gi, rng.uniform(0, 1e-30, (5, 7, 3)).astype(np.float32)):  # and tiny values: E = 0
        cases.append(("rgbe-png", a, base64.b64encode(codec.encode(a, "rgbe-png")).decode()))
    out = page.js(
        """(cases) => Promise.all(cases.map(async ([name, shape, data]) => {
          const a = await window.icbModules.codec.decodePart(
              window.icbModules.protocol.unb64(data), name, shape);
          const u8 = new Uint8Array(a.buffer, a.byteOffset, a.byteLength);
          return window.icbModules.protocol.b64(u8);
        }))""",
        [[n, list(a.shape), d] for n, a, d in cases],
    )
    for (name, a, data), b in zip(cases, out, strict=True):
        got = np.frombuffer(base64.b64decode(b), np.float32).reshape(a.shape)
        want = codec.decode(base64.b64decode(data), name, a.shape)
        np.testing.assert_array_equal(got, want, err_msg=name)  # bit for bit, inf included
    # every one of the 65536 log-u16-png codes decodes to Python's float32 (0 and inf too)
    assert np.isinf(every_code).sum() == 1 and (every_code == 0).sum() == 1
    # a corrupt PNG is "malformed", naming the codec
    png = bytearray(codec.encode(gi, "rgbe-png"))
    png[45] ^= 0xFF  # inside IDAT: its CRC-32 no longer matches
    err = page.js(
        """async (d) => { try { await window.icbModules.codec.decodePart(
              window.icbModules.protocol.unb64(d), "rgbe-png", [12, 17, 3]); return null; }
            catch (e) { return [e.code, e.message]; } }""",
        base64.b64encode(bytes(png)).decode(),
    )
    assert err is not None and err[0] == "malformed" and "rgbe-png" in err[1], err
    # LPM: a level's chunks assemble to the Python arrays; a corrupt one names the chunk
    from icbtool.net import mesh_stream

    ms = mesh_stream.MeshStream(scene, lpm=True, send_full=False, max_chunk_bytes=2**20)
    level = ms.levels[0]
    pieces = ms.pieces(level, 500)  # small pieces: files arrive in several messages
    assert len(pieces) > len(level.chunks)
    msgs = [
        {"fields": {"level": 0, "index": i, "name": name}, "data": base64.b64encode(b).decode()}
        for i, (name, _, b, _) in enumerate(pieces)
    ]
    res = page.js(
        """(msgs) => {
          const M = window.icbModules, c = new M.lpm.LevelCollector();
          for (const m of msgs) c.add(m.fields, M.protocol.unb64(m.data));
          const lv = c.level(0);
          const enc = (a) => M.protocol.b64(new Uint8Array(a.buffer, a.byteOffset, a.byteLength));
          const bad = new M.lpm.LevelCollector();
          for (const m of msgs) {
            const d = M.protocol.unb64(m.data);
            if (m.fields.name.includes("normals")) d[d.length - 1] ^= 1;
            bad.add(m.fields, d);
          }
          let err = null;
          try { bad.level(0); } catch (e) { err = e.message; }
          return {vertices: enc(lv.arrays.vertices), faces: enc(lv.arrays.faces),
                  n_faces: lv.manifest.n_faces, err};
        }""",
        msgs,
    )
    ref = mesh_stream.assemble(list(level.chunks), ms.base)
    v = np.frombuffer(base64.b64decode(res["vertices"]), np.float32).reshape(-1, 3)
    f = np.frombuffer(base64.b64decode(res["faces"]), np.int32).reshape(-1, 3)
    np.testing.assert_array_equal(v, ref.vertices)
    np.testing.assert_array_equal(f, ref.faces)
    assert res["n_faces"] == len(ref.faces)
    assert "normals" in res["err"] and "CRC-32 mismatch" in res["err"]


# ---------------------------------------------------------------- the client at work
def test_handshake_every_level_and_frames_without_console_errors(page, server, scene):
    levels = [lv["level"] for lv in server.scene_info()["lpm"]["levels"]]
    page.js("window.icb.client.requestFinerLevels()")  # (else: after the first frame)
    page.page.wait_for_function(
        "(n) => window.icb.state.levels.size === n", arg=len(levels), timeout=T_MS
    )
    assert sorted(page.js("[...window.icb.state.levels]")) == levels
    assert page.js("window.icb.state.level") == max(levels)
    path = scene.paths["test"]
    stats = [
        page.js("(t) => window.icb.client.step({t, latency: 0.1}).then(s => ({...s}))", float(t))
        for t in np.linspace(path.times[0], path.times[-1], 3)
    ]
    for s in stats:
        assert s["level"] == max(levels)
        assert s["bytes"] > 0 and 0 <= s["hole_ratio"] < 0.5
        for k in ("raster_ms", "request_ms", "decode_ms", "warp_ms", "transfer_ms", "wait_ms"):
            assert s[k] >= 0, k
        # the request's parts: network + server up to the reply's arrival, then the wait for
        # the main thread, then decoding (the page's stalls are not the network's)
        parts = s["transfer_ms"] + s["server_ms"] + s["wait_ms"] + s["decode_ms"]
        assert parts == pytest.approx(s["request_ms"], abs=0.5) or s["transfer_ms"] == 0
    # the page's path interpolation is icbtool.camera.CameraPath's
    intr = path.intrinsics.resized(SIZE, SIZE)
    for s in stats:
        want = path.with_intrinsics(intr).camera_at(s["t"])
        np.testing.assert_allclose(s["camera"]["world_from_cam"], want.world_from_cam, atol=1e-9)
    final = page.read("final")
    assert np.isfinite(final).all() and final[..., :3].mean() > 0
    assert "LPM level" in page.js("document.getElementById('overlay').textContent")
    assert page.js("document.getElementById('error').hidden")
    assert not page.errors(), page.errors()


def test_opened_page_walks_the_test_path_by_itself(browser, server):
    """The URL as `icbtool serve --web` prints it (no test hooks): the page plays the path."""
    shot = os.environ.get("ICBTOOL_WEB_SCREENSHOT")  # `make docs/images/web.png`
    p = _open(browser, server, extra="&size=256" if shot else "")
    try:
        p.page.wait_for_function(
            "window.icb && window.icb.state.frames >= 6 && window.icb.client.renderer.refs.length"
        )
        st = p.js(
            "({t: window.icb.state.pathT, hits: window.icb.state.hits,"
            " misses: window.icb.state.misses, playing: window.icb.state.playing})"
        )
        assert st["playing"] and st["t"] > 0 and st["hits"] + st["misses"] >= 1
        assert "#token" not in p.page.url  # the token is taken out of the address bar
        assert not p.errors(), p.errors()
        if shot:  # a fixed view of the path, its GI settled
            p.js("""() => { const c = window.icb.client, s = window.icb.state;
                      s.playing = false;
                      c.controls.pose = c.path.poseAt(0.2 * c.path.duration); }""")
            p.page.wait_for_function("window.icb.state.frames >= 40")
            p.page.locator("main").screenshot(path=shot)
    finally:
        p.close()


def test_serve_web_prints_one_url_and_never_logs_the_token(tmp_path):
    import subprocess
    import sys

    token = "cli-secret-7f3a-0123456789abcdef-0123456789abcdef"
    cmd = [
        sys.executable,
        "-m",
        "icbtool",
        "serve",
        "cornell_box",
        "--store",
        str(tmp_path),
        "--port",
        "0",
        "--token",
        token,
        "--no-denoise",
        "--web",
        "--log-level",
        "DEBUG",
    ]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines = []
        for _ in range(50):
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.strip())
            if line.startswith("web client:"):
                break
        url = lines[-1].removeprefix("web client: ")
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/#token=" + token, url), lines
        with urllib.request.urlopen(url.split("#")[0], timeout=30) as r:
            assert r.status == 200
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=60)
    assert token not in err and token not in out  # only the URL line holds it


def test_wrong_token_is_a_readable_error_and_no_scene_data(browser, server):
    p = _open(browser, server, token="not-the-token")
    try:
        p.page.wait_for_function("!document.getElementById('error').hidden")
        p.page.wait_for_timeout(500)  # a later message would replace the first
        msg = p.js("document.getElementById('error').textContent")
        assert "refused the token" in msg, msg
        assert p.js("window.icb.state.levels.size") == 0
        assert p.js("window.icb.client.session.bytesReceived.lpm_chunk || 0") == 0
    finally:
        p.close()


def test_server_gone_is_a_readable_error(browser, scene, tmp_path):
    srv = Server(scene, tmp_path, TOKEN, ServerConfig(web=True), CLOUD).start()
    p = _open(browser, srv)
    try:
        p.ready()
        srv.stop()
        p.page.wait_for_function("!document.getElementById('error').hidden")
        msg = p.js("document.getElementById('error').textContent")
        assert "server" in msg and ("lost" in msg or "closed" in msg), msg
    finally:
        p.close()
        srv.stop()


def _wrt(scene, cam):
    with raster.Rasterizer(scene) as rz:
        return rz.render(cam)


def test_gbuffers_and_direct_light_equal_icbtool_raster(page, scene):
    path = scene.paths["test"]
    for t in (0.0, 0.6 * path.times[-1]):
        cam = path.with_intrinsics(path.intrinsics.resized(SIZE, SIZE)).camera_at(float(t))
        page.js("(c) => window.icb.renderWRT(c)", protocol.camera_to_json(cam))
        al, nr, po, dl = (page.read(n) for n in ("albedo", "normal", "position", "dl"))
        ref = _wrt(scene, cam)
        m = ref.mask[..., 0] > 0.5
        assert np.mean((po[..., 3] > 0) == m) >= TOL["mask_agree"]
        both = m & (po[..., 3] > 0)
        rel = np.abs(po[..., 3][both] - ref.depth[..., 0][both]) / ref.depth[..., 0][both]
        assert np.percentile(rel, 99) <= TOL["depth_rel_p99"]
        cos = np.clip((nr[..., :3] * ref.normal_world).sum(-1), -1, 1)
        assert np.percentile(np.degrees(np.arccos(cos))[both], 99) <= TOL["normal_deg_p99"]
        off = np.abs(al[..., :3] - ref.albedo).max(-1) > 1e-3
        assert off[both].mean() <= TOL["albedo_off_frac"]
        d = np.abs(dl[..., :3] - ref.dl)[both]
        assert d.mean() / ref.dl[both].mean() <= TOL["dl_rel_mean"]
        assert np.percentile(d, 99) <= TOL["dl_p99"]
        # the shadows are there: DL spans shadowed and lit floor alike in both
        assert abs(np.percentile(dl[..., :3][both], 10) - np.percentile(ref.dl[both], 10)) < 0.01
    assert not page.errors()


def test_final_frames_match_the_python_client(page, server, scene):
    from icbtool.net.client import NetClientConfig, NetworkSource

    path = scene.paths["test"]
    intr = path.intrinsics.resized(SIZE, SIZE)
    p = path.with_intrinsics(intr)
    times = np.linspace(path.times[0], path.times[-1], 4)
    page.page.wait_for_function(
        "(window.icb.client.requestFinerLevels(), "
        "window.icb.state.level === Math.max(...window.icb.client.levelsOffered))"
    )
    browser_final = []
    for k, t in enumerate(times):
        page.js("(a) => window.icb.client.step({t: a[0], latency: 0.1, seq: a[1]})", [float(t), k])
        browser_final.append(page.read("final")[..., :3].copy())
    with NetworkSource(server.url, TOKEN, NetClientConfig(timeout_s=T_MS / 1e3)) as src:
        src.request_lpm()
        src.wait_level(max(lv["level"] for lv in src.levels))
        with system.Client(src.best_scene()[1], src) as client:
            for k, t in enumerate(times):
                t_req = max(float(t) - 0.1, float(path.times[0]))
                v_t, v_r = p.velocity_cam(t_req)
                req = system.GIRequest(p.camera_at(t_req), v_t, v_r, t_req, seq=k)
                fr = client.frame(p.camera_at(float(t)), req)
                s = metrics.ssim(browser_final[k], fr.final)
                assert s >= TOL["ssim_final"], (k, s)
    assert not page.errors()


def test_onnx_generator_in_the_browser_equals_onnxruntime(page, tmp_path):
    pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    import torch

    from icbtool.gan import Generator
    from icbtool.gan.data import InputEncoding
    from icbtool.gan.models import GeneratorConfig, UNetGenerator

    torch.manual_seed(0)
    enc = InputEncoding(inputs=("dl", "albedo", "normal_world", "depth"))
    gen = Generator(UNetGenerator(GeneratorConfig(in_channels=enc.n_channels, base=8)), enc)
    path = gen.export_onnx(tmp_path / "g.onnx", 64, 64)
    x = np.random.default_rng(0).uniform(-1, 1, (1, enc.n_channels, 64, 64)).astype(np.float32)
    want = ort.InferenceSession(str(path)).run(None, {"maps": x})[0]
    got = page.js(
        """async (a) => {
          const M = window.icbModules;
          const g = await M.OnnxGenerator.load(M.protocol.unb64(a.model));
          const x = new Float32Array(M.protocol.unb64(a.x).buffer);
          const y = await g.run(x, a.c, 64, 64);
          const u8 = new Uint8Array(y.data.buffer, y.data.byteOffset, y.data.byteLength);
          return {y: M.protocol.b64(u8), dims: y.dims, threads: g.threads,
                  isolated: crossOriginIsolated};
        }""",
        {
            "model": base64.b64encode(path.read_bytes()).decode(),
            "x": base64.b64encode(x.tobytes()).decode(),
            "c": enc.n_channels,
        },
    )
    y = np.frombuffer(base64.b64decode(got["y"]), np.float32).reshape(got["dims"])
    assert y.shape == want.shape
    assert np.abs(y - want).max() <= TOL["onnx_max_abs"]
    assert got["isolated"] is True  # COOP/COEP: WebAssembly threads allowed
    assert not page.errors()


# ---------------------------------------------------------------- the served client model
@pytest.fixture(scope="module", params=["gan", "radiance"])
def model_server(request, scene, tmp_path_factory):
    """A server offering a client model: a GAN run and a radiance run (random weights), the
    parameter's kind with the better recorded test SSIM."""
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from client_models import write_gan_run, write_radiance_run

    _need_browser()
    tmp = tmp_path_factory.mktemp("models")
    b = np.asarray(scene.bounds)
    win = request.param == "gan"
    gan = write_gan_run(tmp / "gan", b, ssim=0.9 if win else 0.8)
    rad = write_radiance_run(tmp / "radiance", b, ssim=0.8 if win else 0.9)
    cfg = ServerConfig(web=True, models=(str(gan), str(rad)), chunk_bytes=65536)
    srv = Server(scene, tmp / "store", TOKEN, cfg, CLOUD)
    assert srv.model.candidate.kind == request.param
    srv.start()
    yield srv
    srv.stop()


def test_served_model_in_the_browser_equals_the_python_client(browser, model_server, scene):
    """The page downloads the offered model (in chunks, SHA-256 checked) and runs it in
    onnxruntime-web: on the same buffers its GI equals the Python client's (onnxruntime), and
    its final frames along the test path match the Python client's with the served model."""
    from icbtool.net.client import NetClientConfig, NetworkSource
    from icbtool.net.client_model import ServedModel

    srv = model_server
    kind = srv.model.candidate.kind
    info = srv.model.scene_info()
    assert info["chunks"] >= 2 or kind == "radiance"
    page = _open(browser, srv)
    try:
        page.ready()
        page.page.wait_for_function("window.icb.state.model !== null")
        assert page.js("window.icb.state.model.kind") == kind
        # the same buffers (icbtool.raster's) through both: the encoding and the runtime
        path = scene.paths["test"]
        p = path.with_intrinsics(path.intrinsics.resized(SIZE, SIZE))
        wrt = _wrt(scene, p.camera_at(0.4))
        want = ServedModel(srv.model.data, info).generate(wrt)
        maps = {
            n: base64.b64encode(np.ascontiguousarray(getattr(wrt, n), np.float32)).decode()
            for n in ("dl", "albedo", "normal_world", "normal_view", "depth", "position", "mask")
        }
        got = page.js(
            """async (a) => {
              const P = window.icbModules.protocol, maps = {};
              for (const [k, v] of Object.entries(a.maps)) {
                maps[k] = new Float32Array(P.unb64(v).buffer);
              }
              const r = await window.icb.state.model.generate(maps, a.h, a.w);
              return P.b64(new Uint8Array(r.gi.buffer));
            }""",
            {"maps": maps, "h": SIZE, "w": SIZE},
        )
        gi = np.frombuffer(base64.b64decode(got), np.float32).reshape(SIZE, SIZE, 3)
        assert want.std() > 0
        rel = np.abs(gi - want).max() / np.abs(want).max()
        assert rel <= TOL["model_rel"], rel
        # frames along the path, the page's own buffers: against the Python client's
        page.page.wait_for_function(
            "(window.icb.client.requestFinerLevels(), "
            "window.icb.state.level === Math.max(...window.icb.client.levelsOffered))"
        )
        times = np.linspace(path.times[0], path.times[-1], 3)
        browser_final = []
        for k, t in enumerate(times):
            step = "(a) => window.icb.client.step({t: a[0], latency: 0.1, seq: a[1]})"
            st = page.js(step + ".then(s => ({...s}))", [float(t), k])
            assert st["bytes"] == 0 and st["generate_ms"] > 0  # made here, nothing asked
            browser_final.append(page.read("final")[..., :3].copy())
        assert page.js("window.icb.state.generated") == len(times)
        assert page.js("window.icb.client.session.bytesSent.gi_request || 0") == 0
        with NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=T_MS / 1e3)) as src:
            src.request_lpm()
            src.wait_level(max(lv["level"] for lv in src.levels))
            src.request_generator()
            assert src.wait_generator(T_MS / 1e3)
            with system.Client(src.best_scene()[1], src) as client:
                for k, t in enumerate(times):
                    req = system.GIRequest(p.camera_at(float(t)), time_s=float(t), seq=k)
                    fr = client.frame(p.camera_at(float(t)), req)
                    assert fr.reply.timings_ms.get("generate", 0) > 0
                    s = metrics.ssim(browser_final[k], fr.final)
                    assert s >= TOL["ssim_final"], (kind, k, s)
            assert src.remote == 0
        assert not page.errors(), page.errors()
    finally:
        page.close()
    # the page as opened by a user: its own loop asks for GI until the model is here, then
    # generates every frame and asks for none
    auto = _open(browser, srv, extra="")
    try:
        auto.page.wait_for_function("window.icb && window.icb.state.generated >= 1")
        asked = "window.icb.client.session.bytesSent.gi_request || 0"
        before = auto.js(asked)
        auto.page.wait_for_function("window.icb.state.generated >= 4")
        assert auto.js(asked) == before
        assert "client model: " + kind in auto.js("document.getElementById('overlay').textContent")
        assert not auto.errors(), auto.errors()
    finally:
        auto.close()


@pytest.mark.parametrize("gi_codec", ["log-u16-png", "rgbe-png"])
def test_png_codec_replies_make_frames(browser, server, gi_codec):
    p = _open(browser, server, extra=f"&test=1&codec={gi_codec}")
    try:
        p.ready()
        st = p.js("window.icb.client.step({t: 0.5, latency: 0.1}).then(s => ({...s}))")
        assert st["bytes"] > 0 and st["decode_ms"] >= 0
        final = p.read("final")
        assert np.isfinite(final).all() and final[..., :3].mean() > 0
        assert not p.errors(), p.errors()
    finally:
        p.close()


@pytest.mark.sponza
@pytest.mark.slow
def test_sponza_textures_sun_and_sky_in_the_browser(browser, sponza_path, tmp_path):
    """The real scene: 16.7k-triangle LPM level, 17 textures, sun shadows, gradient sky."""
    from icbtool.net.client import NetClientConfig, NetworkSource
    from icbtool.scene.load import load

    scene = load(REPO / "data" / "scenes" / "sponza.toml")
    cloud = system.CloudConfig(spp=1, denoise=False, max_depth=2)
    with Server(scene, tmp_path, TOKEN, ServerConfig(web=True), cloud) as srv:
        with NetworkSource(srv.url, TOKEN, NetClientConfig(timeout_s=T_MS / 1e3)) as src:
            src.request_lpm()
            src.wait_level(max(lv["level"] for lv in src.levels))
            level, lscene = src.best_scene()
        p = _open(browser, srv)
        try:
            p.ready()
            p.page.wait_for_function(
                "(window.icb.client.requestFinerLevels(), "
                "window.icb.state.level === Math.max(...window.icb.client.levelsOffered))"
            )
            assert p.js("window.icb.state.level") == level
            path = scene.paths["test"]
            for t in (0.0, 0.5 * path.times[-1]):
                cam = path.with_intrinsics(path.intrinsics.resized(SIZE, SIZE)).camera_at(t)
                p.js("(c) => window.icb.renderWRT(c)", protocol.camera_to_json(cam))
                al, nr, po, dl = (p.read(n) for n in ("albedo", "normal", "position", "dl"))
                ref = _wrt(lscene, cam)
                m = ref.mask[..., 0] > 0.5
                assert np.mean((po[..., 3] > 0) == m) >= TOL["mask_agree"]
                both = m & (po[..., 3] > 0)
                z = ref.depth[..., 0][both]
                assert np.percentile(np.abs(po[..., 3][both] - z) / z, 99) <= 3e-3
                cos = np.clip((nr[..., :3] * ref.normal_world).sum(-1), -1, 1)
                assert np.percentile(np.degrees(np.arccos(cos))[both], 99) <= 3.0
                # textures are resized in the browser (sRGB, the image decoder's filter) and by
                # icbtool (linear light, area filter): texel detail differs a little
                assert np.abs(al[..., :3] - ref.albedo)[both].mean() <= 0.02
                d = np.abs(dl[..., :3] - ref.dl)[both]
                assert d.mean() / ref.dl[both].mean() <= 0.05
                sky = ~m & (po[..., 3] == 0)
                if sky.any():  # the gradient sky on the background, as icbtool.raster's
                    np.testing.assert_allclose(dl[..., :3][sky], ref.dl[sky], atol=2e-3)
            s = p.js("window.icb.client.step({t: 1.0, latency: 0.1}).then(s => s.hole_ratio)")
            assert 0 <= s < 0.5
            assert not p.errors(), p.errors()
        finally:
            p.close()
