"""Headless OpenGL contexts: a small abstract class with OSMesa and EGL versions.

PyOpenGL binds its platform (``PYOPENGL_PLATFORM``) when ``OpenGL`` is first imported, so the
backend must be chosen before that import and cannot change afterwards in the same process. This
module hides that: :func:`create_context` sets the variable right before the first OpenGL import
and raises :class:`GLBackendError` if OpenGL was already imported with another platform.

Context creation reuses pyrender's platform classes (``OSMesaPlatform``, ``EGLPlatform``); all
rendering is our own PyOpenGL code (see :mod:`icbtool.raster.renderer`).
"""

from __future__ import annotations

import abc
import ctypes
import os
import sys
from typing import Any

import numpy as np

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
    if not hasattr(np, "infty"):  # pyrender (numpy 1 era) uses np.infty
        setattr(np, "infty", np.inf)  # noqa: B010
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
        """A pyrender platform object (not yet initialised)."""

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
        from pyrender.platforms.osmesa import OSMesaPlatform

        return OSMesaPlatform(1, 1)


class EGLContext(GLContext):
    """A surfaceless EGL context on the first EGL device (GPU, or Mesa's software device)."""

    backend = "egl"

    def _create(self) -> Any:
        from pyrender.platforms.egl import EGLPlatform

        return EGLPlatform(1, 1)


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
