"""Spreading the refined rigid motions to the rest of their objects (``FloxelsConfig.refine_spread``,
the ``accurate`` preset; issue 47).

DBSCAN (eps 0.5 m, the paper's) splits a far or sparsely sampled vehicle: a 32-beam lidar's rings
lie 0.6 m apart at 40 m, so a car there is a few clusters and unclustered points. The rigid
refinement (estimator/refine.py) fixes the clusters it accepts, but the object's other points keep
the optimiser's flow, which for fast movers stops short (a highway car at 2.7 m/frame: 1.2), or
lose it in the evidence test (the flow of a small cluster pointing the wrong way explains nothing).

Each point near an accepted cluster (within ``radius`` of its sample points' box), outside any
accepted cluster, is offered the rigid motion of its nearest accepted sample point's cluster (for
a DBSCAN cluster: every point of it, each the motion of its own nearest). A group (a DBSCAN cluster,
or an unclustered point alone) takes the offered motion where it explains the support scans better
than its flow and clearly better than zero flow (robust DT residuals, ``min(DT, tau)``, the loss's
weights, counting only the scans that saw each point where the sights are known): a static point
beside a passing car is where the scans show it, so the car's motion explains them worse.
"""

from __future__ import annotations

import torch

from floxels_ext.estimator.group_sums import segment_sum
from floxels_ext.estimator.host_reads import Steps, rows_where, run_one
from floxels_ext.estimator.refine import SEARCH_GAIN, TAU, RigidMotions, Support, _weighted_residuals

__all__ = ["spread_rigid", "spread_rigid_steps", "BOX_CHUNK"]

F = torch.ops.floxels

BOX_CHUNK = 64  # accepted clusters tested against every point at once (memory: points x chunk x 3)


def spread_rigid(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor, supports: list[Support],
                 motions: RigidMotions, radius: float, tau: float = TAU,
                 observed: torch.Tensor | None = None) -> torch.Tensor:
    """``flow`` with the groups near accepted rigid motions that one of them explains better (the
    module's test). ``labels``: the DBSCAN labels of ``points`` (-1: none); ``observed``: (n,) int32
    sight bits (estimator/sight.py) or None. Host synchronisations: two (the numbers of accepted
    sample rows and clusters, then of offered points; :func:`spread_rigid_steps` yields them)."""
    return run_one(spread_rigid_steps(points, flow, labels, supports, motions, radius, tau, observed))


def spread_rigid_steps(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor, supports: list[Support],
                       motions: RigidMotions, radius: float, tau: float = TAU,
                       observed: torch.Tensor | None = None) -> Steps:
    """:func:`spread_rigid` as steps of ``estimator/host_reads.py`` (its two host reads yielded)."""
    m = motions
    ref_rows = m.accept[m.cid]
    num_ref, num_acc = yield [ref_rows.sum(), m.accept.sum()]
    if num_ref == 0:
        return flow
    sample = rows_where(ref_rows, num_ref)
    ref, ref_c = m.q[sample], m.cid[sample]
    acc = rows_where(m.accept, num_acc)
    C = m.accept.shape[0]
    inf = torch.full((C, 3), float("inf"), dtype=points.dtype, device=points.device)
    lo = inf.scatter_reduce(0, ref_c[:, None].expand(-1, 3), ref, "amin")[acc] - radius
    hi = (-inf).scatter_reduce(0, ref_c[:, None].expand(-1, 3), ref, "amax")[acc] + radius
    near = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    for a in range(0, num_acc, BOX_CHUNK):
        inside = (points[:, None] >= lo[None, a:a + BOX_CHUNK]) & (points[:, None] <= hi[None, a:a + BOX_CHUNK])
        near |= inside.all(dim=2).any(dim=1)
    lab = labels.to(torch.int64)
    free = ~m.take
    offered = near & free
    # a DBSCAN cluster touched by an offered point is offered whole (one motion test per cluster);
    # the points of no cluster mark a spare last row (no boolean indexing, and a scatter of a
    # scalar, not an assignment, whose value a CUDA tensor copies from the host: no synchronisation)
    touched = torch.zeros(C + 1, dtype=torch.bool, device=points.device).scatter_(
        0, torch.where(offered & (lab >= 0), lab, torch.full_like(lab, C)), True)
    offered |= free & (lab >= 0) & touched[lab.clamp_min(0)]
    (num_offered,) = yield [offered.sum()]
    if num_offered == 0:
        return flow
    idx = rows_where(offered, num_offered)
    p = points[idx]
    j = F.nearest_neighbor(p.contiguous(), ref.contiguous())
    close = (p - ref[j]).norm(dim=1) <= radius
    u = m.motion_at(p, ref_c[j])
    ob = None if observed is None else observed[idx]
    f = flow[idx]
    # the three motions' residuals in one launch, their group sums in one pass (each column its
    # own fixed-point sum: the same bits as one call each)
    r = _weighted_residuals(supports, p, [u, f, torch.zeros_like(p)], tau, False, ob)
    # groups: a DBSCAN cluster, or an unclustered point alone (only if within the radius)
    li = lab[idx]
    key = torch.where(li >= 0, li, C + torch.arange(idx.shape[0], device=points.device))
    rows = C + idx.shape[0]
    s_u, s_f, s_0 = segment_sum(rows, key, r.T).unbind(1)
    better = (s_u < s_f) & (s_u < (1 - SEARCH_GAIN) * s_0)
    take = better[key] & ((li >= 0) | close)
    out = flow.clone()
    out[idx] = torch.where(take[:, None], u.to(flow.dtype), f)
    return out
