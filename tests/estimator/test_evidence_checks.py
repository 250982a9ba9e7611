"""The two more looks at the groups the evidence test passed (estimator/evidence_checks.py;
issue 47's static EPE): ``upright_groups`` (a group whose flow is more vertical than horizontal
is no road user) and ``far_fails`` (a flow fitted to the nearest scans' sampling does not explain
the farther scans), on hand-made flows and distance transforms; and ``evidence_upright`` in the
estimator: a wall whose lidar rings climb it from scan to scan (the sensor approaching) is fitted
by a vertical flow that passes the evidence test, and keeps none; a car beside it keeps its flow."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from floxels_ext.estimator import FloxelsConfig, estimate_flow
from floxels_ext.estimator.distance import build_dt
from floxels_ext.estimator.evidence_checks import far_fails, upright_groups

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.mark.parametrize("device", DEVICES)
def test_upright_groups_judges_a_cluster_by_its_mean_flow_and_a_lone_point_by_its_own(device):
    labels = torch.tensor([0, 0, 0, 1, 1, -1, -1, 2], device=device)
    flow = torch.tensor([[0.5, 0.0, 0.0], [0.5, 0.1, 0.0], [0.0, 0.0, 0.9],   # cluster 0: mean (0.33, 0.03, 0.3)
                         [0.1, 0.0, 0.3], [0.0, 0.1, 0.2],                      # cluster 1: mostly vertical
                         [0.0, 0.05, -0.2], [0.3, 0.0, 0.2],                    # lone points: up / along
                         [float("nan"), 0.0, 1.0]], device=device)              # a NaN flow: not upright
    want = [False, False, False, True, True, True, False, False]
    assert upright_groups(flow, labels, 3).tolist() == want
    assert upright_groups(flow, labels, None).tolist() == want  # the clusters counted here
    assert upright_groups(flow, None, None).tolist() == [False, False, True, True, True, True, False, False]
    # exactly 45 degrees is not more vertical than horizontal
    assert not upright_groups(torch.tensor([[0.3, 0.4, 0.5]], device=device), None, None).item()


def _dt(points: np.ndarray, cfg: FloxelsConfig, device: str):
    d = build_dt(torch.as_tensor(points, dtype=torch.float32, device=device), cfg)
    return d.values, d.origin


@pytest.mark.parametrize("device", DEVICES)
def test_far_fails_refuses_a_fit_to_the_nearest_scan_alone(device):
    cfg = FloxelsConfig()
    offsets = [1.0, 2.0, 3.0]  # a sequence's first frame: future scans only
    weights = [cfg.time_weight(t) for t in offsets]
    v = np.array([0.5, 0.0, 0.0])
    mover = np.array([[0.0, 0.0, 1.0], [0.0, 0.2, 1.0], [0.0, 0.4, 1.0]])  # 3 lone points, one cell
    post = np.array([[6.0, 0.0, 1.0]])       # a static point whose samples wander: the nearest scan's
    ring = {1.0: 0.3, 2.0: -0.3, 3.0: 0.25}  # lies 0.3 m above it, the farther scans' elsewhere
    hidden = np.array([[12.0, 0.0, 1.0]])   # a lone point the farther scans did not see
    scans = []
    for t in offsets:
        s = [mover + t * v, post + [0.0, 0.0, ring[t]], hidden + [0.0, 0.0, 0.3 if t == 1.0 else 0.6]]
        scans.append(np.concatenate(s + [np.array([[3.0, 3.0, 1.0]])]).astype(np.float32))
    dts = [_dt(s, cfg, device) for s in scans]
    points = np.concatenate([mover, post, hidden, post + [0.0, 2.0, 0.0]]).astype(np.float32)
    flow = np.concatenate([np.repeat(v[None], 3, 0), [[0.0, 0.0, 0.3]], [[0.0, 0.0, 0.3]], [[0.0, 0.0, 0.3]]])
    # groups: the mover (label -1, cell 0), the post (cell 1), the hidden point (cell 2), a cluster
    labels = torch.tensor([-1, -1, -1, -1, -1, 0], device=device)
    cells = torch.tensor([0, 0, 0, 1, 2, 3], device=device)
    observed = torch.tensor([0b111, 0b111, 0b111, 0b111, 0b001, 0b111], dtype=torch.int32, device=device)
    P = torch.as_tensor(points, device=device)
    Fl = torch.as_tensor(flow, dtype=torch.float32, device=device)
    kw = dict(dt_cell=cfg.dt_cell, truncation=cfg.truncation, ratio=cfg.evidence_ratio, observed=observed)
    args = (P, Fl, labels, cells, [d for d, _ in dts], [o for _, o in dts], offsets, weights)
    # the mover explains every scan; the post's flow fits scan 1 only (the farther scans: worse than
    # zero flow); the hidden point keeps its verdict (no farther scan saw it); the cluster is judged
    # only with unclustered=False
    assert far_fails(*args, unclustered=True, **kw).tolist() == [False, False, False, True, False, False]
    assert far_fails(*args, unclustered=False, **kw).tolist() == [False, False, False, True, False, True]
    # a window of one support scan (a frame pair) has no farther scan: no verdict changes
    assert far_fails(*args[:4], args[4][:1], args[5][:1], offsets[:1], weights[:1], unclustered=True, **kw) is None


def _wall_scene(climb: float):
    """A wall 10 m ahead (y -4..4), sampled by four rings 0.5 m apart that climb ``climb`` m a frame
    (a sensor approaching it), and a car 4 m long beside it driving 0.8 m/frame along y."""
    y = np.arange(-4.0, 4.0, 0.1)
    scans = []
    for t in range(5):
        wall = [np.stack([np.full_like(y, 10.0), y, np.full_like(y, 0.4 + 0.5 * k + climb * t)], 1) for k in range(4)]
        cy = np.arange(0.0, 4.0, 0.1) + 0.8 * t - 8.0
        car = [np.stack([np.full_like(cy, 4.0), cy, np.full_like(cy, z)], 1) for z in (0.5, 0.9, 1.3)]
        scans.append(np.concatenate(wall + car).astype(np.float32))
    return scans, len(y) * 4


def test_a_wall_whose_rings_climb_it_keeps_no_vertical_flow():
    scans, n_wall = _wall_scene(0.12)
    cfg = FloxelsConfig(evidence="zero", max_iters=150)
    before = estimate_flow(scans, 2, cfg, device="cpu")
    after = estimate_flow(scans, 2, cfg.replace(evidence_upright=True), device="cpu")
    wall_before = np.abs(before[:n_wall, 2]).mean()
    assert wall_before > 0.05, wall_before  # the rings' climb passes the evidence test as flow
    assert np.abs(after[:n_wall]).max() == 0.0
    # the car keeps its flow, the same bits
    assert np.array_equal(after[n_wall:], before[n_wall:])
    assert np.abs(after[n_wall:, 1].mean() - 0.8) < 0.1
