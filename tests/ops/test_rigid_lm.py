"""``floxels::rigid_lm`` (the rigid refinement's Levenberg-Marquardt loop as one op) against its
pure-PyTorch reference (``floxels_ext.reference.rigid_lm``, the loop refine.py ran before),
CPU and CUDA, on a translating and a turning box whose motions are known."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.ops import distance_transform, rigid_lm
from floxels_ext.reference.rigid_lm import rigid_lm as ref_rigid_lm
from synthetic_boxes import box_sides, posed

ops = torch.ops.floxels
cuda = pytest.mark.cuda
SPACING, TAU = 0.1, 1.0
OFFSETS = (-2, -1, 1, 2)
TRUE = [(0.6, 0.0, 0.0), (0.4, 0.1, 0.06)]  # (vx, vy, yaw rate) per frame of the two boxes


def _moved(body, centre, motion, t):
    vx, vy, w = motion
    return posed(body, np.asarray(centre) + np.array([vx * t, vy * t, 0.0]), w * t)


def case(dtype=torch.float64, device="cpu", start=((0.3, 0.0, 0.0), (0.2, 0.0, 0.0)), every=2):
    """Two boxes (7 m apart), their support scans' DTs, and the op's arguments (rows of box 0,
    then box 1, every ``every``-th point)."""
    # jittered, so that no point sits on a DT sample plane (where the trilinear gradient has a
    # kink and the op and the reference may take different sides)
    box = box_sides(4.0, 1.8, 1.4)
    body = box + np.random.default_rng(0).uniform(-0.02, 0.02, box.shape)
    centres = [(0.0, 0.0, 0.0), (0.0, 7.0, 0.0)]
    dts, origins, ts, ws = [], [], [], []
    for t in OFFSETS:
        scan = np.concatenate([_moved(body, c, m, t) for c, m in zip(centres, TRUE)]).astype(np.float32)
        v, o = distance_transform(torch.from_numpy(scan).to(device), SPACING, 2.0)
        dts.append(v)
        origins += list(o)
        ts.append(float(t))
        ws.append(1.0 / t ** 2)
    wsum = sum(ws)
    rows = [torch.as_tensor(_moved(body, c, (0, 0, 0), 0)[::every]) for c in centres]
    points = torch.cat(rows).to(dtype).to(device)
    rel = torch.cat([r - r.mean(0) for r in rows]).to(dtype).to(device)
    segments = torch.tensor([0, len(rows[0]), len(rows[0]) + len(rows[1])], device=device)
    theta = torch.tensor(start, dtype=dtype, device=device)
    vz = torch.zeros(2, dtype=dtype, device=device)
    return (points, rel, segments, theta, vz, dts, origins, SPACING, ts, [w / wsum for w in ws], TAU)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("iters", [0, 1, 10])
def test_matches_the_reference(dtype, iters):
    args = case(dtype)
    th, cost = rigid_lm(*args, iters)
    th_r, cost_r = ref_rigid_lm(*args, iters)
    tol = dict(atol=1e-6, rtol=1e-6) if dtype == torch.float64 else dict(atol=2e-4, rtol=2e-4)
    torch.testing.assert_close(th, th_r, **tol)
    torch.testing.assert_close(cost, cost_r, **tol)
    if iters == 0:
        assert torch.equal(th, args[3])


def test_recovers_both_motions():
    th, cost = rigid_lm(*case(), 10)
    torch.testing.assert_close(th, torch.tensor(TRUE, dtype=torch.float64), atol=0.01, rtol=0)
    start_cost = rigid_lm(*case(), 0)[1]
    assert bool((cost < 0.1 * start_cost).all())


def test_empty_cluster_keeps_its_start_and_costs_nothing():
    points, rel, segments, theta, vz, *rest = case()
    seg = torch.tensor([0, int(segments[1]), int(segments[1]), int(segments[2])])  # cluster 1 has no rows
    th3 = torch.cat([theta[:1], torch.tensor([[0.5, 0.5, 0.1]], dtype=theta.dtype), theta[1:]])
    vz3 = torch.zeros(3, dtype=vz.dtype)
    th, cost = rigid_lm(points, rel, seg, th3, vz3, *rest, 5)
    assert torch.equal(th[1], th3[1]) and cost[1] == 0
    torch.testing.assert_close(th[[0, 2]], rigid_lm(points, rel, segments, theta, vz, *rest, 5)[0])


def test_threads_do_not_change_the_bits():
    args = case(torch.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a = rigid_lm(*args, 10)
        torch.set_num_threads(max(2, before))
        b = rigid_lm(*args, 10)
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_opcheck():
    torch.library.opcheck(ops.rigid_lm, (*case(every=6), 3))


def test_bad_input_is_named():
    points, rel, segments, theta, vz, dts, origins, spacing, ts, ws, tau = case()
    good = (points, rel, segments, theta, vz, dts, origins, spacing, ts, ws, tau)
    with pytest.raises(ValueError, match="segments must be"):
        rigid_lm(points, rel, segments[:2], theta, vz, dts, origins, spacing, ts, ws, tau, 3)
    with pytest.raises(ValueError, match="segments must rise"):
        rigid_lm(points, rel, torch.tensor([0, 500, 3]), theta, vz, dts, origins, spacing, ts, ws, tau, 3)
    with pytest.raises(ValueError, match="theta must be"):
        rigid_lm(points, rel, segments, theta[:, :2], vz, dts, origins, spacing, ts, ws, tau, 3)
    with pytest.raises(ValueError, match="vz must be"):
        rigid_lm(points, rel, segments, theta, vz[:1], dts, origins, spacing, ts, ws, tau, 3)
    with pytest.raises(ValueError, match="iters"):
        rigid_lm(*good, -1)
    with pytest.raises(ValueError, match="iters"):
        rigid_lm(*good, 10 ** 6)
    with pytest.raises(ValueError, match="tau"):
        rigid_lm(points, rel, segments, theta, vz, dts, origins, spacing, ts, ws, 0.0, 3)
    with pytest.raises(ValueError, match="rel"):
        rigid_lm(points, rel[:5], segments, theta, vz, dts, origins, spacing, ts, ws, tau, 3)
    # the raw op checks too (the same messages as the C++ checks name)
    with pytest.raises(RuntimeError, match="segments must have shape"):
        ops.rigid_lm(points, rel, segments[:2], theta, vz, dts, origins, spacing, ts, ws, tau, 3)
    with pytest.raises(RuntimeError, match="iters must be"):
        ops.rigid_lm(*good, -2)
    with pytest.raises(RuntimeError, match="segments must be int64"):
        ops.rigid_lm(points, rel, segments.int(), theta, vz, dts, origins, spacing, ts, ws, tau, 3)


def test_offsets_out_of_range_are_clamped_by_the_raw_op():
    # the raw op does not read the offsets on the host; a bad one gives a shorter cluster, never
    # a row outside the points
    points, rel, segments, theta, vz, *rest = case()
    th, cost = ops.rigid_lm(points, rel, torch.tensor([-5, 10, 10 ** 9]), theta, vz, *rest, 3)
    assert torch.isfinite(th).all() and torch.isfinite(cost).all()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=cuda)])
def test_a_non_finite_row_stops_only_its_cluster(device):
    # the raw op (the wrapper refuses such rows): cluster 0's cost is NaN, so it takes no step
    points, rel, segments, theta, vz, *rest = case(device=device)
    bad = points.clone()
    bad[3, 1] = float("nan")
    th, cost = ops.rigid_lm(bad, rel, segments, theta, vz, *rest, 10)
    assert torch.equal(th[0], theta[0]) and torch.isnan(cost[0])
    good_th, good_cost = ops.rigid_lm(points, rel, segments, theta, vz, *rest, 10)
    assert torch.equal(th[1], good_th[1]) and torch.equal(cost[1], good_cost[1])


@cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu_and_repeats_its_bytes(dtype):
    cpu = rigid_lm(*case(dtype), 10)
    args = case(dtype, "cuda")
    a = rigid_lm(*args, 10)
    b = rigid_lm(*args, 10)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    tol = dict(atol=1e-6, rtol=1e-6) if dtype == torch.float64 else dict(atol=2e-4, rtol=2e-4)
    for x, y in zip(a, cpu):
        torch.testing.assert_close(x.cpu(), y, **tol)


@cuda
def test_cuda_many_rows_per_cluster_and_opcheck():
    args = case(torch.float32, "cuda", every=1)  # more rows than a block's threads
    cpu = rigid_lm(*case(torch.float32, every=1), 10)
    for x, y in zip(rigid_lm(*args, 10), cpu):
        torch.testing.assert_close(x.cpu(), y, atol=2e-4, rtol=2e-4)
    torch.library.opcheck(ops.rigid_lm, (*case(torch.float64, "cuda", every=6), 3))
