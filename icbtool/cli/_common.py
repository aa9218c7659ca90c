"""Helpers shared by the CLI subcommands."""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any


def add_scene_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "scene",
        help="a procedural scene name (cornell_box, white_furnace, plane, boxes_on_floor), "
        "a scene description (.toml) or a mesh file (.obj, .ply, .glb, .gltf)",
    )


def add_denoise_quality_argument(p: argparse.ArgumentParser) -> None:
    from icbtool.trace.tracer import DENOISE_QUALITIES

    p.add_argument(
        "--denoise-quality",
        choices=DENOISE_QUALITIES,
        default="high",
        help="OIDN quality ('fast': about half the denoising time)",
    )


def load_scene(spec: str):
    """A procedural scene by name, else a file through :func:`icbtool.scene.load`."""
    from icbtool import scene as sc

    if spec in sc.PROCEDURAL:
        return sc.PROCEDURAL[spec]()
    return sc.load(spec)


def run_info() -> dict[str, Any]:
    """Versions of icbtool and key libraries, and the machine, for provenance files."""
    import icbtool

    info: dict[str, Any] = {
        "icbtool": icbtool.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "argv": sys.argv,
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    from importlib import metadata

    for pkg in (
        "numpy",
        "embreex",
        "pyrender",
        "PyOpenGL",
        "torch",
        "kornia",
        "open3d-cpu",
        "opencv-contrib-python-headless",
        "trimesh",
    ):
        try:
            info[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return info


def to_jsonable(obj: Any) -> Any:
    import numpy as np

    if is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | os.PathLike, data: Any) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(data), indent=2))
    os.replace(tmp, path)
    return path


__all__ = ["add_scene_argument", "load_scene", "run_info", "to_jsonable", "write_json"]
