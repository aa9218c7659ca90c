"""Scenes: the data model, procedural scenes with known answers, and loaders for files.

``icb.scene.cornell_box()``, ``icb.scene.load("room.toml")`` (a scene description),
``icb.scene.load("scene.xml")`` (a Mitsuba 3 scene file) or ``icb.scene.load("mesh.obj")`` (a
bare mesh). ``icb.scene.load_scene(SPEC)`` and ``icb.scene.select_cameras(scene, SPEC)`` read a
scene and cameras as the command line names them (a built-in name or a file; ``default`` or
``path:NAME``).
"""

from icbtool.scene import bsdf
from icbtool.scene.animation import Animation, LightTrack, MeshTrack, Track, animate
from icbtool.scene.description import SceneDescription, read_description
from icbtool.scene.emitters import light_faces, promote_emitters
from icbtool.scene.load import has_light, load, load_mesh, with_default_light
from icbtool.scene.obj import MaterialApproximationWarning
from icbtool.scene.procedural import (
    PROCEDURAL,
    boxes_on_floor,
    cornell_box,
    cornell_box_moving_light,
    cornell_camera,
    plane,
    white_furnace,
)
from icbtool.scene.select import load_scene, select_cameras
from icbtool.scene.types import (
    LIGHT_TYPES,
    SHAPE_KINDS,
    AnalyticShape,
    AreaLight,
    DirectionalLight,
    Light,
    Material,
    PointLight,
    Scene,
    SceneBuilder,
    Sky,
    SpotLight,
    light_parameters,
    vertex_normals,
)
from icbtool.scene.validate import SceneError, SceneRepairWarning
from icbtool.scene.view import default_view
from icbtool.scene.walk import check_camera, random_walk, surroundings

__all__ = [
    "bsdf",
    "Animation",
    "LightTrack",
    "MeshTrack",
    "Track",
    "animate",
    "cornell_box_moving_light",
    "LIGHT_TYPES",
    "SHAPE_KINDS",
    "AnalyticShape",
    "light_parameters",
    "PROCEDURAL",
    "AreaLight",
    "DirectionalLight",
    "Light",
    "Material",
    "MaterialApproximationWarning",
    "PointLight",
    "Scene",
    "SceneBuilder",
    "Sky",
    "SpotLight",
    "boxes_on_floor",
    "check_camera",
    "default_view",
    "cornell_box",
    "cornell_camera",
    "plane",
    "random_walk",
    "surroundings",
    "vertex_normals",
    "has_light",
    "light_faces",
    "promote_emitters",
    "load",
    "load_mesh",
    "load_scene",
    "select_cameras",
    "with_default_light",
    "read_description",
    "SceneDescription",
    "SceneError",
    "SceneRepairWarning",
    "white_furnace",
]
