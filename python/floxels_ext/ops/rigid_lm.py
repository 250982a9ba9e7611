"""The rigid refinement's Levenberg-Marquardt loop as one op (``floxels::rigid_lm``,
csrc/kernels/rigid_lm.h): fake and autograd registration and the checked wrapper.

Why an op: the loop in tensor code (``floxels_ext.reference.rigid_lm``, the reference) is ~60
small tensor ops per step, so on a GPU its time was the host's dispatching them (15-22 ms per
call, more than the paper's whole frame); as one op it is one launch per call on CUDA (a block
per cluster runs every step) and one parallel loop over clusters on the CPU. Data only: no
gradient flows.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.ops._checks import as_spacing, require_tensors
from floxels_ext.ops._data_only import check_segments, register_data_only
from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops.dt_loss import check_dt_args

__all__ = ["rigid_lm", "MAX_ITERS"]

MAX_ITERS = 1000  # csrc/cpu/rigid_lm_args.h


@torch.library.register_fake("floxels::rigid_lm")
def _rigid_lm_fake(points, rel, segments, theta, vz, dts, origins, spacing, time_offsets, weights, tau, iters):
    return theta.new_empty(theta.shape), theta.new_empty((theta.shape[0],))


register_data_only("rigid_lm")


def rigid_lm(points: torch.Tensor, rel: torch.Tensor, segments: torch.Tensor, theta: torch.Tensor,
             vz: torch.Tensor, dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float,
             time_offsets: Sequence[float], weights: Sequence[float], tau: float, iters: int):
    """Levenberg-Marquardt on every cluster's planar rigid motion at once; returns ``(theta
    (C, 3), cost (C,))``.

    Cluster ``c`` owns rows ``segments[c]:segments[c + 1]`` of ``points`` (m, 3) (``segments``:
    int64 (C + 1,), non-decreasing from 0 to m) and ``rel`` (m, 3), each row's offset from its
    cluster's centroid. Its motion ``theta[c] = (vx, vy, w)`` moves a row ``u = (vx - w rel_y,
    vy + w rel_x, vz[c])`` per frame; the cost is the mean over its rows of ``sum_k weights[k]
    min(DT_k(p + time_offsets[k] u), tau)^2`` and each step solves the damped normal equations of
    its inliers (``kernels/rigid_lm.h``), taken when the cost falls. ``dts``/``origins``/
    ``spacing``: as :func:`~floxels_ext.ops.dt_residual`. Data only."""
    p, r, d, o, t, w = check_dt_args("rigid_lm", points, rel, dts, origins, time_offsets, weights, "rel")
    require_tensors(theta=theta, vz=vz)
    C = theta.shape[0] if theta.dim() == 2 else -1
    if theta.dim() != 2 or theta.shape[1] != 3 or theta.dtype != p.dtype:
        raise ValueError(f"rigid_lm: theta must be a (C, 3) {p.dtype} tensor, got {theta.dtype} {tuple(theta.shape)}")
    if vz.shape != (C,) or vz.dtype != p.dtype:
        raise ValueError(f"rigid_lm: vz must be a ({C},) {p.dtype} tensor, got {vz.dtype} {tuple(vz.shape)}")
    for name, v in (("theta", theta), ("vz", vz)):
        if v.device != p.device:
            raise ValueError(f"rigid_lm: {name} is on {v.device} but points are on {p.device}")
    segments = check_segments("rigid_lm", segments, p, C)
    tau = float(tau)
    if not 0 < tau < float("inf"):
        raise ValueError(f"rigid_lm: tau must be positive and finite, got {tau}")
    if isinstance(iters, bool) or not isinstance(iters, int) or not 0 <= iters <= MAX_ITERS:
        raise ValueError(f"rigid_lm: iters must be an integer in [0, {MAX_ITERS}], got {iters!r}")
    return ops_ns.rigid_lm(p, r, segments, theta.contiguous(), vz.contiguous(), d, o,
                           as_spacing(spacing), t, w, tau, iters)
