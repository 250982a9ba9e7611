"""Reference of ``floxels::velocity_search`` (the per-cluster velocity search,
csrc/kernels/velocity_search.h) in tensor code: the search estimator/refine.py ran before it
was an op. Every cluster at once: all candidates scored by ``dt_residual`` look-ups and segment
means, then the pattern search. The op sums in double per cluster; the results agree to float
rounding (tests/ops/test_velocity_search.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from floxels_ext.reference.ops import cluster_mean, dt_residual

__all__ = ["velocity_search"]


def velocity_search(points: torch.Tensor, segments: torch.Tensor, observed: torch.Tensor | None,
                    dts: Sequence[torch.Tensor], origins: Sequence[float], spacing: float,
                    time_offsets: Sequence[float], weights: Sequence[float], tau: float, num_directions: int,
                    speed_step: float, num_speeds: int, local_steps: int, local_rounds: int):
    """(best (C, 3), best score (C,), zero flow's score (C,)): see ``floxels_ext.ops.velocity_search``."""
    dev, dt = points.device, points.dtype
    C = segments.shape[0] - 1
    cid = torch.repeat_interleave(torch.arange(C, device=dev), segments.diff())
    ar = torch.arange(C, device=dev)

    def score(cand):  # (C, K, 3) -> (K, C)
        K = cand.shape[1]
        v = cand.transpose(0, 1)[:, cid]  # (K, m, 3)
        x = points.unsqueeze(0).expand_as(v).reshape(-1, 3)
        ob = None if observed is None else observed.repeat(K)
        r = dt_residual(x, v.reshape(-1, 3), dts, origins, spacing, time_offsets, weights, tau, False, ob)
        return cluster_mean(r.view(K, -1).T, cid, C).T

    xy = points[:, :2].to(torch.float64)
    d = xy - cluster_mean(xy, cid, C)[cid]
    cov = cluster_mean(d[:, [0, 0, 1]] * d[:, [0, 1, 1]], cid, C)  # (C, 3): xx, xy, yy
    ang = 0.5 * torch.atan2(2 * cov[:, 1], cov[:, 0] - cov[:, 2])
    axis = torch.stack([torch.cos(ang), torch.sin(ang)], 1).to(dt)  # (C, 2)
    a = torch.arange(num_directions, device=dev, dtype=dt) * (2 * math.pi / num_directions)
    ca, sa = torch.cos(a), torch.sin(a)
    dirs = torch.stack([axis[:, None, 0] * ca - axis[:, None, 1] * sa,
                        axis[:, None, 0] * sa + axis[:, None, 1] * ca], -1)  # (C, D, 2)
    speeds = torch.arange(1, num_speeds + 1, device=dev, dtype=dt) * speed_step
    v2 = (dirs[:, :, None, :] * speeds[None, None, :, None]).reshape(C, -1, 2)
    cand = torch.cat([v2, torch.zeros_like(v2[..., :1])], -1)
    cand = torch.cat([torch.zeros_like(cand[:, :1]), cand], 1)  # candidate 0: zero flow
    scores = score(cand)
    zero = scores[0]
    k = scores.argmin(0)
    best, best_score = cand[ar, k], scores[k, ar]
    off1 = torch.arange(-1, 2, device=dev, dtype=dt)
    gx, gy = torch.meshgrid(off1, off1, indexing="ij")
    unit = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.zeros_like(gx.reshape(-1))], 1)
    step = speed_step
    for _ in range(local_steps):
        for _ in range(local_rounds):
            cand = best[:, None, :] + step * unit[None]
            s = score(cand)
            smin, k = s.min(0)
            better = smin < best_score
            best = torch.where(better[:, None], cand[ar, k], best)
            best_score = torch.minimum(best_score, smin)
            if not bool(better.any()):
                break
        step /= 2
    return best, best_score, zero
