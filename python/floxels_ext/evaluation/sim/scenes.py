"""Procedural scene layouts: urban street, highway, intersection, parking lot.

World frame: x along the main road, y to the left, z up, ground plane z = 0, right-hand
traffic. Layouts are randomised by ``rng`` (sizes, gaps, speeds, counts) but always keep
vehicles in lanes with enough spacing that nothing collides during a short sequence.
"""

from __future__ import annotations

import math

import numpy as np

from floxels_ext.evaluation.sim.scene import BACKGROUND, CAR, OTHER_VEHICLE, PEDESTRIAN, WHEELED_VRU, Scene, Track

__all__ = ["SCENES", "build_scene"]

PI = math.pi


def _car(rng):
    return (rng.uniform(4.2, 4.9), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.7))


def _van(rng):
    return (rng.uniform(5.0, 5.8), rng.uniform(2.0, 2.2), rng.uniform(2.0, 2.5))


def _bus(rng):
    return (rng.uniform(10.0, 12.5), 2.55, rng.uniform(3.0, 3.4))


def _truck(rng):
    return (rng.uniform(12.0, 16.5), 2.5, rng.uniform(3.5, 4.0))


def _ped(rng):
    return (rng.uniform(0.5, 0.7), rng.uniform(0.5, 0.7), rng.uniform(1.6, 1.9))


def _cyclist(rng):
    return (rng.uniform(1.7, 1.9), 0.6, rng.uniform(1.6, 1.8))


def _pole(rng):
    s = rng.uniform(0.2, 0.35)
    return (s, s, rng.uniform(4.0, 8.0))


def _building_row(scene, rng, y_face, side, x0, x1, depth=(8, 15), height=(6, 25), gap=(0.5, 6)):
    """Buildings with their street face at |y| = y_face on ``side`` (+1 left, -1 right)."""
    x = x0
    while x < x1:
        length = rng.uniform(10, 30)
        d = rng.uniform(*depth)
        scene.add((length, d, rng.uniform(*height)), BACKGROUND, x + length / 2, side * (y_face + d / 2))
        x += length + rng.uniform(*gap)


def _parked_row(scene, rng, y, x0, x1, yaw, spacing, occupancy=0.6, van_prob=0.15):
    for x in np.arange(x0, x1, spacing):
        if rng.random() < occupancy:
            is_van = rng.random() < van_prob
            size = _van(rng) if is_van else _car(rng)
            jitter_yaw = yaw + rng.normal(0, 0.03)
            cls = OTHER_VEHICLE if is_van else CAR
            scene.add(size, cls, x + rng.normal(0, 0.2), y + rng.normal(0, 0.1), jitter_yaw)


def _lane_traffic(scene, rng, y, heading, xs, speed, size_fn=_car, cls=CAR):
    for x in xs:
        scene.add(size_fn(rng), cls, x, y, heading, speed + rng.uniform(-1.0, 1.0))


def urban(rng, horizon) -> Scene:
    ego_speed = rng.uniform(6, 10)
    s = Scene("urban", horizon=horizon, ego=Track(0.0, -1.75, 0.0, ego_speed))
    for side in (-1, 1):
        _building_row(s, rng, 11.0, side, -90, 130)
        for x in np.arange(-60, 100, rng.uniform(12, 20)):  # street lights / signs on the sidewalk
            s.add(_pole(rng), BACKGROUND, x + rng.uniform(-1, 1), side * 6.9)
    # traffic in the ego lane (same speed range, spaced so nobody catches up) and oncoming
    ahead = np.cumsum(rng.uniform(14, 24, size=2)) + 6
    _lane_traffic(s, rng, -1.75, 0.0, [*ahead, -rng.uniform(14, 20)], ego_speed)
    xs = np.cumsum(rng.uniform(16, 30, size=5)) - 40
    bus_at = rng.integers(len(xs))
    for i, x in enumerate(xs):
        big = i == bus_at
        s.add(_bus(rng) if big else _car(rng), OTHER_VEHICLE if big else CAR, x, 1.75, PI,
              rng.uniform(7, 9) if big else rng.uniform(8, 14))
    # a car pulling gently out of a parking spot on the left (turning)
    s.add(_car(rng), CAR, rng.uniform(25, 40), 4.2, PI + 0.25, rng.uniform(2, 3.5), -0.2)
    # pedestrians on both sidewalks, some standing
    for _ in range(rng.integers(5, 9)):
        side = rng.choice([-1, 1])
        speed = 0.0 if rng.random() < 0.25 else rng.uniform(1.0, 1.7)
        s.add(_ped(rng), PEDESTRIAN, rng.uniform(-25, 45), side * rng.uniform(7.5, 10.0),
              rng.choice([0.0, PI]) + rng.normal(0, 0.05), speed)
    # a cyclist between the ego lane and the parked cars
    s.add(_cyclist(rng), WHEELED_VRU, rng.uniform(8, 25), -3.4, 0.0, rng.uniform(4, 6))
    for side in (-1, 1):  # parked cars last: a slot whose car would hit a mover stays empty
        _parked_row(s, rng, side * 5.0, -60, 100, 0.0 if side < 0 else PI, 6.5)
    return s


def highway(rng, horizon) -> Scene:
    ego_speed = rng.uniform(22, 27)
    s = Scene("highway", horizon=horizon, ego=Track(0.0, -5.5, 0.0, ego_speed))
    s.add((320, 0.6, 0.9), BACKGROUND, 60, 0.0)  # median barrier
    for side in (-1, 1):
        s.add((320, 0.5, 1.0), BACKGROUND, 60, side * 11.5)
        for x in np.arange(-90, 220, 40):
            s.add(_pole(rng), BACKGROUND, x, side * 12.5)
    lanes_fwd = {-2.0: ego_speed + 3, -5.5: ego_speed, -9.0: ego_speed - 4}
    for y, v in lanes_fwd.items():
        xs = np.cumsum(rng.uniform(25, 45, size=4)) - 70
        for x in xs:
            if y == -5.5 and abs(x) < 25:
                continue  # keep the ego's own lane clear around the ego
            truck = y == -9.0 and rng.random() < 0.5
            s.add(_truck(rng) if truck else _car(rng), OTHER_VEHICLE if truck else CAR, x, y, 0.0,
                  v + rng.uniform(-1, 1))
    for y in (2.0, 5.5, 9.0):
        xs = np.cumsum(rng.uniform(25, 50, size=4)) - 40
        for x in xs:
            truck = y == 9.0 and rng.random() < 0.5
            s.add(_truck(rng) if truck else _car(rng), OTHER_VEHICLE if truck else CAR, x, y, PI,
                  rng.uniform(20, 24) if truck else rng.uniform(24, 32))
    return s


def crossing(rng, horizon) -> Scene:
    ego_speed = rng.choice([0.0, rng.uniform(2, 5)])  # waiting at or creeping up to the stop line
    s = Scene("crossing", horizon=horizon, ego=Track(-22.0, -1.75, 0.0, ego_speed))
    for qx in (-1, 1):
        for qy in (-1, 1):  # one building block per corner
            w, d = rng.uniform(20, 40), rng.uniform(20, 40)
            s.add((w, d, rng.uniform(8, 25)), BACKGROUND, qx * (12 + w / 2), qy * (12 + d / 2))
            s.add(_pole(rng), BACKGROUND, qx * 8.0, qy * 8.0)  # traffic lights
    # turning cars inside the intersection (constant yaw rate arcs)
    s.add(_car(rng), CAR, 6.0, 1.75, PI, rng.uniform(4, 6), rng.uniform(0.45, 0.6))  # left turn
    s.add(_car(rng), CAR, -9.0, -1.75, 0.0, rng.uniform(3, 5), -rng.uniform(0.5, 0.7))  # right turn
    s.add(_car(rng), CAR, 1.75, -14.0, PI / 2, rng.uniform(4, 6), rng.uniform(0.3, 0.5))  # left turn from south
    # straight cross traffic on the y road, away from the turning cars
    s.add(_car(rng), CAR, 1.75, -45.0, PI / 2, rng.uniform(9, 12))
    s.add(_car(rng), CAR, -1.75, rng.uniform(22, 30), -PI / 2, rng.uniform(8, 11))
    s.add(_bus(rng), OTHER_VEHICLE, rng.uniform(35, 45), 1.75, PI, rng.uniform(6, 8))
    # pedestrians on the crosswalks (x = +-9 walking along y, y = +-9 walking along x)
    for _ in range(rng.integers(4, 8)):
        speed = 0.0 if rng.random() < 0.3 else rng.uniform(1.1, 1.6)
        if rng.random() < 0.5:
            s.add(_ped(rng), PEDESTRIAN, rng.choice([-9.5, 9.5]) + rng.normal(0, 0.5), rng.uniform(-7, 7),
                  rng.choice([PI / 2, -PI / 2]), speed)
        else:
            s.add(_ped(rng), PEDESTRIAN, rng.uniform(-7, 7), rng.choice([-9.5, 9.5]) + rng.normal(0, 0.5),
                  rng.choice([0.0, PI]), speed)
    s.add(_cyclist(rng), WHEELED_VRU, 4.5, rng.uniform(-30, -20), PI / 2, rng.uniform(4, 6))
    _parked_row(s, rng, 5.0, 16, 60, PI, 6.5)
    _parked_row(s, rng, -5.0, 16, 60, 0.0, 6.5)
    return s


def parking(rng, horizon) -> Scene:
    s = Scene("parking", horizon=horizon, ego=Track(-20.0, -1.5, 0.0, rng.uniform(2, 4)))
    for side in (-1, 1):
        s.add((120, 10, rng.uniform(6, 12)), BACKGROUND, 0, side * 31)  # shop fronts
        for x in np.arange(-40, 45, 20):
            s.add(_pole(rng), BACKGROUND, x, side * 7.9)  # lamps between the back-to-back rows
    # slow movers: an oncoming car, one turning in the far aisle, a reversing car
    s.add(_car(rng), CAR, rng.uniform(10, 20), 1.6, PI, rng.uniform(2, 3.5))
    s.add(_car(rng), CAR, rng.uniform(-10, 10), 15.8, 0.0, rng.uniform(2, 3), rng.uniform(0.1, 0.25))
    s.add(_car(rng), CAR, rng.uniform(-5, 5), -17.0, PI / 2 + 0.3, -rng.uniform(0.8, 1.5), 0.2)
    for _ in range(rng.integers(4, 8)):  # shoppers in the far aisles, some standing
        speed = 0.0 if rng.random() < 0.3 else rng.uniform(0.8, 1.5)
        s.add(_ped(rng), PEDESTRIAN, rng.uniform(-25, 25), rng.choice([-1, 1]) * rng.uniform(13, 18),
              rng.uniform(-PI, PI), speed)
    for _ in range(rng.integers(2, 5)):  # and some crossing the ego's aisle ahead of it
        s.add(_ped(rng), PEDESTRIAN, rng.uniform(-8, 25), rng.uniform(-2.5, 2.5),
              rng.choice([PI / 2, -PI / 2]) + rng.normal(0, 0.2), rng.uniform(0.8, 1.5))
    s.add(_cyclist(rng), WHEELED_VRU, rng.uniform(27, 35), 1.6, PI, rng.uniform(3.5, 4.5))
    for side in (-1, 1):
        for y in (5.5, 10.3, 21.3):  # rows of perpendicular parking (back-to-back at 5.5 / 10.3)
            _parked_row(s, rng, side * y, -45, 45, side * PI / 2, 2.7, occupancy=0.75)
    return s


SCENES = {"urban": urban, "highway": highway, "crossing": crossing, "parking": parking}


def build_scene(name: str, rng: np.random.Generator, horizon: float = 2.0) -> Scene:
    """Random layout of scene ``name``; actors are collision-free for ``horizon`` seconds."""
    try:
        fn = SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; choose from {sorted(SCENES)}") from None
    return fn(rng, horizon)
