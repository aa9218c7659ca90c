"""What a command names, made into objects: a scene spec (a built-in name or a file) into a
:class:`~icbtool.scene.Scene`, a camera spec (``default`` or ``path:NAME``) into cameras.

These are the command line's readings of SCENE and ``--camera``, public so that the desktop app,
the benchmarks and scripts read them exactly as ``icbtool`` does.
"""

from __future__ import annotations

import sys

from icbtool.camera import Camera
from icbtool.scene.load import has_light, load, with_default_light
from icbtool.scene.procedural import PROCEDURAL
from icbtool.scene.types import Scene
from icbtool.scene.view import default_view


def load_scene(
    spec: str,
    up_axis: str | None = None,
    default_light: bool = False,
    require_light: bool = False,
) -> Scene:
    """A procedural scene by name, else a file through :func:`icbtool.scene.load`.

    Args:
        spec: procedural scene name or file.
        up_axis: the file's up axis (None: the file's or description's default).
        default_light: light a scene that has no light at all with
            :func:`icbtool.scene.with_default_light` (which logs a note); the command line's
            ``--default-light``.
        require_light: a scene without any light (and no ``default_light``) is an error (the
            commands that render light: an unlit scene would render black).

    On a terminal (stderr), a Mitsuba file shows a bar over its shapes while they load.

    Returns:
        The scene.

    Raises:
        ValueError: ``up_axis`` given for a procedural scene.
        SceneError: no light with ``require_light``; a Mitsuba file whose only emitters cannot
            be rendered, without ``default_light``.
    """
    from icbtool.scene.validate import SceneError

    if spec in PROCEDURAL:
        if up_axis is not None:
            raise ValueError(f"--up-axis applies to scene files, not to procedural '{spec}'")
        scene = PROCEDURAL[spec]()
    else:
        bar = sys.stderr.isatty()  # a bar over a Mitsuba file's shapes while they load
        kw = {} if up_axis is None else {"up_axis": up_axis}
        scene = load(spec, progress=bar, default_light=default_light, **kw)
    if default_light:  # logs a note (WARNING) when it adds the default light
        scene = with_default_light(scene)
    if require_light and not has_light(scene):
        raise SceneError(
            f"{spec}: the scene has no light (no lights, sky or emissive faces) and would render "
            "black; pass --default-light to light it with icbtool's default sun and sky"
        )
    return scene


def select_cameras(
    scene: Scene,
    spec: str,
    every: int = 1,
    height: int | None = None,
    width: int | None = None,
    fov_y_deg: float | None = None,
) -> list[tuple[str, Camera]]:
    """The cameras a CLI command renders: ``(name, Camera)`` pairs.

    Args:
        scene: the scene.
        spec: "default" (the scene's default camera; without one,
            :func:`icbtool.scene.view.default_view`: a view from inside the largest room of an
            interior, else :meth:`Camera.frame` of the bounds; 45 degrees, 256 x 256) or
            "path:NAME" (every ``every``-th camera of that path, named ``NAME_0000``...).
        every: keep every K-th camera of a path (>= 1).
        height, width: output size. Given alone, the other side follows the camera's aspect
            ratio; with both, the view is resized to exactly that (the FOV follows the image).
        fov_y_deg: replace the vertical field of view (of an orthographic camera's
            :meth:`~icbtool.camera.Camera.pinhole`).

    Returns:
        The (name, camera) pairs.

    Raises:
        ValueError: bad ``spec``/``every``/size, or a path the scene does not have.
    """
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
            cam = default_view(scene, fov_y_deg=fov_y_deg or 45.0, height=h, width=w)
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
        if fov_y_deg is not None:  # an orthographic camera has none: its pinhole's changes
            c = (c if c.projection == "perspective" else c.pinhole()).with_fov(fov_y_deg)
        if height is not None or width is not None:
            h = height or max(1, round(c.height * (width / c.width)))
            w = width or max(1, round(c.width * (height / c.height)))
            if (h, w) != (c.height, c.width):
                c = c.resized(int(h), int(w))
        out.append((n, c))
    return out


__all__ = ["load_scene", "select_cameras"]
