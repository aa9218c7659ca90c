"""Scenes built in code, with known answers: the Cornell box, a white furnace, a plane, boxes.

None of them needs a file; tests and ``make demo`` use them.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from icbtool.camera import Camera, CameraPath
from icbtool.scene.types import AreaLight, DirectionalLight, Scene, SceneBuilder, Sky

# --------------------------------------------------------------------------- Cornell box
# The published Cornell box geometry (Cornell Program of Computer Graphics, "Cornell Box Data"),
# in millimetres: x from the green (right, x = 0) wall to the red (left, x ~ 556) wall, y up,
# z from the open front (0) to the back wall (559.2). The published camera sits at
# (278, 273, -800) looking +z, with a 35 mm lens on a 25 mm film (fov 39.3 deg).
_CB_QUADS: dict[str, list[tuple[float, float, float]]] = {
    "floor": [(552.8, 0, 0), (0, 0, 0), (0, 0, 559.2), (549.6, 0, 559.2)],
    "ceiling": [(556.0, 548.8, 0), (556.0, 548.8, 559.2), (0, 548.8, 559.2), (0, 548.8, 0)],
    "back": [(549.6, 0, 559.2), (0, 0, 559.2), (0, 548.8, 559.2), (556.0, 548.8, 559.2)],
    "green": [(0, 0, 559.2), (0, 0, 0), (0, 548.8, 0), (0, 548.8, 559.2)],
    "red": [(552.8, 0, 0), (549.6, 0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0)],
}
_CB_SHORT = [
    [(130.0, 165.0, 65.0), (82.0, 165.0, 225.0), (240.0, 165.0, 272.0), (290.0, 165.0, 114.0)],
    [(290.0, 0, 114.0), (290.0, 165.0, 114.0), (240.0, 165.0, 272.0), (240.0, 0, 272.0)],
    [(130.0, 0, 65.0), (130.0, 165.0, 65.0), (290.0, 165.0, 114.0), (290.0, 0, 114.0)],
    [(82.0, 0, 225.0), (82.0, 165.0, 225.0), (130.0, 165.0, 65.0), (130.0, 0, 65.0)],
    [(240.0, 0, 272.0), (240.0, 165.0, 272.0), (82.0, 165.0, 225.0), (82.0, 0, 225.0)],
]
_CB_TALL = [
    [(423.0, 330.0, 247.0), (265.0, 330.0, 296.0), (314.0, 330.0, 456.0), (472.0, 330.0, 406.0)],
    [(423.0, 0, 247.0), (423.0, 330.0, 247.0), (472.0, 330.0, 406.0), (472.0, 0, 406.0)],
    [(472.0, 0, 406.0), (472.0, 330.0, 406.0), (314.0, 330.0, 456.0), (314.0, 0, 456.0)],
    [(314.0, 0, 456.0), (314.0, 330.0, 456.0), (265.0, 330.0, 296.0), (265.0, 0, 296.0)],
    [(265.0, 0, 296.0), (265.0, 330.0, 296.0), (423.0, 330.0, 247.0), (423.0, 0, 247.0)],
]
# The light: 130 x 105 mm, hung 0.5 mm below the ceiling (the data put it in the ceiling plane).
_CB_LIGHT = [
    (343.0, 548.3, 227.0),
    (343.0, 548.3, 332.0),
    (213.0, 548.3, 332.0),
    (213.0, 548.3, 227.0),
]

# Linear RGB reflectances commonly used for the box's measured spectra (as in Mitsuba's and
# PBRT's Cornell box scenes) and the light's radiance.
CORNELL_WHITE = (0.725, 0.71, 0.68)
CORNELL_RED = (0.63, 0.065, 0.05)
CORNELL_GREEN = (0.14, 0.45, 0.091)
CORNELL_LIGHT_RADIANCE = (17.0, 12.0, 4.0)

#: Metres per unit of the published data times the normalisation we use: the box becomes ~2 units
#: wide (x in [-1, 1]), y in [0, 1.97], z in [-1, 1] with the open side towards +z.
_CB_SCALE = 2.0 / 556.0


def _cb_to_world(p) -> np.ndarray:
    """Published mm coordinates -> ours: rotate 180 deg about y so the camera looks down -z."""
    p = np.asarray(p, np.float64)
    return np.stack(
        [-(p[..., 0] - 278.0) * _CB_SCALE, p[..., 1] * _CB_SCALE, -(p[..., 2] - 279.6) * _CB_SCALE],
        axis=-1,
    )


def _oriented_quad(b: SceneBuilder, quad, material: int, towards) -> None:
    """Add a planar quad as two triangles, flat-shaded, facing the point ``towards``
    (or away from it when ``towards`` is given as ('away', point))."""
    q = _cb_to_world(quad)
    n = np.cross(q[1] - q[0], q[2] - q[0])
    n /= np.linalg.norm(n)
    away = isinstance(towards, tuple) and towards[0] == "away"
    ref = np.asarray(towards[1] if away else towards, np.float64)
    side = np.dot(ref - q.mean(0), n)
    if (side < 0) != away:  # wrong way: reverse the winding
        q = q[::-1]
        n = -n
    b.add_mesh(q, [[0, 1, 2], [0, 2, 3]], material, np.tile(n, (4, 1)))


def cornell_camera(height: int = 256, width: int = 256) -> Camera:
    """The published Cornell box camera (fov_y 39.3 deg), in our coordinates."""
    eye = _cb_to_world((278.0, 273.0, -800.0))
    target = _cb_to_world((278.0, 273.0, 0.0))
    fov = math.degrees(2 * math.atan(12.5 / 35.0))
    return Camera.look_at(eye, target, (0, 1, 0), fov_y_deg=fov, height=height, width=width)


def cornell_box(
    light_radiance: tuple[float, float, float] = CORNELL_LIGHT_RADIANCE,
    with_blocks: bool = True,
    height: int = 256,
    width: int = 256,
) -> Scene:
    """The classic Cornell box (published geometry and camera, ceiling area light).

    Coordinates: x in about [-1, 1] (red wall at x = -1, green at x = +1 as seen from the camera:
    red on the left of the image), floor at y = 0, ceiling at y = 1.974, back wall at z = -1, open
    front at z = +1; the camera at z = 3.88 looks down -z.

    Paths: ``train`` (an arc in front of the opening) and ``test`` (a different, lower arc that
    moves inside the box), both 5 s at walking pace.

    Args:
        light_radiance: radiance of the ceiling light (linear RGB).
        with_blocks: include the short and tall blocks.
        height, width: size of the default camera and of the paths' cameras.
    """
    b = SceneBuilder("cornell_box")
    white = b.material("white", albedo=CORNELL_WHITE)
    red = b.material("red", albedo=CORNELL_RED)
    green = b.material("green", albedo=CORNELL_GREEN)
    blocks = {"short": white, "tall": white} if with_blocks else {}
    return _cornell(b, {"red": red, "green": green}, white, blocks, light_radiance, height, width)


def _cornell(
    b: SceneBuilder,
    walls: dict[str, int],
    default: int,
    blocks: dict[str, int],
    light_radiance: tuple[float, float, float],
    height: int,
    width: int,
) -> Scene:
    """The Cornell box's geometry, light, camera and paths into ``b``: the walls ``walls``
    names (floor, ceiling, back, green, red) get that material, the others ``default``; the
    blocks named in ``blocks`` (short, tall) are added with theirs."""
    inside = _cb_to_world((278.0, 274.4, 279.6))
    for name, quad in _CB_QUADS.items():
        _oriented_quad(b, quad, walls.get(name, default), inside)
    for name, block in (("short", _CB_SHORT), ("tall", _CB_TALL)):
        if name not in blocks:
            continue
        # faces point away from the block's centre
        centre = _cb_to_world(np.mean([p for q in block for p in q], axis=0))
        for quad in block:
            _oriented_quad(b, quad, blocks[name], ("away", centre))
    lq = _cb_to_world(_CB_LIGHT)
    # edges chosen so that cross(edge_u, edge_v) points down (-y)
    corner = lq[0]
    eu, ev = lq[1] - lq[0], lq[3] - lq[0]
    if np.cross(eu, ev)[1] > 0:
        eu, ev = ev, eu
    b.add_area_light(AreaLight(corner, eu, ev, light_radiance, name="ceiling_light"))
    cam = cornell_camera(height, width)
    intr = Camera.from_fov(cam.fov_y_deg, height, width)
    train = CameraPath.orbit(
        center=(0.0, 0.0, 0.0),
        radius=3.6,
        height=1.0,
        intrinsics=intr,
        n=48,
        duration_s=5.0,
        start_deg=60.0,
        sweep_deg=60.0,
        look_height=0.95,
        name="train",
    )
    test = CameraPath.flythrough(
        [(-0.55, 0.7, 3.0), (0.0, 0.8, 2.2), (0.45, 0.9, 1.5)],
        intr,
        n=48,
        speed=0.3,
        targets=[(0.2, 0.8, -1.0), (0.0, 0.9, -1.0), (-0.3, 0.8, -1.0)],
        name="test",
    )
    return b.build(
        default_camera=cam, paths={"train": train, "test": test}, source=f"procedural:{b.name}"
    )


def cornell_box_glossy(height: int = 256, width: int = 256) -> Scene:
    """The Cornell box with glossy materials (Mitsuba 3's BSDFs, traced by the general kernel):

    * the tall block: ``roughplastic`` (GGX, alpha 0.3, the box's white under a polypropylene
      coating, ``nonlinear``);
    * the short block: ``roughconductor`` gold (``material="Au"``, GGX, alpha 0.25);
    * the back wall: ``roughplastic`` (Beckmann, alpha 0.1, white): the ceiling light's
      highlight is seen near its top from the default camera.

    The rest, the light, the camera and the ``train``/``test`` paths are :func:`cornell_box`'s.

    Args:
        height, width: size of the default camera and of the paths' cameras.
    """
    from icbtool.scene.bsdf import RoughConductor, RoughPlastic, approximate_albedo

    b = SceneBuilder("cornell_box_glossy")
    white = b.material("white", albedo=CORNELL_WHITE)
    red = b.material("red", albedo=CORNELL_RED)
    green = b.material("green", albedo=CORNELL_GREEN)
    tall = RoughPlastic(
        distribution="ggx", alpha=0.3, diffuse_reflectance=CORNELL_WHITE, nonlinear=True
    )
    short = RoughConductor(material="Au", distribution="ggx", alpha_u=0.25, alpha_v=0.25)
    back = RoughPlastic(distribution="beckmann", alpha=0.1, diffuse_reflectance=CORNELL_WHITE)

    def glossy(name: str, bsdf: object) -> int:  # albedo: the stand-in where no BSDF is seen
        return b.material(name, albedo=approximate_albedo(bsdf), bsdf=bsdf)

    walls = {"red": red, "green": green, "back": glossy("back_glossy", back)}
    blocks = {"short": glossy("short_gold", short), "tall": glossy("tall_plastic", tall)}
    return _cornell(b, walls, white, blocks, CORNELL_LIGHT_RADIANCE, height, width)


# --------------------------------------------------------------------------- known answers
def white_furnace(
    albedo: float = 0.5,
    emission: float = 1.0,
    radius: float = 1.0,
    subdivisions: int = 3,
    height: int = 64,
    width: int = 64,
) -> Scene:
    """A closed sphere seen from inside: every surface has ``albedo`` and emits ``emission``.

    Known answer: the radiance everywhere converges to ``emission / (1 - albedo)`` (for albedo < 1),
    of which the directly seen emission is ``emission`` and the indirect (GI) part
    ``emission * albedo / (1 - albedo)``. Faces point inward. The default camera sits at the centre.
    """
    import trimesh

    if not 0.0 <= albedo < 1.0:
        raise ValueError(f"white_furnace albedo must be in [0, 1), got {albedo}")
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    faces = np.asarray(s.faces)[:, ::-1]  # inward
    verts = np.asarray(s.vertices)
    normals = -verts / np.linalg.norm(verts, axis=1, keepdims=True)
    b = SceneBuilder("white_furnace")
    m = b.material("furnace", albedo=(albedo,) * 3, emission=(emission,) * 3)
    b.add_mesh(verts, faces, m, normals)
    cam = Camera.look_at((0, 0, 0), (0, 0, -1), (0, 1, 0), fov_y_deg=60, height=height, width=width)
    return b.build(default_camera=cam, source="procedural:white_furnace")


def plane(
    size: float = 10.0,
    albedo: tuple[float, float, float] = (0.5, 0.5, 0.5),
    sun_direction: tuple[float, float, float] | None = (0.3, -1.0, 0.2),
    sun_irradiance: float = 3.0,
    sky: float | None = None,
    height: int = 128,
    width: int = 128,
) -> Scene:
    """A square Lambertian plane at y = 0, facing +y, optionally lit by a sun and a uniform sky.

    Known answers: under the sun alone, DL = albedo * E * cos(theta) / pi and GI = 0 (nothing
    else to bounce from). The default camera looks straight down from y = 2 (depth 2 everywhere
    on the plane).
    """
    b = SceneBuilder("plane")
    m = b.material("plane", albedo=albedo)
    h = size / 2
    b.add_quad((-h, 0, h), (size, 0, 0), (0, 0, -size), m)
    if sun_direction is not None:
        b.lights.append(DirectionalLight(sun_direction, (sun_irradiance,) * 3, name="sun"))
    if sky is not None:
        b.sky = Sky((sky,) * 3)
    cam = Camera.look_at((0, 2, 0), (0, 0, 0), (0, 0, -1), fov_y_deg=60, height=height, width=width)
    return b.build(default_camera=cam, source="procedural:plane")


def boxes_on_floor(
    n_boxes: int = 6,
    seed: int = 0,
    sun_direction: tuple[float, float, float] = (-0.4, -1.0, -0.3),
    sun_irradiance: float = 4.0,
    sky: float = 0.3,
    height: int = 128,
    width: int = 128,
) -> Scene:
    """A floor with ``n_boxes`` random boxes (seeded), a sun and a uniform sky.

    Useful for shadows, disocclusion (warping) and cache experiments outside a closed room.
    """
    rng = np.random.default_rng(seed)
    b = SceneBuilder("boxes_on_floor")
    floor = b.material("floor", albedo=(0.6, 0.6, 0.6))
    b.add_quad((-5, 0, 5), (10, 0, 0), (0, 0, -10), floor)
    for i in range(n_boxes):
        col = rng.uniform(0.2, 0.8, 3)
        m = b.material(f"box{i}", albedo=tuple(col))
        size = rng.uniform([0.4, 0.3, 0.4], [1.2, 1.6, 1.2])
        pos = (rng.uniform(-3.5, 3.5), size[1] / 2, rng.uniform(-3.5, 3.5))
        b.add_box(pos, size, m, rotation_y_deg=float(rng.uniform(0, 90)))
    b.lights.append(DirectionalLight(sun_direction, (sun_irradiance,) * 3, name="sun"))
    b.sky = Sky((sky,) * 3)
    cam = Camera.look_at(
        (0, 3, 8), (0, 0.5, 0), (0, 1, 0), fov_y_deg=50, height=height, width=width
    )
    intr = Camera.from_fov(50, height, width)
    train = CameraPath.orbit(
        (0, 0, 0), 7.0, 2.5, intr, n=48, duration_s=20, name="train", look_height=0.5
    )
    test = CameraPath.orbit(
        (0, 0, 0), 5.5, 1.5, intr, n=48, duration_s=20, start_deg=20, name="test", look_height=0.5
    )
    return b.build(
        default_camera=cam, paths={"train": train, "test": test}, source="procedural:boxes_on_floor"
    )


#: Procedural scenes by name (``icbtool render cornell_box`` etc.).
def cornell_box_moving_light(height: int = 256, width: int = 256) -> Scene:
    """The Cornell box whose ceiling light slides along x and back (an animated scene).

    The light is at its published place at t = 0 s, 0.45 m towards +x at t = 1 s, 0.45 m towards
    -x at t = 3 s and back home at t = 4 s (linear in between, held after); see
    :mod:`icbtool.scene.animation`. ``scene.at(t)`` is the box at time t.
    """
    from icbtool.scene.animation import LightTrack, Track, animate

    scene = cornell_box(height=height, width=width)
    light = scene.lights[0]
    dx = np.array([0.45, 0.0, 0.0])
    corners = [light.corner, light.corner + dx, light.corner - dx, light.corner]
    track = LightTrack(0, light, {"corner": Track(np.array([0.0, 1.0, 3.0, 4.0]), corners)})
    moving = animate(scene, [track])
    return dataclasses.replace(moving, name="cornell_box_moving_light")


PROCEDURAL = {
    "cornell_box": cornell_box,
    "cornell_box_glossy": cornell_box_glossy,
    "cornell_box_moving_light": cornell_box_moving_light,
    "white_furnace": white_furnace,
    "plane": plane,
    "boxes_on_floor": boxes_on_floor,
}
