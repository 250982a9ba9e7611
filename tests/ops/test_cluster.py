"""cluster_mean / cluster_consistency_loss (+ backward, fused fwd_bwd) vs the reference."""

import pytest
import torch

import floxels_ext  # noqa: F401
from floxels_ext import ops
from floxels_ext.reference import ops as R

OPS = torch.ops.floxels
DTYPES = [torch.float32, torch.float64]


def _tol(dtype):
    return dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)


def _data(n, c, k, dtype, seed, noise=True):
    gen = torch.Generator().manual_seed(seed)
    f = torch.randn(n, c, generator=gen, dtype=dtype)
    lab = torch.randint(-1 if noise else 0, max(k, 1), (n,), generator=gen)
    if k == 0:
        lab.fill_(-1)
    return f, lab


def _ref_grad(f, lab, k):
    if f.shape[0] == 0:  # the reference returns a constant 0 there
        return torch.zeros_like(f)
    fr = f.clone().requires_grad_()
    R.cluster_consistency_loss(fr, lab, k).backward()
    return fr.grad if fr.grad is not None else torch.zeros_like(f)


CASES = [(0, 3, 4), (1, 3, 1), (1, 1, 2), (50, 1, 7), (300, 3, 20), (40000, 3, 500), (40000, 3, 50000),
         (1000, 3, 0)]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n,c,k", CASES)
def test_match_reference(dtype, n, c, k):
    f, lab = _data(n, c, k, dtype, seed=n + 7 * k)
    torch.testing.assert_close(OPS.cluster_mean(f, lab, k), R.cluster_mean(f, lab, k), **_tol(dtype))
    ref_loss = R.cluster_consistency_loss(f, lab, k)
    torch.testing.assert_close(OPS.cluster_consistency_loss(f, lab, k), ref_loss, **_tol(dtype))
    ref_grad = _ref_grad(f, lab, k)
    g = torch.tensor(1.7, dtype=dtype)
    torch.testing.assert_close(OPS.cluster_consistency_loss_backward(g, f, lab, k), 1.7 * ref_grad, **_tol(dtype))
    loss, grad = OPS.cluster_consistency_fwd_bwd(f, lab, k)
    torch.testing.assert_close(loss, ref_loss, **_tol(dtype))
    torch.testing.assert_close(grad, ref_grad, **_tol(dtype))


def test_identical_flow_gives_zero_gradient():
    f = torch.ones(10, 3, dtype=torch.float64)
    lab = torch.tensor([0, 0, 0, 1, 1, -1, 2, 2, 2, 2])
    loss, grad = OPS.cluster_consistency_fwd_bwd(f, lab, 3)
    assert loss.item() == 0.0 and torch.all(grad == 0) and torch.isfinite(grad).all()


def test_gradcheck():
    f, lab = _data(30, 3, 5, torch.float64, seed=1)
    f.requires_grad_()
    assert torch.autograd.gradcheck(lambda x: OPS.cluster_mean(x, lab, 5), (f,))
    assert torch.autograd.gradcheck(lambda x: OPS.cluster_consistency_loss(x, lab, 5), (f,))


def test_opcheck():
    f, lab = _data(30, 3, 5, torch.float64, seed=2)
    f.requires_grad_()
    torch.library.opcheck(OPS.cluster_mean, (f, lab, 5))
    torch.library.opcheck(OPS.cluster_consistency_loss, (f, lab, 5))
    torch.library.opcheck(OPS.cluster_consistency_loss_backward, (torch.tensor(0.5, dtype=torch.float64),
                                                                  f.detach(), lab, 5))
    torch.library.opcheck(OPS.cluster_consistency_fwd_bwd, (f.detach(), lab, 5))


def test_bad_inputs():
    f = torch.zeros(5, 3)
    lab = torch.tensor([0, 1, -1, 2, 0])
    with pytest.raises(ValueError, match="labels must lie"):
        ops.cluster_mean(f, torch.tensor([0, 1, 3, 0, 0]), 3)
    with pytest.raises(ValueError, match="labels must lie"):
        ops.cluster_consistency_loss(f, torch.tensor([0, -2, 0, 0, 0]), 3)
    with pytest.raises(TypeError, match="int64"):
        ops.cluster_mean(f, lab.int(), 3)
    with pytest.raises(ValueError, match="labels"):
        ops.cluster_mean(f, lab[:4], 3)
    with pytest.raises(ValueError, match="flow"):
        ops.cluster_consistency_loss(f[:, 0], lab, 3)
    with pytest.raises(TypeError):
        ops.cluster_consistency_fwd_bwd(f.int(), lab, 3)
    # the raw CPU ops check too: RuntimeError naming the problem, never a crash
    with pytest.raises(RuntimeError, match="labels must lie"):
        OPS.cluster_mean(f, torch.tensor([0, 1, 3, 0, 0]), 3)
    with pytest.raises(RuntimeError, match="labels must lie"):
        OPS.cluster_consistency_fwd_bwd(f, torch.tensor([0, 1, 7, 0, 0]), 3)
    with pytest.raises(RuntimeError, match="int64"):
        OPS.cluster_consistency_loss(f, lab.int(), 3)
    with pytest.raises(RuntimeError, match="float32 or float64"):
        OPS.cluster_mean(f.int(), lab, 3)
    with pytest.raises(RuntimeError, match="num_clusters"):
        OPS.cluster_mean(f, lab, -1)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("n,c,k", CASES)
def test_cpu_vs_cuda(dtype, n, c, k):
    f, lab = _data(n, c, k, dtype, seed=3 + n)
    if n > 100:  # a hot cluster: exercises the warp-aggregated atomics
        lab[: n // 3] = 0 if k > 0 else -1
    d = "cuda"
    tol = _tol(dtype) if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-5)
    fc, lc = f.to(d), lab.to(d)
    torch.testing.assert_close(OPS.cluster_mean(fc, lc, k).cpu(), OPS.cluster_mean(f, lab, k), **tol)
    torch.testing.assert_close(OPS.cluster_consistency_loss(fc, lc, k).cpu(),
                               OPS.cluster_consistency_loss(f, lab, k), **tol)
    g = torch.tensor(0.7, dtype=dtype)
    torch.testing.assert_close(OPS.cluster_consistency_loss_backward(g.to(d), fc, lc, k).cpu(),
                               OPS.cluster_consistency_loss_backward(g, f, lab, k), **tol)
    a, b = OPS.cluster_consistency_fwd_bwd(fc, lc, k), OPS.cluster_consistency_fwd_bwd(f, lab, k)
    torch.testing.assert_close(a[0].cpu(), b[0], **tol)
    torch.testing.assert_close(a[1].cpu(), b[1], **tol)
