"""Spinning-lidar model and vectorised ray casting against a ground plane and oriented boxes.

Rays form a (beams, azimuth_steps) grid. For each box we only test the sub-grid of rays
whose azimuth and elevation can reach it (a cheap angular bound computed from the box
corners), so even scenes with a hundred boxes cast a 64 x 2048 scan in well under a second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LidarConfig", "SMALL_LIDAR", "BoxSet", "cast_scan"]


@dataclass(frozen=True)
class LidarConfig:
    beams: int = 64
    azimuth_steps: int = 2048
    fov_up: float = 3.0  # degrees above the horizon (top beam)
    fov_down: float = -25.0  # degrees (bottom beam)
    max_range: float = 70.0  # metres; rays hitting nothing closer return no point
    min_range: float = 2.0  # metres; closer returns are discarded, like a real sensor's blind zone
    range_noise: float = 0.02  # std-dev of gaussian range noise along the ray, metres
    dropout: float = 0.05  # probability that a return is randomly lost
    sensor_height: float = 1.8  # metres above the ground plane
    rate_hz: float = 10.0  # scans per second (frame spacing dt = 1 / rate_hz)

    def __post_init__(self):
        if self.beams < 1 or self.azimuth_steps < 1:
            raise ValueError("beams and azimuth_steps must be >= 1")
        if not self.fov_down < self.fov_up or self.fov_down < -89 or self.fov_up > 89:
            raise ValueError("need -89 <= fov_down < fov_up <= 89 degrees")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError("need 0 <= min_range < max_range")
        for name in ("fov_up", "fov_down", "max_range", "min_range", "range_noise", "dropout", "sensor_height",
                     "rate_hz"):
            if not math.isfinite(getattr(self, name)):  # NaN would pass the comparisons below
                raise ValueError(f"{name} must be a finite number, got {getattr(self, name)}")
        if self.range_noise < 0 or not 0 <= self.dropout < 1 or self.rate_hz <= 0:
            raise ValueError("need range_noise >= 0, 0 <= dropout < 1 and rate_hz > 0")

    @property
    def elevations(self) -> np.ndarray:
        """Beam elevations in radians, ascending."""
        return np.deg2rad(np.linspace(self.fov_down, self.fov_up, self.beams))

    @property
    def azimuths(self) -> np.ndarray:
        """Azimuth of each firing in the sensor frame, radians in [0, 2 pi)."""
        return np.arange(self.azimuth_steps) * (2 * math.pi / self.azimuth_steps)


SMALL_LIDAR = {"beams": 32, "azimuth_steps": 512}


@dataclass
class BoxSet:
    """Oriented boxes (yaw only) at one instant: centre (B,3), half extents (B,3), yaw (B,).

    ``parts`` (optional, one entry per box): None for a plain box, or a ``(P, 6)`` array of
    axis-aligned parts in the box's frame (centre offset, half extents; see ``vehicles.py``);
    a ray then hits the box where it first hits one of its parts, and ``half`` must hold them all.
    """

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    parts: list | None = None

    def __len__(self) -> int:
        return int(self.center.shape[0])


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def _box_ray_window(cfg, el, az_world, origin, c, h, yaw):
    """Rows slice and column indices of rays that may hit the box, or None."""
    dx, dy = c[0] - origin[0], c[1] - origin[1]
    dist = math.hypot(dx, dy)
    radius = math.hypot(h[0], h[1])
    if dist - radius > cfg.max_range:
        return None
    if dist <= radius + 0.3:  # sensor next to/inside the footprint: no cheap bound, test all rays
        return slice(0, len(el)), np.arange(len(az_world))
    cy, sy = math.cos(yaw), math.sin(yaw)
    sx = np.array([1, 1, -1, -1]) * h[0]
    sy_ = np.array([1, -1, 1, -1]) * h[1]
    cx_ = c[0] + cy * sx - sy * sy_ - origin[0]
    cyy = c[1] + sy * sx + cy * sy_ - origin[1]
    centre_angle = math.atan2(dy, dx)
    rel = _wrap(np.arctan2(cyy, cx_) - centre_angle)
    az_step = 2 * math.pi / len(az_world)
    rel_cols = _wrap(az_world - centre_angle)
    cols = np.flatnonzero((rel_cols >= rel.min() - az_step) & (rel_cols <= rel.max() + az_step))
    if cols.size == 0:
        return None
    dmin, dmax = max(dist - radius, 0.05), dist + radius
    ztop, zbot = c[2] + h[2] - origin[2], c[2] - h[2] - origin[2]
    el_max = math.atan2(ztop, dmin if ztop > 0 else dmax)
    el_min = math.atan2(zbot, dmin if zbot < 0 else dmax)
    el_step = (el[-1] - el[0]) / max(len(el) - 1, 1)
    r0 = int(np.searchsorted(el, el_min - el_step, "left"))
    r1 = int(np.searchsorted(el, el_max + el_step, "right"))
    if r1 <= r0:
        return None
    return slice(r0, r1), cols


def _first_part_hit(lo: np.ndarray, inv: np.ndarray, parts: np.ndarray) -> np.ndarray:
    """Nearest entry distance of rays (origin ``lo``, inverse directions ``inv`` (..., 3), both in
    the box frame) into any of ``parts`` (P, 6); inf where a ray misses them all."""
    lo_p = lo[None, :] - parts[:, :3]  # ray origin relative to each part centre, (P, 3)
    shape = (parts.shape[0],) + (1,) * (inv.ndim - 1) + (3,)
    h = parts[:, 3:].reshape(shape)
    o = lo_p.reshape(shape)
    t1 = (-h - o) * inv[None]
    t2 = (h - o) * inv[None]
    tnear = np.minimum(t1, t2).max(axis=-1)
    tfar = np.maximum(t1, t2).min(axis=-1)
    tnear = np.where((tnear <= tfar) & (tnear > 0), tnear, np.inf)
    return tnear.min(axis=0)


def cast_scan(cfg: LidarConfig, origin: np.ndarray, sensor_yaw: float, boxes: BoxSet):
    """Cast one full scan from ``origin`` (3,) with the sensor heading ``sensor_yaw``.

    The sensor is assumed level (roll = pitch = 0); the ground is the plane z = 0.
    Returns ``(t, hit, dirs)``: ray length (beams, az) with ``inf`` for no hit, the
    hit target (-1 nothing, -2 ground, k >= 0 box k) and unit ray directions
    (beams, az, 3) in the world frame.
    """
    el = cfg.elevations
    az_world = _wrap(cfg.azimuths + sensor_yaw)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    dirs = np.empty((len(el), len(az_world), 3))
    dirs[..., 0] = ce * np.cos(az_world)[None, :]
    dirs[..., 1] = ce * np.sin(az_world)[None, :]
    dirs[..., 2] = se
    t = np.full(dirs.shape[:2], np.inf)
    hit = np.full(dirs.shape[:2], -1, dtype=np.int64)

    oz = float(origin[2])
    down = dirs[..., 2] < -1e-9
    if oz > 0:
        tg = np.where(down, -oz / np.where(down, dirs[..., 2], -1.0), np.inf)
        t = np.where(down, tg, t)
        hit[down] = -2

    for k in range(len(boxes)):
        c, h, yaw = boxes.center[k], boxes.half[k], float(boxes.yaw[k])
        win = _box_ray_window(cfg, el, az_world, origin, c, h, yaw)
        if win is None:
            continue
        rows, cols = win
        d = dirs[rows][:, cols]  # (nr, nc, 3)
        cyaw, syaw = math.cos(yaw), math.sin(yaw)
        o = origin - c
        lo = np.array([cyaw * o[0] + syaw * o[1], -syaw * o[0] + cyaw * o[1], o[2]])
        ld = np.stack(
            [cyaw * d[..., 0] + syaw * d[..., 1], -syaw * d[..., 0] + cyaw * d[..., 1], d[..., 2]], axis=-1
        )
        # slab test; tiny directions instead of zeros keep the arithmetic free of 0 * inf
        ld = np.where(np.abs(ld) < 1e-12, 1e-12, ld)
        inv = 1.0 / ld
        t1 = (-h - lo) * inv
        t2 = (h - lo) * inv
        tnear = np.minimum(t1, t2).max(axis=-1)
        tfar = np.maximum(t1, t2).min(axis=-1)
        hit_any = (tnear <= tfar) & (tnear > 0)
        parts = boxes.parts[k] if boxes.parts is not None else None
        if parts is not None and hit_any.any():  # only rays through the bounding box can hit a part
            tnear[hit_any] = _first_part_hit(lo, inv[hit_any], parts)
            hit_any &= np.isfinite(tnear)
        cur = t[rows, cols]
        better = hit_any & (tnear < cur)
        if not better.any():
            continue
        t[rows, cols] = np.where(better, tnear, cur)
        hc = hit[rows, cols]
        hc[better] = k
        hit[rows, cols] = hc
    return t, hit, dirs
