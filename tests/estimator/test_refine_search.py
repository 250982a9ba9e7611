"""The refinement's second start (``FloxelsConfig.refine_search``, estimator/refine.py): the
Levenberg-Marquardt loop is local, so a cluster whose flow stopped short can settle in a
partial match of its own structure; started also from the searched velocity, the cluster
takes the motion with the lower cost."""

import numpy as np
import pytest
import torch

from floxels_ext.estimator.api import Floxels
from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.refine import rigid_refine
from floxels_ext.ops import dbscan
from test_refine import _supports  # the support scans' distance transforms

CUDA = pytest.param("cuda", marks=pytest.mark.cuda)
STEP = 0.15  # sampling of the synthetic surfaces (m)


def fence(posts=6, spacing=1.2, width=0.3, height=1.5):
    """Posts ``spacing`` apart joined by a rail (one DBSCAN cluster): a structure that matches
    itself partly at shifts other than its motion (a post onto its neighbour)."""
    parts = [np.stack(np.meshgrid(np.arange(k * spacing, k * spacing + width + 1e-6, STEP), [0.0, 0.3],
                                  np.arange(0.2, height, STEP), indexing="ij"), -1).reshape(-1, 3) for k in range(posts)]
    rail = np.arange(0.0, (posts - 1) * spacing + width + 1e-6, STEP)
    parts.append(np.stack(np.meshgrid(rail, [0.0, 0.3], [height], indexing="ij"), -1).reshape(-1, 3))
    return np.unique(np.round(np.concatenate(parts), 4), axis=0)


def moving_fence(offsets, speed):
    return [(fence() + np.array([speed * t, 3.0, 0.0])).astype(np.float32) for t in offsets]


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_search_start_frees_a_cluster_stopped_short(device):
    offsets, speed = (-1, 0, 1), 0.9
    scans = moving_fence(offsets, speed)
    P = torch.from_numpy(scans[1]).to(device)
    labels, sup = dbscan(P, 0.5, 4), _supports(scans, 1, offsets, device=device)
    assert int(labels.max()) == 0 and bool((labels == 0).all())
    flow = torch.zeros_like(P)
    flow[:, 0] = 0.15  # a flow stopped short, as the grid's can on a pair
    local = rigid_refine(P, flow, labels, sup).cpu().numpy()
    searched = rigid_refine(P, flow, labels, sup, search=True).cpu().numpy()
    truth = np.array([speed, 0.0, 0.0])
    assert np.abs(local - truth).sum(1).mean() > 0.5  # from the short flow alone: stuck
    np.testing.assert_allclose(searched, np.broadcast_to(truth, searched.shape), atol=0.02)


def test_search_start_keeps_a_motion_the_local_loop_finds():
    # where the loop from the flow converges, the second start changes nothing it should not
    offsets, speed = (-1, 0, 1), 0.8
    scans = moving_fence(offsets, speed)
    P = torch.from_numpy(scans[1])
    labels, sup = dbscan(P, 0.5, 4), _supports(scans, 1, offsets)
    flow = torch.zeros_like(P)
    flow[:, 0] = 0.7
    local = rigid_refine(P, flow, labels, sup).numpy()
    searched = rigid_refine(P, flow, labels, sup, search=True).numpy()
    for out in (local, searched):
        np.testing.assert_allclose(out[:, 0], speed, atol=0.03)


def test_static_structure_stays_static_with_the_search():
    # clusters below the refinement's speed floor are not refined, searched or not
    scans = moving_fence((-1, 0, 1), 0.0)
    P = torch.from_numpy(scans[1])
    labels, sup = dbscan(P, 0.5, 4), _supports(scans, 1, (-1, 0, 1))
    flow = torch.full_like(P, 0.02)
    assert torch.equal(rigid_refine(P, flow, labels, sup, search=True), flow)


def test_refine_search_through_the_estimator():
    # a frame pair: the grid stops at ~0.66 of the fence's 1.5 m/frame; the plain refinement
    # keeps that, the searched start finds the motion
    scans = moving_fence((0, 1), 1.5)
    base = dict(rigid_refine=True, max_iters=150)
    plain = Floxels(FloxelsConfig(**base), "cpu").fit(scans, target=0).flow
    searched = Floxels(FloxelsConfig(**base, refine_search=True), "cpu").fit(scans, target=0).flow
    truth = np.array([1.5, 0.0, 0.0])
    assert np.linalg.norm(plain - truth, axis=1).mean() > 0.5
    assert np.linalg.norm(searched - truth, axis=1).mean() < 0.05


def test_refine_search_is_in_the_accurate_preset_only():
    assert FloxelsConfig.preset("accurate").refine_search is True
    assert FloxelsConfig.preset("paper").refine_search is False
    assert FloxelsConfig().refine_search is False
