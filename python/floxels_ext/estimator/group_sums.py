"""Sums of values by group (a DBSCAN cluster, a vertex, a group of sample rows) that are the same
bits in any order and on any device: each term rounded to a fixed point and summed as int64
(``index_add_``'s integer atomics are exact). Float ``index_add_`` adds in whatever order its
atomics land (issue 31); ``index_put_(accumulate=True)``'s fixed order costs a serial loop over
each group's terms on CUDA (bench/RESULTS.md, eighth session). Used by the rigid refinement
(estimator/refine.py) and the steps after it (estimator/spread.py, estimator/unseen.py)."""

from __future__ import annotations

import math

import torch

# The clusters' mean flow (the refinement's selection and start) is summed in fixed point:
# steps of 2^-24 m/frame (a float32's resolution at 1 m/frame), flows clamped to +-4096 m/frame,
# so that sums of up to 2^27 points cannot overflow int64 (cluster_means).
FIXED_POINT = float(2 ** 24)
MAX_FIXED_FLOW = 4096.0
MAX_FIXED_SUM = float(2 ** 18)  # segment_sum's largest term: 2 ** 42 as an integer
SPARE_ROWS = 1024


def segment_sum(rows: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """(rows, ...) sums of ``values`` (m, ...) by ``index`` (m,), in ``values``' dtype: each term
    rounded to a multiple of 1 / FIXED_POINT (6e-8) and summed as integers, so exact and the same
    bits in any order, on any device (``index_add_`` on floats adds with atomics in any order:
    issue 31). A row with a non-finite term is NaN. Why not ``index_put_`` with accumulate (the
    fixed order it sorts into): its CUDA kernel counts each row's terms one by one, ~0.8 ms a
    frame of the accurate preset on an H200 (a large cluster's row; tools/run_gaps.py). Terms
    are clamped to +-MAX_FIXED_SUM (sums of residuals, counts and recentred coordinates stay
    far below it); a row may hold 2 ** 21 terms of that size before its integer overflows."""
    flat = values.reshape(values.shape[0], math.prod(values.shape[1:])).to(torch.float64)
    cols = flat.shape[1]
    bad = ~torch.isfinite(flat)
    fixed = torch.round(flat.nan_to_num(0.0, 0.0, 0.0).clamp(-MAX_FIXED_SUM, MAX_FIXED_SUM) * FIXED_POINT)
    acc = torch.zeros(rows, 2 * cols, dtype=torch.int64, device=values.device).index_add_(
        0, index.to(torch.int64), torch.cat([fixed.to(torch.int64), bad.to(torch.int64)], 1))
    out = torch.where(acc[:, cols:] > 0, float("nan"), acc[:, :cols].to(torch.float64) / FIXED_POINT)
    return out.to(values.dtype).reshape((rows,) + tuple(values.shape[1:]))


def cluster_means(flow: torch.Tensor, lab: torch.Tensor, C: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean flow (C, 3) in the flow's dtype, points (C,) in the flow's dtype) of the clusters
    ``lab`` (n,) in [-1, C) of every point. The sums are of the flow in fixed point (FIXED_POINT
    steps), as integers: exact, so the same bits in any order and on any device, as
    :func:`segment_sum`'s. It differs from that in what it sums over every point of a frame: a
    point with any non-finite component voids its cluster's whole mean (not the one component),
    flows are clamped to +-MAX_FIXED_FLOW, the unclustered points are spread over spare rows (no
    row's atomics take them all), and one pass sums 5 int64 columns (segment_sum would take 8:
    the flow, a count and a non-finite flag a column)."""
    n = lab.shape[0]
    # points of no cluster: spread over spare rows C.., so that no row takes them all
    key = torch.where(lab >= 0, lab, C + (torch.arange(n, device=lab.device) & (SPARE_ROWS - 1)))
    f = flow.to(torch.float64)
    bad = ~torch.isfinite(f).all(dim=1)  # a cluster with a non-finite flow gets a NaN mean (not refined)
    f = f.nan_to_num(0.0, 0.0, 0.0).clamp(-MAX_FIXED_FLOW, MAX_FIXED_FLOW)
    rows = torch.cat([torch.round(f * FIXED_POINT).to(torch.int64), torch.ones_like(key)[:, None],
                      bad.to(torch.int64)[:, None]], 1)
    sums = torch.zeros(C + SPARE_ROWS, 5, dtype=torch.int64, device=lab.device).index_add_(0, key, rows)[:C]
    size = sums[:, 3].to(torch.float64)
    mean = sums[:, :3].to(torch.float64) / FIXED_POINT / size.clamp_min(1)[:, None]
    mean = torch.where(sums[:, 4:] > 0, torch.full_like(mean, float("nan")), mean)
    return mean.to(flow.dtype), size.to(flow.dtype)
