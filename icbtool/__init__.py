"""icbtool: Intelligent CloudBaking, a research tool for web-cloud collaborative rendering.

``import icbtool as icb`` is cheap: subpackages that pull in OpenGL, Embree or torch are imported
on first attribute access (``icb.raster``, ``icb.trace``, ``icb.warp`` ...).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_SUBMODULES = (
    "camera",
    "scene",
    "raster",
    "trace",
    "store",
    "bake",
    "system",
    "buffers",
    "provenance",
    "configdoc",
    "warp",
    "prefetch",
    "metrics",
    "imageio",
    "cli",
    "pipeline",
    "gan",
    "radiance",
    "lpm",
    "net",
)

if TYPE_CHECKING:  # pragma: no cover
    from icbtool import camera, raster, scene, store, trace, warp  # noqa: F401
    from icbtool.camera import Camera, CameraPath  # noqa: F401


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        module = importlib.import_module(f"icbtool.{name}")
        globals()[name] = module
        return module
    if name in ("Camera", "CameraPath"):
        from icbtool import camera

        return getattr(camera, name)
    raise AttributeError(f"module 'icbtool' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_SUBMODULES, "Camera", "CameraPath"])
