"""Data-only look-ups of the loss's distance transforms (the dt_loss kernel family): fake and
autograd registration and public wrappers of ``floxels::dt_residual``, ``floxels::dt_sample``
and ``floxels::dt_evidence``.

No gradient flows through these ops: a backward through one of them raises (they serve
evaluation and the rigid refinement's Levenberg-Marquardt loop, which takes its Jacobians from
``dt_sample``'s gradients). The wrappers refuse NaN/inf rows (a reduction and, on CUDA, a host
synchronisation); hot loops call ``torch.ops.floxels.*`` directly on validated tensors, where a
non-finite row gives NaN (docs/ops.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_spacing, require_tensors
from floxels_ext.ops._data_only import check_observed, register_data_only
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops.dt_loss import check_dt_args


@torch.library.register_fake("floxels::dt_residual")
def _residual_fake(points, motion, dts, origins, spacing, time_offsets, weights, cap, squared, observed=None):
    return points.new_empty((points.shape[0],))


@torch.library.register_fake("floxels::dt_sample")
def _sample_fake(points, motion, dts, origins, spacing, time_offsets):
    return points.new_empty((len(dts), points.shape[0], 4))


@torch.library.register_fake("floxels::dt_evidence")
def _evidence_fake(points, flow, labels, cells, dts, origins, spacing, time_offsets, weights, cap, margin, ratio,
                   observed=None):
    n = points.shape[0]
    return (points.new_empty((n,)), points.new_empty((n,), dtype=torch.bool), points.new_empty((n,)),
            points.new_empty((n,)))


for _name in ("dt_residual", "dt_sample", "dt_evidence"):
    register_data_only(_name, " (use dt_sample's gradients, or dt_loss for a differentiable loss)")


def _check(op, points, motion, dts, origins, time_offsets, weights=None, cap=None, motion_name="motion"):
    checked = check_dt_args(op, points, motion, dts, origins, time_offsets, weights, motion_name)
    if cap is not None:
        cap = float(cap)
        if not 0 < cap < float("inf"):
            raise ValueError(f"{op}: cap must be positive and finite, got {cap}")
    return (*checked, cap)


def dt_residual(points: torch.Tensor, motion: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
                spacing: float, time_offsets: Sequence[float], weights: Sequence[float], cap: float,
                squared: bool = False, observed: torch.Tensor | None = None) -> torch.Tensor:
    """Per point (N,): ``sum_k weights[k] * c(min(DT_k(points + time_offsets[k] * motion), cap))``
    with ``c`` the identity or (``squared``) the square, in one launch for all K scans.
    ``observed`` ((N,) int32), optional: scan k counts for point i only where bit k of
    ``observed[i]`` is set (estimator/sight.py: the scan could see the point's position).

    ``dts[k]``: float32 (Z, Y, X) distance transforms, sample (0,0,0) at ``origins[3k:3k+3]``,
    sample spacing ``spacing``; look-ups clamp at the DT border (like ``trilinear_gather`` and
    ``dt_loss``). ``weights`` are used as given (pass ``w / sum(w)`` for a weighted mean).
    ``motion`` (N, 3) like ``points``. Data only: no gradient flows."""
    p, m, d, o, t, w, c = _check("dt_residual", points, motion, dts, origins, time_offsets, weights, cap)
    return ops_ns.dt_residual(p, m, d, o, as_spacing(spacing), t, w, c, bool(squared),
                              check_observed("dt_residual", observed, p))


def dt_sample(points: torch.Tensor, motion: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float],
              spacing: float, time_offsets: Sequence[float]) -> torch.Tensor:
    """(K, N, 4): for every scan k and point i, ``DT_k(q)`` and its spatial gradient
    ``d DT_k / d q`` (x, y, z; per metre) at ``q = points[i] + time_offsets[k] * motion[i]``, in
    one launch. The gradient is that of the trilinear interpolant (what ``trilinear_gather``'s
    backward gives): 0 along an axis where ``q`` lies on or outside the DT's border. The
    gradient with respect to the motion is ``time_offsets[k]`` times it. Data only."""
    p, m, d, o, t, _, _ = _check("dt_sample", points, motion, dts, origins, time_offsets)
    return ops_ns.dt_sample(p, m, d, o, as_spacing(spacing), t)


def _keys(t, name, n, device):
    require_tensors(**{name: t})
    if t.dim() != 1 or t.shape[0] != n or t.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"dt_evidence: {name} must be an ({n},) int32/int64 tensor, got {t.dtype} {tuple(t.shape)}")
    if t.device != device:
        raise ValueError(f"dt_evidence: {name} is on {t.device} but points are on {device}")
    return t


def dt_evidence(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None, cells: torch.Tensor,
                dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float, time_offsets: Sequence[float],
                weights: Sequence[float], cap: float, margin: float, ratio: float,
                observed: torch.Tensor | None = None):
    """The motion-evidence test (estimator/evidence.py) per group of points: groups are runs of
    consecutive rows with equal ``labels`` and, where the label is < 0 (or ``labels`` is None),
    equal ``cells`` (both (N,) int32/int64). Per group, ``rf`` / ``rz``: mean over its points of
    :func:`dt_residual` (not squared) with ``flow`` / with zero flow (sums in float64). Returns
    per point (score = rz - rf, explained = score > max(ratio * rz, margin), rf, rz); a group
    with a non-finite residual gets NaN and False. Deterministic on every device (no atomics),
    a fixed number of kernels whatever K. ``observed``: as :func:`dt_residual` (a scan that
    could not see a point's position adds to neither of its residuals)."""
    p, f, d, o, t, w, c = _check("dt_evidence", points, flow, dts, origins, time_offsets, weights, cap, "flow")
    n = p.shape[0]
    if labels is not None:
        labels = _keys(labels, "labels", n, p.device)
    cells = _keys(cells, "cells", n, p.device)
    if not (abs(float(margin)) < float("inf") and abs(float(ratio)) < float("inf")):
        raise ValueError(f"dt_evidence: margin and ratio must be finite, got {margin}, {ratio}")
    return ops_ns.dt_evidence(p, f, labels, cells, d, o, as_spacing(spacing), t, w, c, float(margin), float(ratio),
                              check_observed("dt_evidence", observed, p))
