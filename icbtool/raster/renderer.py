"""The OpenGL rasterizer: float G-buffers and shadowed direct lighting, deferred.

Design (see also the shaders in ``shaders/``):

* Visibility pass: the whole merged scene is one vertex array (positions only) drawn with a few
  ``glDrawElements`` (frustum-culled clusters, front to back). The fragment shader writes only
  +-(face index + 1) (sign: facing) into a ``GL_R32F`` target. On a software rasterizer
  (llvmpipe) fragments are shaded in whole 4x4 blocks and Sponza's triangles cover a few pixels
  each, so any real work per fragment would mostly be wasted; here the per-triangle cost is
  vertex processing, setup and binning (single-threaded in llvmpipe) and nothing else.
* Resolve pass: one full-screen triangle computes every requested target of every pixel
  exactly once (MRT, ``GL_RGBA32F``): the camera ray through the pixel centre meets the face's
  plane, and its barycentrics interpolate the vertex position, shading normal and uv (the same
  perspective-correct interpolation the rasterizer does); the texture footprint comes from the
  rays through the neighbouring pixels (``textureGrad``). Per-face data (vertex indices,
  geometric normal, material) and per-vertex data sit in texture buffers; per-material data
  (albedo factor, texture layer, emission) in another; textures in one mipmapped
  ``GL_TEXTURE_2D_ARRAY`` (resized to :attr:`RasterConfig.texture_size`, stored as
  ``GL_SRGB8_ALPHA8`` of the linear texture re-encoded, so GL decodes to linear before
  filtering). DL (lights, shadow lookups, emission, sky on the background) is computed there
  too, only when requested. Packing: depth is the position target's alpha; view normals are the
  world normals rotated on the CPU; the mask is any target's alpha.
* Readback: ``glReadPixels(GL_RGBA, GL_FLOAT)`` per target, flipped upside down into icbtool's
  pixel convention (GL's window origin is bottom-left; :meth:`Camera.gl_projection_matrix`
  makes the fragment centres icbtool's pixel centres).
* Shadows: one depth map per directional light (orthographic, fitted to the scene bounds), six per
  point light (cube faces), one per spot light, one per stratified sample point of each area light
  (perspective); slope-scaled depth bias, a normal offset (sharp lights) or an offset along the
  ray (area-light samples: it does not displace soft shadows); bilinear PCF; penumbra pixels of
  area lights shaded at several points of their footprint. Lights and geometry are
  fixed for a :class:`Rasterizer`, so the shadow maps are rendered on the first frame and reused.
"""

from __future__ import annotations

import ctypes
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from icbtool.raster.config import (
    RasterBuffers,
    RasterConfig,
    check_buffers,
)
from icbtool.raster.context import GLContext, create_context
from icbtool.raster.glossy import has_glossy, pack_bsdfs
from icbtool.raster.shaders import with_defines

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.camera import Camera
    from icbtool.scene import Scene

#: Output targets (colour attachments of the output FBO) and their shader #define names.
_T_ALBEDO, _T_NORMAL, _T_POS, _T_DL = 0, 1, 2, 3
_N_TARGETS = 4
_TARGET_DEFINE = {_T_ALBEDO: "LOC_A", _T_NORMAL: "LOC_N", _T_POS: "LOC_P", _T_DL: "LOC_DL"}
#: Face ids travel as floats in the visibility target: exact below 2^24.
MAX_FACES = 1 << 24
#: Uniform vectors of the resolve shader kept for everything but the lights' arrays.
_UNIFORM_MARGIN = 64
#: Faces per culling cluster (faces are sorted along a Morton curve, then cut into clusters).
CLUSTER_FACES = 1024


def _morton_order(points: np.ndarray) -> np.ndarray:
    """(N,) permutation sorting ``points`` (N, 3) along a Morton (Z-order) curve, 10 bits/axis."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-30) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _provoking(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Give every face a last (provoking) vertex used by no other face as its last vertex.

    Faces keep their cyclic vertex order (so their winding): a face whose last vertex is taken
    is rotated to end with one of its free vertices; if all three are taken, its last vertex is
    duplicated.

    Args:
        faces: (F, 3) vertex indices.
        n_vertices: V.

    Returns:
        (F, 3) int64 faces into the extended vertex list, and (V', ) int64: the original vertex
        of each extended vertex (V' >= V; the first V are the originals).
    """
    claimed = bytearray(n_vertices)
    extra: list[int] = []
    out = faces.tolist()
    for f in out:
        a, b, c = f
        if not claimed[c]:
            claimed[c] = 1
        elif not claimed[a]:
            f[0], f[1], f[2] = b, c, a
            claimed[a] = 1
        elif not claimed[b]:
            f[0], f[1], f[2] = c, a, b
            claimed[b] = 1
        else:
            f[2] = n_vertices + len(extra)
            extra.append(c)
    src = np.concatenate([np.arange(n_vertices), np.asarray(extra, np.int64)])
    return np.asarray(out, np.int64).reshape(-1, 3), src


def _frustum_visible(clip_from_world: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(C,) bool: boxes [lo, hi] (C, 3) not entirely outside one of the 6 clip planes."""
    m = clip_from_world
    planes = np.stack(
        [m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]]
    )
    # the box corner farthest along each plane normal ("positive vertex")
    pv = np.where(planes[None, :, :3] > 0, hi[:, None, :], lo[:, None, :])  # (C, 6, 3)
    dist = (pv * planes[None, :, :3]).sum(-1) + planes[None, :, 3]
    return ~(dist < 0).any(1)


def _rgb(rgba: np.ndarray) -> np.ndarray:
    """(H, W, 3) contiguous float32: the first 3 channels of ``rgba`` (H, W, 4), rows flipped."""
    import cv2

    out = cv2.cvtColor(rgba[::-1], cv2.COLOR_RGBA2RGB)
    return out.reshape(rgba.shape[0], rgba.shape[1], 3)


def _rotate(v: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32: every vector of ``v`` (H, W, 3) multiplied by ``r`` (3, 3)."""
    import cv2

    out = cv2.transform(v, np.asarray(r, np.float64))
    return out.reshape(v.shape).astype(np.float32, copy=False)


class RasterError(RuntimeError):
    """An OpenGL failure inside the rasterizer (shader compile/link, incomplete framebuffer)."""


# --------------------------------------------------------------------------- matrices
def _gl_look(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) OpenGL view matrix (camera looks down -z) at ``eye`` looking along ``forward``."""
    z = -forward / np.linalg.norm(forward)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:  # forward parallel to up: pick another up
        x = np.cross(np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0, 0, 1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = x, y, z
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _perspective(half_deg: float, near: float, far: float) -> np.ndarray:
    f = 1.0 / math.tan(math.radians(half_deg))
    p = np.zeros((4, 4))
    p[0, 0] = p[1, 1] = f
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def _ortho(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Orthographic projection of the GL view box [lo, hi] (x, y, and -z as distance)."""
    p = np.eye(4)
    p[0, 0] = 2.0 / (hi[0] - lo[0])
    p[1, 1] = 2.0 / (hi[1] - lo[1])
    p[2, 2] = -2.0 / (hi[2] - lo[2])
    p[0, 3] = -(hi[0] + lo[0]) / (hi[0] - lo[0])
    p[1, 3] = -(hi[1] + lo[1]) / (hi[1] - lo[1])
    p[2, 3] = -(hi[2] + lo[2]) / (hi[2] - lo[2])
    return p


def _corners(bounds: np.ndarray) -> np.ndarray:
    lo, hi = bounds
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def _bounds_pad(bounds: np.ndarray) -> np.ndarray:
    """Scene bounds grown by 0.1 % of the diagonal (and at least 1e-6) on every side."""
    pad = max(1e-3 * float(np.linalg.norm(bounds[1] - bounds[0])), 1e-6)
    return np.stack([bounds[0] - pad, bounds[1] + pad])


def directional_view(
    direction: np.ndarray, bounds: np.ndarray, res: int
) -> tuple[np.ndarray, float]:
    """Shadow clip-from-world (orthographic, fitted to ``bounds``) and its texel size (world)."""
    b = _bounds_pad(bounds)
    centre = b.mean(0)
    view = _gl_look(centre, np.asarray(direction, np.float64), np.array([0.0, 1.0, 0.0]))
    c = _corners(b) @ view[:3, :3].T + view[:3, 3]
    lo = np.array([c[:, 0].min(), c[:, 1].min(), (-c[:, 2]).min()])
    hi = np.array([c[:, 0].max(), c[:, 1].max(), (-c[:, 2]).max()])
    texel = max(hi[0] - lo[0], hi[1] - lo[1]) / res
    return _ortho(lo, hi) @ view, float(texel)


def perspective_view(
    eye: np.ndarray,
    forward: np.ndarray,
    half_deg: float,
    bounds: np.ndarray,
    res: int,
    up: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Shadow clip-from-world (perspective) and its texel size at light-view depth 1."""
    b = _bounds_pad(bounds)
    far = float(np.linalg.norm(_corners(b) - eye, axis=1).max()) * 1.01 + 1e-6
    near = max(1e-3 * float(np.linalg.norm(b[1] - b[0])), far * 1e-5)
    near = min(near, 0.5 * far)
    up = np.array([0.0, 1.0, 0.0]) if up is None else up
    view = _gl_look(np.asarray(eye, np.float64), np.asarray(forward, np.float64), up)
    texel = 2.0 * math.tan(math.radians(half_deg)) / res
    return _perspective(half_deg, near, far) @ view, float(texel)


def area_polygons(lights: list[Any]) -> np.ndarray:
    """(4 * N, 3) polygon vertices of area lights as the resolve shader takes them: four per
    light, counter-clockwise from the emitting side; a triangle repeats its last vertex."""
    out = []
    for lt in lights:
        v = lt.vertices
        out.append(v if len(v) == 4 else np.concatenate([v, v[-1:]]))
    return np.concatenate(out).astype(np.float64)


_CUBE = [  # (forward, up) of the six point-light faces: +x -x +y -y +z -z
    ((1, 0, 0), (0, 1, 0)),
    ((-1, 0, 0), (0, 1, 0)),
    ((0, 1, 0), (0, 0, 1)),
    ((0, -1, 0), (0, 0, 1)),
    ((0, 0, 1), (0, 1, 0)),
    ((0, 0, -1), (0, 1, 0)),
]


def camera_near_far(
    camera: Camera, bounds: np.ndarray, config: RasterConfig
) -> tuple[float, float]:
    """Near/far planes enclosing the scene bounds for ``camera`` (config values win if set)."""
    b = _bounds_pad(bounds)
    z = (_corners(b) - camera.position) @ camera.forward
    far = float(z.max()) * 1.01 if config.far is None else float(config.far)
    closest = np.clip(camera.position, b[0], b[1])
    dist = float(np.linalg.norm(closest - camera.position))
    if far <= 0:  # the whole scene is behind the camera: any planes will do, nothing is seen
        far = 2.0 * dist + 1.0
    near = max(far * 1e-3, 0.5 * dist) if config.near is None else float(config.near)
    if not near < far:
        raise ValueError(f"camera near plane {near} is not before the far plane {far}")
    return near, far


# --------------------------------------------------------------------------- the rasterizer
class Rasterizer:
    """Renders :class:`RasterBuffers` of one scene for many cameras, reusing GL state and uploads.

    Example:
        >>> with Rasterizer(scene, RasterConfig(backend="osmesa")) as r:  # doctest: +SKIP
        ...     for cam in path:
        ...         buf = r.render(cam, buffers=("dl", "depth"))

    Args:
        scene: the scene (geometry, materials, lights, sky). It must not change while in use.
        config: rendering options.

    Raises:
        GLBackendError: if no OpenGL context can be created (the message says what was tried).
    """

    def __init__(self, scene: Scene, config: RasterConfig | None = None) -> None:
        self.scene = scene
        self.config = RasterConfig() if config is None else config
        if not isinstance(self.config, RasterConfig):
            raise TypeError(f"config must be a RasterConfig, got {type(self.config).__name__}")
        if len(scene.faces) >= MAX_FACES:
            raise ValueError(
                f"scene {scene.name!r} has {len(scene.faces)} triangles; the rasterizer handles "
                f"at most {MAX_FACES - 1}"
            )
        t0 = time.perf_counter()
        self._ctx: GLContext | None = create_context(self.config.backend)
        from OpenGL import GL

        self._gl = GL
        self._programs: dict[tuple, int] = {}
        self._uniform_locs: dict[tuple[int, str], int] = {}
        self._fbo: dict[tuple[int, int], tuple[int, int, int]] = {}
        self._rbos: list[int] = []
        self._staging: dict[int, np.ndarray] = {}
        self._shadow_state: dict[str, Any] | None = None
        self.last_drawn_fraction = 1.0  # faces drawn / all faces in the last frame (culling)
        self._has_tex = scene.has_textures
        self._bounds = scene.bounds  # a property computed from every vertex: once, not per frame
        self._counts = {
            k: len(scene.lights_of(k)) for k in ("directional", "point", "spot", "area")
        }
        try:
            self._check_light_limits()
        except RasterError:
            self.close()
            raise
        self._upload()
        self.setup_ms = 1e3 * (time.perf_counter() - t0)

    # ------------------------------------------------------------------ lifecycle
    @property
    def backend(self) -> str:
        """The OpenGL backend in use ("osmesa" or "egl")."""
        return self._context.backend

    @property
    def _context(self) -> GLContext:
        if self._ctx is None:
            raise RuntimeError("this Rasterizer is closed")
        return self._ctx

    def close(self) -> None:
        """Release the GL context (and with it every GL object). Idempotent."""
        if self._ctx is not None:
            self._ctx.close()
            self._ctx = None

    def __enter__(self) -> Rasterizer:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; use close() or a with block
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown: nothing sensible to do
            pass

    # ------------------------------------------------------------------ GL helpers
    def _compile(self, vert: str, frag: str, defines: dict[str, object]) -> int:
        GL = self._gl
        key = (vert, frag, tuple(sorted(defines.items(), key=lambda kv: kv[0])))
        if key in self._programs:
            return self._programs[key]
        shaders = []
        for name, kind in ((vert, GL.GL_VERTEX_SHADER), (frag, GL.GL_FRAGMENT_SHADER)):
            s = GL.glCreateShader(kind)
            GL.glShaderSource(s, with_defines(name, defines))
            GL.glCompileShader(s)
            if not GL.glGetShaderiv(s, GL.GL_COMPILE_STATUS):
                log = GL.glGetShaderInfoLog(s).decode(errors="replace")
                raise RasterError(f"shader {name} failed to compile ({defines}):\n{log}")
            shaders.append(s)
        prog = GL.glCreateProgram()
        for s in shaders:
            GL.glAttachShader(prog, s)
        GL.glLinkProgram(prog)
        if not GL.glGetProgramiv(prog, GL.GL_LINK_STATUS):
            log = GL.glGetProgramInfoLog(prog).decode(errors="replace")
            raise RasterError(f"program {vert}+{frag} failed to link:\n{log}")
        for s in shaders:
            GL.glDeleteShader(s)
        self._programs[key] = prog
        return prog

    def _loc(self, prog: int, name: str) -> int:
        key = (prog, name)
        if key not in self._uniform_locs:
            self._uniform_locs[key] = self._gl.glGetUniformLocation(prog, name)
        return self._uniform_locs[key]

    def _set(self, prog: int, name: str, value: Any, kind: str) -> None:
        """Set uniform ``name`` (kind: 'i', 'f', 'v2', 'v3', 'v4', 'm3', 'm4'; arrays allowed)."""
        GL = self._gl
        loc = self._loc(prog, name)
        if loc < 0:
            return  # optimised away
        if kind == "i":
            GL.glUniform1i(loc, int(value))
            return
        a = np.ascontiguousarray(value, dtype=np.float32)
        if kind == "f":
            GL.glUniform1fv(loc, a.size, a)
        elif kind == "v2":
            GL.glUniform2fv(loc, a.size // 2, a)
        elif kind == "v3":
            GL.glUniform3fv(loc, a.size // 3, a)
        elif kind == "v4":
            GL.glUniform4fv(loc, a.size // 4, a)
        elif kind == "m3":
            GL.glUniformMatrix3fv(loc, a.size // 9, GL.GL_TRUE, a)
        elif kind == "m4":
            GL.glUniformMatrix4fv(loc, a.size // 16, GL.GL_TRUE, a)
        else:  # pragma: no cover - programming error
            raise ValueError(kind)

    def _buffer_texture(self, data: np.ndarray, integer: bool = False) -> tuple[int, int]:
        """A texture buffer of 4-vectors (N, 4): RGBA32F, or RGBA32I if ``integer``."""
        GL = self._gl
        data = np.ascontiguousarray(data, dtype=np.int32 if integer else np.float32)
        buf = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, buf)
        GL.glBufferData(GL.GL_TEXTURE_BUFFER, data.nbytes, data, GL.GL_STATIC_DRAW)
        tex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, tex)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, GL.GL_RGBA32I if integer else GL.GL_RGBA32F, buf)
        return tex, buf

    def _check_light_limits(self) -> None:
        """Raise :class:`RasterError` (naming the GL limit) for more lights than this GL holds:
        shadow maps per texture array (``GL_MAX_ARRAY_TEXTURE_LAYERS``) and the resolve shader's
        light uniforms (``GL_MAX_FRAGMENT_UNIFORM_VECTORS``)."""
        GL = self._gl
        c, k = self._counts, self.config.area_samples
        max_layers = int(GL.glGetIntegerv(GL.GL_MAX_ARRAY_TEXTURE_LAYERS))
        max_vectors = int(GL.glGetIntegerv(GL.GL_MAX_FRAGMENT_UNIFORM_VECTORS))
        sharp = c["directional"] + 6 * c["point"] + c["spot"]
        where = f"scene {self.scene.name!r}"
        if self.config.shadows and c["area"] * k * k > max_layers:
            raise RasterError(
                f"{where} has {c['area']} area lights x {k}x{k} shadow samples = "
                f"{c['area'] * k * k} shadow maps, more than this GL's "
                f"GL_MAX_ARRAY_TEXTURE_LAYERS = {max_layers}: lower RasterConfig.area_samples or "
                "the number of lights (icbtool.scene.load(..., emitter_budget=N))"
            )
        if self.config.shadows and sharp > max_layers:
            raise RasterError(
                f"{where} needs {sharp} sharp shadow maps (suns + 6 per point light + spots), "
                f"more than this GL's GL_MAX_ARRAY_TEXTURE_LAYERS = {max_layers}"
            )
        # vec4 slots: sun 2, point 2, spot 4, area 5 (4 polygon vertices + radiance); sharp
        # shadow matrix 4 + texel 1; fixed uniforms (camera, sky, ...) within the margin
        vectors = 2 * c["directional"] + 2 * c["point"] + 4 * c["spot"] + 5 * c["area"] + 5 * sharp
        if vectors + _UNIFORM_MARGIN > max_vectors:
            raise RasterError(
                f"{where} has {sum(c.values())} lights ({c}) needing ~{vectors} uniform vectors "
                f"in the resolve shader, more than this GL's GL_MAX_FRAGMENT_UNIFORM_VECTORS = "
                f"{max_vectors} (minus {_UNIFORM_MARGIN} for the rest): use fewer lights "
                "(icbtool.scene.load(..., emitter_budget=N) for emissive meshes)"
            )

    # ------------------------------------------------------------------ uploads
    def _upload(self) -> None:
        GL = self._gl
        sc = self.scene
        self._vao = GL.glGenVertexArrays(1)
        GL.glBindVertexArray(self._vao)
        # the resolve pass reads the vertex data from a texture buffer (per vertex: (position, u),
        # (normal, v)); the rasterizer gets positions only (below)
        uv = sc.uvs if self._has_tex else np.zeros((len(sc.vertices), 2), np.float32)
        verts = np.empty((len(sc.vertices), 2, 4), np.float32)
        verts[:, 0, :3], verts[:, 0, 3] = sc.vertices, uv[:, 0]
        verts[:, 1, :3], verts[:, 1, 3] = sc.normals, uv[:, 1]
        self._vert_tex, _ = self._buffer_texture(verts.reshape(-1, 4))
        self._env_tex = self._upload_envmap() if sc.sky is not None else None
        # Faces sorted along a Morton curve and cut into clusters of CLUSTER_FACES, so that each
        # frame draws only the clusters whose bounding box meets the view frustum (a few draw
        # calls of contiguous ranges).
        order = _morton_order(sc.vertices[sc.faces].mean(1))
        self._face_order = order
        tri = sc.vertices[sc.faces[order]]
        starts = np.arange(0, len(order), CLUSTER_FACES)
        self._cluster_start = starts
        self._cluster_count = np.minimum(CLUSTER_FACES, len(order) - starts)
        self._cluster_lo = np.minimum.reduceat(tri.min(1), starts).astype(np.float64)
        self._cluster_hi = np.maximum.reduceat(tri.max(1), starts).astype(np.float64)
        # The visibility pass learns each fragment's face from a flat vertex attribute (reading
        # gl_PrimitiveID makes llvmpipe run an extra primitive-assembly stage: ~30 % of its
        # vertex work): every face gets a provoking (last) vertex of its own, see _provoking.
        idx, src = _provoking(sc.faces[order], len(sc.vertices))
        rast = np.empty((len(src), 4), np.float32)
        rast[:, :3] = sc.vertices[src]
        rast[:, 3] = 0.0
        rast[idx[:, 2], 3] = np.arange(1, len(idx) + 1, dtype=np.float32)  # face index + 1
        vbo = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
        GL.glBufferData(GL.GL_ARRAY_BUFFER, rast.nbytes, rast, GL.GL_STATIC_DRAW)
        GL.glEnableVertexAttribArray(0)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(0))
        GL.glEnableVertexAttribArray(1)
        GL.glVertexAttribPointer(1, 1, GL.GL_FLOAT, GL.GL_FALSE, 16, ctypes.c_void_p(12))
        self._vbos = [vbo]
        idx = np.ascontiguousarray(idx, dtype=np.uint32)
        self._ebo = GL.glGenBuffers(1)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, self._ebo)
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, GL.GL_STATIC_DRAW)
        self._n_indices = idx.size
        GL.glBindVertexArray(0)

        faces = np.concatenate([sc.face_normals, sc.face_material[:, None].astype(np.float32)], 1)
        faces = faces[order]
        self._face_tex, _ = self._buffer_texture(faces)
        tris = np.concatenate([sc.faces[order], sc.face_material[order, None]], 1)
        self._tri_tex, _ = self._buffer_texture(tris, integer=True)
        layers: dict[int, int] = {}
        mats = np.zeros((2 * len(sc.materials), 4), np.float32)
        for i, m in enumerate(sc.materials):
            if m.is_textured:
                layers[i] = len(layers)
            mats[2 * i, :3] = m.albedo
            mats[2 * i, 3] = layers.get(i, -1)
            mats[2 * i + 1, :3] = m.emission
        self._mat_tex, _ = self._buffer_texture(mats)
        # glossy BSDFs (icbtool.raster.glossy): their table only when some material has one, so
        # a Lambertian scene's shader and uploads are unchanged
        self._bsdf_tex = None
        if has_glossy(sc.materials):
            self._bsdf_tex, _ = self._buffer_texture(pack_bsdfs(sc.materials))
        self._tex_array = None
        if self._has_tex:
            self._upload_textures([sc.materials[i].texture for i in layers])

    def _upload_envmap(self) -> int | None:
        """The sky's lat-long map as an RGB32F texture (H rows, W + 1 columns: the first column
        repeated), read texel by texel by the resolve shader (its own bilinear lookup, the same
        as :meth:`icbtool.scene.Sky.radiance`); None for other skies."""
        sky = self.scene.sky
        if sky is None or sky.kind != "envmap":
            return None
        from icbtool.scene.types import envmap_periodic

        GL = self._gl
        m = envmap_periodic(sky.envmap)
        limit = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE))
        if max(m.shape[:2]) > limit:
            raise RasterError(
                f"scene {self.scene.name!r}: environment map {m.shape[1] - 1}x{m.shape[0]} "
                f"exceeds this GL's GL_MAX_TEXTURE_SIZE = {limit}"
            )
        tex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage2D(
            GL.GL_TEXTURE_2D, 0, GL.GL_RGB32F, m.shape[1], m.shape[0], 0, GL.GL_RGB, GL.GL_FLOAT, m
        )
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        return tex

    def _upload_textures(self, textures: list[np.ndarray]) -> None:
        import cv2

        from icbtool.imageio import srgb_encode

        GL = self._gl
        s = self.config.texture_size
        data = np.empty((len(textures), s, s, 4), np.uint8)
        data[..., 3] = 255
        for k, t in enumerate(textures):
            interp = cv2.INTER_AREA if t.shape[0] >= s and t.shape[1] >= s else cv2.INTER_LINEAR
            r = cv2.resize(np.asarray(t, np.float32), (s, s), interpolation=interp)
            # GL's texel row 0 is t = 0 (bottom); the image's row 0 is the top (v = 1).
            data[k, :, :, :3] = np.round(srgb_encode(r[::-1]) * 255.0).astype(np.uint8)
        tex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, tex)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage3D(
            GL.GL_TEXTURE_2D_ARRAY,
            0,
            GL.GL_SRGB8_ALPHA8,
            s,
            s,
            len(textures),
            0,
            GL.GL_RGBA,
            GL.GL_UNSIGNED_BYTE,
            data,
        )
        GL.glGenerateMipmap(GL.GL_TEXTURE_2D_ARRAY)
        GL.glTexParameteri(
            GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_LINEAR
        )
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_S, GL.GL_REPEAT)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_T, GL.GL_REPEAT)
        self._tex_array = tex

    # ------------------------------------------------------------------ shadows
    def _shadow_views(
        self,
    ) -> tuple[list[tuple[np.ndarray, float]], list[tuple[np.ndarray, float]]]:
        """(sharp views, area-sample views): lists of (clip_from_world, texel size)."""
        cfg = self.config
        sc = self.scene
        bounds = self._bounds
        res, ares = cfg.shadow_map_size, cfg.area_shadow_map_size
        cap = cfg.max_frustum_half_angle_deg
        sharp: list[tuple[np.ndarray, float]] = []
        for light in sc.lights_of("directional"):
            sharp.append(directional_view(light.direction, bounds, res))
        for light in sc.lights_of("point"):
            for fwd, up in _CUBE:
                sharp.append(
                    perspective_view(
                        light.position, np.array(fwd, float), 45.0, bounds, res, np.array(up, float)
                    )
                )
        for light in sc.lights_of("spot"):
            sharp.append(
                perspective_view(
                    light.position, light.direction, min(light.outer_deg + 1.0, 89.0), bounds, res
                )
            )
        area: list[tuple[np.ndarray, float]] = []
        for light in sc.lights_of("area"):
            n = light.normal
            for s in light.sample_points(cfg.area_samples):  # the order the shader expects
                d = _corners(_bounds_pad(bounds)) - s
                d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
                ang = math.degrees(math.acos(float(np.clip((d @ n).min(), -1, 1))))
                area.append(perspective_view(s, n, min(ang + 1.0, cap), bounds, ares))
        return sharp, area

    def _area_sample_table(self, area: list[tuple[np.ndarray, float]]) -> np.ndarray:
        """(5 * samples, 4) float32 rows of the ``u_area_samples`` texture buffer: per sample
        point, the 4 columns of its shadow clip_from_world, then (position, texel size)."""
        k = self.config.area_samples
        pos = [s for lt in self.scene.lights_of("area") for s in lt.sample_points(k)]
        rows = np.zeros((len(area), 5, 4), np.float32)
        for i, ((m, texel), s) in enumerate(zip(area, pos, strict=True)):
            rows[i, :4] = np.asarray(m, np.float64).T
            rows[i, 4, :3] = s
            rows[i, 4, 3] = texel
        return rows.reshape(-1, 4)

    def _depth_array(self, n: int, res: int, linear: bool) -> int:
        GL = self._gl
        tex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D_ARRAY, tex)
        GL.glTexImage3D(
            GL.GL_TEXTURE_2D_ARRAY,
            0,
            GL.GL_DEPTH_COMPONENT32F,
            res,
            res,
            n,
            0,
            GL.GL_DEPTH_COMPONENT,
            GL.GL_FLOAT,
            None,
        )
        filt = GL.GL_LINEAR if linear else GL.GL_NEAREST
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MIN_FILTER, filt)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_MAG_FILTER, filt)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_S, GL.GL_CLAMP_TO_EDGE)
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_WRAP_T, GL.GL_CLAMP_TO_EDGE)
        GL.glTexParameteri(
            GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_COMPARE_MODE, GL.GL_COMPARE_REF_TO_TEXTURE
        )
        GL.glTexParameteri(GL.GL_TEXTURE_2D_ARRAY, GL.GL_TEXTURE_COMPARE_FUNC, GL.GL_LEQUAL)
        return tex

    def _render_shadows(self) -> dict[str, Any]:
        GL = self._gl
        cfg = self.config
        sharp, area = self._shadow_views()
        prog = self._compile("depth.vert", "depth.frag", {})
        GL.glUseProgram(prog)
        GL.glBindVertexArray(self._vao)
        fbo = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, fbo)
        GL.glDrawBuffer(GL.GL_NONE)
        GL.glReadBuffer(GL.GL_NONE)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glEnable(GL.GL_POLYGON_OFFSET_FILL)
        GL.glPolygonOffset(cfg.depth_bias_slope, cfg.depth_bias_units)
        state: dict[str, Any] = {
            "sharp": sharp,
            "area": area,
            "sharp_tex": None,
            "area_tex": None,
            "area_samples": None,
        }
        if area:
            state["area_samples"] = self._buffer_texture(self._area_sample_table(area))
        for key, views, res in (
            ("sharp_tex", sharp, cfg.shadow_map_size),
            ("area_tex", area, cfg.area_shadow_map_size),
        ):
            if not views:
                continue
            tex = self._depth_array(len(views), res, cfg.pcf)
            state[key] = tex
            GL.glViewport(0, 0, res, res)
            for layer, (m, _) in enumerate(views):
                GL.glFramebufferTextureLayer(
                    GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, tex, 0, layer
                )
                self._check_fbo(f"shadow map {key} layer {layer}")
                GL.glClear(GL.GL_DEPTH_BUFFER_BIT)
                self._set(prog, "u_clip_from_world", m, "m4")
                GL.glDrawElements(GL.GL_TRIANGLES, self._n_indices, GL.GL_UNSIGNED_INT, None)
        GL.glDisable(GL.GL_POLYGON_OFFSET_FILL)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        GL.glDeleteFramebuffers(1, [fbo])
        GL.glFinish()
        return state

    def _free_shadows(self) -> None:
        st = self._shadow_state
        if st is not None:
            texs = [t for t in (st["sharp_tex"], st["area_tex"]) if t is not None]
            if st["area_samples"] is not None:
                texs.append(st["area_samples"][0])
                self._gl.glDeleteBuffers(1, [st["area_samples"][1]])
            if texs:
                self._gl.glDeleteTextures(texs)
        self._shadow_state = None

    def _check_fbo(self, what: str) -> None:
        GL = self._gl
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            raise RasterError(f"framebuffer for {what} is incomplete (status 0x{int(status):x})")

    # ------------------------------------------------------------------ camera framebuffers
    def _framebuffer(self, height: int, width: int) -> tuple[int, int, int]:
        """(visibility FBO, visibility texture, output FBO) for this size.

        The visibility FBO has the GL_R32F face-id texture and a float depth buffer; the output
        FBO has one GL_RGBA32F renderbuffer per output target (albedo, normal, position, dl).
        """
        GL = self._gl
        key = (height, width)
        if key in self._fbo:
            return self._fbo[key]
        for vfbo, vtex, ofbo in self._fbo.values():  # one size at a time: free the old one
            GL.glDeleteFramebuffers(2, [vfbo, ofbo])
            GL.glDeleteTextures([vtex])
            GL.glDeleteRenderbuffers(len(self._rbos), self._rbos)
        self._fbo.clear()
        maxsize = int(GL.glGetIntegerv(GL.GL_MAX_RENDERBUFFER_SIZE))
        if height > maxsize or width > maxsize:
            raise ValueError(f"camera {height}x{width} exceeds this GL's maximum size {maxsize}")
        vtex = GL.glGenTextures(1)
        GL.glBindTexture(GL.GL_TEXTURE_2D, vtex)
        GL.glTexImage2D(
            GL.GL_TEXTURE_2D, 0, GL.GL_R32F, width, height, 0, GL.GL_RED, GL.GL_FLOAT, None
        )
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_NEAREST)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_NEAREST)
        rbos = [int(x) for x in np.atleast_1d(GL.glGenRenderbuffers(_N_TARGETS + 1))]
        vfbo = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, vfbo)
        GL.glFramebufferTexture2D(
            GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_TEXTURE_2D, vtex, 0
        )
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rbos[-1])
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, width, height)
        GL.glFramebufferRenderbuffer(
            GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, rbos[-1]
        )
        GL.glDrawBuffers(1, [GL.GL_COLOR_ATTACHMENT0])
        self._check_fbo(f"camera visibility {height}x{width}")
        ofbo = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, ofbo)
        for i in range(_N_TARGETS):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, rbos[i])
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA32F, width, height)
            GL.glFramebufferRenderbuffer(
                GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0 + i, GL.GL_RENDERBUFFER, rbos[i]
            )
        self._check_fbo(f"camera outputs {height}x{width}")
        self._rbos = rbos
        self._fbo[key] = (vfbo, vtex, ofbo)
        return self._fbo[key]

    # ------------------------------------------------------------------ render
    def render(
        self, camera: Camera, buffers: tuple[str, ...] | list[str] | str | None = None
    ) -> RasterBuffers:
        """Rasterize ``buffers`` (default: all) for ``camera``.

        Deferred, in two passes: a visibility pass rasterizes the face id of every pixel (the
        only per-triangle work), then one full-screen resolve pass computes the requested
        targets of every pixel exactly once (interpolated position, normal, textured albedo,
        and dl with the shadow-map lookups and the sky on the background).

        Args:
            camera: the camera (any size up to the GL limit); a thin lens or an orthographic
                camera renders as its :meth:`~icbtool.camera.Camera.pinhole`.
            buffers: names from :data:`icbtool.raster.BUFFER_NAMES` (or a comma-separated string);
                only these are rendered, the others are None in the result; mask is always there.

        Returns:
            RasterBuffers: (H, W, C) float32 arrays in icbtool's pixel convention.

        Raises:
            ValueError: for an unknown buffer name or an unusable camera.
            RasterError: if OpenGL fails.
        """
        from icbtool.camera import Camera

        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be an icbtool Camera, got {type(camera).__name__}")
        camera = camera.pinhole()
        names = check_buffers(buffers)
        k = self.config.dl_supersample
        if k == 1 or "dl" not in names:
            return self._render(camera, names)
        # dl at k x k points per pixel (box filter, as the tracer's jittered pixels); the other
        # buffers at the pixel centres
        t0 = time.perf_counter()
        h, w = camera.height, camera.width
        big = self._render(camera.resized(k * h, k * w), ("dl",))
        out = self._render(camera, tuple(n for n in names if n != "dl"))
        out.dl = np.ascontiguousarray(big.dl.reshape(h, k, w, k, 3).mean(axis=(1, 3)))
        for key, ms in big.timings.items():
            out.timings[f"dl_x{k}_{key}"] = ms
        out.timings["total"] = 1e3 * (time.perf_counter() - t0)
        return out

    def _render(self, camera: Camera, names: tuple[str, ...]) -> RasterBuffers:
        """:meth:`render` of the checked ``names`` (possibly none: the mask alone), one sample
        per pixel."""
        GL = self._gl
        cfg = self.config
        self._context.make_current()
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        want_dl = "dl" in names
        any_light = any(self._counts.values())
        shadows = want_dl and cfg.shadows and any_light
        if shadows and self._shadow_state is not None and not cfg.cache_shadow_maps:
            self._free_shadows()
        if shadows and self._shadow_state is None:
            t0 = time.perf_counter()
            self._shadow_state = self._render_shadows()
            timings["shadow"] = 1e3 * (time.perf_counter() - t0)

        # output targets (attachment index) this request needs; mask only: the position target
        need = {
            _T_ALBEDO: "albedo" in names,
            _T_NORMAL: "normal_world" in names or "normal_view" in names,
            _T_POS: "position" in names or "depth" in names,
            _T_DL: want_dl,
        }
        if not any(need.values()):
            need[_T_POS] = True
        used = [t for t in range(_N_TARGETS) if need[t]]

        h, w = camera.height, camera.width
        near, far = camera_near_far(camera, self._bounds, cfg)
        clip_from_world = camera.gl_projection_matrix(near, far) @ camera.gl_view_matrix()
        vfbo, vtex, ofbo = self._framebuffer(h, w)
        # front-to-back cluster order lets early depth testing skip most hidden fragments
        ranges = self._visible_ranges(
            clip_from_world, None if cfg.depth_prepass else camera.position
        )
        # fraction of the faces sent to GL after frustum culling (diagnostics)
        self.last_drawn_fraction = sum(c for _, c in ranges) / max(1, len(self._face_order))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, vfbo)
        GL.glViewport(0, 0, w, h)
        GL.glBindVertexArray(self._vao)
        GL.glDisable(GL.GL_BLEND)
        GL.glDisable(GL.GL_CULL_FACE)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glClearDepth(1.0)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)

        t0 = time.perf_counter()
        if cfg.depth_prepass:
            dprog = self._compile("depth.vert", "depth.frag", {})
            GL.glUseProgram(dprog)
            self._set(dprog, "u_clip_from_world", clip_from_world, "m4")
            GL.glColorMask(GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE)
            GL.glDepthFunc(GL.GL_LESS)
            for first, count in ranges:
                GL.glDrawElements(
                    GL.GL_TRIANGLES, 3 * count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(12 * first)
                )
            GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
            GL.glDepthFunc(GL.GL_EQUAL)
            GL.glDepthMask(GL.GL_FALSE)
        else:
            GL.glDepthFunc(GL.GL_LESS)
        prog = self._compile("vis.vert", "vis.frag", {})
        GL.glUseProgram(prog)
        self._set(prog, "u_clip_from_world", clip_from_world, "m4")
        for first, count in ranges:
            GL.glDrawElements(
                GL.GL_TRIANGLES, 3 * count, GL.GL_UNSIGNED_INT, ctypes.c_void_p(12 * first)
            )
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glFinish()
        timings["visibility"] = 1e3 * (time.perf_counter() - t0)
        t1 = time.perf_counter()
        self._resolve(camera, used, vtex, ofbo, shadows)
        GL.glFinish()
        timings["resolve"] = 1e3 * (time.perf_counter() - t1)
        timings["draw"] = 1e3 * (time.perf_counter() - t0)

        t0 = time.perf_counter()
        out: dict[str, np.ndarray] = {}
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 4)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, ofbo)
        raw: dict[int, np.ndarray] = {}
        for t in used:
            GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0 + t)
            raw[t] = self._read_rgba(t, h, w)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        # GL's row 0 is the bottom row: flip into icbtool's pixel convention (cv2 copies the
        # 3 of 4 channels ~10x faster than numpy's strided copy)
        mask = np.ascontiguousarray(raw[used[0]][::-1, :, 3:4] != 0, dtype=np.float32)
        if want_dl:
            out["dl"] = _rgb(raw[_T_DL])
        if "albedo" in names:
            out["albedo"] = _rgb(raw[_T_ALBEDO])
        if need[_T_NORMAL]:
            nw = _rgb(raw[_T_NORMAL])
            if "normal_world" in names:
                out["normal_world"] = nw
            if "normal_view" in names:  # rotated into OpenCV camera axes (0 stays 0)
                out["normal_view"] = _rotate(nw, camera.cam_from_world[:3, :3])
        if "position" in names:
            out["position"] = _rgb(raw[_T_POS])
        if "depth" in names:
            out["depth"] = raw[_T_POS][::-1, :, 3:4].copy()  # never a view of the staging array
        timings["readback"] = 1e3 * (time.perf_counter() - t0)
        timings["total"] = 1e3 * (time.perf_counter() - t_start)
        return RasterBuffers(camera=camera, mask=mask, timings=timings, **out)

    def _read_rgba(self, target: int, height: int, width: int) -> np.ndarray:
        """(H, W, 4) float32 of the current read buffer, GL row order (bottom row first).

        Read into a staging array kept per target (fresh memory would cost page faults every
        frame); only valid until the next frame: callers copy out of it.
        """
        arr = self._staging.get(target)
        if arr is None or arr.shape != (height, width, 4):
            arr = self._staging[target] = np.empty((height, width, 4), np.float32)
        self._gl.glReadPixels(0, 0, width, height, self._gl.GL_RGBA, self._gl.GL_FLOAT, arr)
        return arr

    def _resolve(
        self, camera: Camera, used: list[int], vtex: int, ofbo: int, shadows: bool
    ) -> None:
        """The full-screen resolve pass: the ``used`` targets of every pixel from the face ids."""
        GL = self._gl
        cfg = self.config
        sky = self.scene.sky
        want_dl = _T_DL in used
        defines: dict[str, object] = {}
        for t in used:
            defines[_TARGET_DEFINE[t]] = t
        if self._has_tex and (want_dl or _T_ALBEDO in used):
            defines["HAS_TEX"] = True
        if want_dl:
            defines.update(
                N_DIR=self._counts["directional"],
                N_POINT=self._counts["point"],
                N_SPOT=self._counts["spot"],
                N_AREA=self._counts["area"],
                AREA_K=cfg.area_samples,
                AREA_SUB=cfg.penumbra_samples if shadows else 1,
            )
            if shadows:
                defines["SHADOWS"] = True
            if self._bsdf_tex is not None:
                defines["GLOSSY"] = True
                defines["GLOSSY_N"] = cfg.glossy_area_samples
            if sky is not None:
                defines[
                    {"gradient": "SKY_GRADIENT", "envmap": "SKY_ENVMAP"}.get(
                        sky.kind, "SKY_UNIFORM"
                    )
                ] = True
        prog = self._compile("resolve.vert", "resolve.frag", defines)
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, ofbo)
        bufs = [
            GL.GL_COLOR_ATTACHMENT0 + t if t in used else GL.GL_NONE for t in range(max(used) + 1)
        ]
        GL.glDrawBuffers(len(bufs), bufs)
        GL.glDisable(GL.GL_DEPTH_TEST)
        GL.glUseProgram(prog)
        units = [
            (1, GL.GL_TEXTURE_BUFFER, self._face_tex, "u_faces"),
            (2, GL.GL_TEXTURE_BUFFER, self._mat_tex, "u_materials"),
            (5, GL.GL_TEXTURE_2D, vtex, "u_vis"),
            (6, GL.GL_TEXTURE_BUFFER, self._tri_tex, "u_tris"),
            (7, GL.GL_TEXTURE_BUFFER, self._vert_tex, "u_verts"),
        ]
        if "HAS_TEX" in defines:
            units.append((0, GL.GL_TEXTURE_2D_ARRAY, self._tex_array, "u_textures"))
        if "SKY_ENVMAP" in defines:
            units.append((9, GL.GL_TEXTURE_2D, self._env_tex, "u_env"))
        if "GLOSSY" in defines:
            units.append((10, GL.GL_TEXTURE_BUFFER, self._bsdf_tex, "u_bsdf"))
        if shadows:
            st = self._shadow_state
            assert st is not None
            if st["sharp_tex"] is not None:
                units.append((3, GL.GL_TEXTURE_2D_ARRAY, st["sharp_tex"], "u_shadow"))
                self._set(prog, "u_shadow_mat", np.stack([m for m, _ in st["sharp"]]), "m4")
                self._set(prog, "u_shadow_texel", [t for _, t in st["sharp"]], "f")
            if st["area_tex"] is not None:
                units.append((4, GL.GL_TEXTURE_2D_ARRAY, st["area_tex"], "u_area_shadow"))
                units.append((8, GL.GL_TEXTURE_BUFFER, st["area_samples"][0], "u_area_samples"))
            self._set(prog, "u_normal_offset", cfg.normal_offset, "f")
            self._set(prog, "u_area_offset", cfg.area_offset, "f")
        for unit, target, tex, name in units:
            GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
            GL.glBindTexture(target, tex)
            self._set(prog, name, unit, "i")
        GL.glActiveTexture(GL.GL_TEXTURE0)
        self._set(prog, "u_height", float(camera.height), "f")
        self._set(prog, "u_intrinsics", [camera.fx, camera.fy, camera.cx, camera.cy], "v4")
        self._set(prog, "u_world_from_cam", camera.world_from_cam[:3, :3], "m3")
        self._set(prog, "u_cam_pos", camera.position, "v3")
        self._set(prog, "u_cam_forward", camera.forward, "v3")
        if want_dl:
            self._set_light_uniforms(prog)
            if sky is not None:
                self._set(prog, "u_zenith", sky.zenith, "v3")
                self._set(prog, "u_horizon", sky.horizon, "v3")
                self._set(prog, "u_ground", sky.ground, "v3")
                self._set(prog, "u_up", sky.up, "v3")
                if sky.kind == "envmap":
                    self._set(prog, "u_map_from_world", sky.world_from_map.T, "m3")
                    self._set(prog, "u_env_scale", sky.envmap_scale, "f")
        GL.glDrawArrays(GL.GL_TRIANGLES, 0, 3)
        GL.glEnable(GL.GL_DEPTH_TEST)

    def _visible_ranges(
        self, clip_from_world: np.ndarray, eye: np.ndarray | None = None
    ) -> list[tuple[int, int]]:
        """(first face, face count) of the runs of consecutive clusters inside the frustum,
        front to back (by the distance from ``eye`` to the cluster box) when ``eye`` is given."""
        vis = np.flatnonzero(_frustum_visible(clip_from_world, self._cluster_lo, self._cluster_hi))
        if eye is not None:
            lo, hi = self._cluster_lo[vis], self._cluster_hi[vis]
            dist = np.linalg.norm(np.clip(eye, lo, hi) - eye, axis=1)
            vis = vis[np.argsort(dist, kind="stable")]
        ranges: list[tuple[int, int]] = []
        for c in vis:
            first, count = int(self._cluster_start[c]), int(self._cluster_count[c])
            if ranges and ranges[-1][0] + ranges[-1][1] == first:
                ranges[-1] = (ranges[-1][0], ranges[-1][1] + count)
            else:
                ranges.append((first, count))
        return ranges

    def _set_light_uniforms(self, prog: int) -> None:
        sc = self.scene
        d = sc.lights_of("directional")
        if d:
            self._set(prog, "u_dir_dir", np.stack([x.direction for x in d]), "v3")
            self._set(prog, "u_dir_E", np.stack([x.irradiance for x in d]), "v3")
        p = sc.lights_of("point")
        if p:
            self._set(prog, "u_point_pos", np.stack([x.position for x in p]), "v3")
            self._set(prog, "u_point_I", np.stack([x.intensity for x in p]), "v3")
        s = sc.lights_of("spot")
        if s:
            self._set(prog, "u_spot_pos", np.stack([x.position for x in s]), "v3")
            self._set(prog, "u_spot_dir", np.stack([x.direction for x in s]), "v3")
            self._set(prog, "u_spot_I", np.stack([x.intensity for x in s]), "v3")
            cs = [
                (
                    math.cos(math.radians(x.inner_deg)),
                    math.cos(math.radians(x.outer_deg)),
                    float(x.profile == "linear"),
                )
                for x in s
            ]
            self._set(prog, "u_spot_cos", cs, "v3")
        a = sc.lights_of("area")
        if a:
            self._set(prog, "u_area_v", area_polygons(a), "v3")
            self._set(prog, "u_area_L", np.stack([x.radiance for x in a]), "v3")


def render(
    scene: Scene,
    camera: Camera,
    buffers: tuple[str, ...] | list[str] | str | None = None,
    config: RasterConfig | None = None,
) -> RasterBuffers:
    """Rasterize one frame (creates and releases a GL context; use :class:`Rasterizer` for many).

    Args:
        scene: the scene.
        camera: the camera.
        buffers: the buffers to render (default: all); see :meth:`Rasterizer.render`.
        config: options (default :class:`RasterConfig`).

    Returns:
        RasterBuffers.
    """
    names = check_buffers(buffers)  # validate before creating a context
    with Rasterizer(scene, config) as r:
        return r.render(camera, names)
