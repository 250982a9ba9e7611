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


def _check(points, flow, dts, origins, time_offsets, weights, truncation):
    points = as_points(points)
    require_tensors(flow=flow)
    if flow.shape != points.shape:
        raise ValueError(f"flow must have the shape of points {tuple(points.shape)}, got {tuple(flow.shape)}")
    if flow.dtype != points.dtype:
        raise TypeError(f"flow is {flow.dtype} but points are {points.dtype}")
    flow = as_points(flow, "flow")
    dts = list(dts)
    if not dts:
        raise ValueError("dt_loss needs at least one distance transform")
    if len(dts) > MAX_SCANS:
        raise ValueError(f"dt_loss supports at most {MAX_SCANS} distance transforms, got {len(dts)}")
    for k, d in enumerate(dts):
        if not isinstance(d, torch.Tensor) or d.dim() != 3 or d.dtype != torch.float32 or d.numel() == 0:
            raise ValueError(f"dts[{k}] must be a non-empty float32 (Z, Y, X) grid, got "
                             f"{getattr(d, 'dtype', type(d).__name__)} {tuple(getattr(d, 'shape', ()))}")
    named = [("points", points), ("flow", flow)] + [(f"dts[{k}]", d) for k, d in enumerate(dts)]
    same_device(*named)
    K = len(dts)
    origins = [float(v) for v in origins]
    if len(origins) != 3 * K or len(time_offsets) != K or len(weights) != K:
        raise ValueError(f"with {K} distance transforms, origins needs {3 * K} values and "
                         f"time_offsets/weights {K} each; got {len(origins)}, {len(time_offsets)}, {len(weights)}")
    if not float(truncation) > 0:
        raise ValueError(f"truncation must be positive, got {truncation}")
    return points, flow, [d.contiguous() for d in dts], origins, \
        [float(t) for t in time_offsets], [float(w) for w in weights], float(truncation)


def dt_loss(points: torch.Tensor, flow: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
            spacing: float, time_offsets: Sequence[float], weights: Sequence[float], truncation: float = 5.0):
    """``sum_k weights[k] * mean_i DT_k(points_i + time_offsets[k] * flow_i)``, differentiable in flow.

    Each ``dts[k]`` is a float32 (Z, Y, X) distance transform whose sample (0,0,0) sits at
    ``origins[3k:3k+3]``; values interpolated to ``>= truncation`` count as 0 with no gradient.
    NaN/inf points or flows raise ``ValueError`` here; with the raw op such a row makes the
    loss NaN and gets a zero gradient row (README "Op reference", non-finite input).

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
