"""The refinement's per-group sums (estimator/group_sums.py ``segment_sum``): exact fixed-point sums,
so the same bits in any order of the terms and on any device, NaN for a group with a non-finite
term."""

import math

import pytest
import torch

from floxels_ext.estimator.group_sums import FIXED_POINT, segment_sum


def _case(seed=0, m=5000, rows=40, cols=3):
    g = torch.Generator().manual_seed(seed)
    index = torch.randint(0, rows, (m,), generator=g)
    index[: m // 2] = 7  # one large group, as a large cluster's rows
    values = (torch.rand(m, cols, generator=g, dtype=torch.float64) - 0.3) * 10
    return index, values.to(torch.float32)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sums_match_float64_and_do_not_depend_on_order(dtype):
    index, values = _case()
    values = values.to(dtype)
    out = segment_sum(40, index, values)
    assert out.dtype == dtype and out.shape == (40, 3)
    exact = torch.zeros(40, 3, dtype=torch.float64).index_add_(0, index, values.double())
    # each term rounded to 1 / FIXED_POINT: at most half a step each
    assert torch.allclose(out.double(), exact, rtol=1e-6, atol=index.numel() * 0.5 / FIXED_POINT)
    perm = torch.randperm(index.numel(), generator=torch.Generator().manual_seed(1))
    assert torch.equal(segment_sum(40, index[perm], values[perm]), out)


def test_one_dimensional_values_and_empty_rows():
    index = torch.tensor([0, 0, 2, 2, 2])
    out = segment_sum(4, index, torch.tensor([0.5, 0.25, 1.0, 2.0, -4.0]))
    assert out.shape == (4,)
    assert out.tolist() == [0.75, 0.0, -1.0, 0.0]
    assert segment_sum(3, torch.zeros(0, dtype=torch.int64), torch.zeros(0)).tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_term_makes_its_row_nan(bad):
    index = torch.tensor([0, 1, 1, 2])
    out = segment_sum(3, index, torch.tensor([1.0, bad, 3.0, 4.0]))
    assert out[0] == 1.0 and out[2] == 4.0 and math.isnan(out[1])
    # a NaN sum counts as worse in the refinement's side test: ~(sum <= 0)
    assert bool(~(out[1] <= 0))


@pytest.mark.cuda
def test_cuda_gives_the_cpus_bits():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    index, values = _case(seed=3)
    cpu = segment_sum(40, index, values)
    assert torch.equal(segment_sum(40, index.cuda(), values.cuda()).cpu(), cpu)
