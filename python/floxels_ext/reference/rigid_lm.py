"""Reference of ``floxels::rigid_lm`` (the rigid refinement's Levenberg-Marquardt loop,
csrc/kernels/rigid_lm.h) in tensor code: the loop estimator/refine.py ran before it was an op.
Every cluster at once: per step one ``dt_sample`` look-up of every support scan, the clusters'
normal equations and costs from segment sums, and a closed-form 3 x 3 solve in float64. The op
sums in double and solves by the adjugate; results agree to float rounding (tests/ops/test_rigid_lm.py)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from floxels_ext.reference.ops import cluster_mean, dt_sample

__all__ = ["rigid_lm"]

LAM_START, LAM_DOWN, LAM_UP, LAM_MIN, LAM_MAX, DAMP = 1e-2, 0.3, 10.0, 1e-6, 1e6, 1e-3


def _solve3(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``A^-1 b`` of (C, 3, 3) ``A`` by the adjugate, in float64."""
    r0, r1, r2 = A.to(torch.float64).unbind(1)
    cof = torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], 1)
    det = (r0 * cof[:, 0]).sum(-1)
    return (cof.transpose(1, 2) @ b.to(torch.float64).unsqueeze(-1)).squeeze(-1) / det[:, None]


def rigid_lm(points: torch.Tensor, rel: torch.Tensor, segments: torch.Tensor, theta: torch.Tensor, vz: torch.Tensor,
             dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float, time_offsets: Sequence[float],
             weights: Sequence[float], tau: float, iters: int):
    """(theta (C, 3), cost (C,)): see ``floxels_ext.ops.rigid_lm``."""
    dev, dt = points.device, points.dtype
    C = theta.shape[0]
    cid = torch.repeat_interleave(torch.arange(C, device=dev), segments.diff())
    tk = torch.tensor(list(time_offsets), dtype=dt, device=dev)[:, None, None]
    wk = torch.tensor(list(weights), dtype=dt, device=dev)[:, None]
    o, z = torch.ones_like(rel[:, 0]), torch.zeros_like(rel[:, 0])
    M = torch.stack([torch.stack([o, z, -rel[:, 1], z], 1), torch.stack([z, o, rel[:, 0], z], 1),
                     torch.stack([z, z, z, o], 1)], 1)  # u = M (vx, vy, w, vz)
    Mt = M[:, :, :3]
    ia = torch.tensor([0, 0, 0, 1, 1, 2], device=dev)  # upper triangle of the 3 x 3 normal matrix
    ib = torch.tensor([0, 1, 2, 1, 2, 2], device=dev)
    sym = torch.tensor([[0, 1, 2], [1, 3, 4], [2, 4, 5]], device=dev)

    def normal(th):
        """(C, 10): H's upper triangle, b and the cost, each a mean over the cluster's rows."""
        u = (M @ torch.cat([th, vz[:, None]], 1)[cid].unsqueeze(-1)).squeeze(-1)
        smp = dt_sample(points, u, dts, origins, spacing, time_offsets)  # (K, m, 4)
        d, g = smp[..., 0], smp[..., 1:]
        J = tk * (g.unsqueeze(-2) @ Mt).squeeze(-2)  # (K, m, 3)
        wJ = ((d < tau) * wk).unsqueeze(-1) * J
        per = torch.cat([(wJ[..., ia] * J[..., ib]).sum(0), (wJ * d.unsqueeze(-1)).sum(0),
                         (wk * d.clamp_max(tau).square()).sum(0).unsqueeze(-1)], 1)
        return cluster_mean(per, cid, C)

    S = normal(theta)
    lam = torch.full((C,), LAM_START, dtype=dt, device=dev)
    for _ in range(iters):
        H = S[:, sym]
        A = H + lam[:, None, None] * (torch.diag_embed(torch.diagonal(H, dim1=1, dim2=2))
                                      + DAMP * torch.eye(3, dtype=dt, device=dev))
        trial = theta - _solve3(A, S[:, 6:9]).to(dt)
        St = normal(trial)
        better = St[:, 9] < S[:, 9]
        theta = torch.where(better[:, None], trial, theta)
        S = torch.where(better[:, None], St, S)
        lam = torch.where(better, lam * LAM_DOWN, lam * LAM_UP).clamp(LAM_MIN, LAM_MAX)
    return theta, S[:, 9]
