"""Cameras: the one pinhole model (:class:`Camera`) and timed camera paths (:class:`CameraPath`).

See :mod:`icbtool.camera.camera` for the conventions every module follows.
"""

from icbtool.camera.camera import Camera, look_at_pose, pose_from_forward
from icbtool.camera.path import CameraPath
from icbtool.camera.walk import CameraPlacementError, check_camera, random_walk

__all__ = [
    "Camera",
    "CameraPath",
    "CameraPlacementError",
    "check_camera",
    "look_at_pose",
    "pose_from_forward",
    "random_walk",
]
