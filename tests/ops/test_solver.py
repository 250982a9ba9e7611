"""floxels::solver_run (the device-resident optimiser loop) against a plain Python loop over
the single-purpose ops, multi-problem packing, early stopping, CUDA vs CPU, bad input."""

import math

import numpy as np
import pytest
import torch

from floxels_ext import FloxelsConfig
from floxels_ext.estimator.early_stopping import EarlyStopping
from floxels_ext.ops import compact_corners, dbscan, distance_transform, grid_for_points
from floxels_ext.ops.solver import PackedProblems, SolverProblem, problem_segments
from floxels_ext.estimator.solver_run import run_solver

F = torch.ops.floxels


def _scene(seed, n=600, shift=(0.3, 0.1, 0.0)):
    """A few boxes of points; the support scans are the target moved by t * shift."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(6, 3, generator=g) * torch.tensor([12.0, 12.0, 2.0])
    P = (centres[torch.randint(0, 6, (n,), generator=g)] + 0.6 * torch.rand(n, 3, generator=g)).float()
    moving = P[:, 0] < 6.0
    supports = {}
    for t in (-2, -1, 1, 2):
        Q = P.clone()
        Q[moving] += t * torch.tensor(shift)
        supports[t] = Q
    return P, supports


def _problem(P, supports, cfg, labels=True, sort=False):
    """One problem; ``sort``: order the points by (label, voxel) as the estimator does, which
    makes the solver's segments long (unsorted points give mostly one-point segments)."""
    dts, origins, offsets, weights = [], [], [], []
    for t, Q in supports.items():
        d, o = distance_transform(Q, cfg.dt_cell, cfg.dt_padding)
        dts.append(d)
        origins.append(o)
        offsets.append(float(t))
        weights.append(cfg.lambda_d * cfg.time_weight(t))
    go, gs = grid_for_points(P, cfg.voxel_size, cfg.voxel_size)
    corners = compact_corners(P, go, cfg.voxel_size, gs)
    lab = dbscan(P, cfg.dbscan_eps, cfg.dbscan_min_samples) if labels else None
    if sort:
        key = corners.corner_idx[:, 0].long() + (lab + 1) * corners.num_params if lab is not None \
            else corners.corner_idx[:, 0].long()
        order = torch.argsort(key)
        P = P[order].contiguous()
        corners = compact_corners(P, go, cfg.voxel_size, gs)
        lab = lab[order].contiguous() if lab is not None else None
    return SolverProblem(P, corners, lab, dts, origins, offsets, weights, float(len(supports)))


def python_loop(pr: SolverProblem, cfg: FloxelsConfig):
    """The optimiser written plainly with the single-purpose ops (the estimator's loop before
    the fused op): the definition the fused loop must reproduce."""
    idx, cw = pr.corners.corner_idx, pr.corners.corner_w
    n, M = pr.points.shape[0], pr.corners.num_params
    theta = torch.zeros(M, 3)
    m, v = torch.zeros_like(theta), torch.zeros_like(theta)
    best = theta.clone()
    stopper = EarlyStopping(cfg.patience, cfg.min_delta)
    ncl = int(pr.labels.max()) + 1 if pr.labels is not None else 0
    flat_origins = [x for o in pr.origins for x in o]
    losses = []
    b1, b2 = cfg.adam_betas
    for it in range(cfg.max_iters):
        f = F.corner_gather(theta, idx, cw)
        loss, g = F.dt_loss_fwd_bwd(pr.points, f, pr.dts, flat_origins, cfg.dt_cell, pr.time_offsets,
                                    pr.weights, cfg.truncation)
        loss = loss.double()
        if cfg.truncation_mode == "clamp":  # truncated samples count as the truncation
            for d, o, t, w in zip(pr.dts, pr.origins, pr.time_offsets, pr.weights):
                dv = F.trilinear_gather(d[None], (pr.points + t * f).contiguous(), list(o), cfg.dt_cell)[:, 0]
                loss = loss + w * cfg.truncation * float((~(dv < cfg.truncation)).sum()) / n
        if cfg.cluster_loss and ncl > 0:
            lc, gc = F.cluster_consistency_fwd_bwd(f, pr.labels, ncl)
            if cfg.cluster_loss_mean == "clustered":  # op: mean over all n points
                k = n / max(int((pr.labels >= 0).sum()), 1)
                lc, gc = lc * k, gc * k
            loss = loss + pr.reg_scale * cfg.lambda_c * lc.double()
            g = g + pr.reg_scale * cfg.lambda_c * gc
        if cfg.flow_norm_loss:
            lam = pr.reg_scale * cfg.lambda_g(it)
            norms = torch.linalg.vector_norm(f, dim=1)
            loss = loss + lam * norms.double().sum() / n
            g = g + lam / n * f / norms.clamp_min(1e-12)[:, None]
        losses.append(float(loss))
        is_best, stop = stopper.update(losses[-1], it)
        if is_best:
            best = theta.clone()
        if stop or it == cfg.max_iters - 1:
            break
        grad = F.corner_scatter(g, idx, cw, M)
        t = it + 1
        m.lerp_(grad, 1 - b1)
        v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        denom = (v.sqrt() / math.sqrt(1 - b2 ** t)).add_(cfg.adam_eps)
        theta.addcdiv_(m, denom, value=-cfg.lr_at(it) / (1 - b1 ** t))
    return best, losses, stopper.best_iter


@pytest.mark.parametrize("sort", [False, True])
@pytest.mark.parametrize("cluster", [True, False])
def test_matches_python_loop(cluster, sort):
    cfg = FloxelsConfig(max_iters=6, cluster_loss=cluster)
    P, sup = _scene(0)
    pr = _problem(P, sup, cfg, labels=cluster, sort=sort)
    best_ref, losses_ref, best_iter_ref = python_loop(pr, cfg)
    packed = PackedProblems([pr], cfg)
    run_solver(packed)
    np.testing.assert_allclose(packed.losses(0), losses_ref, rtol=2e-5)
    assert packed.best_iter(0) == best_iter_ref
    torch.testing.assert_close(packed.best_params(0), best_ref, rtol=1e-4, atol=1e-5)


READINGS = [dict(lr_milestones=(2, 4), lr_gamma=0.5), dict(truncation_mode="clamp", truncation=0.2),
            dict(cluster_loss_mean="clustered"),
            dict(lr_milestones=(1,), lr_gamma=0.3, truncation_mode="clamp", truncation=0.2,
                 cluster_loss_mean="clustered")]


@pytest.mark.parametrize("reading", READINGS, ids=lambda r: ",".join(r))
def test_readings_match_python_loop(reading):
    """Each faithfulness reading (FloxelsConfig) in the fused solver = the plain loop."""
    cfg = FloxelsConfig(max_iters=7, **reading)
    P, sup = _scene(2)
    # isolated points: DBSCAN noise, so "clustered" differs from "all"
    noise = torch.tensor([[x, -4.0 - 1.5 * (x % 2), 1.0] for x in range(0, 30, 2)], dtype=torch.float32)
    P = torch.cat([P, noise])
    sup = {t: torch.cat([Q, noise]) for t, Q in sup.items()}
    pr = _problem(P, sup, cfg, sort=True)
    assert int((pr.labels < 0).sum()) >= 10
    best_ref, losses_ref, best_iter_ref = python_loop(pr, cfg)
    packed = PackedProblems([pr], cfg)
    run_solver(packed)
    np.testing.assert_allclose(packed.losses(0), losses_ref, rtol=2e-5)
    # (a component whose gradient is zero up to rounding may take Adam's +-lr step either way)
    close = torch.isclose(packed.best_params(0), best_ref, rtol=1e-4, atol=1e-5)
    assert close.float().mean() > 0.98
    # and the reading changes the optimisation (it is not silently ignored)
    base = PackedProblems([_problem(P, sup, FloxelsConfig(max_iters=7, truncation=cfg.truncation), sort=True)],
                          FloxelsConfig(max_iters=7, truncation=cfg.truncation))
    run_solver(base)
    assert not np.allclose(base.losses(0), packed.losses(0), rtol=1e-6, atol=0)


def test_early_stopping_and_lowest_loss():
    cfg = FloxelsConfig(max_iters=80, patience=5, min_delta=1e-3, lr=0.3)
    P, sup = _scene(1)
    packed = PackedProblems([_problem(P, sup, cfg)], cfg)
    run_solver(packed)
    losses = packed.losses(0)
    es = EarlyStopping(cfg.patience, cfg.min_delta)
    for it, l in enumerate(losses):
        _, stop = es.update(l, it)
        assert stop == (it == len(losses) - 1) or it == cfg.max_iters - 1
    assert packed.best_iter(0) == int(np.argmin(losses)) == es.best_iter


def test_several_problems_equal_each_alone():
    """Packed problems do not interact: on the CPU (deterministic) results are identical."""
    cfg = FloxelsConfig(max_iters=25, patience=10)
    probs = []
    for seed, shift in ((2, (0.3, 0.0, 0.0)), (3, (0.0, -0.4, 0.0)), (4, (0.2, 0.2, 0.0))):
        P, sup = _scene(seed, n=400 + 100 * seed, shift=shift)
        probs.append(_problem(P, sup, cfg, labels=seed != 3))
    together = PackedProblems(probs, cfg)
    run_solver(together)
    for b, pr in enumerate(probs):
        alone = PackedProblems([pr], cfg)
        run_solver(alone)
        assert together.losses(b) == alone.losses(0)
        assert torch.equal(together.best_params(b), alone.best_params(0))


def test_deterministic_across_thread_counts():
    cfg = FloxelsConfig(max_iters=15)
    P, sup = _scene(5, n=5000)
    pr = _problem(P, sup, cfg)
    out = []
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            packed = PackedProblems([pr], cfg)
            run_solver(packed)
            out.append((packed.losses(0), packed.best_params(0).clone()))
    finally:
        torch.set_num_threads(old)
    assert out[0][0] == out[1][0] and torch.equal(out[0][1], out[1][1])


def test_bad_inputs_raise_clear_errors():
    cfg = FloxelsConfig(max_iters=3)
    P, sup = _scene(6, n=200)
    packed = PackedProblems([_problem(P, sup, cfg)], cfg)
    packed.corner_idx[3, 2] = packed.theta.shape[0] + 7
    with pytest.raises(RuntimeError, match="corner_idx"):
        packed.run(1)
    packed = PackedProblems([_problem(P, sup, cfg)], cfg)
    packed.labels = packed.labels.to(torch.int64)
    with pytest.raises(RuntimeError, match="labels must be Int"):
        packed.run(1)
    packed = PackedProblems([_problem(P, sup, cfg, sort=True)], cfg)
    seg = int((packed.seg_ptr[1:] - packed.seg_ptr[:-1]).argmax())  # a segment of several points
    packed.labels[int(packed.seg_ptr[seg]) + 1] += 1
    with pytest.raises(RuntimeError, match="segment"):
        packed.run(1)
    packed = PackedProblems([_problem(P, sup, cfg)], cfg)
    packed.point_ranges = [0, 5]
    with pytest.raises(RuntimeError, match="point_ranges"):
        packed.run(1)
    with pytest.raises(ValueError, match="problems"):
        PackedProblems([], cfg)


def test_opcheck():
    cfg = FloxelsConfig(max_iters=4)
    P, sup = _scene(7, n=150)
    p = PackedProblems([_problem(P, sup, cfg)], cfg)
    torch.library.opcheck(torch.ops.floxels.solver_run.default, p.op_args(2),
                          test_utils=("test_schema", "test_faketensor"))


def _to_cuda(pr: SolverProblem) -> SolverProblem:
    dev = lambda t: t.cuda() if t is not None else None  # noqa: E731
    c = pr.corners
    return SolverProblem(pr.points.cuda(), type(c)(dev(c.corner_idx), dev(c.corner_w), dev(c.vertices), c.grid_shape),
                         dev(pr.labels), [d.cuda() for d in pr.dts], pr.origins, pr.time_offsets, pr.weights,
                         pr.reg_scale)


@pytest.mark.cuda
@pytest.mark.parametrize("cluster", [True, False])
@pytest.mark.parametrize("chunk", [16, None])
def test_cuda_matches_cpu(chunk, cluster):
    cfg = FloxelsConfig(max_iters=120, patience=30, cluster_loss=cluster)
    probs_cpu = []
    for seed in (8, 9):
        P, sup = _scene(seed, n=3000)
        probs_cpu.append(_problem(P, sup, cfg, labels=cluster, sort=seed == 9))
    cpu = PackedProblems(probs_cpu, cfg)
    run_solver(cpu)
    gpu = PackedProblems([_to_cuda(pr) for pr in probs_cpu], cfg)
    run_solver(gpu, chunk=chunk)  # chunks of 16, or the default (one launch where the op loops)
    for b in range(2):
        lc, lg = cpu.losses(b), gpu.losses(b)
        # Same rules, float32 sums in another order (the CUDA solver forms cluster means from
        # the vertex parameters): the first losses agree to rounding; after that Adam's first
        # step (lr * sign(g)) amplifies rounding-level gradients of either sign, so the
        # trajectories differ slightly and only the outcome is compared.
        np.testing.assert_allclose(lg[0], lc[0], rtol=1e-5)
        np.testing.assert_allclose(lg[1], lc[1], rtol=1e-3)
        assert min(lg) == pytest.approx(min(lc), rel=3e-2)
        assert gpu.best_iter(b) == int(np.argmin(lg))
        flow_c = F.corner_gather(cpu.best_params(b), probs_cpu[b].corners.corner_idx, probs_cpu[b].corners.corner_w)
        flow_g = F.corner_gather(gpu.best_params(b), gpu.corner_idx[gpu.point_ranges[b]:gpu.point_ranges[b + 1]]
                                 - gpu.vertex_ranges[b],
                                 gpu.corner_w[gpu.point_ranges[b]:gpu.point_ranges[b + 1]]).cpu()
        assert (flow_g - flow_c).norm(dim=1).mean() < 0.1  # same outcome (shifts are 0.3 m)


@pytest.mark.cuda
@pytest.mark.parametrize("persistent", ["0", "1"])  # two-kernel path and persistent loop kernel
@pytest.mark.parametrize("reading", READINGS, ids=lambda r: ",".join(r))
def test_cuda_readings_match_cpu(monkeypatch, persistent, reading):
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    cfg = FloxelsConfig(max_iters=8, **reading)
    P, sup = _scene(2)
    noise = torch.tensor([[x, -4.0 - 1.5 * (x % 2), 1.0] for x in range(0, 30, 2)], dtype=torch.float32)
    P = torch.cat([P, noise])
    sup = {t: torch.cat([Q, noise]) for t, Q in sup.items()}
    pr = _problem(P, sup, cfg, sort=True)
    cpu = PackedProblems([pr], cfg)
    run_solver(cpu)
    gpu = PackedProblems([_to_cuda(pr)], cfg)
    run_solver(gpu)
    # first losses to rounding; later ones drift with Adam's sign steps (see test_cuda_matches_cpu)
    np.testing.assert_allclose(gpu.losses(0)[:2], cpu.losses(0)[:2], rtol=1e-3)
    np.testing.assert_allclose(gpu.losses(0), cpu.losses(0), rtol=5e-2)


@pytest.mark.cuda
@pytest.mark.parametrize("chunk", [7, None])  # None: the whole run in one persistent launch
@pytest.mark.parametrize("persistent", ["1", "0"])
def test_cuda_early_stopping_per_problem(monkeypatch, persistent, chunk):
    """Problems of one call stop on their own (other patience outcomes, odd chunk sizes), and
    the recorded losses follow the stopping rule exactly."""
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    cfg = FloxelsConfig(max_iters=90, patience=6, min_delta=1e-3, lr=0.3)
    probs = []
    for seed, shift in ((10, (0.3, 0.1, 0.0)), (11, (0.0, 0.0, 0.0)), (12, (-0.5, 0.2, 0.0))):
        P, sup = _scene(seed, n=1500, shift=shift)
        probs.append(_to_cuda(_problem(P, sup, cfg, sort=True)))
    gpu = PackedProblems(probs, cfg)
    run_solver(gpu, chunk=chunk)
    for b in range(3):
        losses = gpu.losses(b)
        assert all(math.isfinite(v) for v in losses)
        es = EarlyStopping(cfg.patience, cfg.min_delta)
        for it, l in enumerate(losses):
            _, stop = es.update(l, it)
            assert stop == (it == len(losses) - 1) or it == cfg.max_iters - 1
        assert gpu.best_iter(b) == int(np.argmin(losses)) == es.best_iter


@pytest.mark.cuda
@pytest.mark.parametrize("max_grid", [None, 5])
@pytest.mark.parametrize("cluster", [True, False])
def test_cuda_persistent_matches_two_kernel(monkeypatch, cluster, max_grid):
    """The persistent loop (grid barriers instead of kernel boundaries) follows the same
    trajectory as the two-kernel iteration: same first losses, same outcome. A grid of 5
    blocks makes every block walk many point and vertex blocks, of several problems."""
    if max_grid is not None:
        monkeypatch.setenv("FLOXELS_SOLVER_MAX_GRID", str(max_grid))
    cfg = FloxelsConfig(max_iters=60, patience=1000, cluster_loss=cluster)
    probs = []
    for seed in range(20, 28):  # 8 problems x 4 DTs: the most distinct DTs one call takes
        P, sup = _scene(seed, n=2500 + 40 * seed)
        probs.append(_to_cuda(_problem(P, sup, cfg, labels=cluster, sort=True)))
    runs = {}
    for mode in ("0", "1"):
        monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", mode)
        packed = PackedProblems(probs, cfg)
        run_solver(packed)
        runs[mode] = packed
    for b in range(len(probs)):
        l0, l1 = runs["0"].losses(b), runs["1"].losses(b)
        assert len(l0) == len(l1) == cfg.max_iters
        np.testing.assert_allclose(l1[:2], l0[:2], rtol=1e-4)
        assert min(l1) == pytest.approx(min(l0), rel=3e-2)
        d = (runs["1"].best_params(b) - runs["0"].best_params(b)).norm(dim=1)
        assert d.mean() < 0.05



@pytest.mark.cuda
@pytest.mark.parametrize("persistent", ["1", "0"])
def test_cuda_segments_across_tiles(monkeypatch, persistent):
    """Segment tables whose segments cross the 32-point tiles of the CUDA point phase (built
    with tiles of 4096 points, as another caller might) take the per-tile partial rows: same
    losses as the tiled tables the estimator builds, up to the order of the segment sums."""
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", persistent)
    cfg = FloxelsConfig(max_iters=40, patience=1000)
    P, sup = _scene(31, n=3000)
    pr = _to_cuda(_problem(P, sup, cfg, sort=True))
    tables = {tile: problem_segments(pr.corners.corner_idx, pr.labels, pr.corners.num_params, tile=tile)
              for tile in (32, 4096)}
    assert tables[32][0].shape[0] > tables[4096][0].shape[0]  # the tiles split segments
    losses = {}
    for tile, segs in tables.items():
        q = SolverProblem(pr.points, pr.corners, pr.labels, pr.dts, pr.origins, pr.time_offsets, pr.weights,
                          pr.reg_scale, segments=segs)
        packed = PackedProblems([q], cfg)
        run_solver(packed)
        losses[tile] = packed.losses(0)
    # the segment sums' order differs (per tile), so the trajectories drift apart by rounding only
    np.testing.assert_allclose(losses[4096][:3], losses[32][:3], rtol=1e-4)
    assert min(losses[4096]) == pytest.approx(min(losses[32]), rel=1e-2)


def test_has_profiling_reports_the_build():
    """torch.ops.floxels.has_profiling() says whether this library holds the measurement-only
    solver code (CMake option FLOXELS_PROFILING); tools/profile_solver.py relies on it."""
    assert isinstance(F.has_profiling(), bool)


def _measured_losses(monkeypatch, env):
    monkeypatch.setenv("FLOXELS_SOLVER_PERSISTENT", "1")  # the switches act on the loop kernel
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    cfg = FloxelsConfig(max_iters=20, patience=1000)
    P, sup = _scene(41, n=2000)
    packed = PackedProblems([_to_cuda(_problem(P, sup, cfg, sort=True))], cfg)
    run_solver(packed)
    return packed.losses(0)


@pytest.mark.cuda
def test_cuda_release_build_ignores_measurement_switches(monkeypatch):
    """A release build has no traced loop: FLOXELS_SOLVER_TRACE / FLOXELS_SOLVER_SKIP change
    nothing (in a profiling build, skip mask 8 leaves the loss reduction out)."""
    if F.has_profiling():
        pytest.skip("profiling build: the measurement switches are live")
    plain = _measured_losses(monkeypatch, {})
    measured = _measured_losses(monkeypatch, {"FLOXELS_SOLVER_TRACE": "1", "FLOXELS_SOLVER_SKIP": "127"})
    np.testing.assert_allclose(measured[:2], plain[:2], rtol=1e-4)  # float atomics: rounding only
    assert min(measured) == pytest.approx(min(plain), rel=3e-2)


@pytest.mark.cuda
def test_cuda_profiling_build_skip_switch(monkeypatch):
    """A profiling build's traced loop honours FLOXELS_SOLVER_SKIP: mask 8 leaves the loss
    reduction out, so every recorded loss is 0 (measurement only)."""
    if not F.has_profiling():
        pytest.skip("release build: no traced loop")
    assert min(_measured_losses(monkeypatch, {})) > 0
    assert _measured_losses(monkeypatch, {"FLOXELS_SOLVER_TRACE": "1", "FLOXELS_SOLVER_SKIP": "8"})[0] == 0.0
