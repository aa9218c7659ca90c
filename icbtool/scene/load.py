"""Load a scene from a file: a TOML scene description, a Mitsuba 3 scene file or a bare mesh.

:func:`load` dispatches on the suffix: ``.toml`` (:mod:`icbtool.scene.description`), ``.xml``
(:mod:`icbtool.scene.mitsuba`), ``.obj``/``.gltf``/``.glb``/``.ply`` (:mod:`icbtool.scene.mesh`,
where materials, up axis and repairs are documented), then promotes the emissive faces to area
lights. It is the one module that imports the three readers (they never import it): the
description reads its meshes through :mod:`icbtool.scene.mesh`, not through here.

The names of :mod:`icbtool.scene.mesh` (``load_mesh``, ``decode_texture``, ``guess_up_axis``...)
are also available from this module.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from typing import Any

import numpy as np

from icbtool.scene.description import read_description
from icbtool.scene.emitters import DEFAULT_EMITTER_BUDGET, promote_emitters
from icbtool.scene.mesh import (
    DROPPED_GLTF_MAPS,
    MESH_OPTIONS,
    METALLIC_THRESHOLD,
    UP_AXES,
    UP_AXIS_ROTATIONS,
    Z_UP_AREA_RATIO,
    UpAxisGuess,
    decode_texture,
    guess_up_axis,
    load_mesh,
    up_axis_evidence,
)
from icbtool.scene.mitsuba import load_mitsuba
from icbtool.scene.types import Scene
from icbtool.scene.validate import (
    DESCRIPTION_SUFFIXES,
    MESH_SUFFIXES,
    MITSUBA_SUFFIXES,
    SceneError,
    check_file,
)

log = logging.getLogger(__name__)

#: Scene fields that may be given to :func:`load` for a bare mesh.
SCENE_FIELDS = ("lights", "sky", "paths", "default_camera")
#: Options of :func:`load` itself (for meshes and descriptions alike).
LOAD_OPTIONS = ("emitter_budget", "progress", "default_light")


def load(
    path: str | os.PathLike,
    *,
    emitter_budget: int = DEFAULT_EMITTER_BUDGET,
    progress: bool = False,
    default_light: bool = False,
    **overrides: Any,
) -> Scene:
    """Load a scene description (.toml), a Mitsuba 3 scene (.xml) or a bare mesh file (.obj,
    .gltf, .glb, .ply).

    The mesh's emissive faces (OBJ ``Ke``, glTF ``emissiveFactor`` without texture) become area
    lights (:func:`icbtool.scene.emitters.promote_emitters`): their light is direct light (raster
    DL, the tracer's ``direct``), not GI, while the faces stay in the mesh for the camera. When
    there are more than ``emitter_budget`` of them (not counting faces of the description's own
    area lights) they stay seen emission, their light in GI, and a warning says so.

    Args:
        path: the file.
        emitter_budget: at most this many emissive triangles are promoted to lights (>= 0; 0:
            none, every emissive face stays seen emission). Default
            :data:`~icbtool.scene.emitters.DEFAULT_EMITTER_BUDGET` (64).
        progress: show a tqdm bar (stderr) over a Mitsuba file's shapes as they load (other
            files load as one step).
        default_light: light a scene that has no light with :func:`with_default_light` (a
            warning says so). Without it an unlit scene loads unlit, except a Mitsuba file whose
            only emitters icbtool cannot render (``sunsky``...): that is an error naming them.
        **overrides: for a mesh, any of ``name``, ``scale``, ``up_axis``, ``translation``,
            ``textures`` (see :func:`load_mesh`) and the Scene fields ``lights``, ``sky``,
            ``paths``, ``default_camera``. For a description, the same keys replace the
            description's values (see :meth:`SceneDescription.build
            <icbtool.scene.description.SceneDescription.build>`). For a Mitsuba file:
            ``params`` (its ``$`` parameters), ``textures``, ``name``, the Scene fields and
            ``max_depth`` (see :func:`icbtool.scene.mitsuba.load_mitsuba`).

    Returns:
        The merged :class:`Scene`.

    Raises:
        FileNotFoundError: missing file (or missing mesh named by a description).
        SceneError: unknown file type, unusable content, bad description (message names the
            file); a Mitsuba file whose only emitters cannot be rendered, without
            ``default_light``.
        TypeError: an unknown override.
    """
    p = check_file(path, MESH_SUFFIXES + DESCRIPTION_SUFFIXES + MITSUBA_SUFFIXES)
    if (
        isinstance(emitter_budget, bool)
        or not isinstance(emitter_budget, (int, np.integer))
        or emitter_budget < 0
    ):
        raise SceneError(f"{p}: emitter_budget must be an integer >= 0, got {emitter_budget!r}")
    if p.suffix.lower() in DESCRIPTION_SUFFIXES:
        scene = read_description(p).build(**overrides)
        return _lit(promote_emitters(scene, int(emitter_budget)), default_light)
    if p.suffix.lower() in MITSUBA_SUFFIXES:
        scene = load_mitsuba(p, progress=progress, default_light=default_light, **overrides)
        return _lit(promote_emitters(scene, int(emitter_budget)), default_light)
    unknown = set(overrides) - set(MESH_OPTIONS) - set(SCENE_FIELDS)
    if unknown:
        raise TypeError(
            f"load({p.name}): unknown override(s) {sorted(unknown)}; "
            f"allowed: {sorted(MESH_OPTIONS + SCENE_FIELDS + LOAD_OPTIONS)}"
        )
    mesh_kw = {k: v for k, v in overrides.items() if k in MESH_OPTIONS}
    scene = load_mesh(p, **mesh_kw)
    scene = dataclasses.replace(scene, **{k: overrides[k] for k in SCENE_FIELDS if k in overrides})
    return _lit(promote_emitters(scene, int(emitter_budget)), default_light)


def _lit(scene: Scene, default_light: bool) -> Scene:
    return with_default_light(scene) if default_light else scene


#: Irradiance (W/m^2, white) of the default sun of :func:`with_default_light`.
DEFAULT_SUN_IRRADIANCE = 2.5
#: Radiances of the default gradient sky of :func:`with_default_light` (zenith, horizon, ground).
DEFAULT_SKY_RADIANCE = ((0.35, 0.45, 0.6), (0.6, 0.6, 0.6), (0.15, 0.15, 0.15))


def has_light(scene: Scene) -> bool:
    """True when the scene has a light, a sky or an emissive face."""
    return bool(scene.lights) or scene.sky is not None or len(scene.emissive_faces) > 0


def with_default_light(scene: Scene) -> Scene:
    """The scene itself if it has any light; else a copy lit by the documented default light.

    A bare mesh (no lights, no sky, no emissive faces) would render black. The default light
    is a sun and a sky, both defined relative to ``scene.up``:

    * a :class:`DirectionalLight` "default_sun" of :data:`DEFAULT_SUN_IRRADIANCE` W/m^2 (white)
      travelling along ``normalize(-up - 0.5 * front + 0.3 * right)``, where ``front`` is the
      side the automatic camera stands on (:func:`icbtool.camera.camera.default_view_direction`)
      and ``right`` its right: it comes from above, from the front and a little from the left,
      so the faces the default camera sees are lit and cast visible shadows;
    * a gradient :class:`Sky` (:data:`DEFAULT_SKY_RADIANCE`: blue-grey zenith, grey horizon,
      dark ground), which lights the shadows through the path tracer's GI.

    A note is logged (logger ``icbtool.scene.load``, level WARNING) when the light is added.

    Args:
        scene: the scene (never modified).

    Returns:
        ``scene`` unchanged, or a new Scene (``dataclasses.replace``) with the light.
    """
    from icbtool.camera.camera import default_view_direction
    from icbtool.scene.types import DirectionalLight, Sky

    if has_light(scene):
        return scene
    up = np.asarray(scene.up, np.float64)
    view = default_view_direction(up)
    front = -(view - (view @ up) * up)
    front /= np.linalg.norm(front)
    right = np.cross(view, up)
    right /= np.linalg.norm(right)
    sun = DirectionalLight(
        direction=-up - 0.5 * front + 0.3 * right,
        irradiance=np.full(3, DEFAULT_SUN_IRRADIANCE),
        name="default_sun",
    )
    zenith, horizon, ground = DEFAULT_SKY_RADIANCE
    sky = Sky(zenith=zenith, horizon=horizon, ground=ground, kind="gradient", up=up)
    log.warning(
        "scene '%s' has no light (no lights, sky or emissive faces): using the default sun "
        "(%.3g W/m^2) and gradient sky (icbtool.scene.with_default_light)",
        scene.name,
        DEFAULT_SUN_IRRADIANCE,
    )
    return dataclasses.replace(scene, lights=(sun,), sky=sky)


__all__ = [
    "DEFAULT_SKY_RADIANCE",
    "DEFAULT_SUN_IRRADIANCE",
    "DROPPED_GLTF_MAPS",
    "LOAD_OPTIONS",
    "MESH_OPTIONS",
    "METALLIC_THRESHOLD",
    "SCENE_FIELDS",
    "UP_AXES",
    "UP_AXIS_ROTATIONS",
    "UpAxisGuess",
    "Z_UP_AREA_RATIO",
    "decode_texture",
    "guess_up_axis",
    "has_light",
    "load",
    "load_mesh",
    "up_axis_evidence",
    "with_default_light",
]
