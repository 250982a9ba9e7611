"""Trilinear gather/scatter on dense grids: fake + autograd registration and public wrappers."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_origin, as_points, as_spacing, require_tensors, same_device
from floxels_ext.ops._lib import ops_ns


@torch.library.register_fake("floxels::trilinear_gather")
def _gather_fake(grid, points, origin, spacing):
    return grid.new_empty((points.shape[0], grid.shape[0]))


@torch.library.register_fake("floxels::trilinear_gather_backward")
def _gather_bwd_fake(grad_out, grid, points, origin, spacing, need_grid_grad, need_points_grad):
    gg = torch.empty_like(grid) if need_grid_grad else grid.new_empty((0,))
    gp = torch.empty_like(points) if need_points_grad else points.new_empty((0,))
    return gg, gp


@torch.library.register_fake("floxels::trilinear_scatter")
def _scatter_fake(values, points, origin, spacing, grid_shape):
    return values.new_empty((values.shape[1], *grid_shape))


def _gather_setup(ctx, inputs, output):
    grid, points, origin, spacing = inputs
    ctx.save_for_backward(grid, points)
    ctx.origin, ctx.spacing = origin, spacing


def _gather_backward(ctx, grad):
    grid, points = ctx.saved_tensors
    need_g, need_p = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
    gg, gp = ops_ns.trilinear_gather_backward(grad.contiguous(), grid, points, ctx.origin, ctx.spacing,
                                               need_g, need_p)
    return (gg if need_g else None), (gp if need_p else None), None, None


def _scatter_setup(ctx, inputs, output):
    values, points, origin, spacing, grid_shape = inputs
    ctx.save_for_backward(values, points)
    ctx.origin, ctx.spacing = origin, spacing


def _scatter_backward(ctx, grad):
    # <scatter(v, p), G> = <v, gather(G, p)>: both gradients come from the gather side.
    values, points = ctx.saved_tensors
    grad = grad.contiguous()
    gv = gp = None
    if ctx.needs_input_grad[0]:
        gv = ops_ns.trilinear_gather(grad, points, ctx.origin, ctx.spacing)
    if ctx.needs_input_grad[1]:
        _, gp = ops_ns.trilinear_gather_backward(values.contiguous(), grad, points, ctx.origin, ctx.spacing,
                                                 False, True)
    return gv, gp, None, None, None


torch.library.register_autograd("floxels::trilinear_gather", _gather_backward, setup_context=_gather_setup)
torch.library.register_autograd("floxels::trilinear_scatter", _scatter_backward, setup_context=_scatter_setup)


def _check_grid(grid: torch.Tensor, points: torch.Tensor) -> None:
    if not isinstance(grid, torch.Tensor) or grid.dim() != 4:
        raise ValueError(f"grid must be a (C, Z, Y, X) tensor, got shape {tuple(getattr(grid, 'shape', ()))}")
    if grid.dtype != points.dtype:
        raise TypeError(f"grid is {grid.dtype} but points are {points.dtype}")
    same_device(("grid", grid), ("points", points))


def trilinear_gather(grid: torch.Tensor, points: torch.Tensor, origin: Sequence[float], spacing: float) -> torch.Tensor:
    """Interpolate ``grid`` (C, Z, Y, X) at ``points`` (N, 3) -> (N, C); differentiable in both.

    Sample (iz, iy, ix) sits at ``origin + (ix, iy, iz) * spacing``. Points outside the
    lattice are clamped to its border like ``grid_sample(padding_mode="border",
    align_corners=True)``: border value, zero gradient for the clamped coordinate.
    NaN/inf points raise ``ValueError`` here; the raw op gives them a NaN row (docs/ops.md,
    non-finite input).
    """
    points = as_points(points)
    _check_grid(grid, points)
    return ops_ns.trilinear_gather(grid.contiguous(), points, as_origin(origin), as_spacing(spacing))


def trilinear_scatter(values: torch.Tensor, points: torch.Tensor, origin: Sequence[float], spacing: float,
                      grid_shape: Sequence[int]) -> torch.Tensor:
    """Adjoint of :func:`trilinear_gather`: accumulate ``values`` (N, C) into a zero (C, Z, Y, X) grid.

    NaN/inf points raise ``ValueError`` here; the raw op ignores them."""
    points = as_points(points)
    require_tensors(values=values)
    if values.dim() != 2 or values.shape[0] != points.shape[0]:
        raise ValueError(f"values must be (N, C) with N={points.shape[0]}, got {tuple(values.shape)}")
    if values.dtype != points.dtype:
        raise TypeError(f"values are {values.dtype} but points are {points.dtype}")
    same_device(("values", values), ("points", points))
    shape = [int(s) for s in grid_shape]
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid_shape must be (Z, Y, X) with positive entries, got {grid_shape}")
    return ops_ns.trilinear_scatter(values.contiguous(), points, as_origin(origin), as_spacing(spacing), shape)
