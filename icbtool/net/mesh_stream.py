"""What the server streams of its scene: a *base* (lights, sky, camera paths; JSON) and mesh
levels, coarse to fine, each a list of chunks.

:class:`MeshStream` is the one place the server asks for levels and the client rebuilds them
(:func:`assemble`), so the level-of-detail builder (the LPM, :mod:`icbtool.lpm`) plugs in here.
Without it, the stream has one level: the full scene (``full_levels``).

A chunk is ``(name, part, data)``: ``name`` the file within the level (``vertices``, ``faces``,
``texture_3``, ...), ``part`` ``"mesh"`` or ``"texture"``, ``data`` a ``.npy`` array (never
pickle) or UTF-8 JSON. The base carries no geometry; everything it holds the client needs to
shade (lights) or to move (paths), and none of it is the protected full-detail mesh.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from icbtool.camera import Camera, CameraPath
from icbtool.scene import types as st

log = logging.getLogger(__name__)

#: Light classes by their ``kind`` field.
_LIGHTS: dict[str, type] = {
    "directional": st.DirectionalLight,
    "point": st.PointLight,
    "spot": st.SpotLight,
    "area": st.AreaLight,
}

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
            None if scene.default_camera is None else scene.default_camera.to_dict()
        ),
        "up": _plain(np.asarray(scene.up)),
    }


def base_parts(base: dict[str, Any]) -> dict[str, Any]:
    """The :class:`~icbtool.scene.Scene` keyword arguments of a base (inverse of
    :func:`scene_base`).

    Raises:
        ValueError: a light of unknown kind, or a field that does not validate.
    """
    lights = []
    for d in base.get("lights", []):
        cls = _LIGHTS.get(d.get("kind"))
        if cls is None:
            raise ValueError(f"scene base: unknown light kind {d.get('kind')!r}")
        lights.append(cls(**d))
    sky = None if base.get("sky") is None else st.Sky(**base["sky"])
    cam = base.get("default_camera")
    return {
        "name": str(base["name"]),
        "lights": tuple(lights),
        "sky": sky,
        "paths": {k: CameraPath.from_dict(p) for k, p in base.get("paths", {}).items()},
        "default_camera": None if cam is None else Camera.from_dict(cam),
        "up": np.asarray(base.get("up", (0.0, 1.0, 0.0))),
    }


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def _from_npy(b: bytes, what: str) -> np.ndarray:
    try:
        return np.load(io.BytesIO(b), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"mesh chunk {what!r} is not a valid .npy array: {e}") from e


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


def full_level(scene: st.Scene, index: int = 0) -> MeshLevel:
    """The whole mesh of ``scene`` as one level (materials as JSON, arrays as .npy)."""
    chunks: list[Chunk] = [
        ("vertices", "mesh", _npy(scene.vertices)),
        ("faces", "mesh", _npy(scene.faces)),
        ("normals", "mesh", _npy(scene.normals)),
        ("face_material", "mesh", _npy(scene.face_material)),
    ]
    if scene.uvs is not None:
        chunks.append(("uvs", "mesh", _npy(scene.uvs)))
    mats = [
        {"name": m.name, "albedo": _plain(m.albedo), "emission": _plain(m.emission)}
        for m in scene.materials
    ]
    chunks.append(("materials", "mesh", json.dumps(mats).encode()))
    for i, m in enumerate(scene.materials):
        if m.texture is not None:
            chunks.append((f"texture_{i}", "texture", _npy(m.texture)))
    return MeshLevel(index, scene.n_triangles, tuple(chunks))


def assemble_full(chunks: list[Chunk], base: dict[str, Any]) -> st.Scene:
    """Rebuild a scene from the chunks of one :func:`full_level` and the base.

    Raises:
        ValueError: a part is missing or does not decode, or the scene does not validate.
    """
    parts = {name: data for name, _, data in chunks}
    need = ("vertices", "faces", "normals", "face_material", "materials")
    missing = [p for p in need if p not in parts]
    if missing:
        raise ValueError(f"mesh level is missing parts {missing}")
    mats = []
    for i, m in enumerate(json.loads(parts["materials"].decode())):
        tex = parts.get(f"texture_{i}")
        mats.append(
            st.Material(
                m["name"],
                np.asarray(m["albedo"]),
                np.asarray(m["emission"]),
                None if tex is None else _from_npy(tex, f"texture_{i}").astype(np.float32),
            )
        )
    uvs = parts.get("uvs")
    return st.Scene(
        vertices=_from_npy(parts["vertices"], "vertices"),
        faces=_from_npy(parts["faces"], "faces"),
        normals=_from_npy(parts["normals"], "normals"),
        face_material=_from_npy(parts["face_material"], "face_material"),
        materials=mats,
        uvs=None if uvs is None else _from_npy(uvs, "uvs"),
        source="network",
        **base_parts(base),
    )


class MeshStream:
    """The server's view of what it streams: the base and the levels, coarse to fine.

    Args:
        scene: the full-detail scene (stays on the server).
        lpm: build levels of detail with :func:`icbtool.lpm.build`; False, or open3d missing
            where a level needs decimation (logged), streams the full mesh as the only level.
        lpm_config: :class:`icbtool.lpm.LPMConfig` (default: its defaults).
        send_full: also stream the LPM's finest level, which is the full-detail mesh itself.
            Off by default: the full-detail mesh never leaves the server (ICB.md section 1),
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
        self.build_s = 0.0
        if lpm:
            import dataclasses as dc
            import time

            from icbtool import lpm as lpm_mod
            from icbtool._optional import MissingOptionalDependency

            cfg = lpm_config or lpm_mod.LPMConfig()
            cfg = dc.replace(cfg, max_chunk_bytes=min(cfg.max_chunk_bytes, max_chunk_bytes))
            t0 = time.perf_counter()
            try:
                built = lpm_mod.build(scene, cfg)
            except MissingOptionalDependency as e:
                log.warning("no LPM (%s): streaming the full mesh as one level", e)
            else:
                kept = [lv for lv in built.levels if send_full or lv.ratio < 1.0] or built.levels
                self.levels = [
                    MeshLevel(lv.index, lv.n_triangles, tuple(lv.to_chunks())) for lv in kept
                ]
            self.build_s = time.perf_counter() - t0
        if not self.levels:
            self.levels = [full_level(scene)]

    def info(self, chunk_bytes: int) -> list[dict[str, Any]]:
        """Per level: level, triangles, bytes, chunks (messages when files are cut into pieces of
        ``chunk_bytes``): the ``scene_info.lpm.levels`` entries."""
        return [
            {
                "level": lv.index,
                "triangles": lv.triangles,
                "bytes": lv.nbytes,
                "chunks": sum(max(1, -(-len(d) // chunk_bytes)) for _, _, d in lv.chunks),
            }
            for lv in self.levels
        ]


def assemble(chunks: list[Chunk], base: dict[str, Any]) -> st.Scene:
    """The client side of :class:`MeshStream`: one level's chunks plus the base -> a Scene.

    LPM chunks (names ``L<level>/...``) go to :func:`icbtool.lpm.assemble`; the base adds the
    camera paths and the default camera to what the LPM carries.

    Raises:
        ValueError: a missing or damaged chunk (the message names it).
    """
    if chunks and all("/" in name for name, _, _ in chunks):
        from icbtool import lpm as lpm_mod

        scene = lpm_mod.assemble(chunks, base={k: base[k] for k in ("lights", "sky", "up")})
        extra = base_parts(base)
        return dataclasses.replace(
            scene, paths=extra["paths"], default_camera=extra["default_camera"]
        )
    return assemble_full(chunks, base)


__all__ = ["MeshLevel", "MeshStream", "assemble", "base_parts", "full_level", "scene_base"]
