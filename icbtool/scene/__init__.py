"""Scenes: the data model, procedural scenes with known answers, and loaders for files.

``icb.scene.cornell_box()``, ``icb.scene.load("room.toml")`` (a scene description) or
``icb.scene.load("mesh.obj")`` (a bare mesh).
"""

from icbtool.scene.procedural import (
    PROCEDURAL,
    boxes_on_floor,
    cornell_box,
    cornell_camera,
    plane,
    white_furnace,
)
from icbtool.scene.types import (
    AreaLight,
    DirectionalLight,
    Light,
    Material,
    PointLight,
    Scene,
    SceneBuilder,
    Sky,
    SpotLight,
    vertex_normals,
)

__all__ = [
    "PROCEDURAL",
    "AreaLight",
    "DirectionalLight",
    "Light",
    "Material",
    "PointLight",
    "Scene",
    "SceneBuilder",
    "Sky",
    "SpotLight",
    "boxes_on_floor",
    "cornell_box",
    "cornell_camera",
    "plane",
    "vertex_normals",
    "white_furnace",
]
