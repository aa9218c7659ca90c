"""Alias of :mod:`icbtool.scene.raycast` (the Embree ray-query wrapper lives with the scene)."""

from icbtool.scene.raycast import MIN_RAYS_PER_THREAD, EmbreeScene, Hits

__all__ = ["MIN_RAYS_PER_THREAD", "EmbreeScene", "Hits"]
