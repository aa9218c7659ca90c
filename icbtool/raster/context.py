"""Headless OpenGL contexts: a small abstract class with OSMesa and EGL versions.

PyOpenGL binds its platform (``PYOPENGL_PLATFORM``) when ``OpenGL`` is first imported, so the
backend must be chosen before that import and cannot change afterwards in the same process. This
module hides that: :func:`create_context` sets the variable right before the first OpenGL import
and raises :class:`GLBackendError` if OpenGL was already imported with another platform.

Contexts are created directly with PyOpenGL's OSMesa and EGL bindings (:class:`_OSMesaPlatform`,
:class:`_EGLPlatform`, the same calls as pyrender's platform classes, which icbtool used before).
icbtool does not depend on pyrender: pyrender 0.1.45 pins PyOpenGL==3.1.0, whose OSMesa binding is
broken, and a package that declares both cannot be installed by plain ``pip install``. All
rendering is our own PyOpenGL code (see :mod:`icbtool.raster.renderer`).
"""

from __future__ import annotations

import abc
import ctypes
import os
import sys
from typing import Any

#: Backends tried by ``backend="auto"`` when ICBTOOL_GL_BACKEND is not set, in order.
PREFERENCE = ("egl", "osmesa")
BACKENDS = ("osmesa", "egl")
ENV_VAR = "ICBTOOL_GL_BACKEND"


class GLBackendError(RuntimeError):
    """No usable OpenGL backend, or the requested one cannot be used in this process."""


def _bound_platform() -> str | None:
    """The platform PyOpenGL was bound to in this process, or None if OpenGL is not imported."""
    if "OpenGL" not in sys.modules:
        return None
    plat = os.environ.get("PYOPENGL_PLATFORM", "")
    return plat or "default"


def _import_gl(backend: str) -> None:
    """Import OpenGL bound to ``backend`` (set PYOPENGL_PLATFORM first if not yet imported).

    Raises:
        GLBackendError: if OpenGL was already imported with another platform.
    """
    bound = _bound_platform()
    if bound is None:
        os.environ["PYOPENGL_PLATFORM"] = backend
    elif bound != backend:
        raise GLBackendError(
            f"OpenGL backend {backend!r} requested, but PyOpenGL was already imported in this "
            f"process with PYOPENGL_PLATFORM={bound!r}; a process can use only one platform. "
            f"Import icbtool.raster (or set ICBTOOL_GL_BACKEND={bound}) before anything imports "
            f"OpenGL, or run the other backend in a subprocess."
        )
    import OpenGL  # noqa: F401
    import OpenGL.GL  # noqa: F401


class GLContext(abc.ABC):
    """An offscreen OpenGL (>= 3.3 core) context. Use as a context manager or call :meth:`close`.

    Rendering happens in framebuffer objects, so the context's own surface is tiny.
    """

    backend: str = ""

    def __init__(self) -> None:
        self._platform: Any = None
        _import_gl(self.backend)
        try:
            self._platform = self._create()
            self._platform.init_context()
            self._platform.make_current()
        except Exception as e:  # report which backend failed and why
            raise GLBackendError(f"could not create an {self.backend} OpenGL context: {e!r}") from e
        from OpenGL import GL

        version = GL.glGetString(GL.GL_VERSION)
        self.version = version.decode() if version else "?"
        renderer = GL.glGetString(GL.GL_RENDERER)
        self.renderer = renderer.decode() if renderer else "?"

    @abc.abstractmethod
    def _create(self) -> Any:
        """A platform object (not yet initialised): ``init_context``, ``make_current``,
        ``delete_context``."""

    def make_current(self) -> None:
        """Make this context current on the calling thread."""
        if self._platform is None:
            raise GLBackendError(f"{self.backend} context is closed")
        self._platform.make_current()

    def close(self) -> None:
        """Destroy the context (idempotent)."""
        if self._platform is not None:
            try:
                self._platform.delete_context()
            finally:
                self._platform = None

    def __enter__(self) -> GLContext:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.version}, {self.renderer})"


class OSMesaContext(GLContext):
    """Mesa's software offscreen context (needs Debian's libosmesa6)."""

    backend = "osmesa"

    def _create(self) -> Any:
        return _OSMesaPlatform()


class EGLContext(GLContext):
    """A surfaceless EGL context on the first EGL device (GPU, or Mesa's software device)."""

    backend = "egl"

    def _create(self) -> Any:
        return _EGLPlatform()


class _OSMesaPlatform:
    """An OSMesa 3.3 core context drawing into a 1 x 1 RGBA buffer (we render into FBOs)."""

    def __init__(self) -> None:
        self._context: Any = None
        self._buffer: Any = None

    def init_context(self) -> None:
        from OpenGL import arrays
        from OpenGL import osmesa as om

        attrs = arrays.GLintArray.asArray(
            [
                om.OSMESA_FORMAT, om.OSMESA_RGBA,
                om.OSMESA_DEPTH_BITS, 24,
                om.OSMESA_PROFILE, om.OSMESA_CORE_PROFILE,
                om.OSMESA_CONTEXT_MAJOR_VERSION, 3,
                om.OSMESA_CONTEXT_MINOR_VERSION, 3,
                0,
            ]
        )  # fmt: skip
        self._context = om.OSMesaCreateContextAttribs(attrs, None)
        if not self._context:
            raise GLBackendError("OSMesaCreateContextAttribs returned no context (3.3 core)")
        self._buffer = arrays.GLubyteArray.zeros((1, 1, 4))

    def make_current(self) -> None:
        from OpenGL import GL
        from OpenGL import osmesa as om

        if not om.OSMesaMakeCurrent(self._context, self._buffer, GL.GL_UNSIGNED_BYTE, 1, 1):
            raise GLBackendError("OSMesaMakeCurrent failed")

    def delete_context(self) -> None:
        from OpenGL import osmesa as om

        if self._context is not None:
            om.OSMesaDestroyContext(self._context)
        self._context = None
        self._buffer = None


class _EGLPlatform:
    """A surfaceless EGL 4.1 core context on the first EGL device (EGL_EXT_platform_device)."""

    def __init__(self) -> None:
        self._display: Any = None
        self._context: Any = None

    def init_context(self) -> None:
        from OpenGL import EGL, arrays
        from OpenGL._opaque import opaque_pointer_cls

        def proc(name: bytes, restype: Any, *argtypes: Any) -> Any:
            address = EGL.eglGetProcAddress(name)
            if not address:
                raise GLBackendError(f"EGL lacks {name.decode()}")
            proto = ctypes.CFUNCTYPE(restype)
            proto.argtypes = argtypes
            return proto(address)

        device_t = opaque_pointer_cls("EGLDeviceEXT")
        query_devices = proc(b"eglQueryDevicesEXT", EGL.EGLBoolean)
        get_display = proc(b"eglGetPlatformDisplayEXT", EGL.EGLDisplay)
        n = EGL.EGLint()
        if not query_devices(0, None, ctypes.pointer(n)) or n.value < 1:
            raise GLBackendError("EGL reports no devices")
        devices = (device_t * n.value)()
        if not query_devices(n.value, devices, ctypes.pointer(n)) or n.value < 1:
            raise GLBackendError("EGL reports no devices")
        display = os.environ.pop("DISPLAY", None)  # never pick an X11 display
        try:
            self._display = get_display(0x313F, devices[0], None)  # EGL_PLATFORM_DEVICE_EXT
        finally:
            if display is not None:
                os.environ["DISPLAY"] = display
        major, minor = ctypes.c_long(), ctypes.c_long()
        if not EGL.eglInitialize(self._display, major, minor):
            raise GLBackendError("eglInitialize failed on the first device")
        config_attrs = arrays.GLintArray.asArray(
            [
                EGL.EGL_SURFACE_TYPE, EGL.EGL_PBUFFER_BIT,
                EGL.EGL_RED_SIZE, 8, EGL.EGL_GREEN_SIZE, 8, EGL.EGL_BLUE_SIZE, 8,
                EGL.EGL_DEPTH_SIZE, 24,
                EGL.EGL_COLOR_BUFFER_TYPE, EGL.EGL_RGB_BUFFER,
                EGL.EGL_RENDERABLE_TYPE, EGL.EGL_OPENGL_BIT,
                EGL.EGL_CONFORMANT, EGL.EGL_OPENGL_BIT,
                EGL.EGL_NONE,
            ]
        )  # fmt: skip
        context_attrs = arrays.GLintArray.asArray(
            [
                EGL.EGL_CONTEXT_MAJOR_VERSION, 4,
                EGL.EGL_CONTEXT_MINOR_VERSION, 1,
                EGL.EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL.EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
                EGL.EGL_NONE,
            ]
        )  # fmt: skip
        configs = (EGL.EGLConfig * 1)()
        n_configs = ctypes.c_long()
        if not EGL.eglChooseConfig(self._display, config_attrs, configs, 1, n_configs):
            raise GLBackendError("eglChooseConfig found no config")
        if not EGL.eglBindAPI(EGL.EGL_OPENGL_API):
            raise GLBackendError("eglBindAPI(EGL_OPENGL_API) failed")
        self._context = EGL.eglCreateContext(
            self._display, configs[0], EGL.EGL_NO_CONTEXT, context_attrs
        )
        if not self._context:
            raise GLBackendError("eglCreateContext returned no context (4.1 core)")
        self.make_current()

    def make_current(self) -> None:
        from OpenGL import EGL

        if not EGL.eglMakeCurrent(
            self._display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, self._context
        ):
            raise GLBackendError("eglMakeCurrent failed")

    def delete_context(self) -> None:
        from OpenGL import EGL

        if self._display is not None:
            if self._context is not None:
                EGL.eglDestroyContext(self._display, self._context)
                self._context = None
            EGL.eglTerminate(self._display)
            self._display = None


_CLASSES: dict[str, type[GLContext]] = {"osmesa": OSMesaContext, "egl": EGLContext}


def _probe_egl() -> None:
    """Check that EGL can initialise a device display without importing OpenGL (ctypes only).

    Raises:
        GLBackendError: naming the failing step.
    """
    try:
        lib = ctypes.CDLL("libEGL.so.1")
    except OSError as e:
        raise GLBackendError(f"libEGL.so.1 not loadable ({e})") from e
    lib.eglGetProcAddress.restype = ctypes.c_void_p
    lib.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    q_addr = lib.eglGetProcAddress(b"eglQueryDevicesEXT")
    d_addr = lib.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
    if not q_addr or not d_addr:
        raise GLBackendError("EGL lacks eglQueryDevicesEXT / eglGetPlatformDisplayEXT")
    query = ctypes.CFUNCTYPE(
        ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int)
    )(q_addr)
    get_display = ctypes.CFUNCTYPE(
        ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p
    )(d_addr)
    devices = (ctypes.c_void_p * 8)()
    n = ctypes.c_int(0)
    if not query(8, devices, ctypes.byref(n)) or n.value < 1:
        raise GLBackendError("EGL reports no devices")
    dpy = get_display(0x313F, devices[0], None)  # EGL_PLATFORM_DEVICE_EXT
    if not dpy:
        raise GLBackendError("eglGetPlatformDisplayEXT returned no display")
    lib.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    lib.eglTerminate.argtypes = [ctypes.c_void_p]
    major, minor = ctypes.c_int(), ctypes.c_int()
    if not lib.eglInitialize(dpy, ctypes.byref(major), ctypes.byref(minor)):
        raise GLBackendError("eglInitialize failed on the first device")
    lib.eglTerminate(dpy)


def resolve_backend(backend: str) -> list[str]:
    """The backends to try for a requested ``backend``, in order.

    ``"auto"``: $ICBTOOL_GL_BACKEND (read now) if set, else :data:`PREFERENCE`.

    Raises:
        ValueError: for an unknown name (in the argument or the environment variable).
    """
    if backend == "auto":
        env = os.environ.get(ENV_VAR, "").strip().lower()
        if env:
            if env not in BACKENDS:
                raise ValueError(f"{ENV_VAR}={env!r} is not a GL backend; use one of {BACKENDS}")
            return [env]
        bound = _bound_platform()
        if bound in BACKENDS:  # OpenGL already bound: only that platform can work
            return [bound]
        return list(PREFERENCE)
    if backend not in BACKENDS:
        raise ValueError(f"unknown GL backend {backend!r}; use one of {('auto', *BACKENDS)}")
    return [backend]


def create_context(backend: str = "auto") -> GLContext:
    """Create an offscreen context on ``backend`` ("auto", "osmesa" or "egl").

    Raises:
        ValueError: unknown backend name.
        GLBackendError: no candidate worked; the message lists each backend tried and why it failed.
    """
    candidates = resolve_backend(backend)
    errors: list[str] = []
    for i, name in enumerate(candidates):
        last = i == len(candidates) - 1
        try:
            if name == "egl" and not last and _bound_platform() is None:
                _probe_egl()  # fail early, before OpenGL gets bound to EGL
            return _CLASSES[name]()
        except GLBackendError as e:
            errors.append(f"{name}: {e}")
    raise GLBackendError(
        f"no usable OpenGL backend (requested {backend!r}); tried " + "; ".join(errors)
    )
