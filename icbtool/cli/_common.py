"""Helpers shared by the CLI subcommands."""

from __future__ import annotations

import argparse

from icbtool.provenance import run_info, to_jsonable, write_json


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


__all__ = ["add_scene_argument", "load_scene", "run_info", "to_jsonable", "write_json"]
