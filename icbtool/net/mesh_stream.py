"""What the server streams of its scene: a *base* (lights, sky, camera paths; JSON) and mesh
levels, coarse to fine, each a list of chunks.

:class:`MeshStream` is the one place the server asks for levels and the client rebuilds them
(:func:`assemble`). Levels are always the LPM's (:mod:`icbtool.lpm`, layout in docs/lpm.md):
without open3d, or with ``lpm=False``, the stream has one level, the full scene, in the same
chunk layout (an LPM of the single ratio 1, which needs no decimation), so a client reads one
format. The base carries no geometry; everything it holds the client needs to shade (lights) or
to move (paths), and none of it is the protected full-detail mesh.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from icbtool.camera import Camera, CameraPath
from icbtool.scene import types as st

log = logging.getLogger(__name__)

Chunk = tuple[str, str, bytes]


def _plain(v: Any) -> Any:
    return v.tolist() if isinstance(v, np.ndarray) else v


def _fields(obj: Any) -> dict[str, Any]:
    return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}


def scene_base(scene: st.Scene) -> dict[str, Any]:
    """The JSON-able part of ``scene`` a client needs besides the mesh (no geometry)."""
    return {
        "name": scene.name,
        "lights": [_fields(li) for li in scene.lights],
        "sky": None if scene.sky is None else _fields(scene.sky),
        "paths": {k: p.to_dict() for k, p in scene.paths.items()},
        "default_camera": (
            None if scene.default_camera is None else scene.default_camera.pinhole().to_dict()
        ),
        "up": _plain(np.asarray(scene.up)),
    }


def base_parts(base: dict[str, Any]) -> dict[str, Any]:
    """The :class:`~icbtool.scene.Scene` keyword arguments of a base (inverse of
    :func:`scene_base`): lights, sky and up through :func:`icbtool.lpm.read_scene_info`, plus
    the name, camera paths and default camera.

    Raises:
        ValueError: a light of unknown kind, or a field that does not validate.
    """
    from icbtool.lpm import read_scene_info

    cam = base.get("default_camera")
    return {
        "name": str(base["name"]),
        **read_scene_info(base),
        "paths": {k: CameraPath.from_dict(p) for k, p in base.get("paths", {}).items()},
        "default_camera": None if cam is None else Camera.from_dict(cam),
    }


@dataclass(frozen=True)
class MeshLevel:
    """One level of the stream.

    Attributes:
        index: 0 = coarsest.
        triangles: its triangle count.
        chunks: ``(name, part, data)`` in sending order.
    """

    index: int
    triangles: int
    chunks: tuple[Chunk, ...]

    @property
    def nbytes(self) -> int:
        return sum(len(c[2]) for c in self.chunks)


class MeshStream:
    """The server's view of what it streams: the base and the levels, coarse to fine.

    Args:
        scene: the full-detail scene (stays on the server).
        lpm: build levels of detail with :func:`icbtool.lpm.build`; False, or open3d missing
            where a level needs decimation (logged), streams the full mesh as the only level
            (in the LPM's layout).
        lpm_config: :class:`icbtool.lpm.LPMConfig` (default: its defaults).
        send_full: also stream the LPM's finest level, which is the full-detail mesh itself.
            Off by default: the full-detail mesh never leaves the server (docs/design.md section 1),
            unless it is the only level there is.
        max_chunk_bytes: the LPM's chunk size bound.
    """

    def __init__(
        self,
        scene: st.Scene,
        lpm: bool = True,
        lpm_config: Any = None,
        send_full: bool = False,
        max_chunk_bytes: int = 2**20,
    ) -> None:
        self.base = scene_base(scene)
        self.levels: list[MeshLevel] = []
        self._pieces: dict[tuple[int, int], list[tuple[str, str, bytes, str]]] = {}
        from icbtool import lpm as lpm_mod
        from icbtool.optional import MissingOptionalDependency

        cfg = lpm_config or lpm_mod.LPMConfig()
        cfg = dataclasses.replace(cfg, max_chunk_bytes=min(cfg.max_chunk_bytes, max_chunk_bytes))
        whole = dataclasses.replace(cfg, ratios=(1.0,), texture_max=(0,))  # no decimation
        t0 = time.perf_counter()
        built = None
        if lpm:
            try:
                built = lpm_mod.build(scene, cfg)
            except MissingOptionalDependency as e:
                log.warning("no LPM (%s): streaming the full mesh as one level", e)
        if built is None:
            built = lpm_mod.build(scene, whole)
        kept = [lv for lv in built.levels if send_full or lv.ratio < 1.0] or built.levels
        self.levels = [MeshLevel(lv.index, lv.n_triangles, tuple(lv.to_chunks())) for lv in kept]
        self.build_s = time.perf_counter() - t0

    def pieces(self, level: MeshLevel, chunk_bytes: int) -> list[tuple[str, str, bytes, str]]:
        """``level``'s files cut into pieces of at most ``chunk_bytes``, in sending order, as
        ``(name, part, piece, sha256 hex)``: the ``lpm_chunk`` messages (cut and hashed once per
        level and size, not for every client)."""
        key = (level.index, chunk_bytes)
        if key not in self._pieces:
            self._pieces[key] = [
                (name, part, piece, hashlib.sha256(piece).hexdigest())
                for name, part, data in level.chunks
                for piece in (
                    data[i : i + chunk_bytes] for i in range(0, max(len(data), 1), chunk_bytes)
                )
            ]
        return self._pieces[key]

    def info(self, chunk_bytes: int) -> list[dict[str, Any]]:
        """Per level: level, triangles, bytes, chunks (messages when files are cut into pieces of
        ``chunk_bytes``): the ``scene_info.lpm.levels`` entries."""
        return [
            {
                "level": lv.index,
                "triangles": lv.triangles,
                "bytes": lv.nbytes,
                "chunks": len(self.pieces(lv, chunk_bytes)),
            }
            for lv in self.levels
        ]


def assemble(chunks: list[Chunk], base: dict[str, Any]) -> st.Scene:
    """The client side of :class:`MeshStream`: one level's chunks plus the base -> a Scene.

    The chunks go to :func:`icbtool.lpm.assemble` (lights, sky and up from the base); the base
    adds the camera paths and the default camera to what the LPM carries.

    Raises:
        ValueError: a missing or damaged chunk (the message names it).
    """
    from icbtool import lpm as lpm_mod

    scene = lpm_mod.assemble(chunks, base={k: base[k] for k in ("lights", "sky", "up")})
    extra = base_parts(base)
    return dataclasses.replace(scene, paths=extra["paths"], default_camera=extra["default_camera"])


__all__ = ["MeshLevel", "MeshStream", "assemble", "base_parts", "scene_base"]
