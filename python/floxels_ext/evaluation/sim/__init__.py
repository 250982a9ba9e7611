"""Synthetic lidar sequences with exact ground-truth scene flow.

``simulate_sequence("urban", num_frames=13, seed=0)`` builds a randomised scene (see
``scenes.py``), moves the ego vehicle and the actors along closed-form trajectories and
ray-casts one scan per frame (``lidar.py``). Every frame carries, per point:

* ``points``: position in ONE world frame (scans are ego-motion compensated, so static
  structure has exactly zero flow);
* ``flow``: exact rigid motion of the point to the next frame, ``T(t+1) T(t)^-1 p - p`` with
  T the pose of the box the ray hit (the actors are simulated one step beyond the last
  frame, so the last frame has flow too);
* ``classes`` (0 background, 1 car, 2 other vehicle, 3 pedestrian, 4 wheeled VRU),
  ``instance`` (-1 for background), ``dynamic`` (|flow| > 0.05 m), ``ground``;
* ``pose``: the 4x4 sensor-to-world pose.

Vehicles are not featureless boxes (``vehicle_detail=True``, the default): cars (sedan,
hatchback, pickup), vans, buses and trucks are unions of vehicle-aligned parts with wheels,
wheel arches, mirrors, recessed windows between pillars, hood/trunk and bed steps and
trailer gaps (``vehicles.py``), because flat box sides sliding along themselves leave the DT
loss without a gradient along the motion. ``vehicle_detail=False`` gives the plain boxes of
earlier versions, and with them the earlier default range noise (0.015 m), so it reproduces
earlier output exactly. Range noise (default 0.02 m, gaussian along the ray) and random
dropout (default 5 % of returns) model a real sensor; the flow is the exact rigid motion of
the measured (noisy) point, so it stays exact.

Deterministic for a given seed and options. ``small=True`` (or ``**SMALL_LIDAR``) gives a
32 x 512 scan for fast tests.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from floxels_ext.evaluation.seqio import Frame, Sequence, load_sequence, read_frame, write_frame
from floxels_ext.evaluation.sim.lidar import SMALL_LIDAR, BoxSet, LidarConfig, cast_scan
from floxels_ext.evaluation.sim.scene import Actor, Scene, Track
from floxels_ext.evaluation.sim.scenes import SCENES, build_scene
from floxels_ext.evaluation.sim.vehicles import parts_extent, vehicle_parts

__all__ = [
    "simulate_sequence",
    "simulate_frame",
    "Frame",
    "Sequence",
    "LidarConfig",
    "SMALL_LIDAR",
    "Scene",
    "Actor",
    "Track",
    "SCENES",
    "build_scene",
    "load_sequence",
    "read_frame",
    "write_frame",
    "DYNAMIC_THRESHOLD",
    "LEGACY_RANGE_NOISE",
    "actor_parts",
]

DYNAMIC_THRESHOLD = 0.05  # metres per frame
LEGACY_RANGE_NOISE = 0.015  # the default range noise of the box-only simulator (vehicle_detail=False)
_LIDAR_FIELDS = {f.name for f in dataclasses.fields(LidarConfig)}


def actor_parts(actors: list[Actor]) -> list[np.ndarray | None]:
    """Per actor: its vehicle parts (``vehicles.vehicle_parts``) or None for a plain box."""
    return [vehicle_parts(a) for a in actors]


def _boxes_at(actors: list[Actor], t: float, parts: list | None = None) -> tuple[BoxSet, np.ndarray]:
    """Box set at time t and the (B, 4, 4) actor poses (box centre at the box's mid-height).

    With ``parts`` (from ``actor_parts``) a vehicle's box grows to hold all its parts (mirrors)."""
    mats = np.stack([a.track.matrix(t, a.z + a.size[2] / 2) for a in actors]) if actors else np.zeros((0, 4, 4))
    half = np.array([a.size for a in actors], dtype=np.float64).reshape(-1, 3) / 2
    if parts is not None:
        for k, pk in enumerate(parts):
            if pk is not None:
                half[k] = np.maximum(half[k], parts_extent(pk))
    yaw = np.arctan2(mats[:, 1, 0], mats[:, 0, 0])
    return BoxSet(mats[:, :3, 3].copy(), half, yaw, parts), mats


def simulate_frame(scene: Scene, cfg: LidarConfig, t: float, dt: float, rng: np.random.Generator,
                   parts: list | None = None) -> Frame:
    """One scan at time t (seconds) with flow to time t + dt. ``parts``: per-actor vehicle parts
    (``actor_parts(scene.actors)``) or None for plain boxes."""
    actors = scene.actors
    boxes, m_now = _boxes_at(actors, t, parts)
    _, m_next = _boxes_at(actors, t + dt)
    ego = scene.ego.matrix(t)
    pose = ego.copy()
    pose[2, 3] += cfg.sensor_height
    origin = pose[:3, 3]
    yaw = math.atan2(pose[1, 0], pose[0, 0])

    tr, hit, dirs = cast_scan(cfg, origin, yaw, boxes)
    tr, hit, dirs = tr.reshape(-1), hit.reshape(-1), dirs.reshape(-1, 3)
    keep = (hit != -1) & (tr >= cfg.min_range) & (tr <= cfg.max_range)
    if cfg.dropout > 0:
        keep &= rng.random(tr.shape[0]) >= cfg.dropout
    tr, hit, dirs = tr[keep], hit[keep], dirs[keep]
    if cfg.range_noise > 0:
        tr = tr + rng.normal(0.0, cfg.range_noise, tr.shape[0])
    pts = origin[None, :] + tr[:, None] * dirs

    n = pts.shape[0]
    flow = np.zeros((n, 3))
    classes = np.zeros(n, dtype=np.int32)
    instance = np.full(n, -1, dtype=np.int32)
    for k in np.unique(hit[hit >= 0]):
        a = actors[k]
        sel = hit == k
        classes[sel] = a.cls
        instance[sel] = a.instance
        if a.track.moving:
            rel = m_next[k] @ np.linalg.inv(m_now[k])  # rigid motion of the box over one frame
            p = pts[sel]
            flow[sel] = p @ rel[:3, :3].T + rel[:3, 3] - p
    flow = flow.astype(np.float32)
    return Frame(
        points=pts.astype(np.float32),
        flow=flow,
        classes=classes,
        instance=instance,
        dynamic=np.linalg.norm(flow, axis=1) > DYNAMIC_THRESHOLD,
        ground=hit == -2,
        pose=pose,
    )


def simulate_sequence(scene: str | Scene = "urban", num_frames: int = 13, seed: int = 0, *,
                      small: bool = False, vehicle_detail: bool = True, **options) -> Sequence:
    """Simulate ``num_frames`` consecutive scans of a scene.

    ``scene`` is a name from ``SCENES`` (urban, highway, crossing, parking) or a ``Scene``.
    ``options`` are ``LidarConfig`` fields (beams, azimuth_steps, fov_up, fov_down, max_range,
    min_range, range_noise, dropout, sensor_height, rate_hz); ``small=True`` starts from
    ``SMALL_LIDAR`` (32 beams x 512 azimuth steps). ``vehicle_detail=False`` simulates vehicles
    as plain boxes with the old default range noise (``LEGACY_RANGE_NOISE``) unless
    ``range_noise`` is given: the output of the box-only simulator, bit for bit.
    """
    if num_frames < 1:
        raise ValueError("num_frames must be >= 1")
    unknown = set(options) - _LIDAR_FIELDS
    if unknown:
        raise TypeError(f"unknown simulate_sequence option(s) {sorted(unknown)}; "
                        f"lidar options: {sorted(_LIDAR_FIELDS)}")
    if not vehicle_detail:
        options.setdefault("range_noise", LEGACY_RANGE_NOISE)
    cfg = LidarConfig(**{**(SMALL_LIDAR if small else {}), **options})
    seed = int(seed)
    dt = 1.0 / cfg.rate_hz
    if isinstance(scene, str):
        # keep actors collision-free a little beyond the last flow target
        horizon = (num_frames + 1) * dt
        scene_obj = build_scene(scene, np.random.default_rng([seed, 0]), horizon)
    else:
        scene_obj = scene
    parts = actor_parts(scene_obj.actors) if vehicle_detail else None
    frames = [
        simulate_frame(scene_obj, cfg, i * dt, dt, np.random.default_rng([seed, 1, i]), parts)
        for i in range(num_frames)
    ]
    meta = {
        "scene": scene_obj.name,
        "seed": seed,
        "num_frames": num_frames,
        "dt": dt,
        "lidar": dataclasses.asdict(cfg),
        "vehicle_detail": bool(vehicle_detail),
        "generator": "floxels_ext.evaluation.sim",
    }
    return Sequence(frames=frames, meta=meta)
