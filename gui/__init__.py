"""The icbtool desktop app: watch and steer the ICB system in a Qt + PyVista window.

``icbtool gui [SCENE] [--store DIR] [--run DIR] [--screenshot FILE]`` opens it
(:mod:`gui.app`). It uses only icbtool's public API:

- :mod:`gui.model` (no Qt): the session (scene, store, path, client frames computed with
  :class:`icbtool.system.Client` against an :class:`icbtool.system.Cloud`, the prefetch camera,
  SSIM/FLIP maps from :mod:`icbtool.metrics`) and the geometry drawn in 3D (frusta, octree leaves);
- :mod:`gui.scene_view`: the 3D view (scene, octree leaves, pickable reference frusta, the client
  and its prefetch frustum);
- :mod:`gui.panels`: the image panels and heatmaps;
- :mod:`gui.trainer`: a GAN training in a background process (:mod:`gui.train_job`) with live
  curves;
- :mod:`gui.forms`: settings forms generated from the config dataclasses;
- :mod:`gui.calls`: the log of the equivalent Python calls;
- :mod:`gui.display`: a private Xvfb server for offscreen screenshots.

Nothing here is imported by ``import icbtool``; the Qt modules need the ``gui`` extra
(``pip install "icbtool[gui]"``) and an X display (Xvfb headless).
"""

from __future__ import annotations
