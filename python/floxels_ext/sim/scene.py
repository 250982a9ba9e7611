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


@dataclass
class Scene:
    name: str
    ego: Track
    actors: list[Actor] = field(default_factory=list)

    def add(self, size, cls, x, y, yaw=0.0, speed=0.0, yaw_rate=0.0, z=0.0) -> Actor:
        """Append an actor; foreground classes get the next instance id."""
        inst = -1 if cls == BACKGROUND else 1 + max([a.instance for a in self.actors] + [-1])
        a = Actor(tuple(float(v) for v in size), int(cls), Track(x, y, yaw, speed, yaw_rate), inst, z)
        self.actors.append(a)
        return a
