"""Cameras: the one pinhole model (:class:`Camera`) and timed camera paths (:class:`CameraPath`).

See :mod:`icbtool.camera.camera` for the conventions every module follows. Scene-aware camera
motion (the random walk, the "inside a wall" check) is in :mod:`icbtool.scene.walk`: this package
imports nothing else of icbtool.
"""

from icbtool.camera.camera import (
    Camera,
    CameraPlacementError,
    default_view_direction,
    look_at_pose,
    pose_from_forward,
)
from icbtool.camera.path import CameraPath

__all__ = [
    "Camera",
    "CameraPath",
    "CameraPlacementError",
    "default_view_direction",
    "look_at_pose",
    "pose_from_forward",
]
