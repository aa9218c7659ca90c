"""The classic Cornell box written as a glTF in millimetres (node scale 0.001), for the emitter
tests and ``benchmarks/emitter_split.py``.

Geometry: the Cornell data's room (556 x 548.8 x 559.2 mm, open at z = 0; red wall at x = 556,
green at x = 0), its two blocks (tops at 165 and 330 mm, sides down to the floor) and its light
(x 213..343, z 227..332) as one emissive quad (two triangles) 0.8 mm below the ceiling, facing
down, radiance (17, 12, 4) (``emissiveFactor`` (1, 12/17, 4/17) x ``KHR_materials_emissive_
strength`` 17). No punctual lights. Materials are diffuse (``metallicFactor`` 0).
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

#: Light quad (mm): x, z ranges and height.
LIGHT_X = (213.0, 343.0)
LIGHT_Z = (227.0, 332.0)
LIGHT_Y = 548.0
LIGHT_RADIANCE = (17.0, 12.0, 4.0)
ROOM = (556.0, 548.8, 559.2)
#: Classic camera (mm): eye, target, vertical field of view (deg).
CAMERA_EYE = (278.0, 273.0, -800.0)
CAMERA_TARGET = (278.0, 273.0, 0.0)
CAMERA_FOV_Y = 39.3

SHORT_TOP = [(130, 165, 65), (82, 165, 225), (240, 165, 272), (290, 165, 114)]
TALL_TOP = [(423, 330, 247), (265, 330, 296), (314, 330, 456), (472, 330, 406)]

MATERIALS = {  # name: (base colour, emissive factor, strength)
    "white": ((0.73, 0.73, 0.73), None, None),
    "red": ((0.63, 0.065, 0.05), None, None),
    "green": ((0.14, 0.45, 0.091), None, None),
    "light": ((0.78, 0.78, 0.78), (1.0, 12 / 17, 4 / 17), 17.0),
}


def _oriented(quad: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """The quad's corners ordered so its normal points along ``towards``."""
    n = np.cross(quad[1] - quad[0], quad[2] - quad[0])
    return quad if n @ towards > 0 else quad[::-1].copy()


def cornell_quads(blocks: bool = True) -> dict[str, list[np.ndarray]]:
    """Quads (4, 3) in mm by material, counter-clockwise seen from their front."""
    w, h, d = ROOM
    centre = np.array([w / 2, h / 2, d / 2])
    q: dict[str, list[np.ndarray]] = {k: [] for k in MATERIALS}

    def wall(pts, mat):
        p = np.array(pts, np.float64)
        q[mat].append(_oriented(p, centre - p.mean(0)))

    wall([(0, 0, 0), (w, 0, 0), (w, 0, d), (0, 0, d)], "white")  # floor
    wall([(0, h, 0), (w, h, 0), (w, h, d), (0, h, d)], "white")  # ceiling
    wall([(0, 0, d), (w, 0, d), (w, h, d), (0, h, d)], "white")  # back
    wall([(w, 0, 0), (w, 0, d), (w, h, d), (w, h, 0)], "red")
    wall([(0, 0, 0), (0, 0, d), (0, h, d), (0, h, 0)], "green")
    (x0, x1), (z0, z1) = LIGHT_X, LIGHT_Z
    light = np.array([(x0, LIGHT_Y, z0), (x1, LIGHT_Y, z0), (x1, LIGHT_Y, z1), (x0, LIGHT_Y, z1)])
    q["light"].append(_oriented(light, np.array([0.0, -1.0, 0.0])))
    if blocks:
        for top in (SHORT_TOP, TALL_TOP):
            t = np.array(top, np.float64)
            c = t.mean(0) * np.array([1, 0.5, 1])
            q["white"].append(_oriented(t, np.array([0.0, 1.0, 0.0])))
            for i in range(4):
                a, b = t[i], t[(i + 1) % 4]
                side = np.array([a, b, b * (1, 0, 1), a * (1, 0, 1)])
                q["white"].append(_oriented(side, side.mean(0) - c))
    return q


def write_cornell_gltf(path: str | Path, blocks: bool = True) -> Path:
    """Write the Cornell box glTF (one mesh per material, an embedded buffer) to ``path``."""
    path = Path(path)
    chunks: list[bytes] = []
    views, accessors, meshes, mats = [], [], [], []
    offset = 0

    def add(arr: np.ndarray, target: int, ctype: int, kind: str, minmax: bool) -> int:
        nonlocal offset
        b = arr.tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(b), "target": target})
        chunks.append(b)
        offset += len(b)
        acc = {
            "bufferView": len(views) - 1,
            "componentType": ctype,
            "count": len(arr),
            "type": kind,
        }
        if minmax:
            acc["min"] = arr.min(0).tolist()
            acc["max"] = arr.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    for mi, (name, quads) in enumerate(cornell_quads(blocks).items()):
        base, ef, strength = MATERIALS[name]
        m: dict = {
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*base, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
        }
        if ef is not None:
            m["emissiveFactor"] = list(ef)
            m["extensions"] = {"KHR_materials_emissive_strength": {"emissiveStrength": strength}}
        mats.append(m)
        v = np.concatenate(quads).astype(np.float32)
        f = np.concatenate([np.array([0, 1, 2, 0, 2, 3]) + 4 * i for i in range(len(quads))])
        pos = add(v, 34962, 5126, "VEC3", True)
        idx = add(f.astype(np.uint32), 34963, 5125, "SCALAR", False)
        meshes.append(
            {
                "name": name,
                "primitives": [{"attributes": {"POSITION": pos}, "indices": idx, "material": mi}],
            }
        )
    data = b"".join(chunks)
    gltf = {
        "asset": {"version": "2.0", "generator": "icbtool tests/cornell_gltf.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "cornell_mm", "scale": [0.001] * 3, "children": list(range(1, 5))}]
        + [{"mesh": i} for i in range(len(meshes))],
        "meshes": meshes,
        "materials": mats,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [
            {
                "byteLength": len(data),
                "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode(),
            }
        ],
    }
    path.write_text(json.dumps(gltf))
    return path


def cornell_camera_m(height: int, width: int):
    """The classic Cornell camera in metres (icbtool Camera, OpenCV axes)."""
    from icbtool.camera import Camera

    eye = np.array(CAMERA_EYE) / 1000
    target = np.array(CAMERA_TARGET) / 1000
    return Camera.look_at(eye, target, (0, 1, 0), CAMERA_FOV_Y, height, width)
