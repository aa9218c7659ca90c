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
    probe = _Probe(scene, _embree(scene), (lo_h, hi_h), clearance)
    pos = probe.start_position(rng, start, name)
    walker = _Walker(probe, rng, pos, speed, dt, turn_rate_deg, lookahead, max_floor_step)
    target_h = float(np.clip(walker.eye_h, lo_h, hi_h))
    view = _View(rng, walker.heading, dt, (lo_h, hi_h), pitch_range_deg, target_h)
    positions, yaws, pitches = [pos.copy()], [view.yaw], [view.pitch]
    for _ in range(n - 1):
        walker.turn()
        if not walker.step(view.eye_height):
            raise ValueError(
                f"random_walk '{name}': the walker got stuck at "
                f"{np.round(walker.pos, 3).tolist()} in scene '{scene.name}' (try a smaller "
                "clearance or another seed)"
            )
        view.follow(walker.heading)
        positions.append(walker.pos.copy())
        yaws.append(view.yaw)
        pitches.append(view.pitch)
    poses = []
    for p, yw, pt in zip(positions, yaws, pitches):
        fwd = math.cos(pt) * probe.hdir(yw) + math.sin(pt) * probe.up
        poses.append(pose_from_forward(p, fwd, probe.up))
    times = dt * np.arange(n, dtype=np.float64)
    return CameraPath(times, np.stack(poses), intrinsics, name)


#: Horizontal directions of the clearance test and of the blocked walker's search.
_N_DIRS = 16
_RING = 2 * math.pi * np.arange(_N_DIRS) / _N_DIRS


class _Probe:
    """The ray casts of the walk: horizontal directions, the floor below a point, the clearance
    around it, and whether it is a valid eye position."""

    def __init__(
        self, scene: Scene, es: Any, height_range: tuple[float, float], clearance: float
    ) -> None:
        self.scene, self.es = scene, es
        self.up = np.asarray(scene.up, np.float64)
        self.ax, self.bx = _horizontal_basis(self.up)
        self.lo, self.hi = scene.bounds
        self.lo_h, self.hi_h = height_range
        self.clearance = clearance

    def hdir(self, theta: np.ndarray | float) -> np.ndarray:
        """Horizontal unit direction(s) at angle(s) ``theta`` (radians): (..., 3)."""
        th = np.asarray(theta, np.float64)[..., None]
        return np.cos(th) * self.ax + np.sin(th) * self.bx

    def free(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance to the first hit along each of ``dirs`` (k, 3) from ``origin`` (inf: none)."""
        return self.cast(origin[None], dirs).t

    def cast(self, origins: np.ndarray, dirs: np.ndarray):
        return self.es.intersect(np.broadcast_to(origins, dirs.shape), dirs)

    def floor_below(self, p: np.ndarray) -> float | None:
        """Height of p above the floor (facing up) below it, or None."""
        up = self.up
        h = self.cast(p[None], -up[None])
        if h.prim[0] < 0 or float(h.ng[0] @ up) < 0.5 or h.t[0] > self.hi_h + 1.0:
            return None
        return float(h.t[0])

    def clear(self, p: np.ndarray) -> bool:
        """Inside the bounds (less the clearance) and no surface within the clearance in the
        horizontal ring of directions or above."""
        margin = self.clearance
        if np.any(p < self.lo + margin) or np.any(p > self.hi - margin):
            return False
        dirs = np.concatenate([self.hdir(_RING), self.up[None]])
        return bool(np.all(self.free(p, dirs) > self.clearance))

    def valid(self, p: np.ndarray) -> float | None:
        """Eye height above the floor if p is a valid eye position, else None."""
        hf = self.floor_below(p)
        if hf is None or hf < 0.5 * self.lo_h or not self.clear(p):
            return None
        return hf

    def start_position(self, rng: np.random.Generator, start: Any, name: str) -> np.ndarray:
        """``start`` checked, or a random valid eye position (2000 tries)."""
        if start is not None:
            pos = np.asarray(start, np.float64).reshape(3)
            if self.valid(pos) is None:
                raise ValueError(
                    f"random_walk '{name}': start {pos.tolist()} is not a valid eye position in "
                    f"scene '{self.scene.name}' (needs a floor below within {self.hi_h + 1:g}, "
                    f"and clearance {self.clearance:g} from every surface horizontally and above)"
                )
            return pos
        for _ in range(2000):
            p = self.lo + rng.random(3) * (self.hi - self.lo)
            hf = self.floor_below(p)
            if hf is None:
                continue
            p = p - hf * self.up + rng.uniform(self.lo_h, self.hi_h) * self.up
            if self.valid(p) is not None:
                return p
        raise ValueError(
            f"random_walk '{name}': found no valid start in scene '{self.scene.name}' after 2000 "
            "tries (is there a floor facing scene.up with room above it?)"
        )


class _Walker:
    """The walker's body: position on the floor, heading and turn rate (an Ornstein-Uhlenbeck
    process steered away from walls ahead)."""

    def __init__(
        self,
        probe: _Probe,
        rng: np.random.Generator,
        pos: np.ndarray,
        speed: float,
        dt: float,
        turn_rate_deg: float,
        lookahead: float,
        max_floor_step: float,
    ) -> None:
        self.probe, self.rng, self.pos, self.dt = probe, rng, pos, dt
        self.step_length = speed * dt
        self.lookahead, self.max_floor_step = lookahead, max_floor_step
        heading = rng.uniform(0, 2 * math.pi)
        free0 = probe.free(pos, probe.hdir(heading + _RING))
        self.heading = float(heading + _RING[int(np.argmax(free0))])  # towards the most open side
        self.omega = 0.0  # turn rate, rad/s
        self.sigma = math.radians(turn_rate_deg)
        self.eye_h = float(probe.valid(pos) or probe.lo_h)
        self.floor_h = float(pos @ probe.up) - self.eye_h

    def turn(self) -> None:
        """A random turn rate (OU process), then steering away from a wall ahead (harder when
        closer), towards the freer side."""
        self.omega = 0.8 * self.omega + self.sigma * math.sqrt(1 - 0.8**2) * (
            self.rng.standard_normal()
        )
        probe, clearance = self.probe, self.probe.clearance
        ahead = self.heading + np.radians([-60.0, -30.0, 0.0, 30.0, 60.0])
        free = np.minimum(probe.free(self.pos, probe.hdir(ahead)), 10 * self.lookahead)
        if free[2] < self.lookahead + clearance:
            side = 1.0 if (free[3] + free[4]) > (free[0] + free[1]) else -1.0
            urgency = 1.0 - max(free[2] - clearance, 0.0) / self.lookahead
            self.omega = side * max(abs(self.omega), math.radians(45.0) * (0.5 + urgency))

    def step(self, target_h: float) -> bool:
        """One step along the turned heading; when blocked, face the freest direction, then
        random ones. The eye height moves smoothly towards ``target_h`` above the floor.

        Returns:
            False when every try was blocked (the walker is stuck).
        """
        probe, up, step = self.probe, self.probe.up, self.step_length
        for attempt in range(_N_DIRS + 1):
            th = self.heading + self.omega * self.dt
            cand = self.pos + step * probe.hdir(th)
            hf = probe.floor_below(cand)
            if hf is not None and abs(float(cand @ up) - hf - self.floor_h) <= self.max_floor_step:
                self.eye_h = float(
                    np.clip(self.eye_h + 0.2 * (target_h - self.eye_h), probe.lo_h, probe.hi_h)
                )
                cand = cand + (self.eye_h - hf) * up
                path_free = not (probe.free(self.pos, probe.hdir(th)[None])[0] < step)
                if probe.valid(cand) is not None and path_free:
                    self.pos, self.heading = cand, th
                    self.floor_h = float(cand @ up) - self.eye_h
                    return True
            if attempt == 0:  # blocked: face the freest horizontal direction
                free_all = probe.free(self.pos, probe.hdir(self.heading + _RING))
                self.heading = float(self.heading + _RING[np.argsort(-free_all)[0]])
                self.omega = 0.0
            else:
                self.heading = float(self.heading + _RING[self.rng.integers(1, _N_DIRS)])
        return False


class _View:
    """Where the camera looks: the target eye height (new every ~3 s), the yaw following the
    heading at a bounded rate, and a slowly varying pitch."""

    def __init__(
        self,
        rng: np.random.Generator,
        heading: float,
        dt: float,
        height_range: tuple[float, float],
        pitch_range_deg: tuple[float, float],
        eye_height: float,
    ) -> None:
        self.rng, self.dt = rng, dt
        self.lo_h, self.hi_h = height_range
        self.yaw = heading
        self.pitch = 0.0
        self.pitch_lo, self.pitch_hi = (math.radians(x) for x in pitch_range_deg)
        self.eye_height = eye_height  # the target eye height above the floor

    def follow(self, heading: float) -> None:
        """After a step: maybe a new target eye height, the yaw towards ``heading`` and the
        pitch's random drift."""
        dt, rng = self.dt, self.rng
        if rng.random() < dt / 3.0:  # a new eye height every ~3 s
            self.eye_height = rng.uniform(self.lo_h, self.hi_h)
        dyaw = (heading - self.yaw + math.pi) % (2 * math.pi) - math.pi
        max_yaw = math.radians(90.0) * dt
        self.yaw += float(np.clip(dyaw, -max_yaw, max_yaw))
        self.pitch = float(
            np.clip(
                0.9 * self.pitch + math.radians(2.0) * rng.standard_normal(),
                self.pitch_lo,
                self.pitch_hi,
            )
        )
