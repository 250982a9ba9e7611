"""Which groups that no support scan saw keep their flow (``FloxelsConfig.evidence_keep_unseen``,
the ``accurate`` preset; issue 47).

The evidence test cannot judge a group that every support scan shows hidden behind a nearer
return: it is marked ``hidden`` (estimator/evidence.py), and estimator/post.py keeps its flow only
where a rigid motion of its cluster fits the scans clearly better than zero flow (a car
approaching from behind at a sequence's first frame hides its own old place in every later scan).
Zero flow is a weak rival there: the group's place is hidden in every scan, so zero flow leaves
each point unmatched, and almost any motion that lands it on some surface wins. Two tests of the
flow the group would keep:

* it explains the scans clearly better than zero flow itself. Where the sides' test of the
  refinement rejected the rigid motion, the flow kept is the optimiser's, not the motion that fit
  (simulated highway, tuning seed 0: 50 static points at 0.98 m/frame, explaining the scans
  worse than zero flow);
* its moved place is not static structure of the target scan. What stands still in the target
  scan stands there in the support scans too, so a group moved onto it at a support scan's time
  matches that structure, not its own later or earlier self; no object can occupy a place that
  static structure holds. A parked car hidden behind a passing truck in every past scan, in a row
  of parked cars 4.8 m apart, took 4.81 m/frame: moved by one period it lands on the next car
  (simulated urban, tuning seed 1, the last frame: 213 points, 0.00114 of the tuning seeds' mean
  static EPE of 0.0066). A mover's place at another time is road (removed ground), its own body
  or other movers: on the tuning seeds no hidden mover came within ``LANDING_RADIUS`` of the
  target's static points at any support scan's time.
"""

from __future__ import annotations

import torch

from floxels_ext.estimator.group_sums import segment_sum
from floxels_ext.estimator.refine import REFINE_MIN_SPEED, SEARCH_GAIN, TAU, Support, _weighted_residuals
from floxels_ext.ops._small import device_values

__all__ = ["hidden_keeps", "LANDING_RADIUS", "LANDING_SHARE"]

F = torch.ops.floxels

# A moved point "lands" on the target's static structure within this distance (m; two DT cells:
# a passing vehicle's surface and the static surface beside it stay farther apart).
LANDING_RADIUS = 0.2
# A group whose landed share (weighted by the support scans' loss weights) reaches this keeps no flow.
LANDING_SHARE = 0.5


def hidden_keeps(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor, hidden: torch.Tensor,
                 fits: torch.Tensor, supports: list[Support], num_clusters: int | None = None,
                 tau: float = TAU) -> torch.Tensor:
    """(n,) bool: the ``hidden`` points whose group keeps ``flow`` (after the refinement). A group
    (a DBSCAN cluster: ``fits``, its rigid motion fits the scans clearly better than zero flow, is
    set only for clustered points) keeps it where its flow explains the support scans clearly
    better than zero flow (robust DT residuals, the refinement's gain) and moves at most
    ``LANDING_SHARE`` of it (weighted by the scans' loss weights) within ``LANDING_RADIUS`` of a
    target point outside the group that keeps less than ``REFINE_MIN_SPEED`` (the module's
    tests). Host synchronisations: two (the candidate rows, the static rows near their moved places)."""
    cand = hidden & fits
    idx = torch.nonzero(cand).squeeze(1)
    if idx.numel() == 0 or not supports:
        return cand
    lab = labels[idx].to(torch.int64)
    C = int(num_clusters) if num_clusters is not None else int(labels.max()) + 1
    p, u = points[idx], flow[idx]
    wsum = max(sum(s.w for s in supports), 1e-12)
    # the flow kept explains the scans clearly better than zero flow (per cluster, summed)
    # (both motions' residuals in one launch, their sums in one pass: the same bits as apart)
    s_u, s_0 = segment_sum(C, lab, _weighted_residuals(supports, p, [u, torch.zeros_like(u)], tau, False).T).unbind(1)
    keep = s_u < (1 - SEARCH_GAIN) * s_0
    # its moved place at each support scan's time is not the target's static structure; the
    # static points are those inside the moved places' box (a brute-force search over them all
    # would cost hidden points x support scans x the frame's points)
    q = torch.cat([p + s.t * u for s in supports]).contiguous()  # (scans x hidden points, 3)
    lo, hi = q.min(dim=0).values - LANDING_RADIUS, q.max(dim=0).values + LANDING_RADIUS
    static = (flow.norm(dim=1) < REFINE_MIN_SPEED) & ~cand & ((points >= lo) & (points <= hi)).all(dim=1)
    ref = points[static].contiguous()
    if ref.shape[0]:
        hit = ((q - ref[F.nearest_neighbor(q, ref)]).norm(dim=1) <= LANDING_RADIUS).to(p.dtype)
        w = device_values([s.w / wsum for s in supports], p.dtype, p.device)  # (no blocking copy on CUDA)
        landed = (w[:, None] * hit.view(len(supports), -1)).sum(dim=0)
        landed_sum, count = segment_sum(C, lab, torch.stack([landed, torch.ones_like(landed)], 1)).unbind(1)
        share = landed_sum / count.clamp_min(1)
        keep &= share < LANDING_SHARE
    out = torch.zeros_like(cand)
    out[idx] = keep[lab]
    return out
