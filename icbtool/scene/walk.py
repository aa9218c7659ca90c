"""Scene-aware camera motion: a collision-free random walk, and a "camera inside a wall" check.

Both cast rays against the scene with :class:`icbtool.scene.raycast.EmbreeScene` (imported lazily:
importing this module stays cheap). They live with the scene, not the camera: the camera package
knows nothing about geometry.

The walk is a person walking on the scene's floors: a horizontal heading that turns smoothly
(an Ornstein-Uhlenbeck turn rate), eye height above the floor found by a ray cast straight down,
steering away from walls seen by look-ahead rays, and a hard clearance from every surface checked
at every step. It is deterministic for a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from icbtool.camera.camera import Camera, CameraPlacementError, pose_from_forward
from icbtool.camera.path import CameraPath

if TYPE_CHECKING:  # pragma: no cover
    from icbtool.scene.types import Scene


def _embree(scene: Scene):
    from icbtool.scene.raycast import EmbreeScene

    return EmbreeScene.from_scene(scene)


def sphere_directions(n: int) -> np.ndarray:
    """(n, 3) float64 unit directions spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@dataclass(frozen=True)
class Surroundings:
    """What rays from one point see.

    Attributes:
        nearest: distance to the nearest surface hit (inf if nothing).
        back_fraction: fraction of all rays whose first hit is a back face (inside a closed
            solid this is ~1; in an open room ~0).
        hit_fraction: fraction of rays that hit anything.
    """

    nearest: float
    back_fraction: float
    hit_fraction: float


def surroundings(scene: Scene, position: Any, n_rays: int = 128) -> Surroundings:
    """Cast ``n_rays`` rays in all directions from ``position`` (3,) and summarise the hits."""
    es = _embree(scene)
    d = sphere_directions(n_rays)
    o = np.broadcast_to(np.asarray(position, np.float64), d.shape)
    h = es.intersect(o, d)
    hit = h.prim >= 0
    back = hit & (np.einsum("ij,ij->i", h.ng, d) > 0)
    return Surroundings(
        nearest=float(h.t[hit].min()) if hit.any() else math.inf,
        back_fraction=float(back.mean()),
        hit_fraction=float(hit.mean()),
    )


def check_camera(
    scene: Scene,
    camera: Camera,
    min_distance: float | None = None,
    max_back_fraction: float = 0.5,
    n_rays: int = 128,
) -> Surroundings:
    """Raise if ``camera`` is inside geometry or closer than ``min_distance`` to a surface.

    Args:
        scene: the scene.
        camera: the camera to check.
        min_distance: the smallest allowed distance to any surface; default 1e-3 of the scene's
            bounds diagonal.
        max_back_fraction: more rays than this hitting back faces first means "inside a wall"
            (a closed solid). One-sided open geometry seen from behind counts as back faces too.
        n_rays: rays cast evenly over the sphere.

    Returns:
        The :class:`Surroundings` (when the camera is fine).

    Raises:
        CameraPlacementError: naming the camera position and the problem.
    """
    s = surroundings(scene, camera.position, n_rays)
    md = 1e-3 * scene.diagonal if min_distance is None else float(min_distance)
    p = np.round(camera.position, 4).tolist()
    if s.back_fraction > max_back_fraction:
        raise CameraPlacementError(
            f"camera at {p} is inside geometry of scene '{scene.name}': "
            f"{100 * s.back_fraction:.0f}% of rays from it hit back faces first"
        )
    if s.nearest < md:
        raise CameraPlacementError(
            f"camera at {p} is {s.nearest:.3g} from a surface of scene '{scene.name}' "
            f"(minimum {md:.3g}): it would clip through the wall"
        )
    return s


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    return a, np.cross(a, up)


def random_walk(
    scene: Scene,
    intrinsics: Camera,
    n: int,
    seed: int,
    speed: float = 1.4,
    dt: float = 0.1,
    height_range: tuple[float, float] = (1.5, 1.8),
    clearance: float = 0.4,
    lookahead: float = 2.0,
    turn_rate_deg: float = 30.0,
    pitch_range_deg: tuple[float, float] = (-10.0, 10.0),
    max_floor_step: float = 0.3,
    start: Any | None = None,
    name: str = "random_walk",
) -> CameraPath:
    """A person's random walk through ``scene``: on the floor, inside the bounds, off the walls.

    Every step is checked with ray casts: the floor (within ``max_floor_step`` of the last one)
    must be below (a surface facing up within
    ``height_range[1] + 1`` units), and no surface may be closer than ``clearance`` in 16
    horizontal directions or above. Look-ahead rays steer the heading away from walls before
    they are reached; when a step is blocked anyway the walker turns towards the freest
    direction. The camera looks along the (smoothed) heading with a slowly varying pitch.

    Args:
        scene: the scene (``scene.up`` is the walking up axis).
        intrinsics: camera size and intrinsics of every pose.
        n: number of cameras (>= 2).
        seed: random seed (same seed, same path).
        speed: walking speed, world units per second.
        dt: seconds between cameras.
        height_range: eye height above the floor (min, max), world units.
        clearance: minimal distance from the eye to any surface.
        lookahead: distance at which walls start to steer the heading.
        turn_rate_deg: standard deviation of the random turn rate, degrees per second.
        pitch_range_deg: the camera pitch (up positive) stays inside this range.
        max_floor_step: the floor may rise or drop by at most this much per step (stairs);
            larger changes (ledges, walls) block the step.
        start: (3,) start eye position; default: a random valid point (on a floor, clear).
        name: the path's name.

    Returns:
        A :class:`CameraPath` with ``n`` cameras ``dt`` apart.

    Raises:
        ValueError: bad arguments, or no valid start position / a start inside geometry.
    """
    lo_h, hi_h = (float(x) for x in height_range)
    if n < 2 or speed <= 0 or dt <= 0 or not (0 < lo_h <= hi_h) or clearance <= 0:
        raise ValueError(
            f"random_walk '{name}': need n >= 2, speed > 0, dt > 0, 0 < height_range[0] <= "
            f"height_range[1], clearance > 0; got n={n}, speed={speed}, dt={dt}, "
            f"height_range={height_range}, clearance={clearance}"
        )
    if not (-89 < pitch_range_deg[0] <= pitch_range_deg[1] < 89):
        raise ValueError(f"random_walk '{name}': bad pitch_range_deg {pitch_range_deg}")
    rng = np.random.default_rng(seed)
    es = _embree(scene)
    up = np.asarray(scene.up, np.float64)
    ax, bx = _horizontal_basis(up)
    lo, hi = scene.bounds
    margin = clearance
    n_dirs = 16
    ring = 2 * math.pi * np.arange(n_dirs) / n_dirs

    def hdir(theta: np.ndarray | float) -> np.ndarray:
        th = np.asarray(theta, np.float64)[..., None]
        return np.cos(th) * ax + np.sin(th) * bx

    def cast(origins: np.ndarray, dirs: np.ndarray):
        o = np.broadcast_to(origins, dirs.shape)
        return es.intersect(o, dirs)

    def floor_below(p: np.ndarray) -> float | None:
        """Height of p above the floor (facing up) below it, or None."""
        h = cast(p[None], -up[None])
        if h.prim[0] < 0 or float(h.ng[0] @ up) < 0.5 or h.t[0] > hi_h + 1.0:
            return None
        return float(h.t[0])

    def clear(p: np.ndarray) -> bool:
        if np.any(p < lo + margin) or np.any(p > hi - margin):
            return False
        dirs = np.concatenate([hdir(ring), up[None]])
        h = cast(p[None], dirs)
        return bool(np.all(h.t > clearance))

    def valid(p: np.ndarray) -> float | None:
        """Eye height above the floor if p is a valid eye position, else None."""
        hf = floor_below(p)
        if hf is None or hf < 0.5 * lo_h or not clear(p):
            return None
        return hf

    # ---- start
    if start is not None:
        pos = np.asarray(start, np.float64).reshape(3)
        if valid(pos) is None:
            raise ValueError(
                f"random_walk '{name}': start {pos.tolist()} is not a valid eye position in "
                f"scene '{scene.name}' (needs a floor below within {hi_h + 1:g}, and clearance "
                f"{clearance:g} from every surface horizontally and above)"
            )
    else:
        pos = None
        for _ in range(2000):
            p = lo + rng.random(3) * (hi - lo)
            hf = floor_below(p)
            if hf is None:
                continue
            p = p - hf * up + rng.uniform(lo_h, hi_h) * up
            if valid(p) is not None:
                pos = p
                break
        if pos is None:
            raise ValueError(
                f"random_walk '{name}': found no valid start in scene '{scene.name}' after 2000 "
                "tries (is there a floor facing scene.up with room above it?)"
            )

    # ---- walk
    step = speed * dt
    heading = rng.uniform(0, 2 * math.pi)
    free0 = cast(pos[None], hdir(heading + ring)).t
    heading = float(heading + ring[int(np.argmax(free0))])  # start towards the most open side
    look_yaw = heading
    omega = 0.0  # turn rate, rad/s
    sigma = math.radians(turn_rate_deg)
    eye_h = float(valid(pos) or lo_h)
    floor_h = float(pos @ up) - eye_h
    target_h = float(np.clip(eye_h, lo_h, hi_h))
    pitch = 0.0
    pitch_lo, pitch_hi = (math.radians(x) for x in pitch_range_deg)
    positions, yaws, pitches = [pos.copy()], [look_yaw], [pitch]
    for _ in range(n - 1):
        # random turn rate (OU process), then steering away from walls ahead
        omega = 0.8 * omega + sigma * math.sqrt(1 - 0.8**2) * rng.standard_normal()
        probe = heading + np.radians([-60.0, -30.0, 0.0, 30.0, 60.0])
        free = cast(pos[None], hdir(probe)).t
        free = np.minimum(free, 10 * lookahead)
        if free[2] < lookahead + clearance:
            # turn towards the freer side, harder when closer
            side = 1.0 if (free[3] + free[4]) > (free[0] + free[1]) else -1.0
            urgency = 1.0 - max(free[2] - clearance, 0.0) / lookahead
            omega = side * max(abs(omega), math.radians(45.0) * (0.5 + urgency))
        new = None
        for attempt in range(n_dirs + 1):
            th = heading + omega * dt
            cand = pos + step * hdir(th)
            hf = floor_below(cand)
            if hf is not None and abs(float(cand @ up) - hf - floor_h) <= max_floor_step:
                # the eye height moves smoothly towards the target height above this floor
                eye_h = float(np.clip(eye_h + 0.2 * (target_h - eye_h), lo_h, hi_h))
                cand = cand + (eye_h - hf) * up
                if valid(cand) is not None and not cast(pos[None], hdir(th)[None]).t[0] < step:
                    new = cand
                    heading = th
                    floor_h = float(cand @ up) - eye_h
                    break
            if attempt == 0:  # blocked: face the freest horizontal direction
                free_all = cast(pos[None], hdir(heading + ring)).t
                order = np.argsort(-free_all)
                heading = float(heading + ring[order[0]])
                omega = 0.0
            else:
                heading = float(heading + ring[rng.integers(1, n_dirs)])
        if new is None:
            raise ValueError(
                f"random_walk '{name}': the walker got stuck at {np.round(pos, 3).tolist()} in "
                f"scene '{scene.name}' (try a smaller clearance or another seed)"
            )
        pos = new
        if rng.random() < dt / 3.0:  # a new eye height every ~3 s
            target_h = rng.uniform(lo_h, hi_h)
        # the view follows the heading with a limited yaw rate (smooth camera)
        dyaw = (heading - look_yaw + math.pi) % (2 * math.pi) - math.pi
        max_yaw = math.radians(90.0) * dt
        look_yaw += float(np.clip(dyaw, -max_yaw, max_yaw))
        pitch = float(
            np.clip(0.9 * pitch + math.radians(2.0) * rng.standard_normal(), pitch_lo, pitch_hi)
        )
        positions.append(pos.copy())
        yaws.append(look_yaw)
        pitches.append(pitch)
    poses = []
    for p, yw, pt in zip(positions, yaws, pitches):
        fwd = math.cos(pt) * hdir(yw) + math.sin(pt) * up
        poses.append(pose_from_forward(p, fwd, up))
    times = dt * np.arange(n, dtype=np.float64)
    return CameraPath(times, np.stack(poses), intrinsics, name)
