"""Sums of values by group (a DBSCAN cluster, a vertex, a group of sample rows) that are the same
bits in any order and on any device: each term rounded to a fixed point and summed as int64
(``floxels::fixed_segment_sum``: integer sums are exact). Float ``index_add_`` adds in whatever order its
atomics land (issue 31); ``index_put_(accumulate=True)``'s fixed order costs a serial loop over
each group's terms on CUDA (bench/RESULTS.md, eighth session). Used by the rigid refinement
(estimator/refine.py) and the steps after it (estimator/spread.py, estimator/unseen.py)."""

from __future__ import annotations

import math

import torch

from floxels_ext.ops.segment_sum import fixed_segment_sum

# The clusters' mean flow (the refinement's selection and start) is summed in fixed point:
# steps of 2^-24 m/frame (a float32's resolution at 1 m/frame), flows clamped to +-4096 m/frame,
# so that sums of up to 2^27 points cannot overflow int64 (cluster_means).
FIXED_POINT = float(2 ** 24)  # the op's scale (csrc/kernels/segment_sum.h kScale; a test holds them equal)
MAX_FIXED_FLOW = 4096.0
MAX_FIXED_SUM = float(2 ** 18)  # segment_sum's largest term: 2 ** 42 as an integer


def segment_sum(rows: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """(rows, ...) sums of ``values`` (m, ...) by ``index`` (m,), in ``values``' dtype: each term
    rounded to a multiple of 1 / FIXED_POINT (6e-8) and summed as integers, so exact and the same
    bits in any order, on any device (``index_add_`` on floats adds with atomics in any order:
    issue 31). A row with a non-finite term is NaN. One ``floxels::fixed_segment_sum`` (two
    kernels on CUDA; the same arithmetic in ~15 PyTorch ops was ~60 launches a frame of the
    accurate preset); ``index_put_`` with accumulate (a fixed order) counts each row's terms one
    by one on CUDA, ~0.8 ms a frame on an H200 (a large cluster's row; tools/run_gaps.py). Terms
    are clamped to +-MAX_FIXED_SUM (sums of residuals, counts and recentred coordinates stay
    far below it); a row may hold 2 ** 21 terms of that size before its integer overflows."""
    cols = math.prod(values.shape[1:])
    flat = values.reshape(values.shape[0], cols)
    if flat.dtype not in (torch.float32, torch.float64):
        flat = flat.to(torch.float64)
    if index.dtype not in (torch.int64, torch.int32):
        index = index.to(torch.int64)
    out = fixed_segment_sum(flat, index, rows, MAX_FIXED_SUM)
    return out.to(values.dtype).reshape((rows,) + tuple(values.shape[1:]))


def cluster_means(flow: torch.Tensor, lab: torch.Tensor, C: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean flow (C, 3) in the flow's dtype, points (C,) in the flow's dtype) of the clusters
    ``lab`` (n,) in [-1, C) of every point (the unclustered, -1, in no row). The sums are of the
    flow in fixed point (FIXED_POINT steps), as integers: exact, so the same bits in any order
    and on any device, as :func:`segment_sum`'s. It differs from that in what it sums over every
    point of a frame: a point with any non-finite component voids its cluster's whole mean (not
    the one component), flows are clamped to +-MAX_FIXED_FLOW, and the points are counted."""
    if lab.dtype not in (torch.int64, torch.int32):
        lab = lab.to(torch.int64)
    sums = fixed_segment_sum(flow, lab, C, MAX_FIXED_FLOW, void_row=True, count=True)
    size = sums[:, 3]
    mean = sums[:, :3] / size.clamp_min(1)[:, None]
    return mean.to(flow.dtype), size.to(flow.dtype)
