"""The motion-evidence test's numbers (estimator/evidence.py, ``floxels::dt_evidence``), tested
rather than derived (issue 46): the defaults written as literals, groups just either side of
each threshold on scans whose distance transform is known exactly, the grouping of unclustered
points by flow-grid cell, the estimator's verdicts against the rule written out, and the same
on CUDA.

The rule: a group is explained when ``gain = R_zero - R_flow > max(margin, ratio * R_zero)``.
The scenes: a support scan that is a plane x = 0 of points on the 0.1 m DT lattice, so the DT
at a point x = a in front of it is a exactly (and linear in a between lattice samples); a
group at x = a has R_zero = a, and the flow (-g, 0, 0) brings it to a - g: gain g.
"""

import numpy as np
import pytest
import torch

from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.estimator.evidence import group_ids, motion_evidence
from floxels_ext.ops import distance_transform

CUDA = pytest.param("cuda", marks=pytest.mark.cuda)
CELL = 0.1


def test_the_defaults_are_pinned():
    c = FloxelsConfig()
    # issue 29 / bench/RESULTS.md "Motion evidence": 2 cm of residual (about automotive lidar's
    # range noise) and 5 % of the zero-flow residual (far, sparse groups)
    assert c.evidence_margin == 0.02 and c.evidence_ratio == 0.05 and c.evidence == "off"
    acc = FloxelsConfig.preset("accurate")
    assert acc.evidence_margin == 0.02 and acc.evidence_ratio == 0.05 and acc.evidence == "zero"


def _plane(device):
    """The support scan: the plane x = 0, y and z in [-2, 2], every 0.1 m."""
    y, z = np.meshgrid(np.arange(-20, 21) * CELL, np.arange(-20, 21) * CELL)
    pts = np.stack([np.zeros(y.size), y.ravel(), z.ravel()], 1)
    return torch.tensor(pts, dtype=torch.float32, device=device)


def _evidence(device, groups, weight=2.0, **kw):
    """Evidence of groups [(a, g, n)]: n points at x = a (y, z on the lattice inside the plane)
    with flow (-g, 0, 0), one group each; one support scan at t = +1 with loss weight
    ``weight`` (the test normalises the weights: any weight gives the same verdict). Margin and
    ratio: ``kw``'s, else the estimator's defaults (FloxelsConfig's)."""
    kw.setdefault("margin", FloxelsConfig().evidence_margin)
    kw.setdefault("ratio", FloxelsConfig().evidence_ratio)
    values, origin = distance_transform(_plane(device), CELL, 2.0)
    pts, flow, gid = [], [], []
    for k, (a, g, n) in enumerate(groups):
        yz = (np.arange(n) % 10 - 5) * CELL
        pts.append(np.stack([np.full(n, a), yz, (np.arange(n) // 10 - 2) * CELL], 1))
        flow.append(np.tile([-g, 0.0, 0.0], (n, 1)))
        gid.append(np.full(n, k))
    as_t = lambda x, dt=torch.float32: torch.tensor(np.concatenate(x), dtype=dt, device=device)  # noqa: E731
    ev = motion_evidence(as_t(pts), as_t(flow), as_t(gid, torch.int64), [values], [origin], [1.0], [weight],
                         dt_cell=CELL, truncation=5.0, **kw)
    ends = np.cumsum([n for _, _, n in groups])[:-1]
    return [tuple(np.split(x.cpu().numpy(), ends)) for x in (ev.explained, ev.score, ev.residual_zero)]


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_each_side_of_the_margin_and_the_ratio(device):
    groups = [
        (0.3, 0.022, 20),   # R_zero 0.3: 5 % of it is 0.015, the 2 cm margin decides: 0.022 > 0.02
        (0.3, 0.018, 20),   # ... 0.018 is not
        (0.3, 0.016, 20),   # ... nor 0.016 (> 5 % of R_zero: the margin is a floor, not a cap)
        (1.0, 0.055, 20),   # R_zero 1.0: 5 % of it, 0.05, decides: 0.055 > 0.05
        (1.0, 0.045, 20),   # ... 0.045 is not (> the 2 cm margin: the ratio is a floor too)
        (1.5, 0.08, 20),    # R_zero 1.5: 0.08 > 0.075
        (1.5, 0.07, 20),    # ... 0.07 is not
    ]
    explained, score, rz = _evidence(device, groups)
    for (a, g, _), e, s, r in zip(groups, explained, score, rz):
        np.testing.assert_allclose(r, a, atol=1e-5)   # the scene is what it says
        np.testing.assert_allclose(s, g, atol=1e-5)
    assert [bool(e.all()) for e in explained] == [True, False, False, True, False, True, False]
    assert [bool(e.any()) for e in explained] == [True, False, False, True, False, True, False]


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_margin_and_ratio_given_are_the_ones_used(device):
    groups = [(0.3, 0.022, 20), (1.0, 0.055, 20), (1.0, 0.2, 20)]
    verdict = lambda **kw: [bool(e.all()) for e in _evidence(device, groups, **kw)[0]]  # noqa: E731
    assert verdict() == [True, True, True]
    assert verdict(margin=0.03) == [False, True, True]
    assert verdict(ratio=0.06) == [True, False, True]
    assert verdict(margin=0.0, ratio=0.0) == [True, True, True]


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_zero_gain_is_no_evidence_even_without_thresholds(device):
    """A group whose flow changes nothing (here: zero flow) has gain exactly 0, which is never
    evidence of motion, not even with margin 0 and ratio 0 (the test is a strict >)."""
    explained, score, _ = _evidence(device, [(0.3, 0.0, 20), (1.0, 0.0, 20)], margin=0.0, ratio=0.0)
    assert all(not e.any() for e in explained) and all((s == 0).all() for s in score)


def _unclustered(device):
    """Unclustered points (labels -1) in two 0.5 m cells: 30 points whose flow removes 0.2 m of
    residual, and 10 points 1 m away whose flow removes nothing."""
    values, origin = distance_transform(_plane(device), CELL, 2.0)
    a = np.stack([np.full(30, 0.4), (np.arange(30) % 3) * CELL, -0.2 + (np.arange(30) // 3) * 0.04], 1)
    b = np.stack([np.full(10, 0.4), 1.0 + (np.arange(10) % 3) * CELL, (np.arange(10) // 3) * 0.05], 1)
    pts = torch.tensor(np.concatenate([a, b]), dtype=torch.float32, device=device)
    flow = torch.zeros_like(pts)
    flow[:30, 0] = -0.2
    return pts, flow, values, origin


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_unclustered_points_are_judged_per_flow_grid_cell(device):
    pts, flow, values, origin = _unclustered(device)
    labels = torch.full((len(pts),), -1, dtype=torch.int64, device=device)
    groups = group_ids(pts, labels, 0.5, [0.0, -0.25, -0.25])
    assert len(torch.unique(groups[:30])) == 1 and len(torch.unique(groups[30:])) == 1 and groups[0] != groups[30]
    ev = motion_evidence(pts, flow, groups, [values], [origin], [1.0], [1.0], dt_cell=CELL, truncation=5.0)
    # one group of all 40 would have gain 0.15 > max(0.02, 5 % of 0.4): the still points explained
    assert ev.explained[:30].all() and not ev.explained[30:].any()


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_estimator_judges_unclustered_points_per_cell(device):
    """Through the estimator: DBSCAN noise points in two places, three moving 0.5 m a frame,
    three standing still; the moving ones are explained, the still ones are not (in one group
    the moving ones' gain would explain the still ones too)."""
    moving = np.array([[0.0, 0.0, 0.0], [0.0, 0.7, 0.0], [0.0, 0.0, 0.7]], np.float32)
    still = np.array([[3.0, 3.0, 0.0], [3.0, 3.7, 0.0], [3.0, 3.0, 0.7]], np.float32)
    scans = [np.concatenate([moving + np.float32([0.5 * t, 0, 0]), still]) for t in (-1, 0, 1)]
    res = Floxels(FloxelsConfig(evidence="score", max_iters=200), device).fit(scans, target=1)
    assert (res.labels.cpu().numpy() == -1).all()  # every point is DBSCAN noise
    np.testing.assert_allclose(res.flow[:3], np.tile([0.5, 0, 0], (3, 1)), atol=0.05)
    assert res.explained[:3].all() and not res.explained[3:].any()
    assert np.abs(res.flow[3:]).max() < 0.05


def _rule(score, rz):
    """The test written out with the documented defaults (literals, not the constants)."""
    return score > np.maximum(0.02, 0.05 * rz)


@pytest.fixture(scope="module")
def default_verdicts():
    return {}


# (margin, ratio) given to the estimator: None = its defaults, which the rule writes out as 0.02, 0.05
@pytest.mark.parametrize("margin, ratio", [(None, None), (0.3, 0.05), (0.02, 0.99)])
def test_estimator_verdicts_follow_the_rule_written_out(default_verdicts, margin, ratio):
    """The estimator's per-point verdicts are the rule applied to each group's residuals, with
    its defaults or the margin and ratio it is given: the groups (DBSCAN clusters; unclustered
    points by flow-grid cell, counted from the result's grid origin) and their R_zero
    recomputed here with group_ids and motion_evidence."""
    from test_evidence import _scans

    scans, t = _scans(seed=3)
    given = {} if margin is None else dict(evidence_margin=margin, evidence_ratio=ratio)
    cfg = FloxelsConfig(evidence="score", max_iters=100, **given)
    res = Floxels(cfg, "cpu").fit(scans, t)
    pts = torch.as_tensor(scans[t])
    groups = group_ids(pts, res.labels, cfg.voxel_size, res.grid_origin)
    dts, origins, offsets, weights = [], [], [], []
    for k, s in enumerate(scans):
        if k != t:
            v, o = distance_transform(torch.as_tensor(s), cfg.dt_cell, cfg.dt_padding)
            dts.append(v)
            origins.append(o)
            offsets.append(float(k - t))
            weights.append(1.0 / (k - t) ** 2)
    ev = motion_evidence(pts, torch.as_tensor(res.flow), groups, dts, origins, offsets, weights,
                         dt_cell=0.1, truncation=5.0)
    np.testing.assert_allclose(res.evidence, ev.score.numpy(), atol=1e-6)
    score, rz = ev.score.numpy(), ev.residual_zero.numpy()
    rule = _rule(score, rz) if margin is None else score > np.maximum(margin, ratio * rz)
    assert np.array_equal(res.explained, rule)
    if margin is None:
        assert 0.2 < rule.mean() < 0.9  # both verdicts occur
        default_verdicts["explained"] = rule
    elif "explained" in default_verdicts:  # the given margin or ratio changes some verdict
        assert not np.array_equal(rule, default_verdicts["explained"])
