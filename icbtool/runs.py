"""Run directories of the trainers (:mod:`icbtool.gan.training`, :mod:`icbtool.radiance.training`):
the helpers both write a run with, so that their runs read alike.

A run directory holds ``config.json``, checkpoints written atomically (:func:`atomic_save`),
``evals.json`` + ``evals.csv`` (:func:`write_evals`) and sample strips (:func:`sample_png`).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.imageio import to_display, write_png
from icbtool.provenance import write_json


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save(obj)`` to ``path`` through a temporary file and ``os.replace``: a reader (or
    a crash) never sees half a checkpoint."""
    import torch

    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def sample_png(path: Path, pred: np.ndarray, truth: np.ndarray, exposure: float) -> None:
    """Prediction | truth | their absolute difference (display scale), side by side.

    Args:
        path: the PNG to write.
        pred, truth: (H, W, 3) float32 linear HDR.
        exposure: of the display transform.
    """
    a, b = to_display(pred, exposure), to_display(truth, exposure)
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).astype(np.uint8)
    write_png(path, np.concatenate([a, b, diff], axis=1))


def scene_key(scene: Any) -> str | None:
    """How a run names the scene it trained on: None, a name or hash as given, or a scene's
    ``name (content hash, light hash)``."""
    if scene is None or isinstance(scene, str):
        return scene
    return f"{getattr(scene, 'name', '?')} ({scene.content_hash}, light {scene.light_hash})"


def write_evals(run_dir: Path, evals: list[dict[str, Any]], columns: Sequence[str]) -> None:
    """``evals.json`` (every key) and ``evals.csv`` (``columns``), the CSV written atomically."""
    write_json(run_dir / "evals.json", evals)
    tmp = run_dir / "evals.csv.tmp"
    with open(tmp, "w", newline="") as f:
        wr = csv.DictWriter(f, list(columns), extrasaction="ignore")
        wr.writeheader()
        wr.writerows(evals)
    os.replace(tmp, run_dir / "evals.csv")


__all__ = ["atomic_save", "sample_png", "scene_key", "write_evals"]
