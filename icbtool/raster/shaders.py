"""GLSL sources, stored as files in ``icbtool/raster/shaders/`` and loaded by name (cached)."""

from __future__ import annotations

import functools
from importlib import resources

GLSL_VERSION = "#version 330 core"


@functools.cache
def load_shader(name: str) -> str:
    """The text of ``shaders/<name>`` (e.g. ``"scene.frag"``).

    Raises:
        FileNotFoundError: if there is no such shader file.
    """
    path = resources.files("icbtool.raster").joinpath("shaders", name)
    if not path.is_file():
        raise FileNotFoundError(f"no shader named {name!r} in icbtool/raster/shaders/")
    return path.read_text()


def with_defines(name: str, defines: dict[str, object]) -> str:
    """The shader ``name`` with the version line and ``#define KEY VALUE`` lines prepended."""
    lines = [GLSL_VERSION]
    for k, v in defines.items():
        lines.append(f"#define {k}" if v is None or v is True else f"#define {k} {v}")
    return "\n".join(lines) + "\n#line 1\n" + load_shader(name)
