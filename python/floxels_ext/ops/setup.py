"""Per-target preparation of the optimiser (``floxels::problem_setup``) and host staging of
scans (``floxels::stage_points``): fake registrations and wrappers."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from floxels_ext.ops._checks import as_origin, as_spacing, require_tensors
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops.corners import CompactCorners


@torch.library.register_fake("floxels::problem_setup")
def _setup_fake(points, labels, origin, spacing, grid_shape, tile):
    ctx = torch.library.get_ctx()
    n = points.shape[0]
    m, s = ctx.new_dynamic_size(), ctx.new_dynamic_size()
    i32 = dict(dtype=torch.int32)
    lab = points.new_empty((n if labels is not None else 0,), dtype=torch.int64)  # empty without labels
    return (points.new_empty((n,), dtype=torch.int64), points.new_empty((n, 3)), lab,
            points.new_empty((n, 8), **i32), points.new_empty((n, 8)), points.new_empty((m,), dtype=torch.int64),
            points.new_empty((s + 1,), **i32), points.new_empty((m + 1,), **i32), points.new_empty((8 * s,), **i32),
            ctx.new_dynamic_size())


@torch.library.register_fake("floxels::stage_points")
def _stage_fake(points, out):
    return torch.empty((len(points), 7), dtype=torch.float64)


@dataclass
class ProblemSetup:
    """What :func:`problem_setup` returns: see csrc/ops.cpp."""

    order: torch.Tensor            # (N,) int64: sorted point k is input point order[k]
    points: torch.Tensor           # (N, 3) points[order]
    labels: torch.Tensor | None    # (N,) int64 labels[order], or None
    corners: CompactCorners
    segments: tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # seg_ptr, vtx_ptr, vtx_entry
    num_clusters: int


def problem_setup(points: torch.Tensor, labels: torch.Tensor | None, origin: Sequence[float], spacing: float,
                  grid_shape: Sequence[int], tile: int) -> ProblemSetup:
    """Points sorted by (label, cell), their compact corners and the solver's segment tables,
    with one host synchronisation (see ``reference.problem_setup`` for the definition).
    Points with NaN/inf coordinates are refused (RuntimeError, after that synchronisation)."""
    require_tensors(points=points)
    if labels is not None:
        require_tensors(labels=labels)
    order, ps, lab, idx, w, verts, seg_ptr, vtx_ptr, vtx_entry, ncl = ops_ns.problem_setup(
        points, labels, as_origin(origin), as_spacing(spacing), [int(s) for s in grid_shape], int(tile))
    return ProblemSetup(order, ps, lab if labels is not None else None,
                        CompactCorners(idx, w, verts, [int(s) for s in grid_shape]),
                        (seg_ptr, vtx_ptr, vtx_entry), int(ncl))


def stage_points(points: Sequence[torch.Tensor], out: Sequence[torch.Tensor]) -> list[tuple]:
    """Copy each host scan (N_k, 3) into ``out[k]`` (float32, N_k*3 values) in one pass, a
    thread per scan, and return per scan (min xyz, max xyz, all finite)."""
    if len(points) == 0:
        return []
    rows = ops_ns.stage_points(list(points), list(out)).tolist()
    return [(r[:3], r[3:6], r[6] == 1.0) for r in rows]
