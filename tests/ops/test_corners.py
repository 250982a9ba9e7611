"""Compact corner gather/scatter: vs reference, adjointness, gradcheck, opcheck, errors."""

import pytest
import torch

from floxels_ext import ops
from floxels_ext.reference import ops as reference

F = torch.ops.floxels


def _random(n, m, c, dtype, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    params = torch.randn(m, c, generator=g, dtype=dtype)
    idx = torch.randint(0, max(m, 1), (n, 8), generator=g, dtype=torch.int32)
    w = torch.rand(n, 8, generator=g, dtype=dtype)
    vals = torch.randn(n, c, generator=g, dtype=dtype)
    return [t.to(device) for t in (params, idx, w, vals)]


@pytest.mark.parametrize("n,m,c", [(0, 5, 3), (1, 1, 3), (257, 40, 3), (5000, 300, 1), (20000, 3000, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_reference(n, m, c, dtype):
    params, idx, w, vals = _random(n, m, c, dtype, seed=n + m)
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(F.corner_gather(params, idx, w), reference.corner_gather(params, idx, w), **tol)
    torch.testing.assert_close(F.corner_scatter(vals, idx, w, m), reference.corner_scatter(vals, idx, w, m), **tol)


def test_adjoint():
    params, idx, w, vals = _random(3000, 200, 3, torch.float64, seed=3)
    lhs = (F.corner_scatter(vals, idx, w, 200) * params).sum()
    rhs = (vals * F.corner_gather(params, idx, w)).sum()
    torch.testing.assert_close(lhs, rhs)


def test_gradcheck():
    params, idx, w, vals = _random(40, 12, 3, torch.float64, seed=4)
    params.requires_grad_(True)
    vals.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: F.corner_gather(p, idx, w), (params,))
    assert torch.autograd.gradcheck(lambda v: F.corner_scatter(v, idx, w, 12), (vals,))


def test_opcheck():
    params, idx, w, vals = _random(64, 20, 3, torch.float32, seed=5)
    torch.library.opcheck(F.corner_gather, (params.requires_grad_(True), idx, w))
    torch.library.opcheck(F.corner_scatter, (vals.requires_grad_(True), idx, w, 20))


def test_compact_corners_equals_dense_gather():
    g = torch.Generator().manual_seed(6)
    pts = torch.rand(500, 3, generator=g, dtype=torch.float64) * torch.tensor([9.0, 7.0, 3.0]) - 1.0
    origin, shape = [0.0, 0.0, 0.0], [5, 14, 16]  # some points lie outside: border clamping
    cc = ops.compact_corners(pts, origin, 0.5, shape)
    params = torch.randn(cc.num_params, 3, dtype=torch.float64, generator=g)
    dense = cc.to_dense(params)
    torch.testing.assert_close(F.corner_gather(params, cc.corner_idx, cc.corner_w),
                               reference.trilinear_gather(dense, pts, origin, 0.5))


def test_bad_inputs():
    params, idx, w, vals = _random(10, 5, 3, torch.float32)
    with pytest.raises(RuntimeError, match="int32"):
        F.corner_gather(params, idx.long(), w)
    with pytest.raises(RuntimeError, match="outside"):
        F.corner_gather(params, idx + 100, w)
    with pytest.raises(RuntimeError, match="corner_w"):
        F.corner_gather(params, idx, w.double())
    with pytest.raises(RuntimeError, match="corner_idx"):
        F.corner_scatter(vals, idx[:5], w[:5], 5)


@pytest.mark.cuda
def test_cuda_matches_cpu():
    params, idx, w, vals = _random(30000, 4000, 3, torch.float32, seed=7)
    out = F.corner_gather(params.cuda(), idx.cuda(), w.cuda()).cpu()
    torch.testing.assert_close(out, F.corner_gather(params, idx, w))
    out = F.corner_scatter(vals.cuda(), idx.cuda(), w.cuda(), 4000).cpu()
    torch.testing.assert_close(out, F.corner_scatter(vals, idx, w, 4000), rtol=1e-4, atol=1e-4)
