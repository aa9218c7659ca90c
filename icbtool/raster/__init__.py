"""The client's rasterizer: float G-buffers (albedo, normals, depth, position, mask) and shadowed
direct lighting (DL) with OpenGL (OSMesa or EGL, headless).

>>> import icbtool as icb                                            # doctest: +SKIP
>>> buf = icb.raster.render(icb.scene.cornell_box(), cam)           # doctest: +SKIP
>>> with icb.raster.Rasterizer(scene, icb.raster.RasterConfig(backend="osmesa")) as r:  # +SKIP
...     frames = [r.render(c, buffers=("dl", "depth")) for c in path]

OpenGL is imported only when a context is created (:mod:`icbtool.raster.context` binds
PYOPENGL_PLATFORM right before that first import).
"""

from icbtool.raster.config import (
    BUFFER_CHANNELS,
    BUFFER_NAMES,
    PREVIEW_KIND,
    RasterBuffers,
    RasterConfig,
    check_buffers,
)
from icbtool.raster.context import GLBackendError, GLContext, create_context
from icbtool.raster.renderer import RasterError, Rasterizer, render

__all__ = [
    "BUFFER_CHANNELS",
    "BUFFER_NAMES",
    "PREVIEW_KIND",
    "GLBackendError",
    "GLContext",
    "RasterBuffers",
    "RasterConfig",
    "RasterError",
    "Rasterizer",
    "check_buffers",
    "create_context",
    "render",
]
