"""Outliers and a robust ground on synthetic scans (issue 29): returns far below the road
(multipath) or far above the sensor, slopes, a ramp, a curb, an empty road; every
implementation (numpy reference, compiled op, torch path on CPU tensors) gives the same classes."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from floxels_ext.lidar.preprocess import ground_outliers as go
from floxels_ext.lidar.preprocess import (CROPPED, GROUND, KEPT, OUTLIER, Preprocess, preprocess_classes,
                                          preprocess_classes_numpy, preprocess_mask, preprocess_mask_numpy)
from floxels_ext.lidar.preprocess.masks_torch import preprocess_classes_torch

SENSOR_H = 1.73  # m above the road, as KITTI's Velodyne


def _scan(seed=0, terrain=lambda x, y: 0.0 * x, cars=True, wall=True, beams=40):
    """(points in the sensor frame, is_ground): rings on the terrain z = terrain(x, y) (road
    level 0 under the sensor), two parked cars, a wall, all seen from SENSOR_H above the road."""
    rng = np.random.default_rng(seed)
    az = np.radians(np.arange(0, 360, 0.35))
    pts, ground = [], []
    for r in np.geomspace(3.2, 48.0, beams):
        x, y = r * np.cos(az), r * np.sin(az)
        z = terrain(x, y) + rng.normal(0, 0.02, len(x))
        pts.append(np.c_[x, y, z])
        ground.append(np.ones(len(x), bool))
    objs = []
    if cars:
        for cx, cy in ((12.0, 4.0), (-15.0, -5.0)):
            u = rng.uniform(-1, 1, (1500, 3)) * [2.2, 0.9, 0.7] + [cx, cy, 0.25 + 0.7]
            objs.append(u)
    if wall:
        u = np.c_[rng.uniform(-25, 25, 4000), np.full(4000, 18.0), rng.uniform(0.0, 6.0, 4000)]
        objs.append(u)
    for u in objs:
        u = u.copy()
        u[:, 2] += terrain(u[:, 0], u[:, 1])
        pts.append(u)
        ground.append(np.zeros(len(u), bool))
    p = np.concatenate(pts)
    p[:, 2] -= SENSOR_H
    return p.astype(np.float32), np.concatenate(ground)


def _multipath(n, seed=1, depth=(2.0, 18.0)):
    """n returns far below the road, in clumps (mirror images of objects land together), over
    the road (where no ground is seen, only the cone of ground_outliers.py bounds them)."""
    rng = np.random.default_rng(seed)
    k = max(1, n // 25)
    rc, ac = rng.uniform(5, 40, k), rng.uniform(0, 2 * np.pi, k)
    centres = np.c_[rc * np.cos(ac), rc * np.sin(ac)]
    c = centres[rng.integers(0, len(centres), n)] + rng.normal(0, 1.5, (n, 2))
    z = -SENSOR_H - rng.uniform(*depth, n)
    return np.c_[c, z].astype(np.float32)


def _all_paths(p, st):
    a = preprocess_classes_numpy(p, st)
    np.testing.assert_array_equal(preprocess_classes(p, st), a)
    np.testing.assert_array_equal(preprocess_classes_torch(p, st, "cpu"), a)
    np.testing.assert_array_equal(preprocess_mask(p, st), a == KEPT)
    np.testing.assert_array_equal(preprocess_mask_numpy(p, st), a == KEPT)
    return a


def _quality(cls, ground, n, points):
    """(ground recall, share of the object points below max_height kept) over the first n
    points (the scan), within the range crop."""
    c, g, p = cls[:n], ground[:n], points[:n]
    r = np.hypot(p[:, 0], p[:, 1])
    inr = (r >= 3) & (r <= 50)
    rec = ((c == GROUND) & g & inr).sum() / (g & inr).sum()
    low = inr & ~g & (c != CROPPED)  # the wall's top is cropped (max_height)
    kept = ((c == KEPT) & low).sum() / max(low.sum(), 1)
    return rec, kept


@pytest.mark.parametrize("n_out", [0, 100, 400])
def test_outliers_below_cannot_pull_the_ground_down(n_out):
    p, g = _scan()
    q = np.concatenate([p, _multipath(n_out)])
    cls = _all_paths(q, Preprocess())
    rec, kept = _quality(cls, g, len(p), q)
    assert rec >= 0.99 and kept >= 0.9, (rec, kept)
    if n_out:
        r = np.hypot(q[len(p):, 0], q[len(p):, 1])
        assert (cls[len(p):][(r >= 3) & (r <= 50)] == OUTLIER).mean() >= 0.99
    assert (cls[:len(p)] != OUTLIER).mean() > 0.999


def test_without_the_outlier_test_the_ground_sinks():
    """The failure the outlier test fixes (issue 29): 400 multipath returns, no outlier test."""
    p, g = _scan()
    q = np.concatenate([p, _multipath(400)])
    rec, _ = _quality(preprocess_classes(q, Preprocess(outlier_below=None)), g, len(p), q)
    assert rec < 0.9


def test_outliers_above_the_sensor_are_counted_not_ground():
    p, g = _scan()
    rng = np.random.default_rng(5)
    sky = np.c_[rng.uniform(-30, 30, (300, 2)), rng.uniform(25, 40, 300)].astype(np.float32)
    q = np.concatenate([p, sky])
    cls = _all_paths(q, Preprocess())
    r = np.hypot(sky[:, 0], sky[:, 1])
    inr = (r >= 3) & (r <= 50)
    assert (cls[len(p):][inr] == OUTLIER).all()
    rec, kept = _quality(cls, g, len(p), q)
    assert rec >= 0.99 and kept >= 0.9
    assert (_all_paths(q, Preprocess(outlier_above=None))[len(p):][inr] == CROPPED).all()  # the height crop


@pytest.mark.parametrize("grade", [0.05, 0.12])
def test_slopes_with_outliers(grade):
    p, g = _scan(terrain=lambda x, y: grade * x)
    q = np.concatenate([p, _multipath(150, depth=(3.0, 15.0))])
    rec, kept = _quality(_all_paths(q, Preprocess()), g, len(p), q)
    assert rec >= 0.97 and kept >= 0.85, (rec, kept)


def test_ramp_and_curb():
    """Flat road, a 3 % ramp starting 10 m ahead (1.1 m up at 48 m), a 0.15 m curb on the left.
    (The plane cap bounds the surface at the scene's trimmed plane + 0.5 m: a 6 % ramp from
    10 m loses ~7 % of its ground, the far end of the ramp; docs/user-guide.md, "Preprocessing".)"""
    def terrain(x, y):
        return np.where(x > 10, 0.03 * (x - 10), 0.0) + np.where(y > 6, 0.15, 0.0)

    p, g = _scan(terrain=terrain)
    q = np.concatenate([p, _multipath(100)])
    rec, kept = _quality(_all_paths(q, Preprocess()), g, len(p), q)
    assert rec >= 0.97 and kept >= 0.85, (rec, kept)


def test_empty_road():
    """Nothing but the road (and a few outliers): everything in range is ground or outlier."""
    p, _ = _scan(cars=False, wall=False)
    q = np.concatenate([p, _multipath(50)])
    cls = _all_paths(q, Preprocess())
    inr = cls[:len(p)] != CROPPED
    assert (cls[:len(p)][inr] == GROUND).mean() > 0.999
    r = np.hypot(q[len(p):, 0], q[len(p):, 1])
    assert (cls[len(p):][(r >= 3) & (r <= 50)] == OUTLIER).all()


@pytest.mark.parametrize("st", [Preprocess(max_range=None), Preprocess(remove_ground=False),
                                Preprocess(max_height=None, ground_max_rise=None),
                                Preprocess(outlier_below=0.5, outlier_above=None), Preprocess(ground_window=3.0),
                                Preprocess(remove_ground=False, max_height=None)])
def test_every_path_gives_the_same_classes(st):
    p, _ = _scan(seed=3, terrain=lambda x, y: 0.04 * y)
    q = np.concatenate([p, _multipath(200, seed=4), [[np.nan, 0, 0], [1e30, 2, 0], [900, -40, -3]]]).astype(np.float32)
    _all_paths(q, st)
    _all_paths(q.astype(np.float64), st)


def test_settings_are_checked():
    with pytest.raises(ValueError, match="outlier_below"):
        Preprocess(outlier_below=-1.0)
    with pytest.raises(ValueError, match="outlier_above"):
        Preprocess(outlier_above=float("nan"))


def test_the_op_uses_the_reference_constants():
    """csrc/cpu/lidar_ground.h repeats ground_outliers.py's constants (C++ cannot import them)."""
    text = (Path(__file__).resolve().parents[2] / "csrc" / "cpu" / "lidar_ground.h").read_text()
    for name, value in (("kRefRadiusBlocks", go.REF_RADIUS_BLOCKS), ("kRefMaxSlope", go.REF_MAX_SLOPE),
                        ("kRefConeMargin", go.REF_CONE_MARGIN), ("kNearGroundM", go.NEAR_GROUND_M)):
        m = re.search(rf"{name} = ([0-9.]+);", text)
        assert m and float(m.group(1)) == value, name
