"""Each scan's removed ground returns in ``visibility``'s range images (``ground_points=``,
estimator/sight.py): a direction where a support scan saw only the road shows a place empty,
so the evidence test may count that scan there. Also the argument's checks, that it changes
nothing without ``visibility``, and the same result through ``estimate_sequence``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from floxels_ext.estimator import FloxelsConfig, estimate_flow, estimate_sequence
from floxels_ext.estimator.sight import observed_bits, scan_sight

CUDA = pytest.param("cuda", marks=pytest.mark.cuda)


def _road(x0=2.0, x1=30.0, step=0.25):
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(-3.0, 3.0, step), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1).astype(np.float32)


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_ground_returns_show_a_place_empty(device):
    sensor = np.array([0.0, 0.0, 1.8])
    wall = np.stack(np.meshgrid([-10.0], np.arange(-5, 5, 0.2), np.arange(0.0, 3.0, 0.2), indexing="ij"), -1)
    scan = torch.from_numpy(wall.reshape(-1, 3).astype(np.float32)).to(device)  # only behind the sensor
    place = torch.tensor([[8.0, 0.0, 0.5]], device=device)  # in front, above the road: nothing but road seen
    plain = scan_sight(scan, sensor, band=False, image=True)
    road = torch.from_numpy(_road()).to(device)
    seen = scan_sight(scan, sensor, band=False, image=True, ground=road)
    assert int(observed_bits(place, [plain])[0]) == 0  # no return in that direction: says nothing
    assert int(observed_bits(place, [seen])[0]) == 1   # the road beyond it was hit: the place is empty
    # non-finite rows of the ground are skipped, not an error, and change nothing else
    bad = torch.cat([road, torch.tensor([[float("nan"), 0.0, 0.0], [float("inf"), 1.0, 0.0]], device=device)])
    assert torch.equal(scan_sight(scan, sensor, band=False, image=True, ground=bad).image, seen.image)
    # a host array for a device scan is moved there
    host = scan_sight(scan, sensor, band=False, image=True, ground=road.cpu())
    assert torch.equal(host.image, seen.image)


def _scene():
    """A pedestrian crossing 8 m in front of a sensor that stands still, on a road that
    preprocessing removed: nothing else is in view."""
    g = np.random.default_rng(3)
    body = g.uniform(-1, 1, (400, 3)) * [0.25, 0.25, 0.85] + [0.0, 0.0, 0.85]
    scans = [(body + [8.0, 0.3 * t, 0.0]).astype(np.float32) for t in range(-2, 3)]
    sensors = np.tile([0.0, 0.0, 1.8], (5, 1))
    return scans, sensors, [_road(-20.0, 20.0, 0.3)] * 5


def test_ground_points_change_nothing_without_visibility():
    scans, sensors, grounds = _scene()
    cfg = FloxelsConfig(max_iters=60, evidence="zero", range_mask=True)
    a = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    b = estimate_flow(scans, 2, cfg, sensor_origins=sensors, ground_points=grounds)
    assert np.array_equal(a, b)


def test_a_pedestrian_seen_against_the_road_keeps_its_motion():
    # without the road's returns no support scan saw the pedestrian's place empty (its direction
    # holds no return but the pedestrian's own, elsewhere): no evidence, the flow is zeroed; the
    # road behind shows the place empty in every support scan
    scans, sensors, grounds = _scene()
    cfg = FloxelsConfig(max_iters=150, evidence="zero", visibility=True)
    without = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    with_ground = estimate_flow(scans, 2, cfg, sensor_origins=sensors, ground_points=grounds)
    assert np.abs(without).max() == 0
    np.testing.assert_allclose(np.median(with_ground, axis=0), [0.0, 0.3, 0.0], atol=0.03)
    seq = estimate_sequence(scans, cfg, frames=[2], sensor_origins=sensors, ground_points=grounds)[0]
    assert np.array_equal(with_ground, seq)


@pytest.mark.parametrize("bad, err, match", [
    (lambda g: g[:3], ValueError, "one .* per scan: got 3 for 5"),
    (lambda g: [g[0][:, :2]] + g[1:], ValueError, r"ground_points\[0\] must have shape \(m, 3\)"),
    (lambda g: [g[0].astype(np.int32)] + g[1:], TypeError, "floating-point"),
    (lambda g: ["road"] + g[1:], TypeError, r"ground_points\[0\] must be a numpy array"),
    (lambda g: np.stack(g), TypeError, "one \\(m, 3\\) array \\(or None\\) per scan"),
])
def test_bad_ground_points_are_named(bad, err, match):
    scans, sensors, grounds = _scene()
    with pytest.raises(err, match=match):
        estimate_flow(scans, 2, FloxelsConfig(max_iters=5, visibility=True), sensor_origins=sensors,
                      ground_points=bad(grounds))


def test_none_entries_and_empty_ground_are_allowed():
    scans, sensors, grounds = _scene()
    cfg = FloxelsConfig(max_iters=150, evidence="zero", visibility=True)
    plain = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    same = estimate_flow(scans, 2, cfg, sensor_origins=sensors,
                         ground_points=[None, np.zeros((0, 3), np.float32), None, None, None])
    assert np.array_equal(plain, same)
