"""``floxels::velocity_search`` (the per-cluster velocity search as one op) against its
pure-PyTorch reference (``floxels_ext.reference.velocity_search``, the search refine.py ran
before), CPU and CUDA, on boxes whose velocities are known and a static one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import floxels_ext  # noqa: F401  (registers torch.ops.floxels.*)
from floxels_ext.ops import distance_transform, velocity_search
from floxels_ext.reference.velocity_search import velocity_search as ref_velocity_search
from synthetic_boxes import box_sides, posed

ops = torch.ops.floxels
cuda = pytest.mark.cuda
SPACING, TAU = 0.1, 1.0
OFFSETS = (-2, -1, 1, 2)
# (centre, heading, velocity per frame) of three boxes: along its axis, across it, standing
BOXES = [((0.0, 0.0, 0.0), 0.3, (1.17, 0.36)), ((0.0, 8.0, 0.0), 0.0, (-0.23, 0.64)), ((9.0, 4.0, 0.0), 1.2, (0.0, 0.0))]
SEARCH = dict(num_directions=8, speed_step=0.1, num_speeds=40, local_steps=4, local_rounds=4)


def case(dtype=torch.float64, device="cpu", every=3, bits=False):
    box = box_sides(4.0, 1.8, 1.4)
    body = box + np.random.default_rng(1).uniform(-0.02, 0.02, box.shape)  # off the DT sample planes
    dts, origins, ts, ws = [], [], [], []
    for t in OFFSETS:
        scan = np.concatenate([posed(body, np.add(c, (v[0] * t, v[1] * t, 0.0)), h) for c, h, v in BOXES])
        d, o = distance_transform(torch.from_numpy(scan.astype(np.float32)).to(device), SPACING, 2.0)
        dts.append(d)
        origins += list(o)
        ts.append(float(t))
        ws.append(1.0 / t ** 2)
    rows = [torch.as_tensor(posed(body, c, h)[::every]) for c, h, _ in BOXES]
    points = torch.cat(rows).to(dtype).to(device)
    counts = [len(r) for r in rows]
    segments = torch.tensor([0, *np.cumsum(counts)], device=device)
    observed = None
    if bits:  # every row misses one scan (its index mod 4)
        k = torch.arange(points.shape[0], device=device) % len(OFFSETS)
        observed = (((1 << len(OFFSETS)) - 1) ^ (1 << k)).to(torch.int32)
    wsum = sum(ws)
    return (points, segments, observed, dts, origins, SPACING, ts, [w / wsum for w in ws], TAU)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("bits", [False, True])
def test_matches_the_reference(dtype, bits):
    args = case(dtype, bits=bits)
    got = velocity_search(*args, **SEARCH)
    want = ref_velocity_search(*args, **SEARCH)
    tol = dict(atol=1e-6, rtol=1e-6) if dtype == torch.float64 else dict(atol=1e-4, rtol=1e-4)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, **tol)


def test_finds_the_velocities():
    best, score, zero = velocity_search(*case(), **SEARCH)
    want = torch.tensor([[v[0], v[1], 0.0] for _, _, v in BOXES], dtype=torch.float64)
    torch.testing.assert_close(best, want, atol=0.02, rtol=0)
    assert bool((score[:2] < 0.3 * zero[:2]).all())  # the movers: clear evidence
    assert score[2] == zero[2]  # the standing box: zero flow is its best


def test_no_local_search_is_the_best_candidate():
    args = case()
    best, score, zero = velocity_search(*args, **{**SEARCH, "local_steps": 0})
    speeds = best[:, :2].norm(dim=1)
    # on the candidate lattice: multiples of the speed step
    torch.testing.assert_close(speeds, (speeds / 0.1).round() * 0.1, atol=1e-9, rtol=0)


def test_threads_do_not_change_the_bits():
    args = case(torch.float32)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        a = velocity_search(*args, **SEARCH)
        torch.set_num_threads(max(2, before))
        b = velocity_search(*args, **SEARCH)
    finally:
        torch.set_num_threads(before)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_opcheck():
    p, seg, ob, *rest = case(every=9, bits=True)
    torch.library.opcheck(ops.velocity_search, (p, seg, ob, *rest, 8, 0.2, 10, 2, 2))


def test_bad_input_is_named():
    p, seg, ob, dts, o, sp, ts, ws, tau = case(every=9)
    rest = (dts, o, sp, ts, ws, tau)
    with pytest.raises(ValueError, match="segments must be"):
        velocity_search(p, seg.int(), None, *rest, **SEARCH)
    with pytest.raises(ValueError, match="segments must rise"):
        velocity_search(p, seg.flip(0), None, *rest, **SEARCH)
    with pytest.raises(ValueError, match="observed must be"):
        velocity_search(p, seg, torch.zeros(3, dtype=torch.int32), *rest, **SEARCH)
    with pytest.raises(ValueError, match="num_directions"):
        velocity_search(p, seg, None, *rest, **{**SEARCH, "num_directions": 0})
    with pytest.raises(ValueError, match="num_directions"):
        velocity_search(p, seg, None, *rest, **{**SEARCH, "num_speeds": 500})
    with pytest.raises(ValueError, match="local_steps"):
        velocity_search(p, seg, None, *rest, **{**SEARCH, "local_steps": -1})
    with pytest.raises(ValueError, match="speed_step"):
        velocity_search(p, seg, None, *rest, **{**SEARCH, "speed_step": 0.0})
    with pytest.raises(RuntimeError, match="segments must be int64"):
        ops.velocity_search(p, seg.int(), None, *rest, 8, 0.1, 40, 4, 4)
    with pytest.raises(RuntimeError, match="num_directions"):
        ops.velocity_search(p, seg, None, *rest, 8, 0.1, 4000, 4, 4)
    # offsets out of range: the raw op clamps them to the rows
    best, _, _ = ops.velocity_search(p, torch.tensor([-3, 5, 10 ** 9, 7]), None, *rest, 8, 0.1, 40, 2, 2)
    assert torch.isfinite(best).all()


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=cuda)])
def test_a_non_finite_row_leaves_its_cluster_at_zero(device):
    # the raw op (the wrapper refuses such rows): cluster 0's scores are NaN, zero flow its best
    p, seg, ob, *rest = case(device=device)
    bad = p.clone()
    bad[2, 0] = float("inf")
    best, score, zero = ops.velocity_search(bad, seg, ob, *rest, 8, 0.1, 40, 4, 4)
    assert torch.equal(best[0], torch.zeros(3, dtype=p.dtype, device=device))
    assert torch.isnan(score[0]) and torch.isnan(zero[0])
    good = ops.velocity_search(p, seg, ob, *rest, 8, 0.1, 40, 4, 4)
    assert all(torch.equal(x[1:], y[1:]) for x, y in zip((best, score, zero), good))


@cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("every", [3, 1])
def test_cuda_matches_cpu_and_repeats_its_bytes(dtype, every):
    cpu = velocity_search(*case(dtype, every=every, bits=True), **SEARCH)
    args = case(dtype, "cuda", every=every, bits=True)
    a = velocity_search(*args, **SEARCH)
    b = velocity_search(*args, **SEARCH)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    tol = dict(atol=1e-6, rtol=1e-6) if dtype == torch.float64 else dict(atol=1e-4, rtol=1e-4)
    for x, y in zip(a, cpu):
        torch.testing.assert_close(x.cpu(), y, **tol)


@cuda
def test_cuda_opcheck():
    p, seg, ob, *rest = case(every=9, bits=True, device="cuda")
    torch.library.opcheck(ops.velocity_search, (p, seg, ob, *rest, 8, 0.2, 10, 2, 2))
