"""trilinear_gather / trilinear_gather_backward / trilinear_scatter vs the reference."""

import zlib

import pytest
import torch
import torch.nn.functional as F

import floxels_ext  # noqa: F401  (registers torch.ops.floxels)
from floxels_ext import ops
from floxels_ext.reference import ops as R

OPS = torch.ops.floxels
DTYPES = [torch.float32, torch.float64]
SHAPES = [(3, 5, 6, 7), (1, 4, 3, 5), (2, 1, 4, 3), (3, 1, 1, 1), (1, 2, 1, 6)]


def _tol(dtype):
    return dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)


def _points(n, shape_zyx, origin, spacing, dtype, gen, margin=0.3):
    """Uniform points covering the lattice plus `margin` of its extent outside on every side."""
    Z, Y, X = shape_zyx
    ext = torch.tensor([max(X - 1, 1), max(Y - 1, 1), max(Z - 1, 1)], dtype=dtype) * spacing
    u = torch.rand(n, 3, generator=gen, dtype=dtype) * (1 + 2 * margin) - margin
    return torch.tensor(origin, dtype=dtype) + u * ext


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("n", [0, 1, 257, 6000])
def test_gather_scatter_match_reference(dtype, shape, n):
    # zlib, not hash(): str hashes are salted per process, which drew new data every run
    gen = torch.Generator().manual_seed(zlib.crc32(repr((str(dtype), shape, n)).encode()))
    C, Z, Y, X = shape
    origin, spacing = [0.3, -1.2, 0.7], 0.45
    grid = torch.randn(shape, generator=gen, dtype=dtype)
    pts = _points(n, (Z, Y, X), origin, spacing, dtype, gen)
    torch.testing.assert_close(OPS.trilinear_gather(grid, pts, origin, spacing),
                               R.trilinear_gather(grid, pts, origin, spacing), **_tol(dtype))
    vals = torch.randn(n, C, generator=gen, dtype=dtype)
    # a scatter sums up to n / cells terms per cell (hundreds here) in another order than the
    # reference: float32 rounding grows with the sum, so its tolerance is relative to that size
    tol = _tol(dtype) if dtype != torch.float32 else dict(rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(OPS.trilinear_scatter(vals, pts, origin, spacing, [Z, Y, X]),
                               R.trilinear_scatter(vals, pts, origin, spacing, (Z, Y, X)), **tol)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("need", [(True, True), (True, False), (False, True)])
def test_gather_backward_matches_reference_autograd(dtype, need):
    gen = torch.Generator().manual_seed(3)
    shape, origin, spacing = (3, 4, 5, 6), [0.0, 0.5, -0.5], 0.8
    grid = torch.randn(shape, generator=gen, dtype=dtype, requires_grad=True)
    pts = _points(3000, shape[1:], origin, spacing, dtype, gen).requires_grad_()
    gout = torch.randn(3000, 3, generator=gen, dtype=dtype)
    R.trilinear_gather(grid, pts, origin, spacing).backward(gout)
    gg, gp = OPS.trilinear_gather_backward(gout, grid.detach(), pts.detach(), origin, spacing, *need)
    if need[0]:
        torch.testing.assert_close(gg, grid.grad, **_tol(dtype))
    else:
        assert gg.numel() == 0
    if need[1]:
        torch.testing.assert_close(gp, pts.grad, **_tol(dtype))
    else:
        assert gp.numel() == 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_gather_equals_grid_sample_border(dtype):
    """Our gather == grid_sample(border, align_corners=True) on a 5D input, values and gradients."""
    gen = torch.Generator().manual_seed(7)
    C, Z, Y, X = 3, 6, 7, 9
    origin, spacing = [-1.0, 2.0, 0.5], 0.3
    grid = torch.randn(C, Z, Y, X, generator=gen, dtype=dtype)
    pts = _points(4000, (Z, Y, X), origin, spacing, dtype, gen, margin=0.5)
    lo = torch.tensor(origin, dtype=dtype)
    ext = torch.tensor([X - 1, Y - 1, Z - 1], dtype=dtype) * spacing
    norm = ((pts - lo) / ext * 2 - 1).view(1, 1, 1, -1, 3)
    g5 = grid[None].clone().requires_grad_()
    n5 = norm.clone().requires_grad_()
    ref = F.grid_sample(g5, n5, mode="bilinear", padding_mode="border", align_corners=True)
    ref = ref.view(C, -1).T
    ours = OPS.trilinear_gather(grid, pts, origin, spacing)
    torch.testing.assert_close(ours, ref, **_tol(dtype))
    gout = torch.randn_like(ref)
    ref.backward(gout)
    gg, gp = OPS.trilinear_gather_backward(gout, grid, pts, origin, spacing, True, True)
    torch.testing.assert_close(gg, g5.grad[0], **_tol(dtype))
    # chain rule through the normalisation: d norm / d p = 2 / ext
    gtol = _tol(dtype) if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(gp, n5.grad.view(-1, 3) * (2 / ext), **gtol)


def test_adjoint_identity():
    gen = torch.Generator().manual_seed(11)
    C, Z, Y, X = 3, 5, 8, 6
    origin, spacing = [0.0, 0.0, 0.0], 1.0
    G = torch.randn(C, Z, Y, X, generator=gen, dtype=torch.float64)
    for n in (1, 50, 20000):  # 20000 takes the sorted multithreaded scatter path
        p = _points(n, (Z, Y, X), origin, spacing, torch.float64, gen)
        v = torch.randn(n, C, generator=gen, dtype=torch.float64)
        lhs = (OPS.trilinear_scatter(v, p, origin, spacing, [Z, Y, X]) * G).sum()
        rhs = (v * OPS.trilinear_gather(G, p, origin, spacing)).sum()
        torch.testing.assert_close(lhs, rhs, rtol=1e-10, atol=1e-10)


def test_scatter_thread_count_independent():
    gen = torch.Generator().manual_seed(5)
    shape = (2, 6, 30, 40)
    p = _points(50000, shape[1:], [0, 0, 0], 1.0, torch.float32, gen)
    v = torch.randn(50000, 2, generator=gen)
    prev = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        a = OPS.trilinear_scatter(v, p, [0, 0, 0], 1.0, list(shape[1:]))
        b = OPS.trilinear_scatter(v, p, [0, 0, 0], 1.0, list(shape[1:]))
    finally:
        torch.set_num_threads(prev)
    assert torch.equal(a, b)
    torch.testing.assert_close(a, R.trilinear_scatter(v, p, [0, 0, 0], 1.0, shape[1:]), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("shape", [(2, 3, 4, 5), (1, 1, 3, 4)])
def test_gradcheck(shape):
    gen = torch.Generator().manual_seed(1)
    C, Z, Y, X = shape
    origin, spacing = [0.1, 0.2, 0.3], 0.7
    grid = torch.randn(shape, generator=gen, dtype=torch.float64, requires_grad=True)
    pts = _points(12, (Z, Y, X), origin, spacing, torch.float64, gen).requires_grad_()
    vals = torch.randn(12, C, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g, p: OPS.trilinear_gather(g, p, origin, spacing), (grid, pts))
    assert torch.autograd.gradcheck(lambda v, p: OPS.trilinear_scatter(v, p, origin, spacing, [Z, Y, X]),
                                    (vals, pts))


def test_opcheck():
    gen = torch.Generator().manual_seed(2)
    grid = torch.randn(2, 3, 4, 5, generator=gen, dtype=torch.float64, requires_grad=True)
    pts = _points(10, (3, 4, 5), [0, 0, 0], 0.5, torch.float64, gen).requires_grad_()
    vals = torch.randn(10, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    torch.library.opcheck(OPS.trilinear_gather, (grid, pts, [0.0, 0.0, 0.0], 0.5))
    torch.library.opcheck(OPS.trilinear_scatter, (vals, pts, [0.0, 0.0, 0.0], 0.5, [3, 4, 5]))
    gout = torch.randn(10, 2, dtype=torch.float64)
    for need in [(True, True), (False, True), (True, False)]:
        torch.library.opcheck(OPS.trilinear_gather_backward,
                              (gout, grid.detach(), pts.detach(), [0.0, 0.0, 0.0], 0.5, *need))


def test_bad_inputs():
    grid = torch.zeros(2, 3, 4, 5)
    pts = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="NaN"):
        ops.trilinear_gather(grid, torch.tensor([[0.0, float("nan"), 0.0]]), [0, 0, 0], 1.0)
    with pytest.raises(ValueError, match="NaN"):
        ops.trilinear_scatter(torch.zeros(1, 2), torch.tensor([[0.0, float("inf"), 0.0]]), [0, 0, 0], 1.0, [3, 4, 5])
    with pytest.raises((ValueError, TypeError), match="points"):
        ops.trilinear_gather(grid, torch.zeros(4, 2), [0, 0, 0], 1.0)
    with pytest.raises(TypeError):
        ops.trilinear_gather(grid, pts.double(), [0, 0, 0], 1.0)
    with pytest.raises(TypeError):
        ops.trilinear_gather(grid.int(), pts.int(), [0, 0, 0], 1.0)
    with pytest.raises(ValueError, match="spacing"):
        ops.trilinear_gather(grid, pts, [0, 0, 0], 0.0)
    with pytest.raises(ValueError, match="origin"):
        ops.trilinear_gather(grid, pts, [0, 0], 1.0)
    with pytest.raises(ValueError, match="grid"):
        ops.trilinear_gather(grid[0], pts, [0, 0, 0], 1.0)
    with pytest.raises(ValueError, match="values"):
        ops.trilinear_scatter(torch.zeros(3, 2), pts, [0, 0, 0], 1.0, [3, 4, 5])
    with pytest.raises(ValueError, match="grid_shape"):
        ops.trilinear_scatter(torch.zeros(4, 2), pts, [0, 0, 0], 1.0, [3, 0, 5])
    # the raw ops check too (RuntimeError naming the argument), never crash
    with pytest.raises(RuntimeError, match="grid"):
        OPS.trilinear_gather(grid, pts.double(), [0.0, 0.0, 0.0], 1.0)
    with pytest.raises(RuntimeError, match="points"):
        OPS.trilinear_gather(grid, torch.zeros(4, 2), [0.0, 0.0, 0.0], 1.0)
    with pytest.raises(RuntimeError, match="grad_out"):
        OPS.trilinear_gather_backward(torch.zeros(3, 2), grid, pts, [0.0, 0.0, 0.0], 1.0, True, True)
    with pytest.raises(RuntimeError, match="spacing"):
        OPS.trilinear_scatter(torch.zeros(4, 2), pts, [0.0, 0.0, 0.0], -1.0, [3, 4, 5])
    # NaN through the raw op (no wrapper check) stays in bounds and gives NaN rows
    # (the full contract: tests/ops/test_ops_nonfinite.py)
    out = OPS.trilinear_gather(grid, torch.full((2, 3), float("nan")), [0.0, 0.0, 0.0], 1.0)
    assert out.shape == (2, 2) and torch.isnan(out).all()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("dtype", DTYPES)
def test_cpu_vs_cuda(dtype):
    gen = torch.Generator().manual_seed(9)
    shape, origin, spacing = (3, 7, 20, 30), [0.5, -0.5, 1.0], 0.4
    C, Z, Y, X = shape
    grid = torch.randn(shape, generator=gen, dtype=dtype)
    for n in (0, 1, 40000):
        pts = _points(n, (Z, Y, X), origin, spacing, dtype, gen)
        # many points in one voxel: exercises the warp-aggregated atomics
        pts[: n // 4] = torch.tensor(origin, dtype=dtype) + 0.3 * spacing
        vals = torch.randn(n, C, generator=gen, dtype=dtype)
        gout = torch.randn(n, C, generator=gen, dtype=dtype)
        tol = _tol(dtype) if dtype == torch.float64 else dict(rtol=1e-4, atol=1e-3)
        d = "cuda"
        torch.testing.assert_close(OPS.trilinear_gather(grid.to(d), pts.to(d), origin, spacing).cpu(),
                                   OPS.trilinear_gather(grid, pts, origin, spacing), **tol)
        torch.testing.assert_close(OPS.trilinear_scatter(vals.to(d), pts.to(d), origin, spacing, [Z, Y, X]).cpu(),
                                   OPS.trilinear_scatter(vals, pts, origin, spacing, [Z, Y, X]), **tol)
        for need in [(True, True), (False, True), (True, False)]:
            a = OPS.trilinear_gather_backward(gout.to(d), grid.to(d), pts.to(d), origin, spacing, *need)
            b = OPS.trilinear_gather_backward(gout, grid, pts, origin, spacing, *need)
            for x, y in zip(a, b):
                torch.testing.assert_close(x.cpu(), y, **tol)
    with pytest.raises((RuntimeError, ValueError)):
        ops.trilinear_gather(grid.cuda(), pts, origin, spacing)
