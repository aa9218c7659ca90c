"""What icbtool reads from a glTF file's JSON itself (trimesh reads the geometry).

* :func:`read_gltf_json`: the JSON of a ``.gltf`` file or of a ``.glb``'s first (JSON) chunk.
* :func:`read_punctual_lights`: ``KHR_lights_punctual`` lights placed by the node hierarchy's
  world transforms (``matrix`` or ``translation``/``rotation``/``scale`` of every ancestor) of the
  default scene (``scene``, else scene 0, else every root node), as icbtool lights in the file's
  coordinates (the loader then applies its scale and up-axis rotation).

Units: glTF gives point and spot intensities in candela (lm/sr) and directional ones in lux
(lm/m^2); icbtool's lights are radiometric (W/sr and W/m^2). We divide by
:data:`LUMENS_PER_WATT` = 683 lm/W (the luminous efficacy at 555 nm, the conversion Blender's
glTF exporter uses in its "standard" lighting mode) and multiply by ``color``:
``intensity_W_per_sr = color * intensity_cd / 683``, ``irradiance_W_per_m2 = color * lux / 683``.
A light points along its node's local -z. Spot cones: ``innerConeAngle`` (default 0) and
``outerConeAngle`` (default pi/4) become ``inner_deg``/``outer_deg``. ``range`` is ignored
(icbtool lights follow the inverse square law to infinity), with a warning.

Materials are handled in :mod:`icbtool.scene.load` (emission textures, metals and transmission
become diffuse with a :class:`~icbtool.scene.obj.MaterialApproximationWarning`).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from icbtool.scene.types import DirectionalLight, Light, PointLight, SpotLight
from icbtool.scene.validate import SceneError, repair_warning

#: Lumens per watt used to turn glTF's photometric light units into radiometric ones.
LUMENS_PER_WATT = 683.0


def read_gltf_json(path: str | Path, data: bytes | None = None) -> dict[str, Any]:
    """The glTF JSON document of a ``.gltf`` or ``.glb`` file.

    Raises:
        SceneError: the file is not valid glTF JSON / GLB.
    """
    p = Path(path)
    if data is None:
        data = p.read_bytes()
    try:
        if data[:4] == b"glTF":
            if len(data) < 20:
                raise ValueError("truncated GLB header")
            length, ctype = struct.unpack_from("<II", data, 12)
            if ctype != 0x4E4F534A:  # 'JSON'
                raise ValueError("first GLB chunk is not JSON")
            doc = json.loads(data[20 : 20 + length].decode("utf-8"))
        else:
            doc = json.loads(data.decode("utf-8"))
    except (ValueError, UnicodeDecodeError, struct.error) as e:
        raise SceneError(f"{p}: not a valid glTF file (truncated or corrupt?): {e}") from None
    if not isinstance(doc, dict):
        raise SceneError(f"{p}: glTF JSON must be an object")
    return doc


def _node_matrix(node: dict[str, Any]) -> np.ndarray:
    """(4, 4) local transform of a glTF node (column-major ``matrix`` or T * R * S)."""
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
    t = np.asarray(node.get("translation", (0, 0, 0)), np.float64)
    x, y, z, w = np.asarray(node.get("rotation", (0, 0, 0, 1)), np.float64)
    s = np.asarray(node.get("scale", (1, 1, 1)), np.float64)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = t
    return m


def node_world_matrices(doc: dict[str, Any]) -> dict[int, np.ndarray]:
    """(4, 4) world transform of every node reachable from the default scene, by node index."""
    nodes = doc.get("nodes", [])
    scenes = doc.get("scenes", [])
    if scenes:
        roots = scenes[int(doc.get("scene", 0))].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out: dict[int, np.ndarray] = {}
    stack = [(int(i), np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        if i in out or not (0 <= i < len(nodes)):
            continue
        m = parent @ _node_matrix(nodes[i])
        out[i] = m
        stack += [(int(c), m) for c in nodes[i].get("children", [])]
    return out


def read_punctual_lights(path: str | Path, doc: dict[str, Any]) -> list[Light]:
    """``KHR_lights_punctual`` lights of the default scene as icbtool lights (file coordinates).

    Args:
        path: the file (for messages).
        doc: its JSON (:func:`read_gltf_json`).

    Returns:
        Directional, point and spot lights (see the module docstring for units and defaults).

    Raises:
        SceneError: a light with an unknown type or a node naming a missing light.
    """
    where = str(path)
    defs = doc.get("extensions", {}).get("KHR_lights_punctual", {}).get("lights", [])
    if not defs:
        return []
    nodes = doc.get("nodes", [])
    lights: list[Light] = []
    for i, m in sorted(node_world_matrices(doc).items()):
        ext = nodes[i].get("extensions", {}).get("KHR_lights_punctual")
        if not ext or "light" not in ext:
            continue
        li = int(ext["light"])
        if not (0 <= li < len(defs)):
            raise SceneError(f"{where}: node {i} names KHR_lights_punctual light {li}: none such")
        d = defs[li]
        kind = d.get("type")
        name = d.get("name") or nodes[i].get("name") or f"light{li}"
        color = np.asarray(d.get("color", (1.0, 1.0, 1.0)), np.float64)
        power = color * float(d.get("intensity", 1.0)) / LUMENS_PER_WATT
        pos = m[:3, 3]
        axis = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
        if "range" in d:
            repair_warning(where, f"light '{name}': range {d['range']} ignored (inverse square)")
        if kind == "directional":
            lights.append(DirectionalLight(direction=axis, irradiance=power, name=name))
        elif kind == "point":
            lights.append(PointLight(position=pos, intensity=power, name=name))
        elif kind == "spot":
            spot = d.get("spot", {})
            inner = math.degrees(float(spot.get("innerConeAngle", 0.0)))
            outer = math.degrees(float(spot.get("outerConeAngle", math.pi / 4)))
            outer = min(outer, 90.0)
            if not inner < outer:
                repair_warning(
                    where, f"light '{name}': innerConeAngle >= outerConeAngle: inner set to 0"
                )
                inner = 0.0
            lights.append(
                SpotLight(
                    position=pos,
                    direction=axis,
                    intensity=power,
                    inner_deg=inner,
                    outer_deg=outer,
                    name=name,
                )
            )
        else:
            raise SceneError(f"{where}: light '{name}' has unknown type {kind!r}")
    return lights


__all__ = ["LUMENS_PER_WATT", "node_world_matrices", "read_gltf_json", "read_punctual_lights"]
