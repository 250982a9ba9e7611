"""``FloxelsConfig.range_mask`` / ``visibility`` with ``sensor_origins`` (the accurate preset,
estimator/sight.py): long walls beside a moving sensor, cropped to a range around each scan's
own sensor, get the sensor's motion from the paper's loss and pass the plain evidence test;
counting only what each support scan could see, the evidence test rejects them, while a car
passing the other way keeps its motion. Also the sights themselves and the argument checks."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from floxels_ext.estimator import FloxelsConfig, estimate_flow, estimate_sequence
from floxels_ext.estimator.sight import AZ_BIN, EL_BIN, SEEN_MARGIN, THROUGH_BINS, observed_bits, scan_sight

EGO = 1.5     # m/frame along x
CAR = -1.0    # m/frame: oncoming, in the lane at y = -2
RANGE = (3.0, 15.0)


def street(n_scans=5, seed=0):
    """Scans of two walls (y = 4, y = -6, x -60..60, 0-2 m high) and a 4 x 1.8 x 1.5 m car, in
    the world frame, each cropped to RANGE around its own sensor (the ego at EGO m/frame);
    the sensors, and the target's car mask."""
    g = np.random.default_rng(seed)
    scans, sensors, car_masks = [], [], []
    for i in range(n_scans):
        s = np.array([EGO * (i - n_scans // 2), 0.0, 1.8])
        x = g.uniform(-60, 60, 12000)
        z = g.uniform(0, 2, 12000)
        walls = np.concatenate([np.stack([x, np.full_like(x, y) + g.normal(0, 0.01, x.shape), z], 1)
                                for y in (4.0, -6.0)])
        cx = 6.0 + CAR * (i - n_scans // 2)  # the car's centre
        u = g.uniform(-1, 1, (1500, 3)) * [2.0, 0.9, 0.75]
        face = g.integers(0, 3, 1500)
        u[np.arange(1500), face] = np.sign(u[np.arange(1500), face]) * np.array([2.0, 0.9, 0.75])[face]
        car = u + [cx, -2.0, 0.75]
        pts = np.concatenate([walls, car])
        r = np.hypot(pts[:, 0] - s[0], pts[:, 1] - s[1])
        keep = (r >= RANGE[0]) & (r <= RANGE[1])
        scans.append(pts[keep].astype(np.float32))
        sensors.append(s)
        car_masks.append(np.r_[np.zeros(len(walls), bool), np.ones(len(car), bool)][keep])
    return scans, sensors, car_masks[n_scans // 2]


@pytest.fixture(scope="module")
def scene():
    return street()


def _speed(flow):
    return np.linalg.norm(flow, axis=1)


@pytest.mark.parametrize("sight", [dict(range_mask=True), dict(visibility=True),
                                   dict(range_mask=True, visibility=True)])
def test_walls_keep_the_sensors_motion_unless_the_test_counts_what_was_seen(scene, sight):
    scans, sensors, car = scene
    paper = estimate_flow(scans, 2, FloxelsConfig(), sensor_origins=sensors)
    plain_ev = estimate_flow(scans, 2, FloxelsConfig(evidence="zero"), sensor_origins=sensors)
    masked = estimate_flow(scans, 2, FloxelsConfig(evidence="zero", **sight), sensor_origins=sensors)
    wall = ~car
    assert np.median(_speed(paper[wall])) > 0.3        # the failure: walls follow the sensor
    assert np.median(_speed(plain_ev[wall])) > 0.3     # and pass the plain evidence test
    assert np.mean(_speed(masked[wall]) < 0.05) > 0.95   # rejected when only what was seen counts
    # the car keeps its motion (the scans saw where it was and where it went)
    v = np.median(masked[car], axis=0)
    assert abs(v[0] - CAR) < 0.15 and abs(v[1]) < 0.1


def test_velocity_search_keeps_the_car_and_not_the_walls(scene):
    scans, sensors, car = scene
    cfg = FloxelsConfig(evidence="zero", range_mask=True, visibility=True, velocity_search=True)
    f = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    assert np.mean(_speed(f[~car]) < 0.05) > 0.95
    assert abs(np.median(f[car][:, 0]) - CAR) < 0.15


def test_without_range_mask_sensor_origins_change_nothing(scene):
    scans, sensors, _ = scene
    cfg = FloxelsConfig(evidence="zero", max_iters=60)
    a = estimate_flow(scans, 2, cfg)
    b = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    assert np.array_equal(a, b)


def test_sequence_uses_each_scans_own_sensor(scene):
    scans, sensors, _ = scene
    cfg = FloxelsConfig(evidence="zero", range_mask=True, num_scans=5, max_iters=80)
    seq = estimate_sequence(scans, cfg, frames=[2], sensor_origins=np.stack(sensors))[0]
    one = estimate_flow(scans, 2, cfg, sensor_origins=sensors)
    assert np.array_equal(seq, one)


def test_range_mask_without_sensors_warns_and_runs_as_without_it(scene):
    scans, _, _ = scene
    cfg = FloxelsConfig(evidence="zero", range_mask=True, max_iters=40)
    with pytest.warns(UserWarning, match="range_mask and visibility .* need sensor_origins"):
        a = estimate_flow(scans, 2, cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b = estimate_flow(scans, 2, FloxelsConfig(evidence="zero", max_iters=40))
    assert np.array_equal(a, b)


def test_no_known_sensor_is_as_without_sights(scene):
    scans, sensors, _ = scene
    cfg = FloxelsConfig(evidence="zero", range_mask=True, visibility=True, max_iters=40)
    a = estimate_flow(scans, 2, cfg, sensor_origins=[None] * 5)
    b = estimate_flow(scans, 2, FloxelsConfig(evidence="zero", max_iters=40))
    assert np.array_equal(a, b)


@pytest.mark.parametrize("bad, err, match", [
    ([np.zeros(3)] * 4, ValueError, "one .* position per scan: got 4 for 5 scans"),
    ([np.zeros(3)] * 4 + [np.array([0.0, np.nan, 0.0])], ValueError, r"sensor_origins\[4\] is not finite"),
    ([np.zeros(2)] * 5, ValueError, r"sensor_origins\[0\] must be 3 numbers"),
    ([np.zeros(3)] * 4 + ["abc"], (TypeError, ValueError), r"sensor_origins\[4\]"),
    (3.0, TypeError, "one \\(x, y, z\\) position per scan"),
])
def test_bad_sensor_origins_are_refused(scene, bad, err, match):
    scans, _, _ = scene
    with pytest.raises(err, match=match):
        estimate_flow(scans, 2, FloxelsConfig(range_mask=True, max_iters=2), sensor_origins=bad)


def test_bad_sensor_origins_in_a_sequence_are_refused_before_any_work(scene):
    scans, sensors, _ = scene
    with pytest.raises(ValueError, match="got 3 for 5 scans"):
        estimate_sequence(scans, FloxelsConfig(range_mask=True), sensor_origins=sensors[:3])


def test_scan_sight_band_is_the_scans_range_around_its_sensor():
    g = np.random.default_rng(1)
    ang, r = g.uniform(0, 2 * np.pi, 5000), g.uniform(3, 20, 5000)
    p = torch.tensor(np.stack([10 + r * np.cos(ang), -5 + r * np.sin(ang), g.uniform(0, 2, 5000)], 1),
                     dtype=torch.float32)
    s = scan_sight(p, np.array([10.0, -5.0, 1.8]), band=True, image=False)
    assert s.image is None and s.band.dtype == torch.float32
    torch.testing.assert_close(s.band, torch.tensor([float(r.min()), float(r.max())]), rtol=1e-5, atol=1e-4)
    q = torch.tensor([[10.0, -5.0, 1.0], [14.0, -5.0, 1.0], [10.0, 18.0, 1.0]])  # in the blind zone, in, beyond
    assert observed_bits(q, [s]).tolist() == [0, 1, 0]


def test_scan_sight_image_sees_through_free_space_not_behind_occluders():
    """Scan: a wall 10 m ahead (x = 10) and, in one narrow direction, a post 4 m ahead. A point
    6 m ahead in front of the wall was seen through (bit set); one behind the post (occluded)
    and one in a direction with no return (beyond the wall's ends) say nothing."""
    y, z = np.meshgrid(np.linspace(-3, 3, 121), np.linspace(-1, 1, 41))
    wall = np.stack([np.full(y.size, 10.0), y.ravel(), z.ravel()], 1)
    post = np.stack([np.full(50, 4.0), np.linspace(1.95, 2.05, 50), np.linspace(-0.2, 0.2, 50)], 1)
    pts = torch.tensor(np.concatenate([wall, post]), dtype=torch.float32)
    s = scan_sight(pts, np.zeros(3), band=False, image=True)
    q = torch.tensor([[6.0, 0.0, 0.0],     # free space before the wall: seen
                      [7.0, 3.5, 0.0],     # behind the post (same direction, farther): occluded
                      [6.0, 9.0, 0.0],     # no return in that direction
                      [10.4, 0.0, 0.0],    # 0.4 m behind the wall's return: within the 0.5 m margin, seen
                      [10.6, 0.0, 0.0]])   # 0.6 m behind it: hidden by the wall
    assert observed_bits(q, [s]).tolist() == [1, 0, 0, 1, 0]
    assert observed_bits(q, [None, s]).tolist() == [1 | 2, 1, 1, 1 | 2, 1]  # a scan without sight counts


def test_sight_constants_are_pinned():
    # estimator/sight.py: range image bins of 0.5 x 0.5 degrees (coarser than a 64-beam lidar's
    # rays), a return 0.5 m nearer than a point still counts as seeing it
    assert SEEN_MARGIN == 0.5
    assert (AZ_BIN, EL_BIN) == (math.radians(0.5), math.radians(0.5))
    assert THROUGH_BINS == 4  # 2 degrees above and below an empty bin


def _at(az_bin: int, el_bin: int, r: float) -> list[float]:
    """The point at range r in the centre of the range image's direction bin (az_bin, el_bin)."""
    az = (az_bin + 0.5) * AZ_BIN - math.pi
    el = (el_bin + 0.5) * EL_BIN - math.pi / 2
    return [r * math.cos(el) * math.cos(az), r * math.cos(el) * math.sin(az), r * math.sin(el)]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_scan_sight_sees_through_the_gap_between_two_rings(device):
    """An empty direction bin (the rings of a sparse lidar pass above and below it) counts as seen
    where the nearest returns above and below it in its azimuth column lie beyond the place (the
    beams next to it passed it: the place is empty), or below it beyond and nothing above it in
    the column at all (sky); not where they lie at its range (a surface the rings skip: a low
    barrier between two rings' range bands), nor where one is nearer (the road in front of it),
    nor where the column has none below within THROUGH_BINS, nor with a gap above and returns
    higher up (foliage), nor where the column beside it holds a return at its range at its
    elevation (a hole in foliage) (issue 47: an oncoming bus's vacated place between the rings)."""
    e = 180  # the horizon's elevation bin; rings 2 bins (1 degree) apart: e - 2 and e + 2
    columns = {  # azimuth bin: the column's returns (elevation bin, range)
        400: [(e - 2, 20.0), (e + 2, 20.0)],  # a wall 20 m away behind the place
        410: [(e - 2, 10.1), (e + 2, 10.1)],  # a surface at the place's range (the rings skip it)
        420: [(e - 2, 20.0)],                 # sky above, the far wall below
        430: [(e - 2, 6.0), (e + 2, 20.0)],   # something nearer below
        440: [],                              # no return in the column at all
        450: [(e - 5, 20.0), (e + 5, 20.0)],  # the nearest returns 2.5 degrees away: beyond THROUGH_BINS
        460: [(e - 1, 20.0), (e + 2, 20.0), (e + 3, 10.0)],  # the nearest on each side decide
        470: [(e - 2, 10.1), (e - 2, 20.0), (e + 2, 20.0)],  # a bin with a surface and what lies beyond its edge
        480: [(e - 2, 20.0), (e + 6, 10.0)],  # a gap above, then a return higher up: not sky
        490: [(e - 2, 20.0), (e + 2, 20.0)],  # as 400, but the column beside it (491) ...
    }
    beside = [(491, e, 10.1)]                 # ... holds a return at the place's range at its elevation
    pts = [_at(a, el, r) for a, rets in columns.items() for el, r in rets] + [_at(*b) for b in beside]
    pts += [_at(300, el, 30.0) for el in range(e - 10, e + 10)]  # elsewhere: every bin has a return
    s = scan_sight(torch.tensor(pts, dtype=torch.float32, device=device), np.zeros(3), band=False, image=True)
    q = torch.tensor([_at(a, e, 10.0) for a in columns] + [_at(400, e, 19.8), _at(300, e + 20, 10.0)],
                     dtype=torch.float32, device=device)
    # 19.8 m: the wall at 20 m is not beyond it by SEEN_MARGIN; bin e + 20 of column 300: 10 bins
    # above its last return (sky above, but nothing below within THROUGH_BINS)
    assert observed_bits(q, [s]).tolist() == [1, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0]
    _, front = observed_bits(q, [s], occluded=True)
    assert front.tolist() == [0] * 12  # an empty bin is never "something in front"


def test_scan_sight_band_is_horizontal_range():
    """The band is the horizontal range around the sensor (a scan's crop, as floxels run's 3-50
    m): a point 3 m below the sensor just inside the band's outer edge is inside, one just inside
    the blind zone is outside, whatever their 3-D range."""
    ang = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = lambda r: np.stack([r * np.cos(ang), r * np.sin(ang), np.zeros_like(ang)], 1)  # noqa: E731
    pts = torch.tensor(np.concatenate([ring(3.0), ring(10.0), ring(20.0)]), dtype=torch.float32)
    s = scan_sight(pts, np.zeros(3), band=True, image=False)
    q = torch.tensor([[19.9, 0.0, -3.0], [0.0, 3.1, 1.5], [20.1, 0.0, 0.0], [2.9, 0.0, -1.5]])
    assert observed_bits(q, [s]).tolist() == [1, 1, 0, 0]


def test_a_sensor_beyond_any_lidars_reach_is_not_used(scene):
    # positions in another frame than the scans (issue 42: world-frame files far out, the world
    # origin taken as their sensor): 2.5 km from every point the range bands cut the scene and
    # the range images hold it in a few bins; such a sensor is dropped with one warning
    scans, sensors, _ = scene
    cfg = FloxelsConfig(evidence="zero", range_mask=True, visibility=True, max_iters=40)
    far = [s + [2500.0, 0.0, 0.0] for s in sensors]
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        a = estimate_flow(scans, 2, cfg, sensor_origins=far)
    said = [str(w.message) for w in got if "more than 1000 m from every point" in str(w.message)]
    assert said and "range_mask and visibility" in said[0] and "--no-ego-motion" in said[0]
    b = estimate_flow(scans, 2, cfg, sensor_origins=[None] * 5)
    assert np.array_equal(a, b)
    one = [sensors[0] + [2500.0, 0.0, 0.0]] + list(sensors[1:])  # the others keep their sights
    with pytest.warns(UserWarning, match="more than 1000 m from every point"):
        c = estimate_flow(scans, 2, cfg, sensor_origins=one)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a sensor among its points: no warning
        d = estimate_flow(scans, 2, cfg, sensor_origins=[None] + list(sensors[1:]))
    assert np.array_equal(c, d)


def _through_oracle(flat, tops, idx, ret, far, bins=THROUGH_BINS):
    """The seen-through rule of estimator/sight.py element by element, as its docstring reads."""
    from floxels_ext.estimator.sight import NUM_AZ, NUM_EL
    out = []
    for i, r, f in zip(idx.tolist(), ret.tolist(), far.tolist()):
        ie, col = i % NUM_EL, i - i % NUM_EL  # the bin's elevation, its column's first bin
        ok = r < 0
        for sign in (1, -1):  # the nearest return above / below within THROUGH_BINS
            side = next((flat[col + ie + sign * d] for d in range(1, bins + 1)
                         if 0 <= ie + sign * d < NUM_EL and flat[col + ie + sign * d] >= 0), -1.0)
            up_empty = sign > 0 and side < 0 and ie > tops[(i // NUM_EL)]
            ok &= side >= f or up_empty
        local = i % (NUM_AZ * NUM_EL)
        ia = local // NUM_EL
        for step in (-1, 1):
            v = flat[i - local + ((ia + step) % NUM_AZ) * NUM_EL + ie]
            ok &= v < 0 or v >= f
        out.append(bool(ok))
    return out


@pytest.mark.parametrize("bins", [THROUGH_BINS, 2, 0])
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_seen_through_matches_the_rule_bin_by_bin(device, bins, monkeypatch):
    """The seen-through test (its look-ups in one gather, the nearest return on each side by an
    argmax: issue 42's fewer launches) against the rule evaluated bin by bin, on two random
    sparse images (columns at the image's elevation ends and its azimuth wrap included); with
    THROUGH_BINS set otherwise too (tests turn the seen-through bins off with 0)."""
    from floxels_ext.estimator import sight
    from floxels_ext.estimator.sight import NUM_AZ, NUM_EL, _through

    monkeypatch.setattr(sight, "THROUGH_BINS", bins)
    g = np.random.default_rng(3)
    flat = np.full(2 * NUM_AZ * NUM_EL, -1.0, dtype=np.float32)
    hit = g.random(flat.shape) < 0.3
    flat[hit] = g.uniform(1.0, 30.0, hit.sum()).astype(np.float32)
    cols = flat.reshape(2 * NUM_AZ, NUM_EL)
    top = np.array([np.flatnonzero(c >= 0).max() if (c >= 0).any() else -1 for c in cols])
    n = 4000
    az = np.concatenate([g.integers(0, NUM_AZ, n - 8), [0, 0, NUM_AZ - 1, NUM_AZ - 1, 5, 5, 9, 9]])
    el = np.concatenate([g.integers(0, NUM_EL, n - 8), [0, NUM_EL - 1, 0, NUM_EL - 1, 1, NUM_EL - 2, 2, 3]])
    idx = (az * NUM_EL + el).reshape(2, -1) + np.arange(2)[:, None] * NUM_AZ * NUM_EL
    ret = flat[idx]
    far = g.uniform(1.0, 30.0, idx.shape).astype(np.float32)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    got = _through(t(flat), t(top.reshape(2, NUM_AZ)), t(idx), t(ret), t(far))
    want = _through_oracle(flat, top, idx.reshape(-1), ret.reshape(-1), far.reshape(-1), bins)
    assert got.reshape(-1).tolist() == want
    assert (0 < sum(want) < len(want)) if bins else sum(want) == 0
