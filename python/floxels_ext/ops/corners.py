"""Compact voxel parameters: only the flow-grid vertices touched by points are optimised.

The points of the target scan never move during the optimisation, so their 8 trilinear
corners and weights are computed once (:func:`compact_corners`); the optimiser then keeps
a (M, 3) table of the M touched vertices. Vertices no point touches would receive zero
gradient, and Adam leaves a parameter with only zero gradients at exactly zero, so this
is exactly dense Adam on the full grid, at a fraction of the cost.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from floxels_ext.ops._checks import require_tensors
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops._small import device_values


@torch.library.register_fake("floxels::corner_gather")
def _gather_fake(params, corner_idx, corner_w):
    return params.new_empty((corner_idx.shape[0], params.shape[1]))


@torch.library.register_fake("floxels::corner_scatter")
def _scatter_fake(values, corner_idx, corner_w, num_params):
    return values.new_empty((num_params, values.shape[1]))


def _gather_setup(ctx, inputs, output):
    params, idx, w = inputs
    ctx.save_for_backward(idx, w)
    ctx.num_params = params.shape[0]


def _gather_backward(ctx, grad):
    idx, w = ctx.saved_tensors
    if ctx.needs_input_grad[2]:
        raise RuntimeError("floxels::corner_gather is not differentiable with respect to corner_w")
    return ops_ns.corner_scatter(grad.contiguous(), idx, w, ctx.num_params), None, None


def _scatter_setup(ctx, inputs, output):
    values, idx, w, num_params = inputs
    ctx.save_for_backward(idx, w)


def _scatter_backward(ctx, grad):
    idx, w = ctx.saved_tensors
    if ctx.needs_input_grad[2]:
        raise RuntimeError("floxels::corner_scatter is not differentiable with respect to corner_w")
    return ops_ns.corner_gather(grad.contiguous(), idx, w), None, None, None


torch.library.register_autograd("floxels::corner_gather", _gather_backward, setup_context=_gather_setup)
torch.library.register_autograd("floxels::corner_scatter", _scatter_backward, setup_context=_scatter_setup)


# corner j = (cx, cy, cz) with j = cz * 4 + cy * 2 + cx, the order of trilinear_gather
_CORNER_OFFSETS = [[cx, cy, cz] for cz in (0, 1) for cy in (0, 1) for cx in (0, 1)]


@dataclass
class CompactCorners:
    corner_idx: torch.Tensor   # (N, 8) int32 rows into the compact table
    corner_w: torch.Tensor     # (N, 8) trilinear weights
    vertices: torch.Tensor     # (M,) int64 linear index (z * Y + y) * X + x of each compact row
    grid_shape: list[int]      # [Z, Y, X] of the dense lattice the vertices live on

    @property
    def num_params(self) -> int:
        return int(self.vertices.shape[0])

    def to_dense(self, params: torch.Tensor) -> torch.Tensor:
        """Dense (C, Z, Y, X) grid holding ``params`` (M, C) at their vertices, 0 elsewhere."""
        Z, Y, X = self.grid_shape
        dense = params.new_zeros(params.shape[1], Z * Y * X)
        dense[:, self.vertices] = params.T
        return dense.view(params.shape[1], Z, Y, X)


def compact_corners(points: torch.Tensor, origin: Sequence[float], spacing: float,
                    grid_shape: Sequence[int]) -> CompactCorners:
    """Trilinear corners of ``points`` on the lattice (same clamping as trilinear_gather),
    renumbered densely over the vertices actually touched.

    ``points`` must be finite (the estimator drops NaN/inf rows first; ``problem_setup``
    refuses them). A non-finite row still gets in-range corners (NaN clamps to the lower
    corner, +-inf to the border), never an invalid index, but its weights are meaningless.
    """
    Z, Y, X = (int(s) for s in grid_shape)
    dev, dt = points.device, points.dtype
    # All 8 corners at once (a dozen kernels instead of ~120 small ones: this runs once per
    # frame, where launch overhead matters); same arithmetic as trilinear_gather's clamping.
    # constants copied without blocking (ops/_small.py)
    size = device_values([X, Y, Z], torch.int64, dev)
    o = device_values([float(v) for v in origin], dt, dev)
    hi = (size - 1).to(dt)
    # clamped in floating point before any conversion to an index; fmax/fmin (unlike
    # clamp/minimum) send NaN to the bound instead of propagating it
    u = torch.fmin(torch.fmax((points - o) / spacing, hi.new_zeros(())), hi)
    i0 = torch.minimum(u.floor().long(), (size - 2).clamp(min=0))
    t = u - i0.to(dt)
    offs = device_values(_CORNER_OFFSETS, torch.int64, dev)         # (8, 3): x fastest, then y, then z
    idx = torch.minimum(i0[:, None, :] + offs, size - 1)            # (N, 8, 3)
    lin = (idx[..., 2] * Y + idx[..., 1]) * X + idx[..., 0]
    wf = torch.where(offs.bool(), t[:, None, :], 1 - t[:, None, :])  # (N, 8, 3) per-axis weights
    w = wf[..., 0] * wf[..., 1] * wf[..., 2]
    vertices, inverse = torch.unique(lin, return_inverse=True)
    if vertices.numel() >= 2**31:
        raise ValueError("too many touched voxel corners for int32 indexing")
    return CompactCorners(inverse.to(torch.int32).contiguous(), w.contiguous(),
                          vertices, [Z, Y, X])


def corner_gather(params: torch.Tensor, corner_idx: torch.Tensor, corner_w: torch.Tensor) -> torch.Tensor:
    """(N, C) = sum_j corner_w[:, j] * params[corner_idx[:, j]]; differentiable in params.
    Non-finite params or weights propagate (NaN/inf in the rows they touch)."""
    require_tensors(params=params, corner_idx=corner_idx, corner_w=corner_w)
    return ops_ns.corner_gather(params.contiguous(), corner_idx.contiguous(), corner_w.contiguous())


def corner_scatter(values: torch.Tensor, corner_idx: torch.Tensor, corner_w: torch.Tensor,
                   num_params: int) -> torch.Tensor:
    """Adjoint of :func:`corner_gather`: (num_params, C) sums of weighted values. Non-finite
    values or weights propagate into the rows they touch."""
    require_tensors(values=values, corner_idx=corner_idx, corner_w=corner_w)
    return ops_ns.corner_scatter(values.contiguous(), corner_idx.contiguous(), corner_w.contiguous(),
                                 int(num_params))
