"""problem_setup (the optimiser's per-target tables) and stage_points (host staging of
scans): op vs reference exactly, both renumbering paths, edge sizes, errors, CPU vs CUDA,
and the estimator's staged upload."""

import numpy as np
import pytest
import torch

from floxels_ext import Floxels, FloxelsConfig, ops
from floxels_ext.reference import ops as reference

F = torch.ops.floxels


def _cloud(n, seed, labels=True, extent=(10.0, 6.0, 2.0), dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    p = (torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor(extent, dtype=torch.float64) - 1).to(dtype)
    lab = torch.randint(-1, 6, (n,), generator=g) if labels else None
    return p, lab


def _assert_same(a, b):
    assert len(a) == len(b) == 10
    for k, (x, y) in enumerate(zip(a, b)):
        if isinstance(x, int):
            assert x == y, k
        else:
            assert x.dtype == y.dtype and x.shape == y.shape, (k, x.dtype, y.dtype, x.shape, y.shape)
            assert torch.equal(x, y), k


@pytest.mark.parametrize("n", [0, 1, 2, 31, 33, 1000, 5000])
@pytest.mark.parametrize("labels", [True, False])
@pytest.mark.parametrize("tile", [1, 32, 10**9])
def test_problem_setup_matches_reference(n, labels, tile):
    p, lab = _cloud(n, n + tile, labels)
    args = (p, lab, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], tile)
    _assert_same(F.problem_setup(*args), reference.problem_setup(*args))


def test_problem_setup_sparse_lattice_and_clamping():
    # a lattice far larger than the points (renumbered through torch.unique), points outside
    # it (clamped), float64 points
    p, lab = _cloud(300, 7, True, extent=(100.0, 100.0, 100.0), dtype=torch.float64)
    args = (p, lab, [0.0, 0.0, 0.0], 0.5, [150, 201, 190], 32)
    _assert_same(F.problem_setup(*args), reference.problem_setup(*args))


def test_problem_setup_tables_are_consistent():
    p, lab = _cloud(4000, 3)
    st = ops.problem_setup(p, lab, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32)
    assert torch.equal(st.points, p[st.order]) and torch.equal(st.labels, lab[st.order])
    key = st.labels.long() * 10**6 + st.corners.vertices[st.corners.corner_idx.long()].min(1).values
    assert bool((key[1:] >= key[:-1]).all())  # sorted by (label, cell)
    seg_ptr, vtx_ptr, vtx_entry = st.segments
    assert seg_ptr[0] == 0 and seg_ptr[-1] == 4000 and bool((seg_ptr[1:] > seg_ptr[:-1]).all())
    assert vtx_ptr[-1] == vtx_entry.numel() == 8 * (seg_ptr.numel() - 1)
    assert st.num_clusters == int(lab.max()) + 1
    # compact corners reproduce the dense lattice indices
    cc = ops.compact_corners(st.points, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24])
    assert torch.equal(cc.vertices, st.corners.vertices) and torch.equal(cc.corner_idx, st.corners.corner_idx)
    assert torch.equal(cc.corner_w, st.corners.corner_w)


def test_problem_setup_errors():
    p, lab = _cloud(10, 0)
    with pytest.raises(RuntimeError, match="points must be"):
        F.problem_setup(p[:, :2], lab, [0.0, 0.0, 0.0], 0.5, [2, 2, 2], 32)
    with pytest.raises(RuntimeError, match="labels must be"):
        F.problem_setup(p, lab[:5], [0.0, 0.0, 0.0], 0.5, [2, 2, 2], 32)
    with pytest.raises(RuntimeError, match="tile"):
        F.problem_setup(p, lab, [0.0, 0.0, 0.0], 0.5, [2, 2, 2], 0)
    with pytest.raises(RuntimeError, match="spacing"):
        F.problem_setup(p, lab, [0.0, 0.0, 0.0], 0.0, [2, 2, 2], 32)


def test_problem_setup_opcheck():
    p, lab = _cloud(200, 1)
    torch.library.opcheck(F.problem_setup, (p, lab, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32),
                          test_utils=("test_schema", "test_autograd_registration"))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stage_points(dtype):
    p, _ = _cloud(70001, 2, dtype=dtype)
    out = torch.empty(p.numel())
    (lo, hi, finite), = ops.stage_points([p], [out])
    assert finite and torch.equal(out.view(-1, 3), p.float())
    assert lo == p.float().min(0).values.double().tolist() and hi == p.float().max(0).values.double().tolist()
    for row in (12345, 70000):  # inside the vectorised blocks and in the tail
        for bad in (float("nan"), float("inf"), -float("inf")):
            q = p.clone()
            q[row, 1] = bad
            assert not ops.stage_points([q], [out])[0][2]
    # float64 values beyond float32's range become inf: not finite either
    big = torch.tensor([[1e300, 0.0, 0.0]], dtype=torch.float64)
    assert not ops.stage_points([big], [torch.empty(3)])[0][2]
    assert ops.stage_points([p[:0]], [torch.empty(0)])[0][2]


def test_stage_points_several_scans():
    # a thread per scan: each scan's copy and bounds as if staged alone
    scans = [_cloud(n, n)[0] for n in (5, 0, 40000, 33333)]
    scans[2][7, 0] = float("nan")
    outs = [torch.empty(s.numel()) for s in scans]
    res = ops.stage_points(scans, outs)
    for s, o, (lo, hi, finite) in zip(scans, outs, res):
        assert torch.equal(o, s.reshape(-1)) or torch.isnan(s).any()
        assert finite == bool(torch.isfinite(s).all())
        if finite and s.shape[0]:
            assert lo == s.min(0).values.double().tolist() and hi == s.max(0).values.double().tolist()
    assert ops.stage_points([], []) == []


def test_stage_points_errors():
    p, _ = _cloud(10, 0)
    with pytest.raises(RuntimeError, match="out must be"):
        ops.stage_points([p], [torch.empty(29)])
    with pytest.raises(RuntimeError, match="points must be"):
        ops.stage_points([p.to(torch.int32)], [torch.empty(30)])
    with pytest.raises(RuntimeError, match="outputs"):
        F.stage_points([p, p], [torch.empty(30)])


@pytest.mark.cuda
@pytest.mark.parametrize("labels", [True, False])
def test_problem_setup_cuda_matches_cpu(labels):
    p, lab = _cloud(20000, 5, labels)
    args = ([-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32)
    a = F.problem_setup(p.cuda(), lab.cuda() if labels else None, *args)
    b = F.problem_setup(p, lab, *args)
    _assert_same([x.cpu() if isinstance(x, torch.Tensor) else x for x in a], b)


@pytest.mark.cuda
def test_staged_upload_matches_device_input():
    # numpy scans go through page-locked staging (bounds from the host); CUDA tensors through
    # the device checks: same flow. Reusing the staging buffers across calls, with other
    # scans in between, changes nothing.
    rng = np.random.default_rng(0)
    scans = [(rng.random((3000, 3)) * [20, 10, 2]).astype(np.float32) for _ in range(3)]
    other = [(rng.random((5000, 3)) * [30, 10, 2]).astype(np.float32) for _ in range(3)]
    cfg = FloxelsConfig(max_iters=30, patience=10**9)
    a = Floxels(cfg, "cuda").fit(scans, 1)
    Floxels(cfg, "cuda").fit(other, 1)
    b = Floxels(cfg, "cuda").fit(scans, 1)
    c = Floxels(cfg, "cuda").fit([torch.from_numpy(s).cuda() for s in scans], 1)
    # (float atomics make GPU runs differ in the last bits, which Adam's normalised steps
    # can grow on near-zero gradients: compare loosely, as a staging mix-up would differ by
    # metres)
    for other_flow in (b.flow, c.flow.cpu().numpy()):
        np.testing.assert_allclose(a.flow, other_flow, atol=1e-2)
        assert np.abs(a.flow - other_flow).mean() < 1e-4
    # a NaN row in a staged scan: dropped with a warning, NaN flow in the target
    bad = [s.copy() for s in scans]
    bad[1][7] = np.nan
    with pytest.warns(UserWarning, match="dropping 1 point"):
        r = Floxels(cfg, "cuda").fit(bad, 1)
    assert np.isnan(r.flow[7]).all() and np.isfinite(np.delete(r.flow, 7, 0)).all()


@pytest.mark.cuda
def test_staging_buffers_are_reused_by_size():
    # uploads larger than the smallest staging buffer, of slowly growing sizes (ground returns),
    # reuse buffers once their copies have run: no new page-locked memory per upload; a small
    # upload takes the smallest free buffer, leaving the large one to the next large upload
    from floxels_ext.estimator import schedule as S

    dev = torch.device("cuda")
    stager = S._STAGER
    made = []
    orig = torch.empty

    def counting_empty(*a, **k):
        if k.get("pin_memory"):
            made.append(a)
        return orig(*a, **k)

    sizes = [110_000 + 500 * k for k in range(12)]  # rows; 330k+ floats, above the 2^18 minimum
    torch.empty = counting_empty
    try:
        for k, n in enumerate(sizes):
            t = torch.full((n, 3), float(k))
            out = S.upload(t, dev)
            small = S.upload(torch.ones(1000, 3), dev)
            torch.cuda.synchronize()
            assert torch.equal(out.cpu(), t) and torch.equal(small.cpu(), torch.ones(1000, 3))
    finally:
        torch.empty = orig
    assert len(made) <= 2, f"{len(made)} page-locked buffers for {len(sizes)} uploads"
    assert all(b.numel() >= 1 << 18 for b, _ in stager.free[S._index(dev)])
