"""The wire layout of LPM levels: chunks of little-endian typed arrays, PNG/JPEG texture bytes
and JSON, each with a small JSON header (the full layout is in docs/lpm.md).

A chunk is ``(name, part, data)``; ``data`` is::

    magic    4 bytes   b"ICBL"
    hlen     uint32    little-endian: length of the header in bytes
    header   hlen      UTF-8 JSON object (see below)
    payload  rest      header["size"] bytes

Every header has ``v`` (format version, 1), ``level``, ``name`` (the chunk's name, also given
outside), ``part`` ("materials" | "geometry" | "texture"), ``size`` and ``crc32`` (zlib CRC-32
of the payload). Per part:

* "materials" (one per level, first): the payload is UTF-8 JSON, the level's manifest: scene
  name, vertex and face counts, whether uvs exist, the materials (name, albedo, emission, texture
  size and format or null, texture_path) and the list of every chunk name of the level. The
  scene's ``source`` and the materials' ``texture_path`` are file names only (no folders): a
  level goes to clients, the server's file layout does not (:func:`file_name`).
* "geometry": ``array`` (vertices, normals, uvs, faces, face_material), ``dtype`` ("<f4" or
  "<i4"), ``shape`` of the whole array, ``row0`` and ``rows``: the payload is rows ``row0 ..
  row0 + rows`` of the array, C order, little-endian.
* "texture": ``material`` (index), ``format`` ("png" | "jpeg"), ``offset`` and ``total``: the
  payload is bytes ``offset .. offset + size`` of the encoded image file.

Lights, sky and up are scene-level (:func:`scene_info`, JSON, sent once), not part of a level.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from collections.abc import Iterable
from typing import Any, Protocol

import numpy as np

from icbtool.lpm.textures import decode_texture_bytes
from icbtool.scene.types import (
    LIGHT_TYPES,
    Material,
    Scene,
    Sky,
)


class Level(Protocol):
    """What :func:`level_chunks` reads of a level (an :class:`icbtool.lpm.build.Level`): a
    structural type, so that this module does not import the builder (which imports it)."""

    index: int
    ratio: float
    scene: Scene
    texture_bytes: dict[int, bytes]
    texture_format: str


#: First 4 bytes of every chunk.
CHUNK_MAGIC = b"ICBL"
#: Version of the chunk layout (header key ``v``).
FORMAT_VERSION = 1
#: Parts a chunk can be.
PARTS = ("materials", "geometry", "texture")
#: Geometry arrays, their dtype and columns.
ARRAYS: dict[str, tuple[str, int]] = {
    "vertices": ("<f4", 3),
    "normals": ("<f4", 3),
    "uvs": ("<f4", 2),
    "faces": ("<i4", 3),
    "face_material": ("<i4", 1),
}
#: Largest header accepted (bytes).
MAX_HEADER_BYTES = 64 * 1024
_PREFIX = struct.Struct("<4sI")


def _chunk(header: dict[str, Any], payload: bytes) -> bytes:
    header = dict(header, v=FORMAT_VERSION, size=len(payload), crc32=zlib.crc32(payload))
    h = json.dumps(header, separators=(",", ":"), sort_keys=True).encode()
    return _PREFIX.pack(CHUNK_MAGIC, len(h)) + h + payload


def _header_bytes(header: dict[str, Any]) -> int:
    """Size of the prefix + header of ``header`` once finished (worst case size/crc digits)."""
    h = dict(header, v=FORMAT_VERSION, size=10**12, crc32=2**32 - 1)
    return _PREFIX.size + len(json.dumps(h, separators=(",", ":"), sort_keys=True).encode())


def _array_chunks(
    level: int, name: str, a: np.ndarray, max_bytes: int
) -> list[tuple[str, str, bytes]]:
    dtype, cols = ARRAYS[name]
    arr = np.ascontiguousarray(a, dtype=np.dtype(dtype)).reshape(len(a), -1)
    row_bytes = max(arr.shape[1] * arr.itemsize, 1)
    shape = [int(arr.shape[0])] + ([cols] if cols > 1 else [])
    probe = {
        "level": level,
        "name": f"L{level}/geometry/{name}/000000",
        "part": "geometry",
        "array": name,
        "dtype": dtype,
        "shape": shape,
        "row0": 10**12,
        "rows": 10**12,
    }
    per = (max_bytes - _header_bytes(probe)) // row_bytes
    if per < 1:
        raise ValueError(f"max_chunk_bytes {max_bytes} cannot hold one row of {name}")
    out = []
    for k, r0 in enumerate(range(0, max(len(arr), 1), per)):
        rows = arr[r0 : r0 + per]
        cname = f"L{level}/geometry/{name}/{k:06d}"
        hdr = {
            "level": level,
            "name": cname,
            "part": "geometry",
            "array": name,
            "dtype": dtype,
            "shape": shape,
            "row0": r0,
            "rows": int(len(rows)),
        }
        out.append((cname, "geometry", _chunk(hdr, rows.tobytes())))
    return out


def _bytes_chunks(
    level: int, material: int, fmt: str, data: bytes, max_bytes: int
) -> list[tuple[str, str, bytes]]:
    probe = {
        "level": level,
        "name": f"L{level}/texture/{material}/000000",
        "part": "texture",
        "material": material,
        "format": fmt,
        "offset": 10**12,
        "total": 10**12,
    }
    per = max_bytes - _header_bytes(probe)
    out = []
    for k, o in enumerate(range(0, max(len(data), 1), per)):
        piece = data[o : o + per]
        cname = f"L{level}/texture/{material}/{k:06d}"
        hdr = {
            "level": level,
            "name": cname,
            "part": "texture",
            "material": material,
            "format": fmt,
            "offset": o,
            "total": len(data),
        }
        out.append((cname, "texture", _chunk(hdr, piece)))
    return out


def level_chunks(level: Level, max_chunk_bytes: int) -> list[tuple[str, str, bytes]]:
    """The chunks of ``level`` (see the module docstring); each at most ``max_chunk_bytes``."""
    s = level.scene
    li = level.index
    body: list[tuple[str, str, bytes]] = []
    arrays = {
        "vertices": s.vertices,
        "normals": s.normals,
        "faces": s.faces,
        "face_material": s.face_material,
    }
    if s.uvs is not None:
        arrays["uvs"] = s.uvs
    for name in ARRAYS:
        if name in arrays:
            body += _array_chunks(li, name, arrays[name], max_chunk_bytes)
    for mi, data in sorted(level.texture_bytes.items()):
        body += _bytes_chunks(li, mi, level.texture_format, data, max_chunk_bytes)
    mats = []
    for m in s.materials:
        tex = None
        if m.texture is not None:
            tex = {
                "height": int(m.texture.shape[0]),
                "width": int(m.texture.shape[1]),
                "format": level.texture_format,
            }
        mats.append(
            {
                "name": m.name,
                "albedo": m.albedo.tolist(),
                "emission": m.emission.tolist(),
                "texture": tex,
                "texture_path": file_name(m.texture_path),
            }
        )
    manifest = {
        "scene": s.name,
        "source": file_name(s.source),
        "ratio": level.ratio,
        "n_vertices": int(len(s.vertices)),
        "n_faces": int(len(s.faces)),
        "has_uvs": s.uvs is not None,
        "materials": mats,
        "chunks": [c[0] for c in body],
    }
    payload = json.dumps(manifest, separators=(",", ":")).encode()
    mname = f"L{li}/materials"
    head = (mname, "materials", _chunk({"level": li, "name": mname, "part": "materials"}, payload))
    if len(head[2]) > max_chunk_bytes:
        raise ValueError(
            f"level {li}: the materials manifest needs {len(head[2])} bytes, more than "
            f"max_chunk_bytes {max_chunk_bytes}"
        )
    return [head, *body]


def file_name(path: str | None) -> str | None:
    """The last component of a file path (``/srv/scenes/sponza/sp_luk.JPG`` -> ``sp_luk.JPG``,
    either separator), what a manifest says of the server's files; None stays None and a name
    without folders (``procedural:cornell_box``) is kept."""
    if path is None:
        return None
    return re.split(r"[\\/]", str(path))[-1]


# --------------------------------------------------------------------------- reading
def chunk_header(data: bytes, name: str = "chunk") -> tuple[dict[str, Any], bytes]:
    """Parse and check one chunk: its header and payload.

    Args:
        data: the chunk's bytes.
        name: its name, for messages.

    Returns:
        (header, payload).

    Raises:
        ValueError: bad magic, truncated, bad JSON, wrong version, size or CRC mismatch; the
            message names the chunk and the problem.
    """
    where = f"LPM chunk '{name}'"
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f"{where}: data must be bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < _PREFIX.size:
        raise ValueError(f"{where}: truncated: {len(data)} bytes, shorter than the 8-byte prefix")
    magic, hlen = _PREFIX.unpack_from(data)
    if magic != CHUNK_MAGIC:
        raise ValueError(f"{where}: bad magic {magic!r}, expected {CHUNK_MAGIC!r}")
    if hlen > MAX_HEADER_BYTES:
        raise ValueError(f"{where}: header length {hlen} exceeds {MAX_HEADER_BYTES}")
    if len(data) < _PREFIX.size + hlen:
        raise ValueError(f"{where}: truncated inside the header ({len(data)} bytes)")
    try:
        header = json.loads(data[_PREFIX.size : _PREFIX.size + hlen].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{where}: header is not UTF-8 JSON ({e})") from None
    if not isinstance(header, dict):
        raise ValueError(f"{where}: header must be a JSON object")
    for key in ("v", "level", "name", "part", "size", "crc32"):
        if key not in header:
            raise ValueError(f"{where}: header lacks '{key}'")
    if header["v"] != FORMAT_VERSION:
        raise ValueError(f"{where}: format version {header['v']!r}, expected {FORMAT_VERSION}")
    if header["part"] not in PARTS:
        raise ValueError(f"{where}: unknown part {header['part']!r}; known {list(PARTS)}")
    payload = data[_PREFIX.size + hlen :]
    if len(payload) != header["size"]:
        raise ValueError(
            f"{where}: payload is {len(payload)} bytes, header says {header['size']}"
            + (" (truncated)" if len(payload) < header["size"] else "")
        )
    if zlib.crc32(payload) != header["crc32"]:
        raise ValueError(f"{where}: CRC-32 mismatch (corrupt payload)")
    if header["name"] != name and name != "chunk":
        raise ValueError(f"{where}: header names it {header['name']!r}")
    return header, payload


def levels_in(chunks: Iterable[tuple[str, str, bytes]]) -> list[int]:
    """The levels whose chunks are all present in ``chunks`` (complete levels), ascending.

    Raises:
        ValueError: a corrupt chunk (names it).
    """
    return _complete_levels(_by_level(list(chunks)))


def _by_level(chunks: list[tuple[str, str, bytes]]) -> dict[int, dict[str, tuple[dict, bytes]]]:
    by: dict[int, dict[str, tuple[dict, bytes]]] = {}
    for item in chunks:
        if not (isinstance(item, tuple) and len(item) == 3):
            raise ValueError(f"LPM chunks must be (name, part, data) tuples, got {item!r:.80}")
        name, part, data = item
        header, payload = chunk_header(data, name)
        if header["part"] != part:
            raise ValueError(
                f"LPM chunk '{name}': given as part {part!r}, its header says {header['part']!r}"
            )
        lvl = header["level"]
        if not isinstance(lvl, int) or lvl < 0:
            raise ValueError(f"LPM chunk '{name}': bad level {lvl!r}")
        by.setdefault(lvl, {})[name] = (header, payload)
    return by


def _get(d: dict, key: str, types: Any, where: str) -> Any:
    if key not in d or not isinstance(d[key], types) or isinstance(d[key], bool) != (types is bool):
        raise ValueError(f"{where}: '{key}' missing or of the wrong type")
    return d[key]


def assemble(
    chunks: Iterable[tuple[str, str, bytes]],
    base: Scene | dict[str, Any] | bytes | None = None,
    level: int | None = None,
) -> Scene:
    """Rebuild a level's :class:`Scene` from its chunks.

    Args:
        chunks: ``(name, part, data)`` chunks, of one level or several, in any order.
        base: where lights, sky, up (and, from a Scene, paths and cameras) come from: a Scene,
            the JSON of :func:`scene_info` (bytes or already parsed), or None (no lights).
        level: the level to assemble; None: the finest complete level present.

    Returns:
        The level's Scene (equal, array for array, to ``Level.scene`` apart from what ``base``
        provides).

    Raises:
        ValueError: a corrupt or truncated chunk, a missing chunk, inconsistent sizes; the
            message names the chunk and the problem.
    """
    by = _by_level(list(chunks))
    if not by:
        raise ValueError("LPM assemble: no chunks given")
    if level is None:
        complete = _complete_levels(by)
        if not complete:
            raise ValueError(
                f"LPM assemble: no complete level among levels {sorted(by)} "
                "(a materials manifest or a listed chunk is missing)"
            )
        level = complete[-1]
    if level not in by:
        raise ValueError(f"LPM assemble: no chunk of level {level} (have {sorted(by)})")
    items = by[level]
    mname = f"L{level}/materials"
    if mname not in items:
        raise ValueError(f"LPM assemble: chunk '{mname}' (the level's manifest) is missing")
    try:
        man = json.loads(items[mname][1].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"LPM chunk '{mname}': manifest is not UTF-8 JSON ({e})") from None
    where = f"LPM chunk '{mname}'"
    if not isinstance(man, dict):
        raise ValueError(f"{where}: manifest must be a JSON object")
    names = _get(man, "chunks", list, where)
    missing = [n for n in names if n not in items]
    if missing:
        raise ValueError(
            f"LPM assemble: level {level} lacks {len(missing)} chunk(s): {missing[:5]}"
        )
    nv = _get(man, "n_vertices", int, where)
    nf = _get(man, "n_faces", int, where)
    has_uvs = _get(man, "has_uvs", bool, where)
    rows_of = {"vertices": nv, "normals": nv, "uvs": nv, "faces": nf, "face_material": nf}
    arrays: dict[str, np.ndarray] = {}
    filled: dict[str, np.ndarray] = {}
    tex_parts: dict[int, dict[str, Any]] = {}
    for n in names:
        header, payload = items[n]
        cw = f"LPM chunk '{n}'"
        if header["part"] == "geometry":
            a = header.get("array")
            if a not in ARRAYS:
                raise ValueError(f"{cw}: unknown array {a!r}")
            dtype, cols = ARRAYS[a]
            if header.get("dtype") != dtype:
                raise ValueError(f"{cw}: dtype {header.get('dtype')!r}, expected {dtype!r}")
            total = rows_of[a]
            if a not in arrays:
                arrays[a] = np.zeros((total, cols), np.dtype(dtype))
                filled[a] = np.zeros(total, bool)
            r0, rows = _get(header, "row0", int, cw), _get(header, "rows", int, cw)
            if r0 < 0 or rows < 0 or r0 + rows > total:
                raise ValueError(f"{cw}: rows {r0}..{r0 + rows} outside the array's {total}")
            if len(payload) != rows * cols * 4:
                raise ValueError(
                    f"{cw}: payload {len(payload)} bytes for {rows} rows of {cols} x 4 bytes"
                )
            arrays[a][r0 : r0 + rows] = np.frombuffer(payload, np.dtype(dtype)).reshape(rows, cols)
            filled[a][r0 : r0 + rows] = True
        elif header["part"] == "texture":
            mi = _get(header, "material", int, cw)
            t = tex_parts.setdefault(
                mi, {"total": header.get("total"), "pieces": [], "format": header.get("format")}
            )
            off = _get(header, "offset", int, cw)
            if header.get("total") != t["total"] or not isinstance(t["total"], int):
                raise ValueError(f"{cw}: texture total size disagrees with its other chunks")
            if off < 0 or off + len(payload) > t["total"]:
                raise ValueError(f"{cw}: bytes {off}..{off + len(payload)} outside {t['total']}")
            t["pieces"].append((off, payload))
    need = ["vertices", "normals", "faces", "face_material"] + (["uvs"] if has_uvs else [])
    for a in need:
        if a not in arrays or not filled[a].all():
            raise ValueError(f"LPM assemble: level {level}: array '{a}' is incomplete")
    mats_json = _get(man, "materials", list, where)
    materials = []
    for mi, mj in enumerate(mats_json):
        mw = f"{where} material {mi}"
        if not isinstance(mj, dict):
            raise ValueError(f"{mw}: must be a JSON object")
        texture = None
        if mj.get("texture") is not None:
            t = tex_parts.get(mi)
            if t is None:
                raise ValueError(f"LPM assemble: level {level}: texture of material {mi} missing")
            buf = bytearray(t["total"])
            got = 0
            for off, piece in t["pieces"]:
                buf[off : off + len(piece)] = piece
                got += len(piece)
            if got != t["total"]:
                raise ValueError(
                    f"LPM assemble: level {level}: texture {mi} has {got} of {t['total']} bytes"
                )
            texture = decode_texture_bytes(bytes(buf), f"LPM level {level} texture {mi}")
            tj = mj["texture"]
            if [tj.get("height"), tj.get("width")] != list(texture.shape[:2]):
                raise ValueError(
                    f"{mw}: texture is {texture.shape[:2]}, manifest says "
                    f"{tj.get('height')}x{tj.get('width')}"
                )
        try:
            materials.append(
                Material(
                    str(mj["name"]),
                    np.array(mj["albedo"], np.float64),
                    np.array(mj["emission"], np.float64),
                    texture,
                    mj.get("texture_path"),
                )
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"{mw}: bad material ({e})") from None
    kw = _base_fields(base)
    try:
        return Scene(
            name=str(man.get("scene", "lpm")),
            vertices=arrays["vertices"],
            faces=arrays["faces"],
            normals=arrays["normals"],
            face_material=arrays["face_material"].reshape(-1),
            materials=materials,
            uvs=arrays.get("uvs") if has_uvs else None,
            source=str(man.get("source", "")),
            **kw,
        )
    except ValueError as e:
        raise ValueError(f"LPM assemble: level {level}: inconsistent data: {e}") from None


def _complete_levels(by: dict[int, dict[str, tuple[dict, bytes]]]) -> list[int]:
    out = []
    for li, items in sorted(by.items()):
        man = items.get(f"L{li}/materials")
        if man is None:
            continue
        try:
            names = json.loads(man[1])["chunks"]
        except (ValueError, KeyError, TypeError):
            continue
        if all(n in items for n in names):
            out.append(li)
    return out


# --------------------------------------------------------------------------- scene info
def _enc(v: Any) -> Any:
    return v.tolist() if isinstance(v, np.ndarray) else v


def scene_info(scene: Scene) -> bytes:
    """The scene-level data a client needs besides the levels, as UTF-8 JSON: name, up, lights
    (each with its ``kind`` and fields), sky (or null), bounds. Sent once."""
    lights = [{k: _enc(v) for k, v in vars(light).items()} for light in scene.lights]
    sky = None if scene.sky is None else {k: _enc(v) for k, v in vars(scene.sky).items()}
    info = {
        "v": FORMAT_VERSION,
        "name": scene.name,
        "up": scene.up.tolist(),
        "lights": lights,
        "sky": sky,
        "bounds": scene.bounds.tolist(),
    }
    return json.dumps(info, separators=(",", ":")).encode()


def read_scene_info(data: bytes | dict[str, Any]) -> dict[str, Any]:
    """Parse :func:`scene_info` JSON into Scene fields: ``lights`` (tuple), ``sky``, ``up``.

    Raises:
        ValueError: not valid scene info (names the problem).
    """
    try:
        info = json.loads(data) if isinstance(data, (bytes, bytearray, str)) else data
        lights = []
        for lj in info["lights"]:
            cls = LIGHT_TYPES[lj["kind"]]
            lights.append(cls(**lj))
        sky = None if info["sky"] is None else Sky(**info["sky"])
        return {"lights": tuple(lights), "sky": sky, "up": np.array(info["up"], np.float64)}
    except (KeyError, TypeError, json.JSONDecodeError) as e:
        raise ValueError(f"LPM scene info: invalid ({type(e).__name__}: {e})") from None


def _base_fields(base: Scene | dict[str, Any] | bytes | None) -> dict[str, Any]:
    if base is None:
        return {}
    if isinstance(base, Scene):
        return {f: getattr(base, f) for f in ("lights", "sky", "up", "paths", "default_camera")}
    return read_scene_info(base)


__all__ = [
    "ARRAYS",
    "CHUNK_MAGIC",
    "FORMAT_VERSION",
    "PARTS",
    "assemble",
    "chunk_header",
    "level_chunks",
    "levels_in",
    "read_scene_info",
    "scene_info",
]
