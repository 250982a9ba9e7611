"""floxels::fixed_segment_sum against its reference (bit for bit), the estimator's group sums
against the PyTorch arithmetic they replaced, order independence, CPU against CUDA."""

import pytest
import torch

import floxels_ext  # noqa: F401
from floxels_ext.estimator import group_sums
from floxels_ext.ops import fixed_segment_sum
from floxels_ext.reference import ops as R

OPS = torch.ops.floxels


def _data(m, c, rows, dtype, seed, bad=True, index_dtype=torch.int64, device="cpu"):
    gen = torch.Generator().manual_seed(seed)
    v = (torch.randn(m, c, generator=gen, dtype=torch.float64) * 3).to(dtype)
    v[::7] *= 1e5  # some terms beyond the clamp
    if bad and m > 8:
        v[3, 0] = float("nan")
        v[5, c - 1] = float("inf")
        v[8, 0] = float("-inf")
    idx = torch.randint(-2, rows + 2, (m,), generator=gen).to(index_dtype)  # some outside [0, rows)
    return v.to(device), idx.to(device)


def _same_bits(a, b):
    assert a.dtype == b.dtype and a.shape == b.shape
    assert torch.equal(torch.isnan(a), torch.isnan(b))
    assert torch.equal(a.nan_to_num(0.0).view(torch.int64), b.nan_to_num(0.0).view(torch.int64))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
@pytest.mark.parametrize("void_row,count", [(False, False), (True, True), (False, True), (True, False)])
def test_matches_reference_bit_for_bit(dtype, index_dtype, void_row, count):
    for seed, (m, c, rows) in enumerate([(500, 3, 17), (40, 1, 3), (1000, 5, 1), (64, 2, 200)]):
        v, idx = _data(m, c, rows, dtype, seed, index_dtype=index_dtype)
        for limit in (2.0 ** 18, 4096.0, 1.5):
            out = fixed_segment_sum(v, idx, rows, limit, void_row, count)
            assert out.shape == (rows, c + count) and out.dtype == torch.float64
            _same_bits(out, R.fixed_segment_sum(v, idx, rows, limit, void_row, count))


def test_nonfinite_terms_void_their_column_or_row_and_still_count():
    v = torch.tensor([[1.0, 2.0], [float("nan"), 3.0], [4.0, 5.0], [6.0, float("inf")]], dtype=torch.float64)
    idx = torch.tensor([0, 0, 1, 2])
    out = fixed_segment_sum(v, idx, 4, 100.0, count=True)
    assert torch.isnan(out[0, 0]) and out[0, 1] == 5.0 and out[0, 2] == 2.0
    assert out[1].tolist() == [4.0, 5.0, 1.0] and out[3].tolist() == [0.0, 0.0, 0.0]
    assert out[2, 0] == 6.0 and torch.isnan(out[2, 1])
    row = fixed_segment_sum(v, idx, 4, 100.0, void_row=True, count=True)
    assert torch.isnan(row[0, :2]).all() and row[0, 2] == 2.0 and torch.isnan(row[2, :2]).all()
    assert row[1].tolist() == [4.0, 5.0, 1.0]
    clamped = fixed_segment_sum(torch.tensor([[1e9], [-3.0]]), torch.tensor([0, 0]), 1, 10.0)
    assert clamped.item() == 7.0  # 10 - 3: each term clamped to +-limit before the sum


def test_the_fixed_point_step_is_group_sums_constant():
    step = 1 / group_sums.FIXED_POINT
    v = torch.tensor([[step], [0.4 * step], [0.5 * step], [1.5 * step]], dtype=torch.float64)
    out = fixed_segment_sum(v, torch.arange(4), 4, 1.0)[:, 0]
    assert out.tolist() == [step, 0.0, 0.0, 2 * step]  # rounded to the step, ties to even


def test_order_of_the_terms_does_not_change_a_bit():
    v, idx = _data(4000, 3, 5, torch.float32, 7, bad=False)
    ref = fixed_segment_sum(v, idx, 5, 2.0 ** 18, count=True)
    for seed in range(3):
        p = torch.randperm(v.shape[0], generator=torch.Generator().manual_seed(seed))
        _same_bits(fixed_segment_sum(v[p], idx[p], 5, 2.0 ** 18, count=True), ref)


def test_empty_inputs():
    assert fixed_segment_sum(torch.zeros(0, 3), torch.zeros(0, dtype=torch.int64), 4, 1.0, count=True).tolist() == \
        [[0.0, 0.0, 0.0, 0.0]] * 4
    assert fixed_segment_sum(torch.zeros(5, 2), torch.zeros(5, dtype=torch.int64), 0, 1.0).shape == (0, 2)
    assert fixed_segment_sum(torch.ones(3, 0), torch.tensor([0, 1, 1]), 2, 1.0, count=True).tolist() == [[1.0], [2.0]]


def test_bad_arguments_are_named():
    v, idx = torch.zeros(4, 3), torch.zeros(4, dtype=torch.int64)
    for args, says in (((v[:, 0], idx, 2, 1.0), "values must be an (M, C)"),
                       ((v.long(), idx, 2, 1.0), "values must be an (M, C)"),
                       ((v, idx[:3], 2, 1.0), "index must be an (4,)"),
                       ((v, idx.float(), 2, 1.0), "index must be an (4,)")):
        with pytest.raises(ValueError, match=says.replace("(", r"\(").replace(")", r"\)")):
            fixed_segment_sum(*args)
    for rows, limit, says in ((-1, 1.0, "rows must be"), (2, 0.0, "limit must be"), (2, float("nan"), "limit must be"),
                              (2, 2.0 ** 40, "limit must be")):
        with pytest.raises(RuntimeError, match=says):
            OPS.fixed_segment_sum(v, idx, rows, limit, False, False)
    with pytest.raises(RuntimeError, match="data-only"):
        x = torch.ones(3, 1, requires_grad=True)
        OPS.fixed_segment_sum(x, torch.zeros(3, dtype=torch.int64), 1, 1.0, False, False).sum().backward()


def test_opcheck():
    v, idx = _data(50, 3, 6, torch.float32, 1, bad=False)  # (opcheck's comparisons treat NaN as different)
    torch.library.opcheck(OPS.fixed_segment_sum, (v, idx, 6, 4096.0, True, True))
    torch.library.opcheck(OPS.fixed_segment_sum, (v.double(), idx.int(), 6, 2.0 ** 18, False, False))


# --- the estimator's group sums: the same bits as the PyTorch arithmetic the op replaced ---------

def _old_segment_sum(rows, index, values):
    flat = values.reshape(values.shape[0], -1).to(torch.float64)
    cols = flat.shape[1]
    bad = ~torch.isfinite(flat)
    fixed = torch.round(flat.nan_to_num(0.0, 0.0, 0.0).clamp(-group_sums.MAX_FIXED_SUM, group_sums.MAX_FIXED_SUM)
                        * group_sums.FIXED_POINT)
    acc = torch.zeros(rows, 2 * cols, dtype=torch.int64).index_add_(
        0, index.to(torch.int64), torch.cat([fixed.to(torch.int64), bad.to(torch.int64)], 1))
    out = torch.where(acc[:, cols:] > 0, float("nan"), acc[:, :cols].to(torch.float64) / group_sums.FIXED_POINT)
    return out.to(values.dtype).reshape((rows,) + tuple(values.shape[1:]))


def _old_cluster_means(flow, lab, C):
    n = lab.shape[0]
    key = torch.where(lab >= 0, lab, C + (torch.arange(n) & 1023))
    f = flow.to(torch.float64)
    bad = ~torch.isfinite(f).all(dim=1)
    f = f.nan_to_num(0.0, 0.0, 0.0).clamp(-group_sums.MAX_FIXED_FLOW, group_sums.MAX_FIXED_FLOW)
    rows = torch.cat([torch.round(f * group_sums.FIXED_POINT).to(torch.int64), torch.ones_like(key)[:, None],
                      bad.to(torch.int64)[:, None]], 1)
    sums = torch.zeros(C + 1024, 5, dtype=torch.int64).index_add_(0, key, rows)[:C]
    size = sums[:, 3].to(torch.float64)
    mean = sums[:, :3].to(torch.float64) / group_sums.FIXED_POINT / size.clamp_min(1)[:, None]
    mean = torch.where(sums[:, 4:] > 0, torch.full_like(mean, float("nan")), mean)
    return mean.to(flow.dtype), size.to(flow.dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_group_sums_keep_their_bits(dtype):
    gen = torch.Generator().manual_seed(3)
    for shape in ((300,), (300, 3), (300, 2, 2)):
        v = (torch.randn(*shape, generator=gen, dtype=torch.float64) * 50).to(dtype)
        v.view(300, -1)[4, 0] = float("nan")
        v.view(300, -1)[::11] *= 1e4  # beyond MAX_FIXED_SUM: the clamp's bits too
        idx = torch.randint(0, 9, (300,), generator=gen)
        _same_bits(group_sums.segment_sum(9, idx, v).view(9, -1).double(), _old_segment_sum(9, idx, v).view(9, -1).double())
        assert group_sums.segment_sum(9, idx, v).dtype == dtype
    flow = (torch.randn(500, 3, generator=gen, dtype=torch.float64) * 2).to(dtype)
    flow[10, 1] = float("inf")
    flow[20, 0] = 1e5  # beyond MAX_FIXED_FLOW
    lab = torch.randint(-1, 12, (500,), generator=gen)
    for lab_ in (lab, lab.int()):
        mean, size = group_sums.cluster_means(flow, lab_, 12)
        old_mean, old_size = _old_cluster_means(flow, lab, 12)
        _same_bits(mean.double(), old_mean.double())
        _same_bits(size.double(), old_size.double())
        assert mean.dtype == dtype and size.dtype == dtype


@pytest.mark.cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu_bit_for_bit(dtype):
    for seed, (m, c, rows) in enumerate([(100000, 3, 40), (5000, 4, 1), (300, 1, 300), (0, 3, 5)]):
        v, idx = _data(m, c, rows, dtype, seed)
        for void_row, count in ((False, False), (True, True)):
            cpu = fixed_segment_sum(v, idx, rows, 4096.0, void_row, count)
            _same_bits(fixed_segment_sum(v.cuda(), idx.cuda().int(), rows, 4096.0, void_row, count).cpu(), cpu)
    v, idx = _data(2000, 3, 7, dtype, 9, bad=False)
    torch.library.opcheck(OPS.fixed_segment_sum, (v.cuda(), idx.cuda(), 7, 4096.0, True, True))
