"""Shared fixtures. GL tests use the backend named by ICBTOOL_GL_BACKEND (``make test``: osmesa)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

REPO = Path(__file__).resolve().parents[1]


#: ``make test`` (CI) runs the property tests with ``--hypothesis-profile=ci``: the same examples
#: on every run, so a green run stays green; a plain ``pytest`` draws new examples each time, which
#: is how new counterexamples are found.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)


def sponza_dir() -> Path:
    """Where the Sponza scene is: $ICBTOOL_SPONZA, else ../shared/scenes/sponza beside the repo."""
    return Path(os.environ.get("ICBTOOL_SPONZA", REPO.parent / "shared" / "scenes" / "sponza"))


@pytest.fixture
def sponza_path() -> Path:
    p = sponza_dir() / "sponza_textured.obj"
    if not p.is_file():
        pytest.skip(f"Sponza not found at {p} (set ICBTOOL_SPONZA)")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def pytest_collection_modifyitems(config, items):
    """The desktop app's tests (marker ``gui``) run first, in their own order.

    OpenGL has one owner per process: the window's process draws with Qt's and VTK's OpenGL
    (GLX), and once PyOpenGL is bound to OSMesa / EGL in a process (any test that rasterizes in
    this one), a window's 3D view may stay blank. Running the gui tests before every other test
    makes the order, not the luck of the load, decide (icbtool_gui.app.check_gl_owner refuses
    a window in a process that already holds headless OpenGL). With several test processes
    (``make test``: pytest-xdist, ``--dist loadfile --no-loadscope-reorder``) the files are
    handed out in this order, so the first process starts with the desktop app's file."""
    items.sort(key=lambda item: item.get_closest_marker("gui") is None)  # stable: gui first
