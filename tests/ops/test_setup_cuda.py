"""The CUDA problem_setup (csrc/cuda/problem_setup*.{cu,cpp}: its own kernels instead of ~90
ATen calls) against the CPU op bit for bit: edge sizes, tiles, labels of any integer dtype or
none, float64 points, a spacing whose inverse float32 cannot hold (the CUDA op divides, as
the CPU does), the ATen fallback (a sparse lattice), and the errors.
Needs a GPU."""

import pytest
import torch

from test_setup_ops import _assert_same, _cloud

pytestmark = pytest.mark.cuda
F = torch.ops.floxels


def _both(p, lab, *args):
    a = F.problem_setup(p.cuda(), lab.cuda() if lab is not None else None, *args)
    b = F.problem_setup(p, lab, *args)
    _assert_same([x.cpu() if isinstance(x, torch.Tensor) else x for x in a], b)
    return b


@pytest.mark.parametrize("n", [1, 2, 31, 33, 1000, 70000])
@pytest.mark.parametrize("labels", [True, False])
@pytest.mark.parametrize("tile", [1, 32, 10**9])
def test_cuda_matches_cpu(n, labels, tile):
    p, lab = _cloud(n, n + tile, labels)
    _both(p, lab, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], tile)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu_any_spacing_and_dtype(dtype):
    # 0.3 m: 1 / 0.3 is not exact in float32, where a multiply by the inverse would move
    # corner weights by an ulp; an origin off the cells
    p, lab = _cloud(5000, 11, True, extent=(7.0, 5.0, 2.0), dtype=dtype)
    _both(p, lab.to(torch.int32), [-1.13, -0.97, -1.01], 0.3, [12, 26, 34], 32)


def test_cuda_clamps_points_outside_the_grid():
    p, lab = _cloud(3000, 4, True, extent=(30.0, 20.0, 6.0))
    st = _both(p, lab, [2.0, 1.0, 0.0], 0.5, [4, 20, 30], 32)
    assert int(st[3].max()) < st[5].numel()  # corner rows within the compact table


@pytest.mark.parametrize("labels", [True, False])
def test_cuda_falls_back_for_sparse_lattices(labels):
    p, lab = _cloud(300, 7, labels, extent=(100.0, 100.0, 100.0), dtype=torch.float64)
    _both(p, lab, [0.0, 0.0, 0.0], 0.5, [150, 201, 190], 32)  # renumbered through torch.unique


def test_cuda_refuses_non_finite_points_and_bad_labels():
    p, lab = _cloud(500, 2, True)
    for bad in (float("nan"), float("inf")):
        q = p.clone()
        q[17, 1] = bad
        with pytest.raises(RuntimeError, match="finite"):
            F.problem_setup(q.cuda(), lab.cuda(), [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32)
    with pytest.raises(RuntimeError, match="labels must be on the points' device"):
        F.problem_setup(p.cuda(), lab, [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32)
    with pytest.raises(RuntimeError, match=r"labels must be \(N,\)"):
        F.problem_setup(p.cuda(), lab[:-1].cuda(), [-1.0, -1.0, -1.0], 0.5, [6, 15, 24], 32)
