"""Provenance of results: the versions and machine behind a number, and JSON that always lands.

Every command, experiment and benchmark writes :func:`run_info` next to its numbers.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any


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
    # the model name alone does not tell hosts apart ("AMD EPYC"): family/model and the widest
    # SIMD the CPU offers (vectorising code, Mitsuba's JIT for one, runs 2x wider with AVX-512)
    wanted = {"model name": "cpu", "cpu family": "cpu_family", "model": "cpu_model"}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key in wanted and wanted[key] not in info:
                    info[wanted[key]] = value.strip()
                elif key == "flags":
                    flags = set(value.split())
                    simd = ("avx512f", "avx2", "avx", "sse4_2")
                    info["cpu_simd"] = next((x for x in simd if x in flags), "none")
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


__all__ = ["run_info", "to_jsonable", "write_json"]
