"""Scene description: actors (oriented boxes) on closed-form trajectories, and the ego track."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Track", "Actor", "Scene", "BACKGROUND", "CAR", "OTHER_VEHICLE", "PEDESTRIAN", "WHEELED_VRU"]

BACKGROUND, CAR, OTHER_VEHICLE, PEDESTRIAN, WHEELED_VRU = range(5)


@dataclass(frozen=True)
class Track:
    """Planar motion with constant speed and yaw rate (a straight line or a circular arc).

    ``speed`` is along the heading (negative = reversing); ``yaw_rate`` in rad/s.
    """

    x: float
    y: float
    yaw: float = 0.0
    speed: float = 0.0
    yaw_rate: float = 0.0

    @property
    def moving(self) -> bool:
        return self.speed != 0.0 or self.yaw_rate != 0.0

    def pose2d(self, t: float) -> tuple[float, float, float]:
        """(x, y, yaw) at time t seconds."""
        w, v = self.yaw_rate, self.speed
        if abs(w) < 1e-9:
            return (self.x + v * t * math.cos(self.yaw), self.y + v * t * math.sin(self.yaw), self.yaw)
        yaw_t = self.yaw + w * t
        r = v / w
        return (
            self.x + r * (math.sin(yaw_t) - math.sin(self.yaw)),
            self.y - r * (math.cos(yaw_t) - math.cos(self.yaw)),
            yaw_t,
        )

    def poses(self, ts: np.ndarray) -> np.ndarray:
        """(T, 3) array of (x, y, yaw) at the times ``ts``, vectorised ``pose2d``."""
        ts = np.asarray(ts, dtype=np.float64)
        w, v = self.yaw_rate, self.speed
        if abs(w) < 1e-9:
            yaw = np.full_like(ts, self.yaw)
            return np.stack([self.x + v * ts * math.cos(self.yaw), self.y + v * ts * math.sin(self.yaw), yaw], -1)
        yaw = self.yaw + w * ts
        r = v / w
        return np.stack([self.x + r * (np.sin(yaw) - math.sin(self.yaw)),
                         self.y - r * (np.cos(yaw) - math.cos(self.yaw)), yaw], -1)

    def matrix(self, t: float, z: float = 0.0) -> np.ndarray:
        """4x4 pose (local -> world) at time t with the local origin lifted to height z."""
        x, y, yaw = self.pose2d(t)
        c, s = math.cos(yaw), math.sin(yaw)
        m = np.eye(4)
        m[:2, :2] = [[c, -s], [s, c]]
        m[:3, 3] = (x, y, z)
        return m


@dataclass(frozen=True)
class Actor:
    """An oriented box standing on the ground (bottom at height ``z``).

    ``size`` = (length along heading, width, height) in metres. Background structures
    (buildings, walls, poles, barriers) use class 0 and instance -1.
    """

    size: tuple[float, float, float]
    cls: int
    track: Track
    instance: int = -1
    z: float = 0.0


EGO_SIZE = (4.6, 1.9, 1.6)
_MARGIN = 0.3  # metres of clearance kept between foreground boxes


def _obb_overlap(pa, sa, pb, sb) -> np.ndarray:
    """Separating-axis test for 2D oriented boxes; poses (..., 3) = (x, y, yaw), sizes (..., 2) full."""
    d = pb[..., :2] - pa[..., :2]
    axes = [pa[..., 2], pa[..., 2] + math.pi / 2, pb[..., 2], pb[..., 2] + math.pi / 2]
    overlap = np.ones(np.broadcast_shapes(pa.shape[:-1], pb.shape[:-1]), dtype=bool)
    for ang in axes:
        ux, uy = np.cos(ang), np.sin(ang)

        def radius(p, s):
            return (s[..., 0] / 2 * np.abs(ux * np.cos(p[..., 2]) + uy * np.sin(p[..., 2]))
                    + s[..., 1] / 2 * np.abs(-ux * np.sin(p[..., 2]) + uy * np.cos(p[..., 2])))

        overlap &= np.abs(d[..., 0] * ux + d[..., 1] * uy) <= radius(pa, sa) + radius(pb, sb)
    return overlap


@dataclass
class Scene:
    """Actors plus the ego track. ``horizon`` (seconds) is how long ``add`` keeps foreground
    actors (and the ego vehicle) from intersecting each other."""

    name: str
    ego: Track
    actors: list[Actor] = field(default_factory=list)
    horizon: float = 2.0

    def __post_init__(self):
        self._times = np.linspace(0.0, self.horizon, int(math.ceil(self.horizon / 0.05)) + 1)
        self._fg_poses = [self.ego.poses(self._times)]  # (T, 3) per foreground actor, ego first
        self._fg_sizes = [EGO_SIZE[:2]]
        self._next_instance = 0

    def collides(self, size, track: Track) -> bool:
        """Whether a box of ``size`` on ``track`` would intersect a foreground actor or the ego."""
        p = track.poses(self._times)[None]  # (1, T, 3)
        s = np.array(size[:2], dtype=np.float64) + _MARGIN
        others = np.stack(self._fg_poses)  # (K, T, 3)
        osz = np.array(self._fg_sizes, dtype=np.float64)[:, None, :] + _MARGIN  # (K, 1, 2)
        return bool(_obb_overlap(p, s, others, osz).any())

    def add(self, size, cls, x, y, yaw=0.0, speed=0.0, yaw_rate=0.0, z=0.0, check=True) -> Actor | None:
        """Append an actor, or return None if a foreground actor would collide with another.

        Foreground classes get the next instance id; background structures are never checked.
        """
        track = Track(float(x), float(y), float(yaw), float(speed), float(yaw_rate))
        size = tuple(float(v) for v in size)
        if cls == BACKGROUND:
            a = Actor(size, int(cls), track, -1, z)
        else:
            if check and self.collides(size, track):
                return None
            a = Actor(size, int(cls), track, self._next_instance, z)
            self._next_instance += 1
            self._fg_poses.append(track.poses(self._times))
            self._fg_sizes.append(size[:2])
        self.actors.append(a)
        return a
