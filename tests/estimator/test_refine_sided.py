"""The rigid refinement in windows of many support scans (``FloxelsConfig.refine_sided``,
estimator/refine.py): a turning car, whose yaw the grid's cluster consistency cannot hold,
gets its rigid motion; a rigid motion that explains one side of the window better at the
other side's cost is refused."""

import numpy as np
import pytest
import torch

from floxels_ext.estimator.api import Floxels
from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.refine import rigid_refine
from floxels_ext.ops import dbscan
from synthetic_boxes import box_sides, posed
from test_refine import _supports  # the support scans' distance transforms

CUDA = pytest.param("cuda", marks=pytest.mark.cuda)
STEP = 0.15  # the pole's sampling (m)


def turning_car(offsets, v=(0.45, 0.0), w=0.07, centre=(0.0, 3.0, 0.0)):
    """Scans at time offsets ``offsets`` of a car turning at yaw rate ``w`` rad/frame while its
    centre moves ``v`` m/frame, plus a static pole; returns (scans, car rows of the scan at
    t = 0, the car's true flow to t = +1)."""
    body = box_sides()
    pole = np.stack(np.meshgrid([-6.0, -5.85], [-4.0, -3.85], np.arange(0.2, 3.0, STEP), indexing="ij"), -1).reshape(-1, 3)
    scans = []
    for t in offsets:
        c = np.asarray(centre) + np.array([v[0], v[1], 0.0]) * t
        scans.append(np.concatenate([posed(body, c, w * t), pole]).astype(np.float32))
    at0 = posed(body, centre, 0.0)
    at1 = posed(body, np.asarray(centre) + np.array([v[0], v[1], 0.0]), w)
    return scans, slice(0, len(body)), (at1 - at0).astype(np.float32)


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_sided_refinement_gives_a_turning_car_its_yaw(device):
    # the grid's failure: the car's flow is one translation (its mean), the rotation lost
    offsets = (-3, -2, -1, 0, 1, 2, 3)
    scans, car, truth = turning_car(offsets)
    P = torch.from_numpy(scans[3]).to(device)
    flow = torch.zeros_like(P)
    flow[car] = torch.from_numpy(truth.mean(0)).to(device)
    before = np.linalg.norm(flow[car].cpu().numpy() - truth, axis=1).mean()
    out = rigid_refine(P, flow, dbscan(P, 0.5, 4), _supports(scans, 3, offsets, device=device), sided=True).cpu().numpy()
    after = np.linalg.norm(out[car] - truth, axis=1).mean()
    assert before > 0.05  # the rotation matters: +-0.16 m across the car
    assert after < 0.3 * before, (before, after)
    assert np.abs(out[car.stop:]).max() == 0  # the pole: untouched


@pytest.mark.parametrize("past, future", [(0.8, 0.5), (0.5, 0.8)])
def test_sided_refinement_refuses_a_motion_that_trades_one_side_for_the_other(past, future):
    # the past scans show the box at one speed, the future ones at another; the flow explains
    # the future exactly (past 0.8, future 0.5) or the past (past 0.5, future 0.8); a rigid fit
    # of both sides explains the other side better and this one worse, which is no evidence of
    # the object's motion: both sides are checked
    body = box_sides()
    offsets = (-3, -2, -1, 0, 1, 2, 3)
    scans = [(body + np.array([(past if t < 0 else future) * t, 3.0, 0.0])).astype(np.float32) for t in offsets]
    P = torch.from_numpy(scans[3])
    flow = torch.zeros_like(P)
    flow[:, 0] = 0.5
    labels, sup = dbscan(P, 0.5, 4), _supports(scans, 3, offsets)
    plain = rigid_refine(P, flow, labels, sup)
    assert not torch.equal(plain, flow)  # without the sides' test the refinement moves it
    assert torch.equal(rigid_refine(P, flow, labels, sup, sided=True), flow)


def test_refine_sided_refines_the_long_windows():
    # through the estimator: 7-scan windows (6 supports) are refined only with refine_sided
    offsets = (-3, -2, -1, 0, 1, 2, 3)
    scans, car, truth = turning_car(offsets)
    base = dict(num_scans=7, max_iters=150, rigid_refine=True, refine_max_supports=2)
    off = Floxels(FloxelsConfig(**base), "cpu").fit(scans, target=3).flow
    plain = Floxels(FloxelsConfig(**{**base, "rigid_refine": False}), "cpu").fit(scans, target=3).flow
    on = Floxels(FloxelsConfig(**base, refine_sided=True), "cpu").fit(scans, target=3).flow
    assert np.array_equal(off, plain)  # long windows skipped without refine_sided
    e_off = np.linalg.norm(off[car] - truth, axis=1).mean()
    e_on = np.linalg.norm(on[car] - truth, axis=1).mean()
    assert e_on < 0.5 * e_off, (e_off, e_on)
