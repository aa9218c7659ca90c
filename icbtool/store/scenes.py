"""The scenes of a store: each scene's octree geometry (fixed when the scene is registered,
so records keep their leaves) and its entry in the payload headers. :class:`ScenesMixin` is
that part of :class:`icbtool.store.Store`."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from icbtool.store.octree import OctreeGeometry
from icbtool.store.record import (
    CRTBuffer,
)


class ScenesMixin:
    """Scene registration and octree geometry (part of :class:`~icbtool.store.Store`)."""

    def register_scene(
        self,
        scene: Any = None,
        *,
        scene_hash: str | None = None,
        bounds: Any = None,
        name: str = "",
    ) -> OctreeGeometry:
        """Fix the octree of a scene (from a :class:`~icbtool.scene.Scene` or hash + bounds).

        The geometry of a scene never changes once registered (records keep their leaves). A scene
        first seen through :meth:`put` is registered from ``meta.scene_bounds`` or, without them,
        from the record's masked positions and camera centre.
        """
        if scene is not None:
            scene_hash, bounds, name = scene.content_hash, scene.bounds, scene.name
        if scene_hash is None or bounds is None:
            raise ValueError("register_scene needs a scene, or scene_hash and bounds")
        if scene_hash in self._geoms:
            return self._geoms[scene_hash]
        conn = self._writable()
        leaf = self.config.leaf_size or 2.0 * self.config.alpha_pos
        geom = OctreeGeometry.for_bounds(
            np.asarray(bounds, np.float64), leaf, self.config.max_depth
        )
        conn.execute(
            "INSERT OR IGNORE INTO scenes VALUES (?, ?, ?, ?, ?, ?)",
            (
                scene_hash,
                name,
                json.dumps(np.asarray(bounds, np.float64).tolist()),
                json.dumps(list(geom.root_min)),
                geom.root_size,
                geom.depth,
            ),
        )
        row = conn.execute(
            "SELECT root_min, root_size, depth FROM scenes WHERE scene_hash=?", (scene_hash,)
        ).fetchone()
        geom = OctreeGeometry(tuple(json.loads(row[0])), row[1], row[2])
        self._geoms[scene_hash] = geom
        return geom

    def geometry(self, scene_hash: str) -> OctreeGeometry:
        """The octree geometry (root cube, depth) of a registered scene.

        Raises:
            KeyError: if the scene is not registered.
        """
        if scene_hash not in self._geoms:
            raise KeyError(f"scene {scene_hash!r} is not registered in store {self.root}")
        return self._geoms[scene_hash]

    def _bounds_for(self, buf: CRTBuffer) -> np.ndarray:
        if buf.meta.scene_bounds is not None:
            return np.asarray(buf.meta.scene_bounds, np.float64)
        pts = [buf.camera.position[None]]
        if buf.position is not None:
            m = (
                buf.mask[..., 0] > 0
                if buf.mask is not None
                else np.ones(buf.position.shape[:2], bool)
            )
            pts.append(buf.position[m].astype(np.float64))
        p = np.concatenate(pts)
        p = p[np.all(np.isfinite(p), axis=1)]  # the camera centre is always finite
        return np.stack([p.min(0), p.max(0)])

    def _scene_entry(self, scene_hash: str) -> dict[str, Any]:
        """A registered scene's row, as written into its records' payload headers."""
        name, bounds, root_min, size, depth = (
            self._db()
            .execute(
                "SELECT scene_name, bounds, root_min, root_size, depth FROM scenes "
                "WHERE scene_hash=?",
                (scene_hash,),
            )
            .fetchone()
        )
        return {
            "name": name,
            "bounds": json.loads(bounds),
            "root_min": json.loads(root_min),
            "root_size": size,
            "depth": depth,
        }
