"""icbtool: Intelligent CloudBaking (ICB), a research tool for web-cloud collaborative rendering.

A cloud path tracer renders global illumination (GI) maps and keeps them in an octree cache; a
client rasterizes its own direct light (DL) and G-buffers, warps the cloud's GI to its current
view and shows ``DL + GI``; a model learned from the cloud's renders can make the client's GI.

The parts (subpackages, imported on first use: ``import icbtool as icb`` stays cheap, and
``icb.raster`` or ``icb.trace`` loads OpenGL or Embree only when used):

- ``camera``: the one pinhole camera (OpenCV axes) and timed camera paths (``icb.Camera``).
- ``scene``: the immutable scene, procedural scenes with known answers, OBJ / glTF / PLY /
  Mitsuba 3 XML / TOML loading (``icb.scene.load``, ``icb.scene.cornell_box``).
- ``raster``: the client's buffers through offscreen OpenGL (``icb.raster.render``).
- ``trace``: the cloud's path tracer for GI maps (``icb.trace.render``, ``TraceConfig``).
- ``store``: the octree cache of CRT-buffers (``icb.store.open``); ``bake``: fill it along a path.
- ``warp``: 3D warping with holes by cause; ``prefetch``: the prefetch camera.
- ``system``: the ``Cloud``, the ``Client`` and the ``GISource`` interface between them;
  ``pipeline``: the whole loop (``icb.pipeline.run_loop``, what ``make demo`` runs).
- ``gan``: the GAN pre-renderer; ``radiance``: world-space GI models (torch).
- ``lpm``: the lightweight progressive mesh; ``net``: the networked system (protocol, server,
  client); ``metrics``, ``imageio``, ``buffers``, ``provenance``, ``configdoc``, ``runs`` (the
  trainers' run directories), ``optional`` (optional libraries, imported so that a missing one
  names its extra): shared pieces.
- ``cli``: the ``icbtool`` command (``icbtool --help``); ``icbtool_gui`` (a package beside this
  one) is the desktop app, ``icbtool gui``.

Where to read on: README.md (the two commands, ``make demo`` and ``make test``, and a tour) and
docs/index.md in the repository: the guide (docs/guide/: one page per way of using icbtool),
the design notes (docs/design.md, docs/conventions.md ...) and the measured numbers
(docs/benchmarks.md).
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
    "runs",
    "configdoc",
    "optional",
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
