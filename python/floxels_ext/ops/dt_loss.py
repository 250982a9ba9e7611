"""Fused multi-scan distance-transform loss: fake + autograd registration and public wrappers."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_points, as_spacing, require_tensors, same_device
from floxels_ext.ops._lib import ops_ns

MAX_SCANS = 32  # csrc/kernels/dt_loss.h kMaxScans: per-scan metadata travels in the kernel parameters


@torch.library.register_fake("floxels::dt_loss")
def _fake(points, flow, dts, origins, spacing, time_offsets, weights, truncation):
    return flow.new_empty(())


@torch.library.register_fake("floxels::dt_loss_backward")
def _bwd_fake(grad, points, flow, dts, origins, spacing, time_offsets, weights, truncation):
    return torch.empty_like(flow)


@torch.library.register_fake("floxels::dt_loss_fwd_bwd")
def _fwd_bwd_fake(points, flow, dts, origins, spacing, time_offsets, weights, truncation):
    return flow.new_empty(()), torch.empty_like(flow)


def _setup(ctx, inputs, output):
    points, flow, dts, origins, spacing, time_offsets, weights, truncation = inputs
    ctx.save_for_backward(points, flow, *dts)
    ctx.args = (origins, spacing, time_offsets, weights, truncation)


def _backward(ctx, grad):
    points, flow, *dts = ctx.saved_tensors
    # The loss is differentiable in the flow only; points and distance transforms are data.
    if ctx.needs_input_grad[0]:
        raise RuntimeError("floxels::dt_loss is not differentiable with respect to points")
    g = ops_ns.dt_loss_backward(grad, points, flow, dts, *ctx.args) if ctx.needs_input_grad[1] else None
    # Tensor[] inputs need one (None) gradient per element.
    return None, g, [None] * (len(ctx.saved_tensors) - 2), None, None, None, None, None


torch.library.register_autograd("floxels::dt_loss", _backward, setup_context=_setup)


def check_dt_args(op, points, motion, dts, origins, time_offsets, weights=None, motion_name="motion"):
    """The arguments every op of the dt_loss family shares, checked for the Python wrappers
    (dt_loss, dt_residual, dt_sample, dt_evidence): points and a per-point motion of one shape
    and dtype, 1..MAX_SCANS non-empty float32 (Z, Y, X) DTs on their device, 3 origins and one
    time offset (and weight, when given) per DT. Returns them normalised (contiguous DTs, float
    lists; ``weights`` stays None when not given)."""
    points = as_points(points)
    require_tensors(**{motion_name: motion})
    if motion.shape != points.shape:
        raise ValueError(f"{op}: {motion_name} must have the shape of points {tuple(points.shape)}, "
                         f"got {tuple(motion.shape)}")
    if motion.dtype != points.dtype:
        raise TypeError(f"{op}: {motion_name} is {motion.dtype} but points are {points.dtype}")
    motion = as_points(motion, motion_name)
    dts = list(dts)
    if not dts:
        raise ValueError(f"{op} needs at least one distance transform")
    if len(dts) > MAX_SCANS:
        raise ValueError(f"{op} supports at most {MAX_SCANS} distance transforms, got {len(dts)}")
    for k, d in enumerate(dts):
        if not isinstance(d, torch.Tensor) or d.dim() != 3 or d.dtype != torch.float32 or d.numel() == 0:
            raise ValueError(f"{op}: dts[{k}] must be a non-empty float32 (Z, Y, X) grid, got "
                             f"{getattr(d, 'dtype', type(d).__name__)} {tuple(getattr(d, 'shape', ()))}")
    same_device(("points", points), (motion_name, motion), *[(f"dts[{k}]", d) for k, d in enumerate(dts)])
    K = len(dts)
    origins = [float(v) for v in origins]
    time_offsets = [float(t) for t in time_offsets]
    if len(origins) != 3 * K or len(time_offsets) != K or (weights is not None and len(weights) != K):
        raise ValueError(f"{op}: with {K} distance transforms, origins needs {3 * K} values and "
                         f"time_offsets{'/weights' if weights is not None else ''} {K} each; got {len(origins)}, "
                         f"{len(time_offsets)}{'' if weights is None else f', {len(weights)}'}")
    if weights is not None:
        weights = [float(w) for w in weights]
    return points, motion, [d.contiguous() for d in dts], origins, time_offsets, weights


def _check(points, flow, dts, origins, time_offsets, weights, truncation):
    checked = check_dt_args("dt_loss", points, flow, dts, origins, time_offsets, weights, motion_name="flow")
    if not float(truncation) > 0:
        raise ValueError(f"truncation must be positive, got {truncation}")
    return (*checked, float(truncation))


def dt_loss(points: torch.Tensor, flow: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
            spacing: float, time_offsets: Sequence[float], weights: Sequence[float], truncation: float = 5.0):
    """``sum_k weights[k] * mean_i DT_k(points_i + time_offsets[k] * flow_i)``, differentiable in flow.

    Each ``dts[k]`` is a float32 (Z, Y, X) distance transform whose sample (0,0,0) sits at
    ``origins[3k:3k+3]``; values interpolated to ``>= truncation`` count as 0 with no gradient.
    NaN/inf points or flows raise ``ValueError`` here; with the raw op such a row makes the
    loss NaN and gets a zero gradient row (docs/ops.md, non-finite input).

    Speed: the kernels gather 8 DT samples per point and scan; ordering the points
    spatially (e.g. by voxel index, once per frame) lets neighbouring points share cache
    lines and is markedly faster than sensor order on large grids.
    """
    p, f, d, o, t, w, tr = _check(points, flow, dts, origins, time_offsets, weights, truncation)
    return ops_ns.dt_loss(p, f, d, o, as_spacing(spacing), t, w, tr)


def dt_loss_fwd_bwd(points, flow, dts, origins, spacing, time_offsets, weights, truncation=5.0):
    """(loss, d loss / d flow) of :func:`dt_loss` in one fused pass (no autograd graph)."""
    p, f, d, o, t, w, tr = _check(points, flow, dts, origins, time_offsets, weights, truncation)
    return ops_ns.dt_loss_fwd_bwd(p, f, d, o, as_spacing(spacing), t, w, tr)
