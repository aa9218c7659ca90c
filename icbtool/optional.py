"""Optional dependencies: import them through :func:`require` so that a missing one names its extra.

The extras are declared in setup.cfg (``[options.extras_require]``); :data:`EXTRAS` maps each
optional top-level module to the extra that installs it. A missing module raises
:class:`MissingOptionalDependency` (an ImportError) whose message says what needs it and what to
install, e.g. ``pip install ".[denoise]"`` run in the icbtool checkout (icbtool is not on a package
registry, so ``pip install "icbtool[denoise]"`` would fail), or the distribution alone
(``pip install pyoidn``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: Optional top-level module -> (extra that installs it, the PyPI distribution).
EXTRAS: dict[str, tuple[str, str]] = {
    "open3d": ("mesh", "open3d-cpu"),
    "pyoidn": ("denoise", "pyoidn"),
    "flip_evaluator": ("metrics", "flip-evaluator"),
    "pyvista": ("gui", "pyvista"),
    "pyvistaqt": ("gui", "pyvistaqt"),
    "PySide6": ("gui", "PySide6-Essentials"),
    "qtpy": ("gui", "QtPy"),
    "mitsuba": ("bench", "mitsuba"),
    "onnx": ("gan", "onnx"),
    "onnxruntime": ("gan", "onnxruntime"),
    "tensorboard": ("gan", "tensorboard"),
    "websockets": ("net", "websockets"),
    "cryptography": ("net", "cryptography"),
    "zstandard": ("net", "zstandard"),
    "dask": ("cloud", "dask[distributed]"),
    "distributed": ("cloud", "dask[distributed]"),
    "tornado": ("cloud", "dask[distributed]"),  # distributed's web server, installed with it
    "psutil": ("cloud", "dask[distributed]"),  # process memory outside Linux, installed with it
}


class MissingOptionalDependency(ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


def install_hint(module: str) -> str:
    """The pip command that installs optional ``module`` (its extra).

    Raises:
        ValueError: ``module`` is not an optional dependency of icbtool.
    """
    top = module.split(".", 1)[0]
    if top not in EXTRAS:
        raise ValueError(
            f"{module!r} is not an optional dependency of icbtool; known: {sorted(EXTRAS)}"
        )
    extra, dist = EXTRAS[top]
    return f'pip install ".[{extra}]" in the icbtool checkout (or pip install {dist})'


def require(module: str, purpose: str) -> ModuleType:
    """Import optional ``module`` (e.g. ``"pyoidn"``, ``"open3d"``) or explain how to install it.

    Args:
        module: the module to import (a submodule such as ``"mitsuba.foo"`` is allowed; its top
            level must be in :data:`EXTRAS`).
        purpose: what needs it, for the message (e.g. ``"denoising"``).

    Returns:
        The imported module.

    Raises:
        ValueError: ``module`` is not a known optional dependency (a programming error).
        MissingOptionalDependency: the module (or a library it needs) cannot be imported; the
            message names the extra, and the original ImportError is chained.
    """
    hint = install_hint(module)
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise MissingOptionalDependency(
            f"{purpose} needs the optional package {module!r}, which could not be imported "
            f"({e}); install it with: {hint}"
        ) from e


__all__ = ["EXTRAS", "MissingOptionalDependency", "install_hint", "require"]
