"""The ``accurate`` preset's ingredients (estimator/refine.py) on small synthetic scenes whose
answer is known: a rigid box sliding along itself, and two cars passing each other; and the
presets themselves (``paper`` = the defaults, bit for bit)."""

import numpy as np
import pytest
import torch

from floxels_ext import estimate_flow, estimate_sequence
from floxels_ext.estimator.api import Floxels
from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.refine import (cluster_velocity_search, rigid_refine, robust_residual, supports_of,
                                          vertex_init)
from floxels_ext.ops import dbscan, distance_transform

CUDA = pytest.param("cuda", marks=pytest.mark.cuda)
STEP = 0.15  # sampling step of the synthetic surfaces (m)


def box_points(x0, y0, length, width, height, back=True, front=False):
    """Faces of a box seen from y < y0: the side y = y0 and the back x = x0 (front x = x0 + L),
    sampled at world-fixed positions like a lidar (so a side sliding along itself looks
    the same in every scan where it overlaps)."""
    xs = np.arange(np.ceil(x0 / STEP) * STEP, x0 + length, STEP)
    zs = np.arange(0.2, height, STEP)
    faces = [np.stack(np.meshgrid(xs, [y0], zs, indexing="ij"), -1).reshape(-1, 3)]
    ys = np.arange(np.ceil(y0 / STEP) * STEP, y0 + width, STEP)
    for on, x in ((back, x0), (front, x0 + length)):
        if on:
            faces.append(np.stack(np.meshgrid([x], ys, zs, indexing="ij"), -1).reshape(-1, 3))
    return np.concatenate(faces)


def wall():
    """A static wall parallel to the motion (it slides along itself under any x motion)."""
    xs = np.arange(-8, 8, STEP)
    zs = np.arange(0.2, 2.0, STEP)
    return np.stack(np.meshgrid(xs, [-3.0], zs, indexing="ij"), -1).reshape(-1, 3)


def sliding_box(v, offsets, back=True):
    """Scans at time offsets ``offsets`` of a 6 m box moving at ``v`` m/frame along its long
    axis next to a static wall; returns (scans, number of box points of each scan)."""
    scans, nbox = [], []
    for t in offsets:
        b = box_points(-3 + v * t, 2.0, 6.0, 2.0, 1.5, back=back)
        scans.append(np.concatenate([b, wall()]).astype(np.float32))
        nbox.append(len(b))
    return scans, nbox


def endless_side(v, offsets):
    """The aperture case: the long side of a truck that spans the whole view (x in [-3, 3]) in
    every scan, no end visible, moving at ``v`` along itself; the scans cannot tell its speed."""
    scans, nbox = [], []
    for t in offsets:
        b = box_points(-10 + v * t, 2.0, 20.0, 2.0, 1.5, back=False)
        b = b[np.abs(b[:, 0]) <= 3.0]
        scans.append(np.concatenate([b, wall()]).astype(np.float32))
        nbox.append(len(b))
    return scans, nbox


def passing_cars(v, offsets):
    """Two 4.5 m cars passing each other in opposite directions, 1.5 m apart (lanes y = 2
    and y = 5.5); car A at +v, car B at -v. Returns (scans, rows of A, rows of B) of each scan."""
    scans, rows = [], []
    for t in offsets:
        a = box_points(-6 + v * t, 2.0, 4.5, 1.8, 1.5, back=True, front=True)
        b = box_points(2 - v * t, 5.5, 4.5, 1.8, 1.5, back=True, front=True)
        scans.append(np.concatenate([a, b, wall()]).astype(np.float32))
        rows.append((slice(0, len(a)), slice(len(a), len(a) + len(b))))
    return scans, rows


def _supports(scans, target, offsets, cfg=FloxelsConfig(), device="cpu"):
    dts, origins, ts, ws = [], [], [], []
    for s, t in zip(scans, offsets):
        if t == 0:
            continue
        v, o = distance_transform(torch.from_numpy(s).to(device), cfg.dt_cell, cfg.dt_padding)
        dts.append(v)
        origins.append(o)
        ts.append(float(t))
        ws.append(cfg.time_weight(t))
    return supports_of(dts, origins, ts, ws, cfg.dt_cell)


def _labels(points):
    return dbscan(points, 0.5, 4)


# ---------------------------------------------------------------------------- presets
def test_paper_preset_is_the_default_config():
    assert FloxelsConfig.preset("paper") == FloxelsConfig()
    acc = FloxelsConfig.preset("accurate")
    assert acc != FloxelsConfig()  # (its fields are pinned as literals in test_accurate_preset.py)
    assert FloxelsConfig.preset("accurate", num_scans=5).num_scans == 5
    with pytest.raises(ValueError, match="unknown preset"):
        FloxelsConfig.preset("fast")


def test_paper_preset_is_bit_identical_to_the_defaults():
    scans, _ = sliding_box(0.8, (-1, 0, 1))
    ref = estimate_flow(scans, 1, device="cpu")
    assert np.array_equal(estimate_flow(scans, 1, device="cpu", preset="paper"), ref)
    assert np.array_equal(Floxels(device="cpu", preset="paper").fit(scans, 1).flow, ref)
    seq_ref = estimate_sequence(scans, device="cpu", frames=[1])
    seq = estimate_sequence(scans, device="cpu", frames=[1], preset="paper")
    assert np.array_equal(seq[0], seq_ref[0])


def test_preset_argument_errors():
    scans, _ = sliding_box(0.8, (0, 1))
    with pytest.raises(ValueError, match="not both"):
        estimate_flow(scans, 0, FloxelsConfig(), device="cpu", preset="paper")
    with pytest.raises(ValueError, match="unknown preset"):
        estimate_flow(scans, 0, device="cpu", preset="acurate")
    with pytest.raises(TypeError, match="preset must be a name"):
        Floxels(preset=1)


# ---------------------------------------------------------------------------- velocity search
@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize("offsets,target", [((0, 1), 0), ((-1, 0, 1), 1)])
def test_velocity_search_box_sliding_along_itself(device, offsets, target):
    v = 1.7
    scans, nbox = sliding_box(v, offsets)
    P = torch.from_numpy(scans[target]).to(device)
    vel = cluster_velocity_search(P, _labels(P), _supports(scans, target, offsets, device=device)).cpu()
    box, rest = vel[:nbox[target]], vel[nbox[target]:]
    assert torch.allclose(box, torch.tensor([v, 0.0, 0.0]).expand_as(box), atol=0.03)
    assert rest.abs().max() == 0  # the wall slides along itself: no evidence of motion, zero


def test_velocity_search_side_only_gives_no_motion():
    # the aperture case: the scans cannot tell the speed, and the search must not invent one
    scans, nbox = endless_side(1.0, (0, 1))
    P = torch.from_numpy(scans[0])
    vel = cluster_velocity_search(P, _labels(P), _supports(scans, 0, (0, 1)))
    assert vel.abs().max() == 0


def test_velocity_search_two_cars_passing():
    v = 1.2
    offsets = (-1, 0, 1)
    scans, rows = passing_cars(v, offsets)
    P = torch.from_numpy(scans[1])
    vel = cluster_velocity_search(P, _labels(P), _supports(scans, 1, offsets))
    a, b = rows[1]
    assert torch.allclose(vel[a], torch.tensor([v, 0.0, 0.0]).expand_as(vel[a]), atol=0.03)
    assert torch.allclose(vel[b], torch.tensor([-v, 0.0, 0.0]).expand_as(vel[b]), atol=0.03)
    assert vel[b.stop:].abs().max() == 0


def test_vertex_init_reproduces_a_uniform_velocity():
    from floxels_ext.ops.corners import compact_corners
    from floxels_ext.ops.grid import grid_from_bounds, point_bounds

    pts = torch.rand(500, 3) * 4
    vel = torch.tensor([0.5, -0.25, 0.0]).expand(500, 3).contiguous()
    origin, shape = grid_from_bounds(*point_bounds([pts])[0], 0.5, 0.5, max_cells=1 << 30)
    cc = compact_corners(pts, origin, 0.5, shape)
    params = vertex_init(vel, cc.corner_idx, cc.corner_w, cc.num_params)
    back = (params[cc.corner_idx.long()] * cc.corner_w[..., None]).sum(1)
    assert torch.allclose(back, vel, atol=1e-5)


# ---------------------------------------------------------------------------- rigid refinement
@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_rigid_refine_recovers_a_shrunk_speed(device):
    # the failure mode: the box's flow at 0.6 of its speed (the paper's loss with few scans);
    # the rigid refinement against the support scans restores it
    v, offsets = 1.0, (-1, 0, 1)
    scans, nbox = sliding_box(v, offsets)
    P = torch.from_numpy(scans[1]).to(device)
    flow = torch.zeros_like(P)
    flow[:nbox[1], 0] = 0.6 * v
    out = rigid_refine(P, flow, _labels(P), _supports(scans, 1, offsets, device=device)).cpu()
    box = out[:nbox[1]]
    assert torch.allclose(box, torch.tensor([v, 0.0, 0.0]).expand_as(box), atol=0.05)
    assert out[nbox[1]:].abs().max() == 0  # static cluster (below the speed floor): untouched


@pytest.mark.parametrize("start, refined", [(0.09, False), (0.11, True)])
def test_rigid_refine_speed_floor(start, refined):
    # only clusters whose mean flow is at least 0.1 m/frame are refined (REFINE_MIN_SPEED): the
    # box (0.5 m/frame) flowing 0.09 keeps it, flowing 0.11 gets its speed
    v, offsets = 0.5, (-1, 0, 1)
    scans, nbox = sliding_box(v, offsets)
    P = torch.from_numpy(scans[1])
    flow = torch.zeros_like(P)
    flow[:nbox[1], 0] = start
    out = rigid_refine(P, flow, _labels(P), _supports(scans, 1, offsets))
    if refined:
        assert torch.allclose(out[:nbox[1]], torch.tensor([v, 0.0, 0.0]).expand(nbox[1], 3), atol=0.05)
    else:
        assert torch.equal(out, flow)


def test_rigid_refine_keeps_an_unconstrained_slide():
    # the scans do not constrain the motion along the side, so the refinement has no
    # evidence and leaves the flow as it was
    scans, nbox = endless_side(1.0, (0, 1))
    P = torch.from_numpy(scans[0])
    flow = torch.zeros_like(P)
    flow[:nbox[0], 0] = 0.6
    out = rigid_refine(P, flow, _labels(P), _supports(scans, 0, (0, 1)))
    assert torch.equal(out, flow)


def test_rigid_refine_two_cars_passing():
    v, offsets = 1.2, (-1, 0, 1)
    scans, rows = passing_cars(v, offsets)
    P = torch.from_numpy(scans[1])
    a, b = rows[1]
    flow = torch.zeros_like(P)
    flow[a, 0], flow[b, 0] = 0.5 * v, -0.5 * v  # both cars too slow
    out = rigid_refine(P, flow, _labels(P), _supports(scans, 1, offsets))
    assert torch.allclose(out[a], torch.tensor([v, 0.0, 0.0]).expand_as(out[a]), atol=0.05)
    assert torch.allclose(out[b], torch.tensor([-v, 0.0, 0.0]).expand_as(out[b]), atol=0.05)


def test_robust_residual_is_zero_for_the_true_motion():
    v, offsets = 0.9, (0, 1)
    scans, nbox = sliding_box(v, offsets)
    P = torch.from_numpy(scans[0][:nbox[0]])
    sup = _supports(scans, 0, offsets)
    good = robust_residual(P, torch.tensor([v, 0.0, 0.0]).expand_as(P), sup)
    zero = robust_residual(P, torch.zeros_like(P), sup)
    assert good.mean() < 0.05 and zero.mean() > 4 * good.mean()  # (0.05: the DT's 0.1 m lattice)


# ---------------------------------------------------------------------------- the preset end to end
def test_accurate_preset_on_the_sliding_box():
    v, offsets = 1.7, (-2, -1, 0, 1, 2)
    scans, nbox = sliding_box(v, offsets)
    paper = estimate_flow(scans, 2, device="cpu", preset="paper")
    acc = estimate_flow(scans, 2, device="cpu", preset="accurate")
    n = nbox[2]
    err = lambda f: np.linalg.norm(f[:n] - [v, 0, 0], axis=1).mean()  # noqa: E731
    assert err(acc) <= err(paper) + 0.02 and err(acc) < 0.1
    assert np.abs(acc[n:]).max() < 0.05  # the wall stays put


@pytest.mark.cuda
def test_accurate_preset_same_bytes_twice_on_cuda():
    # issue 31 for the preset's ingredients: their cluster and vertex sums must not add with
    # float atomics, so two runs of the same input give the same bytes
    v, offsets = 1.7, (-2, -1, 0, 1, 2)
    scans, _ = sliding_box(v, offsets)
    cfg = FloxelsConfig.preset("accurate", num_scans=5, velocity_search=True)
    runs = [estimate_flow(scans, 2, cfg, device="cuda") for _ in range(3)]
    assert all(np.array_equal(runs[0], r) for r in runs[1:])


@pytest.mark.parametrize("device", ["cpu", CUDA])
def test_cluster_means_are_exact_in_any_order(device):
    # the refinement's cluster means (fixed-point integer sums): the same bits whatever the row
    # order and device; unclustered rows count nowhere; a non-finite flow makes its cluster's
    # mean NaN (never refined); absurd flows are clamped, not overflowed
    from floxels_ext.estimator.group_sums import MAX_FIXED_FLOW, cluster_means

    g = torch.Generator().manual_seed(3)
    n, C = 20000, 7
    flow = (torch.rand(n, 3, generator=g) * 4 - 2).to(device)
    lab = torch.randint(-1, C, (n,), generator=g).to(device)
    mean, size = cluster_means(flow, lab, C)
    perm = torch.randperm(n, generator=g).to(device)
    mean_p, size_p = cluster_means(flow[perm], lab[perm], C)
    assert torch.equal(mean, mean_p) and torch.equal(size, size_p)
    ref = torch.stack([flow[lab == c].double().mean(0) for c in range(C)]).float()
    torch.testing.assert_close(mean, ref, atol=1e-6, rtol=0)
    assert size.tolist() == [float((lab == c).sum()) for c in range(C)]
    if device == "cuda":
        cpu = cluster_means(flow.cpu(), lab.cpu(), C)
        assert torch.equal(mean.cpu(), cpu[0]) and torch.equal(size.cpu(), cpu[1])
    bad = flow.clone()
    bad[lab == 2] = bad[lab == 2].clone().index_fill_(0, torch.tensor([0], device=device), float("nan"))
    bad[lab == 4] = 1e12
    m, _ = cluster_means(bad, lab, C)
    assert torch.isnan(m[2]).all() and torch.isfinite(m[[0, 1, 3, 5, 6]]).all()
    assert m[4].tolist() == [MAX_FIXED_FLOW] * 3
