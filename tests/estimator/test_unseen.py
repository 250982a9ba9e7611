"""Which hidden groups keep their flow (``evidence_keep_unseen``, estimator/unseen.py; issue 47's
static EPE). At the last frame of a sequence (support scans in the past only), three groups no
support scan saw:

* a parked car in a row of identical parked cars 6 m apart, hidden behind passing traffic in
  every past scan, given the row's period as its motion (6 m/frame): moved back to each past
  scan's time it lands exactly on the next cars of the row, so that motion explains the scans
  far better than zero flow (its own place is empty in them). It must keep no flow: those cars
  stand in the target scan too;
* a car driving at 2.5 m/frame on the other side of the road, with its true flow: its past places
  are road, it keeps its flow;
* a pole given a flow into empty space: the flow explains nothing, it keeps none."""

from __future__ import annotations

import numpy as np
import torch

from floxels_ext.estimator import FloxelsConfig
from floxels_ext.estimator.distance import build_dt
from floxels_ext.estimator.refine import robust_residual, supports_of
from floxels_ext.estimator.unseen import LANDING_RADIUS, hidden_keeps

PERIOD = 6.0                 # m between the parked cars' rears
V = 2.5                      # m/frame of the driving car, along x
HIDDEN = 2                   # the parked car no past scan saw
RINGS = (0.4, 0.7, 1.0, 1.3)  # 0.3 m apart: one DBSCAN cluster (eps 0.5) per car


def _car(x0: float, y0: float) -> np.ndarray:
    """A 4.5 x 1.8 m car's outline every 0.08 m on each ring, its rear at ``x0``, centred on ``y0``."""
    L, W = 4.5, 1.8
    u = np.arange(0, 2 * (L + W), 0.08)
    x = np.where(u < L, u, np.where(u < L + W, L, np.where(u < 2 * L + W, 2 * L + W - u, 0.0)))
    y = np.where(u < L, 0.0, np.where(u < L + W, u - L, np.where(u < 2 * L + W, W, 2 * (L + W) - u)))
    return np.concatenate([np.stack([x0 + x, y0 + y - W / 2, np.full_like(x, z)], 1) for z in RINGS])


def _pole() -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    return np.concatenate([np.stack([20.0 + 0.1 * np.cos(a), 0.0 + 0.1 * np.sin(a), np.full(24, z)], 1)
                           for z in np.arange(0.1, 2.0, 0.15)])


def _scan(t: float, with_hidden: bool) -> tuple[np.ndarray, np.ndarray]:
    """Points at time ``t`` (frames) and each point's part: parked car k (0..5), 10 the driving car, 11 the pole."""
    parts = [(_car(PERIOD * k, 5.0), k) for k in range(6) if with_hidden or k != HIDDEN]
    parts += [(_car(10.0 + V * t, -4.0), 10), (_pole(), 11)]
    return (np.concatenate([p for p, _ in parts]).astype(np.float32),
            np.concatenate([np.full(len(p), k) for p, k in parts]))


def test_a_hidden_group_moved_onto_static_structure_keeps_no_flow():
    cfg = FloxelsConfig()
    target, part = _scan(0.0, with_hidden=True)
    target, part = torch.as_tensor(target), torch.as_tensor(part)
    offsets = [-4.0, -3.0, -2.0, -1.0]  # the last frame: past scans only, none shows the hidden car
    dts = [build_dt(torch.as_tensor(_scan(t, with_hidden=False)[0]), cfg) for t in offsets]
    supports = supports_of([d.values for d in dts], [d.origin for d in dts], offsets,
                           [cfg.time_weight(t) for t in offsets], cfg.dt_cell)
    labels = torch.ops.floxels.dbscan(target, 0.5, 4)
    car, mover, pole = part == HIDDEN, part == 10, part == 11
    for m in (car, mover, pole):
        assert len(set(labels[m].tolist())) == 1 and int(labels[m][0]) >= 0  # one cluster each
    flow = torch.zeros_like(target)
    flow[car] = torch.tensor([-PERIOD, 0.0, 0.0])  # one period a frame: onto the next cars back in time
    flow[mover] = torch.tensor([V, 0.0, 0.0])
    flow[pole] = torch.tensor([0.0, 3.0, 0.0])
    hidden = car | mover | pole
    # the period explains the past scans as well as the mover's true motion does, and far better
    # than zero flow: the residual tests alone would keep it
    for m in (car, mover):
        moved = float(robust_residual(target[m], flow[m], supports).mean())
        still = float(robust_residual(target[m], torch.zeros_like(flow[m]), supports).mean())
        assert moved < 0.1 and still > 0.3, (moved, still)
    keep = hidden_keeps(target, flow, labels, hidden, hidden, supports, int(labels.max()) + 1)
    assert not keep[car].any()          # lands on the row's other cars, which stand in the target scan
    assert keep[mover].all()            # its past places are road
    assert not keep[pole].any()         # its flow explains nothing
    assert not keep[~hidden].any()      # only hidden groups are judged
    # nothing but the moved place decides for the car: with the row's other cars moving too
    # (no static structure there), the car keeps its flow
    moving = flow.clone()
    moving[(part < 6) & ~car] = torch.tensor([-PERIOD, 0.0, 0.0])
    keep = hidden_keeps(target, moving, labels, hidden, hidden, supports, int(labels.max()) + 1)
    assert keep[car].all()
    # and only groups whose rigid motion fit (``fits``) are candidates
    assert not hidden_keeps(target, flow, labels, hidden, torch.zeros_like(hidden), supports).any()
    assert LANDING_RADIUS <= 2 * cfg.dt_cell + 1e-9
