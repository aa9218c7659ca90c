"""Timed camera paths: orbits, smooth fly-throughs and (scene-aware) random walks.

A path is a list of timed poses sharing one set of intrinsics. Between keys, positions follow a
cubic spline (C2) and orientations a spherical-linear interpolation; velocities are derived from
the same interpolants, so ``velocity`` is the exact derivative of ``camera_at``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from icbtool.camera.camera import ArrayLike, Camera, look_at_pose


@dataclass(frozen=True, eq=False)
class CameraPath:
    """Timed camera poses with shared intrinsics.

    Attributes:
        times: (N,) strictly increasing seconds.
        world_from_cam: (N, 4, 4) poses (OpenCV axes).
        intrinsics: a :class:`Camera` whose size and intrinsics every pose uses (its pose ignored).
        name: a label ("train", "test", ...).
    """

    times: np.ndarray
    world_from_cam: np.ndarray
    intrinsics: Camera
    name: str = "path"
    _interp: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        p = np.asarray(self.world_from_cam, dtype=np.float64)
        if p.ndim != 3 or p.shape[1:] != (4, 4):
            raise ValueError(f"CameraPath '{self.name}': poses must be (N, 4, 4), got {p.shape}")
        if len(t) != len(p) or len(t) == 0:
            raise ValueError(
                f"CameraPath '{self.name}': need as many times as poses (>0), "
                f"got {len(t)} times and {len(p)} poses"
            )
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ValueError(f"CameraPath '{self.name}': times must be finite, strictly increasing")
        for i, m in enumerate(p):  # validates each pose
            try:
                self.intrinsics.with_pose(m)
            except ValueError as e:
                raise ValueError(f"CameraPath '{self.name}': pose {i} is invalid: {e}") from e
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "world_from_cam", p)

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.times)

    def __getitem__(self, i: int) -> Camera:
        return self.intrinsics.with_pose(self.world_from_cam[i])

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def cameras(self) -> list[Camera]:
        """The key cameras, in time order."""
        return list(self)

    @property
    def duration(self) -> float:
        """Seconds from the first key to the last."""
        return float(self.times[-1] - self.times[0])

    def _interpolants(self) -> dict[str, Any]:
        if not self._interp:
            from scipy.interpolate import CubicSpline
            from scipy.spatial.transform import Rotation, Slerp

            pos = self.world_from_cam[:, :3, 3]
            rot = Rotation.from_matrix(self.world_from_cam[:, :3, :3])
            if len(self) >= 2:
                bc = "natural" if len(self) >= 3 else "not-a-knot"
                self._interp["pos"] = CubicSpline(self.times, pos, axis=0, bc_type=bc)
                self._interp["rot"] = Slerp(self.times, rot)
            self._interp["Rotation"] = Rotation
        return self._interp

    def pose_at(self, t: float) -> np.ndarray:
        """(4, 4) interpolated pose at time ``t`` (clamped to the path's time range)."""
        if len(self) == 1:
            return self.world_from_cam[0].copy()
        t = float(np.clip(t, self.times[0], self.times[-1]))
        it = self._interpolants()
        m = np.eye(4)
        m[:3, :3] = it["rot"]([t]).as_matrix()[0]
        m[:3, 3] = it["pos"](t)
        return m

    def camera_at(self, t: float) -> Camera:
        """The interpolated camera at time ``t`` (clamped to the path's range)."""
        return self.intrinsics.with_pose(self.pose_at(t))

    def velocity(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Translation and rotation velocity at time ``t``.

        Returns:
            v_world: (3,) translation velocity in world units per second.
            omega_cam: (3,) angular velocity in rad/s about the camera's own axes
                (x right: pitch, y down: yaw, z forward: roll).
        """
        if len(self) == 1:
            return np.zeros(3), np.zeros(3)
        it = self._interpolants()
        t = float(np.clip(t, self.times[0], self.times[-1]))
        v = it["pos"](t, 1)
        h = 1e-3 * max(self.duration / max(len(self) - 1, 1), 1e-6)
        t0, t1 = max(t - h, self.times[0]), min(t + h, self.times[-1])
        r0, r1 = it["rot"]([t0, t1])
        omega = (r0.inv() * r1).as_rotvec() / (t1 - t0)  # in the camera frame at t0
        return np.asarray(v, dtype=np.float64), omega

    def velocity_cam(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`velocity`, with the translation velocity in the camera's frame."""
        v, w = self.velocity(t)
        r = self.pose_at(t)[:3, :3]
        return r.T @ v, w

    def resampled(self, n: int) -> CameraPath:
        """``n`` cameras evenly spaced in time over the same path."""
        ts = np.linspace(self.times[0], self.times[-1], n)
        poses = np.stack([self.pose_at(t) for t in ts])
        return CameraPath(ts, poses, self.intrinsics, self.name)

    def with_intrinsics(self, intrinsics: Camera) -> CameraPath:
        """The same poses seen through another camera (size, FOV)."""
        return CameraPath(self.times, self.world_from_cam, intrinsics, self.name)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "times": self.times.tolist(),
            "world_from_cam": self.world_from_cam.tolist(),
            "intrinsics": self.intrinsics.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraPath:
        return cls(
            np.asarray(d["times"]),
            np.asarray(d["world_from_cam"]),
            Camera.from_dict(d["intrinsics"]),
            d.get("name", "path"),
        )

    # ------------------------------------------------------------------ constructors
    @classmethod
    def orbit(
        cls,
        center: ArrayLike,
        radius: float,
        height: float,
        intrinsics: Camera,
        n: int = 60,
        duration_s: float = 10.0,
        start_deg: float = 0.0,
        sweep_deg: float = 360.0,
        up: ArrayLike = (0.0, 1.0, 0.0),
        look_height: float | None = None,
        name: str = "orbit",
    ) -> CameraPath:
        """Cameras on a horizontal circle around ``center`` (``up`` is the circle's normal),
        looking at ``center`` (raised by ``look_height`` along ``up``, default 0).

        Args:
            center: (3,) orbit centre.
            radius: circle radius (> 0).
            height: camera height above ``center`` along ``up``.
            n: number of key cameras (>= 1).
        """
        if radius <= 0 or n < 1 or duration_s <= 0:
            raise ValueError(f"orbit needs radius > 0, n >= 1, duration_s > 0; got {radius}, {n}")
        c = np.asarray(center, np.float64)
        u = np.asarray(up, np.float64)
        u = u / np.linalg.norm(u)
        a = np.cross(u, [1.0, 0, 0] if abs(u[0]) < 0.9 else [0, 0, 1.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        endpoint = not math.isclose(abs(sweep_deg), 360.0)
        angs = np.radians(start_deg + np.linspace(0, sweep_deg, n, endpoint=endpoint))
        target = c + (0.0 if look_height is None else look_height) * u
        poses = [
            look_at_pose(c + radius * (math.cos(t) * a + math.sin(t) * b) + height * u, target, u)
            for t in angs
        ]
        times = np.linspace(0, duration_s, n) if n > 1 else np.zeros(1)
        return cls(times, np.stack(poses), intrinsics, name)

    @classmethod
    def flythrough(
        cls,
        waypoints: ArrayLike,
        intrinsics: Camera,
        n: int = 60,
        speed: float = 1.4,
        targets: ArrayLike | None = None,
        up: ArrayLike = (0.0, 1.0, 0.0),
        name: str = "flythrough",
    ) -> CameraPath:
        """A smooth path through ``waypoints`` at constant ``speed`` (world units / s).

        Positions follow a centripetal Catmull-Rom-like cubic spline through the waypoints,
        re-parametrised by arc length. Cameras look along the path tangent, or at the matching
        ``targets`` (interpolated the same way) when given.

        Args:
            waypoints: (K, 3), K >= 2, consecutive points distinct.
            n: number of key cameras along the path.
            speed: world units per second (walking: 1.4 m/s).
            targets: optional (K, 3) look-at points.
        """
        from scipy.interpolate import CubicSpline

        w = np.asarray(waypoints, np.float64)
        if w.ndim != 2 or w.shape[1] != 3 or len(w) < 2:
            raise ValueError(f"flythrough waypoints must be (K>=2, 3), got {w.shape}")
        seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
        if np.any(seg < 1e-9):
            raise ValueError("flythrough waypoints must not repeat consecutively")
        if speed <= 0 or n < 2:
            raise ValueError(f"flythrough needs speed > 0 and n >= 2, got {speed}, {n}")
        knots = np.concatenate([[0.0], np.cumsum(np.sqrt(seg))])  # centripetal parameter
        bc = "natural" if len(w) >= 3 else "not-a-knot"
        spl = CubicSpline(knots, w, axis=0, bc_type=bc)
        tspl = None
        if targets is not None:
            tg = np.asarray(targets, np.float64)
            if tg.shape != w.shape:
                raise ValueError(
                    f"targets must have the waypoints' shape {w.shape}, got {tg.shape}"
                )
            tspl = CubicSpline(knots, tg, axis=0, bc_type=bc)
        # arc-length reparametrisation
        s_dense = np.linspace(0, knots[-1], 2048)
        p_dense = spl(s_dense)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_dense, axis=0), axis=1))])
        s_keys = np.interp(np.linspace(0, arc[-1], n), arc, s_dense)
        poses = []
        for s in s_keys:
            p = spl(s)
            if tspl is not None:
                poses.append(look_at_pose(p, tspl(s), up))
            else:
                poses.append(look_at_pose(p, p + spl(s, 1), up))
        times = np.linspace(0.0, arc[-1] / speed, n)
        return cls(times, np.stack(poses), intrinsics, name)
