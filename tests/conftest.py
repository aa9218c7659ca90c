"""Shared fixtures. GL tests use the backend named by ICBTOOL_GL_BACKEND (``make test``: osmesa)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


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
