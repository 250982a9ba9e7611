"""Fixed-point sums by row (``floxels::fixed_segment_sum``): fake registration and wrapper.

The estimator's group sums (estimator/group_sums.py: the refinement's cluster sums, the
clusters' mean flow) must be the same bits in any order and on any device, so each term is
rounded to a fixed point and the integers are summed. In PyTorch that is ~15 element-wise
launches a call (convert, check, clamp, scale, round, cast, concatenate, ``index_add_``,
decode, flag); the op is one zeroed workspace and two kernels on CUDA, one pass on the CPU, with
the same bits as the reference (``floxels_ext.reference.ops.fixed_segment_sum``)."""

from __future__ import annotations

import torch

from floxels_ext.ops._checks import require_tensors
from floxels_ext.ops._data_only import register_data_only
from floxels_ext.ops._lib import ops_ns

__all__ = ["fixed_segment_sum"]


@torch.library.register_fake("floxels::fixed_segment_sum")
def _fake(values, index, rows, limit, void_row, count):
    return values.new_empty((rows, values.shape[1] + (1 if count else 0)), dtype=torch.float64)


register_data_only("fixed_segment_sum")


def fixed_segment_sum(values: torch.Tensor, index: torch.Tensor, rows: int, limit: float, void_row: bool = False,
                      count: bool = False) -> torch.Tensor:
    """(rows, C [+1]) float64: per row r the sum of the rows ``values[i]`` ((M, C) float32 or
    float64) with ``index[i] == r`` ((M,) int64 or int32; indices outside [0, rows) are ignored),
    each term clamped to +-``limit`` and rounded to a multiple of 2^-24 before an exact integer
    sum. A non-finite term makes its row's column NaN (``void_row``: every value column of the
    row); ``count`` appends each row's number of terms (exact). No host synchronisation."""
    require_tensors(values=values, index=index)
    if values.dim() != 2 or values.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"fixed_segment_sum: values must be an (M, C) float32/float64 tensor, got "
                         f"{values.dtype} {tuple(values.shape)}")
    if index.dim() != 1 or index.shape[0] != values.shape[0] or index.dtype not in (torch.int64, torch.int32):
        raise ValueError(f"fixed_segment_sum: index must be an ({values.shape[0]},) int64/int32 tensor, got "
                         f"{index.dtype} {tuple(index.shape)}")
    if index.device != values.device:
        raise ValueError(f"fixed_segment_sum: index is on {index.device} but values on {values.device}")
    return ops_ns.fixed_segment_sum(values, index, int(rows), float(limit), bool(void_row), bool(count))
