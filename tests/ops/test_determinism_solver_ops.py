"""Issue 31: the CUDA path gives the same bytes for the same input, run after run, and a
problem gives the same bytes whatever else is batched with it. Every op with a gradient and
solver_run run twice (or alone and batched) and are compared bit for bit (torch.equal, and
NaN-aware where NaNs are legitimate). Needs a GPU (device tool)."""

import pytest
import torch

from floxels_ext import FloxelsConfig, ops
from floxels_ext.ops.solver import PackedProblems, SolverProblem, problem_segments
from floxels_ext.estimator.solver_run import run_solver

from test_solver import _problem, _scene, _to_cuda

F = torch.ops.floxels
pytestmark = pytest.mark.cuda


def _same(a, b):
    """Bit-identical tensors (NaNs in the same places count as equal)."""
    assert a.dtype == b.dtype and a.shape == b.shape
    if a.is_floating_point():
        a, b = a.view(torch.int32 if a.dtype == torch.float32 else torch.int64), \
            b.view(torch.int32 if b.dtype == torch.float32 else torch.int64)
    assert torch.equal(a, b), "not bit-identical"


def _hot_points(n, dtype, seed=0, device="cuda"):
    """Points piled up in a few voxels (as near the sensor), which makes float atomics add the
    same address from many threads in a varying order."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(5, 3, generator=g, dtype=torch.float64) * 4.0
    pts = centres[torch.randint(0, 5, (n,), generator=g)] + 0.05 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    return pts.to(dtype).to(device)


# --- ops with gradients ---------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_trilinear_ops_are_deterministic(dtype):
    pts = _hot_points(200_000, dtype)
    grid = torch.randn(3, 12, 12, 12, dtype=dtype, device="cuda")
    origin, spacing = [-0.5, -0.5, -0.5], 0.5
    vals = torch.randn(pts.shape[0], 3, dtype=dtype, device="cuda")

    def run():
        s = F.trilinear_scatter(vals, pts, origin, spacing, [12, 12, 12])
        g = grid.clone().requires_grad_(True)
        p = pts.clone().requires_grad_(True)
        out = ops.trilinear_gather(g, p, origin, spacing)
        (out * vals).sum().backward()
        return s, out.detach(), g.grad, p.grad

    for a, b in zip(run(), run()):
        _same(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_corner_ops_are_deterministic(dtype):
    cfg = FloxelsConfig()
    P = _hot_points(200_000, torch.float32)
    go, gs = ops.grid_for_points(P.cpu(), cfg.voxel_size, cfg.voxel_size)
    c = ops.compact_corners(P, go, cfg.voxel_size, gs)
    w = c.corner_w.to(dtype)
    params = torch.randn(c.num_params, 3, dtype=dtype, device="cuda")
    vals = torch.randn(P.shape[0], 3, dtype=dtype, device="cuda")

    def run():
        s = F.corner_scatter(vals, c.corner_idx, w, c.num_params)
        p = params.clone().requires_grad_(True)
        out = ops.corner_gather(p, c.corner_idx, w)
        (out * vals).sum().backward()
        return s, out.detach(), p.grad

    for a, b in zip(run(), run()):
        _same(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cluster_ops_are_deterministic(dtype):
    n, k = 300_000, 7  # few, big clusters: hot addresses
    g = torch.Generator().manual_seed(1)
    labels = (torch.randint(-1, k, (n,), generator=g)).cuda()
    flow = torch.randn(n, 3, generator=g).to(dtype).cuda()

    def run():
        m = ops.cluster_mean(flow, labels, k)
        f = flow.clone().requires_grad_(True)
        loss = ops.cluster_consistency_loss(f, labels, k)
        (loss * 1.7).backward()
        l2, g2 = ops.cluster_consistency_fwd_bwd(flow, labels, k)
        v = flow.clone().requires_grad_(True)
        (ops.cluster_mean(v, labels, k) ** 2).sum().backward()
        return m, loss.detach(), f.grad, l2, g2, v.grad

    for a, b in zip(run(), run()):
        _same(a, b)


def test_dt_loss_is_deterministic():
    cfg = FloxelsConfig()
    P, sup = _scene(5, n=100_000)
    pr = _problem(P, sup, cfg, labels=False)
    pts = pr.points.cuda()
    dts = [d.cuda() for d in pr.dts]
    flow = 0.1 * torch.randn(pts.shape[0], 3, device="cuda")
    origins = [float(v) for o in pr.origins for v in o]

    def run():
        f = flow.clone().requires_grad_(True)
        loss = ops.dt_loss(pts, f, dts, origins, cfg.dt_cell, pr.time_offsets, pr.weights)
        loss.backward()
        l2, g2 = ops.dt_loss_fwd_bwd(pts, flow, dts, origins, cfg.dt_cell, pr.time_offsets, pr.weights)
        return loss.detach(), f.grad, l2, g2

    for a, b in zip(run(), run()):
        _same(a, b)


# --- solver_run -------------------------------------------------------------------------------

def _problems(cluster, count=8, n0=2500):
    cfg = FloxelsConfig(max_iters=60, patience=1000, cluster_loss=cluster)
    probs = []
    for seed in range(40, 40 + count):
        P, sup = _scene(seed, n=n0 + 97 * seed)
        probs.append(_to_cuda(_problem(P, sup, cfg, labels=cluster, sort=True)))
    return probs, cfg


def _solve(probs, cfg, chunk=None):
    packed = PackedProblems(probs, cfg)
    run_solver(packed, chunk=chunk)
    torch.cuda.synchronize()
    return packed


def _assert_same_problem(pa, a, pb, b):
    la, lb = torch.tensor(pa.losses(a), dtype=torch.float64), torch.tensor(pb.losses(b), dtype=torch.float64)
    _same(la, lb)
    assert pa.best_iter(a) == pb.best_iter(b)
    _same(pa.best_params(a), pb.best_params(b))


@pytest.mark.parametrize("max_grid", [None, 5])
@pytest.mark.parametrize("persistent", ["0", "1"])
@pytest.mark.parametrize("cluster", [True, False])
def test_solver_twice_same_bytes(monkeypatch, cluster, persistent, max_grid):
    """Eight frames in one call, twice: the same losses, best iterations and parameters, bit
    for bit (a grid of 5 makes every persistent block walk many point and vertex blocks)."""
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    if max_grid is not None:
        monkeypatch.setenv("FLOXELS_SOLVER_MAX_GRID", str(max_grid))
    probs, cfg = _problems(cluster)
    a, b = _solve(probs, cfg), _solve(probs, cfg)
    for k in range(len(probs)):
        _assert_same_problem(a, k, b, k)


@pytest.mark.parametrize("persistent", ["0", "1"])
def test_solver_launch_modes_same_bytes(monkeypatch, persistent):
    """The persistent loop and the two-kernel iteration run the same bodies with
    order-independent sums: the same bytes as well; and chunked launches too."""
    probs, cfg = _problems(True, count=4)
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", "0")
    ref = _solve(probs, cfg)
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    got = _solve(probs, cfg, chunk=7)
    for k in range(len(probs)):
        _assert_same_problem(ref, k, got, k)


@pytest.mark.parametrize("persistent", ["0", "1"])
@pytest.mark.parametrize("cluster", [True, False])
def test_solver_frame_alone_or_batched_same_bytes(monkeypatch, cluster, persistent):
    """A frame gives the same bytes alone and batched with others, first, in the middle or
    last of the pack."""
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    probs, cfg = _problems(cluster, count=6)
    for k in (0, 3, 5):
        alone = _solve([probs[k]], cfg)
        batched = _solve(probs, cfg)
        _assert_same_problem(alone, 0, batched, k)
    swapped = _solve(probs[::-1], cfg)
    for k in range(len(probs)):
        _assert_same_problem(batched, k, swapped, len(probs) - 1 - k)


@pytest.mark.parametrize("persistent", ["0", "1"])
def test_solver_segments_across_tiles_same_bytes(monkeypatch, persistent):
    """Segment tables built elsewhere (segments crossing the 32-point tiles): per-tile partial
    rows summed in tile order, so twice and batched give the same bytes too."""
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    cfg = FloxelsConfig(max_iters=40, patience=1000)
    probs = []
    for seed in (31, 32, 33):
        P, sup = _scene(seed, n=3000)
        pr = _to_cuda(_problem(P, sup, cfg, sort=True))
        segs = problem_segments(pr.corners.corner_idx, pr.labels, pr.corners.num_params, tile=4096)
        probs.append(SolverProblem(pr.points, pr.corners, pr.labels, pr.dts, pr.origins, pr.time_offsets,
                                   pr.weights, pr.reg_scale, segments=segs))
    a, b = _solve(probs, cfg), _solve(probs, cfg)
    alone = _solve([probs[1]], cfg)
    for k in range(len(probs)):
        _assert_same_problem(a, k, b, k)
    _assert_same_problem(alone, 0, a, 1)

