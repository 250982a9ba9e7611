"""The rigid refinement's vertical velocity (``refine_level``) and the spreading of refined
motions to the rest of an object (``refine_spread``, estimator/spread.py; issue 47's fast
movers). A fast car seen by a sparse lidar: its three scan rings lie 0.6 m apart, so DBSCAN (eps
0.5) makes three clusters; the optimiser left one with a wrong vertical velocity, one short of
its speed and one with no flow (the evidence test zeroed it). A static pole stands 0.8 m beside
the car's path and must stay put."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from floxels_ext.estimator import FloxelsConfig
from floxels_ext.estimator.distance import build_dt
from floxels_ext.estimator.refine import rigid_refine, supports_of
from floxels_ext.estimator.spread import spread_rigid

V = 2.5                       # m/frame along x
RINGS = (0.3, 0.9, 1.5)       # ring heights (m): 0.6 m apart
CAR = (4.5, 1.8)              # length, width


def _car(x0: float) -> np.ndarray:
    """The car's outline sampled every 0.08 m on each ring, its rear at ``x0``."""
    L, W = CAR
    s = np.arange(0, 2 * (L + W), 0.08)
    pts = []
    for z in RINGS:
        u = s % (2 * (L + W))
        x = np.where(u < L, u, np.where(u < L + W, L, np.where(u < 2 * L + W, 2 * L + W - u, 0.0)))
        y = np.where(u < L, 0.0, np.where(u < L + W, u - L, np.where(u < 2 * L + W, W, 2 * (L + W) - u)))
        pts.append(np.stack([x0 + x, y - W / 2, np.full_like(x, z)], 1))
    return np.concatenate(pts)


def _pole() -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    return np.concatenate([np.stack([17.0 + 0.1 * np.cos(a), -1.7 + 0.1 * np.sin(a), np.full(24, z)], 1)
                           for z in np.arange(0.1, 3.0, 0.15)])


def _wall() -> np.ndarray:
    x = np.arange(0.0, 45.0, 0.1)
    return np.concatenate([np.stack([x, np.full_like(x, 6.0), np.full_like(x, z)], 1) for z in (0.5, 1.5, 2.5)])


@pytest.fixture(scope="module")
def case():
    cfg = FloxelsConfig()
    scan = lambda t: np.concatenate([_car(15.0 + V * t), _pole(), _wall()]).astype(np.float32)  # noqa: E731
    target = torch.as_tensor(scan(0))
    offsets = [-2.0, -1.0, 1.0, 2.0]
    dts = [build_dt(torch.as_tensor(scan(t)), cfg) for t in offsets]
    supports = supports_of([d.values for d in dts], [d.origin for d in dts], offsets,
                           [cfg.time_weight(t) for t in offsets], cfg.dt_cell)
    labels = torch.ops.floxels.dbscan(target, 0.5, 4)
    n_car = len(_car(0.0))
    ring = torch.full((len(target),), -1)
    ring[:n_car] = torch.as_tensor(np.repeat(np.arange(3), n_car // 3))
    assert len({int(labels[ring == r][0]) for r in range(3)}) == 3  # three clusters
    # the optimiser's flow: ring 0 right but lifted 0.4 m/frame, ring 1 short, ring 2 zeroed, the rest static
    flow = torch.zeros_like(target)
    flow[ring == 0] = torch.tensor([V, 0.0, 0.4])
    flow[ring == 1] = torch.tensor([1.0, 0.0, 0.0])
    return target, flow, labels, supports, ring, n_car


def test_level_drops_a_wrong_vertical_velocity(case):
    target, flow, labels, supports, ring, _ = case
    kw = dict(num_clusters=int(labels.max()) + 1, search=True)
    lifted = rigid_refine(target, flow, labels, supports, **kw)
    level = rigid_refine(target, flow, labels, supports, level=True, **kw)
    assert abs(float(lifted[ring == 0, 2].mean()) - 0.4) < 1e-6  # kept the optimiser's vertical flow
    assert abs(float(level[ring == 0, 2].mean())) < 1e-6
    assert torch.allclose(level[ring == 0, :2].mean(0), torch.tensor([V, 0.0]), atol=0.05)


def test_spread_gives_the_rest_of_the_car_its_motion_and_not_the_pole(case):
    target, flow, labels, supports, ring, n_car = case
    out, motions = rigid_refine(target, flow, labels, supports, num_clusters=int(labels.max()) + 1, search=True,
                                level=True, motions=True)
    assert float(out[ring == 2].norm(dim=1).max()) == 0.0  # zeroed, so never refined
    spread = spread_rigid(target, out, labels, supports, motions, radius=1.0)
    car = ring >= 0
    err = (spread[car] - torch.tensor([V, 0.0, 0.0])).norm(dim=1)
    assert float(err.mean()) < 0.05
    pole = (torch.arange(len(target)) >= n_car) & (target[:, 1] < -1.0)
    near = torch.cdist(target[pole], target[car]).min(dim=1).values
    assert float(near.min()) < 1.0  # offered (the pole is one cluster): within the radius of the car
    assert float(spread[pole].norm(dim=1).max()) == 0.0  # static: the scans show it where it stands
    # nothing within reach: unchanged
    assert torch.equal(spread_rigid(target, out, labels, supports, motions, radius=0.0)[ring == 2], out[ring == 2])


def test_spread_and_level_are_off_in_paper_and_validated():
    c = FloxelsConfig()
    assert c.refine_spread == 0.0 and not c.refine_level
    with pytest.raises(ValueError, match="refine_spread"):
        FloxelsConfig(refine_spread=-1.0)
    with pytest.raises(ValueError, match="refine_spread"):
        FloxelsConfig(refine_spread=float("nan"))
