"""``poses=`` (issue 47): the API takes each scan's (4, 4) world-from-sensor pose, as users have
it, and derives the sensor positions the ``accurate`` preset's sights read (their translations):
the same flow as with ``sensor_origins=``, through ``estimate_flow``, ``estimate_sequence`` and
``Floxels.fit``; a pose that is not a rigid motion, a wrong count or shape, a non-finite matrix
and poses that contradict ``sensor_origins=`` are refused with errors naming them."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from floxels_ext.estimator import Floxels, FloxelsConfig, estimate_flow, estimate_sequence
from floxels_ext.estimator.poses import check_poses, resolve_sensors

CFG = FloxelsConfig.preset("accurate", max_iters=30, num_scans=5)


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def scene(n=5, seed=0):
    """A wall and a box moving 0.8 m/frame, seen from a sensor driving 1 m/frame and turning a
    little; scans in the world frame, each cropped to 20 m around its sensor; the poses."""
    g = np.random.default_rng(seed)
    scans, poses = [], []
    for i in range(n):
        T = np.eye(4)
        T[:3, :3] = _yaw(0.02 * i)
        T[:3, 3] = [1.0 * i, 0.0, 1.7]
        x = g.uniform(-30, 30, 3000)
        wall = np.stack([x, np.full_like(x, 5.0), g.uniform(0, 2, 3000)], 1)
        box = g.uniform(-1, 1, (600, 3)) * [2.0, 0.9, 0.7] + [4 + 0.8 * i, -2.0, 0.7]
        pts = np.concatenate([wall, box])
        keep = np.hypot(pts[:, 0] - T[0, 3], pts[:, 1] - T[1, 3]) < 20
        scans.append(pts[keep].astype(np.float32))
        poses.append(T)
    return scans, np.stack(poses)


@pytest.fixture(scope="module")
def data():
    return scene()


def test_poses_give_the_flow_of_their_translations(data):
    scans, poses = data
    by_origin = estimate_flow(scans, 2, CFG, sensor_origins=poses[:, :3, 3])
    by_pose = estimate_flow(scans, 2, CFG, poses=poses)
    assert np.array_equal(by_origin, by_pose)
    fit = Floxels(CFG).fit(scans, 2, poses=torch.as_tensor(poses)).flow
    assert np.array_equal(by_origin, fit)
    seq = estimate_sequence(scans, CFG, frames=[0, 2], poses=list(poses))
    seq_o = estimate_sequence(scans, CFG, frames=[0, 2], sensor_origins=poses[:, :3, 3])
    assert all(np.array_equal(a, b) for a, b in zip(seq, seq_o))


def test_poses_and_agreeing_origins_are_accepted(data):
    scans, poses = data
    a = estimate_flow(scans, 2, CFG, poses=poses, sensor_origins=poses[:, :3, 3] + 1e-5)
    assert np.array_equal(a, estimate_flow(scans, 2, CFG, poses=poses))


def test_no_pose_no_warning_but_none_warns(data):
    scans, poses = data
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        estimate_flow(scans, 2, CFG.replace(max_iters=2), poses=poses)
    with pytest.warns(UserWarning, match="poses="):
        estimate_flow(scans, 2, CFG.replace(max_iters=2))


def test_unknown_poses_are_unknown_sensors(data):
    scans, poses = data
    mixed = [None, poses[1], None, poses[3], poses[4]]
    assert [s is None for s in resolve_sensors(None, mixed, 5)] == [True, False, True, False, False]
    a = estimate_flow(scans, 2, CFG, poses=mixed)
    b = estimate_flow(scans, 2, CFG, sensor_origins=[None if p is None else p[:3, 3] for p in mixed])
    assert np.array_equal(a, b)


def _bad(poses, k, fn):
    out = poses.copy()
    out[k] = fn(out[k].copy())
    return out


def _set(m, idx, v):
    m[idx] = v
    return m


@pytest.mark.parametrize("make, err, match", [
    (lambda p: p[:4], ValueError, "one \\(4, 4\\) matrix per scan: got 4 for 5 scans"),
    (lambda p: p[:, :3, :], ValueError, r"shape \(n, 4, 4\).*\(5, 3, 4\)"),
    (lambda p: p[0], ValueError, r"shape \(n, 4, 4\)"),
    (lambda p: [q for q in p[:4]] + [np.eye(3)], ValueError, r"poses\[4\] must be a \(4, 4\)"),
    (lambda p: _bad(p, 3, lambda m: _set(m, (0, 3), np.nan)), ValueError, r"poses\[3\] is not finite"),
    (lambda p: _bad(p, 1, lambda m: _set(m, (slice(0, 3), slice(0, 3)), 2 * m[:3, :3])), ValueError,
     r"poses\[1\] is not a rigid motion.*not orthonormal"),
    (lambda p: _bad(p, 2, lambda m: _set(m, (2, 2), -1.0)), ValueError, r"poses\[2\] is not a rigid motion.*reflection"),
    (lambda p: _bad(p, 0, lambda m: _set(m, (3, 0), 0.5)), ValueError, r"poses\[0\] is not a rigid motion.*last row"),
    (lambda p: [q for q in p[:4]] + ["pose"], (TypeError, ValueError), r"poses\[4\]"),
    (lambda p: 3.0, TypeError, "one \\(4, 4\\) world-from-sensor matrix per scan"),
])
def test_bad_poses_are_refused(data, make, err, match):
    scans, poses = data
    with pytest.raises(err, match=match):
        estimate_flow(scans, 2, CFG.replace(max_iters=2), poses=make(poses))


def test_contradicting_poses_and_origins_are_refused_before_any_work(data):
    scans, poses = data
    origins = poses[:, :3, 3].copy()
    origins[3, 0] += 0.5
    for call in (lambda: estimate_flow(scans, 2, CFG, poses=poses, sensor_origins=origins),
                 lambda: estimate_sequence(scans, CFG, poses=poses, sensor_origins=origins),
                 lambda: Floxels(CFG).fit(scans, 2, poses=poses, sensor_origins=origins)):
        with pytest.raises(ValueError, match="poses and sensor_origins contradict each other at scan 3"):
            call()
    one_none = [None] + list(origins[1:])
    with pytest.raises(ValueError, match="at scan 0: one of them is None"):
        resolve_sensors(one_none, poses, 5)


def test_sensor_from_world_is_still_rigid_but_the_readme_says_which(data):
    # the inverse of a pose is a rigid motion too: accepted (the checks cannot tell), documented
    _, poses = data
    inv = np.stack([np.linalg.inv(p) for p in poses])
    assert len(check_poses(inv, 5)) == 5
