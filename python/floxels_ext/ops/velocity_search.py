"""The per-cluster velocity search as one op (``floxels::velocity_search``,
csrc/kernels/velocity_search.h): fake and autograd registration and the checked wrapper.

Why an op: in tensor code (``floxels_ext.reference.velocity_search``, the reference) the search
scores 321 candidates per cluster in chunks and then runs up to 16 pattern-search rounds, each a
handful of small ops and a host read-back; on a GPU its time was the host's (about 20 ms per
frame, more than the paper's whole frame). As one op it is three launches on CUDA (the
clusters' axes; the global candidates over (cluster, candidate chunk) blocks, so that a few
moving clusters still fill the GPU; the pattern search, a block per cluster) and one parallel
loop over clusters on the CPU. Data only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_spacing
from floxels_ext.ops._data_only import check_observed, check_segments, register_data_only
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops.dt_loss import check_dt_args

__all__ = ["velocity_search", "MAX_CANDIDATES"]

MAX_CANDIDATES = 1025  # 1 + num_directions * num_speeds (csrc/kernels/velocity_search.h)


@torch.library.register_fake("floxels::velocity_search")
def _velocity_search_fake(points, segments, observed, dts, origins, spacing, time_offsets, weights, tau,
                          num_directions, speed_step, num_speeds, local_steps, local_rounds):
    C = segments.shape[0] - 1
    return points.new_empty((C, 3)), points.new_empty((C,)), points.new_empty((C,))


register_data_only("velocity_search")


def velocity_search(points: torch.Tensor, segments: torch.Tensor, observed: torch.Tensor | None,
                    dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float,
                    time_offsets: Sequence[float], weights: Sequence[float], tau: float, num_directions: int,
                    speed_step: float, num_speeds: int, local_steps: int, local_rounds: int):
    """Every cluster's best constant velocity; returns ``(best (C, 3), best score (C,), zero
    flow's score (C,))``.

    Cluster ``c`` owns rows ``segments[c]:segments[c + 1]`` of ``points`` (``segments``: int64
    (C + 1,), non-decreasing from 0 to m). A velocity's score is the mean over the cluster's rows
    of ``sum_k weights[k] min(DT_k(p + time_offsets[k] v), tau)`` (``observed``: as
    :func:`~floxels_ext.ops.dt_residual`). Candidates: zero flow, and speeds
    ``(1..num_speeds) * speed_step`` along ``num_directions`` directions starting at the
    cluster's horizontal principal axis; then a 3 x 3 pattern search around the best,
    ``local_steps`` steps halving from ``speed_step``, at most ``local_rounds`` moves per step.
    Ties go to the lowest candidate. Data only."""
    p, _, d, o, t, w = check_dt_args("velocity_search", points, points, dts, origins, time_offsets, weights)
    segments = check_segments("velocity_search", segments, p)
    observed = check_observed("velocity_search", observed, p)
    for name, v in (("num_directions", num_directions), ("num_speeds", num_speeds), ("local_steps", local_steps),
                    ("local_rounds", local_rounds)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"velocity_search: {name} must be a non-negative integer, got {v!r}")
    if not (num_directions >= 1 and num_speeds >= 1 and 1 + num_directions * num_speeds <= MAX_CANDIDATES):
        raise ValueError(f"velocity_search: 1 + num_directions * num_speeds must be in [2, {MAX_CANDIDATES}], got "
                         f"{num_directions} directions and {num_speeds} speeds")
    if local_steps > 30 or local_rounds > 1000:
        raise ValueError(f"velocity_search: local_steps must be at most 30 and local_rounds at most 1000, got "
                         f"{local_steps} and {local_rounds}")
    tau, speed_step = float(tau), float(speed_step)
    if not 0 < tau < float("inf") or not 0 < speed_step < float("inf"):
        raise ValueError(f"velocity_search: tau and speed_step must be positive and finite, got {tau}, {speed_step}")
    return ops_ns.velocity_search(p, segments, observed, d, o,
                                  as_spacing(spacing), t, w, tau, num_directions, speed_step, num_speeds,
                                  local_steps, local_rounds)
