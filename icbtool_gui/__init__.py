"""The icbtool desktop app: watch and steer the ICB system in a Qt + PyVista window.

``icbtool gui [SCENE] [--store DIR] [--run DIR] [--screenshot FILE]`` opens it
(:mod:`icbtool_gui.app`). It uses only icbtool's public API:

- :mod:`icbtool_gui.model` (no Qt): the session (scene, store, path, client frames computed with
  :class:`icbtool.system.Client` against an :class:`icbtool.system.Cloud`, the prefetch camera,
  SSIM/FLIP maps from :mod:`icbtool.metrics`) and the geometry drawn in 3D (frusta, octree leaves);
- :mod:`icbtool_gui.scene_view`: the 3D view (scene, octree leaves, pickable reference frusta,
  the client and its prefetch frustum);
- :mod:`icbtool_gui.panels`: the image panels and heatmaps (with colour bars);
- :mod:`icbtool_gui.trainer`: a GAN training in a background process
  (:mod:`icbtool_gui.train_job`) with live curves;
- :mod:`icbtool_gui.forms`: settings forms generated from the config dataclasses;
- :mod:`icbtool_gui.calls`: the log of the equivalent Python calls;
- :mod:`icbtool_gui.bakejob`: the quick store baked in a process of its own;
- :mod:`icbtool_gui.display`: a private Xvfb server for offscreen screenshots.

The package is ``icbtool_gui``, not ``gui``: a top-level ``gui`` in site-packages would collide
with other distributions. Nothing here is imported by ``import icbtool``; the Qt modules need the
``gui`` extra (``pip install ".[gui]"`` in the checkout) and an X display (Xvfb headless).

OpenGL has one owner per process: this window's process uses only Qt's and VTK's OpenGL (an X
window); everything that needs icbtool's headless OpenGL (OSMesa / EGL through PyOpenGL) runs in
a process of its own: client frames (:mod:`icbtool_gui.frames`), the quick store's bake
(:mod:`icbtool_gui.bakejob`). :func:`icbtool_gui.app.open_window` refuses to start in a process
that has already bound PyOpenGL to a headless platform.
"""

from __future__ import annotations
