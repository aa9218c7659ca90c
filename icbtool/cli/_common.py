"""Helpers shared by the CLI subcommands."""

from __future__ import annotations

import argparse
from typing import Any

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


def add_up_axis_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--up-axis",
        choices=("auto", "y", "z", "x"),
        default=None,
        help="the mesh file's up axis (rotated to +y); default 'auto': y for glTF, guessed for "
        "OBJ/PLY (see icbtool.scene.load.guess_up_axis)",
    )


def load_scene(spec: str, up_axis: str | None = None, default_light: bool = False):
    """A procedural scene by name, else a file through :func:`icbtool.scene.load`.

    Args:
        spec: procedural scene name or file.
        up_axis: the file's up axis (None: the file's or description's default).
        default_light: light a scene that has no light at all with
            :func:`icbtool.scene.with_default_light` (which logs a note).

    Raises:
        ValueError: ``up_axis`` given for a procedural scene.
    """
    from icbtool import scene as sc

    if spec in sc.PROCEDURAL:
        if up_axis is not None:
            raise ValueError(f"--up-axis applies to scene files, not to procedural '{spec}'")
        scene = sc.PROCEDURAL[spec]()
    else:
        scene = sc.load(spec) if up_axis is None else sc.load(spec, up_axis=up_axis)
    if default_light:  # logs a note (WARNING) when it adds the default light
        scene = sc.with_default_light(scene)
    return scene


def select_cameras(
    scene: Any,
    spec: str,
    every: int = 1,
    height: int | None = None,
    width: int | None = None,
    fov_y_deg: float | None = None,
) -> list[tuple[str, Any]]:
    """The cameras a CLI command renders: ``(name, Camera)`` pairs.

    Args:
        scene: the scene.
        spec: "default" (the scene's default camera; without one, :meth:`Camera.frame` of the
            scene bounds with ``scene.up``, 45 degrees, 256 x 256) or "path:NAME" (every
            ``every``-th camera of that path, named ``NAME_0000``...).
        every: keep every K-th camera of a path (>= 1).
        height, width: output size. Given alone, the other side follows the camera's aspect
            ratio; with both, the view is resized to exactly that (the FOV follows the image).
        fov_y_deg: replace the vertical field of view.

    Returns:
        The (name, camera) pairs.

    Raises:
        ValueError: bad ``spec``/``every``/size, or a path the scene does not have.
    """
    from icbtool.camera import Camera

    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    for name, v in (("--height", height), ("--width", width)):
        if v is not None and v < 1:
            raise ValueError(f"{name} must be >= 1, got {v}")
    if spec == "default":
        cam = scene.default_camera
        if cam is None:
            h = height or width or 256
            w = width or height or 256
            cam = Camera.frame(
                scene.bounds, up=scene.up, fov_y_deg=fov_y_deg or 45.0, height=h, width=w
            )
        cams = [("default", cam)]
    elif spec.startswith("path:"):
        name = spec[5:]
        if name not in scene.paths:
            raise ValueError(
                f"scene '{scene.name}' has no camera path {name!r}; it has {sorted(scene.paths)}"
            )
        cams = [(f"{name}_{i:04d}", c) for i, c in enumerate(scene.paths[name].cameras())]
        cams = cams[::every]
    else:
        raise ValueError(f"--camera must be 'default' or 'path:NAME', got {spec!r}")
    out = []
    for n, c in cams:
        if fov_y_deg is not None:
            c = c.with_fov(fov_y_deg)
        if height is not None or width is not None:
            h = height or max(1, round(c.height * (width / c.width)))
            w = width or max(1, round(c.width * (height / c.height)))
            if (h, w) != (c.height, c.width):
                c = c.resized(int(h), int(w))
        out.append((n, c))
    return out


__all__ = [
    "add_scene_argument",
    "add_up_axis_argument",
    "load_scene",
    "run_info",
    "select_cameras",
    "to_jsonable",
    "write_json",
]
