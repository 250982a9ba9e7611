"""Beyond the paper (issue 33, the ``accurate`` preset): per-cluster motion ingredients that use
the support scans' distance transforms directly, before and after the grid optimisation. The
preset uses :func:`rigid_refine`, whose loop also starts from the refined clusters' searched
velocities (``refine_search``); :func:`cluster_velocity_search` for every cluster as the grid's
start (``velocity_search=True``) is left out of it (on top of the preset it helps dynamic EPE but
not every class: bench/RESULTS.md).

* :func:`cluster_velocity_search`: for every DBSCAN cluster of the target, the constant
  horizontal velocity that best explains the support scans, searched over candidate
  directions (the cluster's principal axis and its rotations by 45 degrees) and speeds, then
  refined locally. The grid is started from it (:func:`vertex_init`). Why: with few support
  scans the paper's loss has a shallow valley from zero to the true speed (a car's points
  slide onto its own next-frame surface; the regularisers pull towards zero), so Adam from
  zero stops short (bench/RESULTS.md: cars at ~0.5-0.6 of their speed on the AV2 pair).
* :func:`rigid_refine`: each moving cluster is refined as a rigid body (translation and yaw
  rate, constant over the window) by Levenberg-Marquardt on the distance transforms,
  started from the cluster's mean Floxels flow. A DT-based ICP (point-to-surface distances
  from the EDT, their gradients as normals): directions the scans do not constrain (a flat
  side sliding along itself) have no gradient and keep the start value (damping). With
  ``search``, also started from the cluster's searched velocity; the lower cost wins (in a
  one-sided window, only where it explains the nearer and the farther scans each no worse).

Both score a motion with the robust residual ``min(DT_t(p + t u), tau)`` over the loss's
support scans, weighted like the loss (``w(t) = 1/t^2``); a cluster's result is kept only if it
explains the scans better than the alternative by a margin. The search and the refinement's
Levenberg-Marquardt loop are ops (``floxels::velocity_search``, ``floxels::rigid_lm``: three
launches and one on CUDA; their references are in ``floxels_ext.reference``);
the rest is a few tensor ops and ``floxels::dt_residual`` look-ups, on the CPU and CUDA alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from floxels_ext.estimator.group_sums import cluster_means, segment_sum
from floxels_ext.estimator.host_reads import Steps, rows_where, run_one

__all__ = ["Support", "supports_of", "robust_residual", "cluster_velocity_search", "vertex_init", "rigid_refine",
           "rigid_refine_steps", "RigidMotions", "one_sided_halves"]

F = torch.ops.floxels

# Robust residual cap (m): a point whose warped position lies farther than this from the
# support scan counts as unmatched (occlusion, scan edge) and costs tau, without gradient.
TAU = 1.0
# Velocity search: horizontal speeds 0.1 .. MAX_SPEED m/frame (4 m per 0.1 s = 144 km/h) in
# SPEED_STEP steps along 8 directions, then a local search around the best; at most
# SEARCH_POINTS points per cluster (evenly spread over the cluster's rows).
MAX_SPEED = 4.0
SPEED_STEP = 0.1
NUM_DIRECTIONS = 8
SEARCH_POINTS = 64
LOCAL_STEPS = 4    # local search steps SPEED_STEP, /2, /4, /8
LOCAL_ROUNDS = 4   # moves per step at most
# Evidence a cluster moves: its best velocity lowers the cluster's mean robust residual below
# (1 - SEARCH_GAIN) times that of zero flow, and by at least SEARCH_MIN_DROP metres.
SEARCH_GAIN = 0.3
SEARCH_MIN_DROP = 0.02
MIN_CLUSTER_POINTS = 10
# Rigid refinement: clusters whose mean flow is at least REFINE_MIN_SPEED m/frame, at most
# REFINE_POINTS points each, REFINE_ITERS Levenberg-Marquardt steps.
REFINE_MIN_SPEED = 0.1
REFINE_POINTS = 256
REFINE_ITERS = 10


@dataclass
class Support:
    """One support scan as the ingredients see it: its DT (Z, Y, X), the DT's origin and
    spacing, the time offset t (frames) and the loss weight w(t)."""

    values: torch.Tensor
    origin: list[float]
    spacing: float
    t: float
    w: float


def supports_of(dts, origins, offsets, weights, spacing: float) -> list[Support]:
    return [Support(d, list(o), float(spacing), float(t), float(w))
            for d, o, t, w in zip(dts, origins, offsets, weights)]


def robust_residual(points: torch.Tensor, motion: torch.Tensor, supports: list[Support], tau: float = TAU,
                    observed: torch.Tensor | None = None):
    """Per point, the loss-weighted mean over support scans of ``min(DT_t(p + t u), tau)``
    for per-frame motions ``motion`` (n, 3) (or broadcastable to ``points``); with ``observed``
    ((n,) int32 bits, estimator/sight.py) only the scans that could see the point count."""
    wsum = sum(s.w for s in supports)
    return _weighted_residual(supports, points, motion.expand_as(points), tau, squared=False,
                              observed=observed) / max(wsum, 1e-12)


def _cluster_index(labels: torch.Tensor, min_points: int, num_clusters: int | None = None):
    """(cluster id per point (-1: not searched), number of clusters, points per cluster).
    ``num_clusters``: ``labels.max() + 1`` if known (saves a host synchronisation)."""
    lab = labels.to(torch.int64)
    C = int(num_clusters) if num_clusters is not None else (int(lab.max()) + 1 if lab.numel() else 0)
    if C <= 0:
        return lab, 0, lab.new_zeros(0)
    counts = torch.zeros(C, dtype=torch.int64, device=lab.device).index_add_(
        0, lab.clamp_min(0), (lab >= 0).to(torch.int64))
    keep = counts >= min_points
    lab = torch.where((lab >= 0) & keep[lab.clamp_min(0)], lab, torch.full_like(lab, -1))
    return lab, C, torch.where(keep, counts, torch.zeros_like(counts))


def _subsample(lab: torch.Tensor, C: int, counts: torch.Tensor, k: int) -> torch.Tensor:
    """Rows of at most ``k`` points per cluster, evenly spread over each cluster's rows
    (deterministic), grouped by cluster in row order. ``counts``: points of each cluster with
    ``lab >= 0``. One host synchronisation (the number of rows kept)."""
    order, keep = _subsample_mask(lab, C, counts, k)
    return order[keep]


def _subsample_mask(lab: torch.Tensor, C: int, counts: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(``order``, ``keep``): :func:`_subsample`'s rows are ``order[keep]`` (no synchronisation)."""
    key = torch.where(lab >= 0, lab, torch.full_like(lab, C))  # points of no cluster sort last
    # int32 keys (C < 2 ** 31): a CUDA radix sort makes half the passes of int64's, same order
    order = torch.argsort(key.to(torch.int32), stable=True)
    ks = key[order]
    counts = torch.cat([counts, counts.new_zeros(1)])
    start = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])
    rank = torch.arange(ks.numel(), device=lab.device) - start[ks]
    stride = torch.clamp((counts[ks] + k - 1) // k, min=1)
    return order, (ks < C) & (rank % stride == 0)


def _segments(cid: torch.Tensor, C: int) -> torch.Tensor:
    """(C + 1,) row offsets of the clusters of sample rows grouped by cluster (``cid``
    non-decreasing): cluster c owns rows ``[offsets[c], offsets[c + 1])``, the ``segments`` of
    ``floxels::velocity_search`` / ``floxels::rigid_lm``."""
    return torch.searchsorted(cid, torch.arange(C + 1, device=cid.device, dtype=cid.dtype))


def _planar(theta: torch.Tensor, rel: torch.Tensor, vz: torch.Tensor) -> torch.Tensor:
    """Per-row motion (m, 3) of planar rigid motions ``theta`` (m, 3) = (vx, vy, yaw rate) at
    offsets ``rel`` (m, 3) from their centroids, vertical velocity ``vz`` (m,):
    ``(vx - w r_y, vy + w r_x, vz)`` (kernels/rigid_lm.h)."""
    return torch.stack([theta[:, 0] - theta[:, 2] * rel[:, 1], theta[:, 1] + theta[:, 2] * rel[:, 0], vz], 1)


def cluster_velocity_search(points: torch.Tensor, labels: torch.Tensor | None, supports: list[Support],
                            tau: float = TAU, observed: torch.Tensor | None = None,
                            num_clusters: int | None = None) -> torch.Tensor:
    """Per-point initial velocity (n, 3) in m/frame: each cluster's best constant horizontal
    velocity where it explains the support scans clearly better than zero flow (see the
    module's constants), zero elsewhere (noise points, small clusters, no evidence). ``observed``:
    (n,) int32 bits, which support scans could see each point (see :func:`robust_residual`).
    ``num_clusters``: ``labels.max() + 1`` if known (saves a host synchronisation)."""
    out = torch.zeros_like(points)
    if labels is None or points.shape[0] == 0 or not supports:
        return out
    lab, C, counts = _cluster_index(labels, MIN_CLUSTER_POINTS, num_clusters)
    if C == 0:
        return out
    rows = _subsample(lab, C, counts, SEARCH_POINTS)
    if rows.numel() == 0:
        return out
    q, cid = points[rows], lab[rows]
    ob = None if observed is None else observed[rows].contiguous()
    best, best_score, zero = _search(q, _segments(cid, C), ob, supports, tau)
    moving = (best_score < (1 - SEARCH_GAIN) * zero) & (zero - best_score >= SEARCH_MIN_DROP)
    vel = torch.where(moving[:, None], best, torch.zeros_like(best))
    has = lab >= 0
    out[has] = vel[lab[has]]
    return out


def vertex_init(point_vel: torch.Tensor, corner_idx: torch.Tensor, corner_w: torch.Tensor,
                num_vertices: int) -> torch.Tensor:
    """Grid parameters (M, 3) whose trilinear interpolation reproduces per-point velocities
    where one velocity covers a vertex's points: each vertex gets the corner-weighted mean
    velocity of the points that touch it (vertices touched only by points with zero
    velocity stay zero)."""
    idx = corner_idx.reshape(-1).to(torch.int64)
    w = corner_w.reshape(-1, 1).to(point_vel.dtype)
    v = point_vel.repeat_interleave(8, 0)
    num = segment_sum(num_vertices, idx, w * v)
    den = segment_sum(num_vertices, idx, w)
    return num / den.clamp_min(1e-12)


def _search(q: torch.Tensor, segments: torch.Tensor, observed: torch.Tensor | None, supports: list[Support],
            tau: float):
    """(best velocity (C, 3), its score (C,), zero flow's score (C,)) of every cluster of the
    sample rows ``q`` (grouped by cluster, ``segments``), with the module's search constants: the
    whole search in one op (floxels::velocity_search: three launches on CUDA; the reference is
    floxels_ext.reference.velocity_search)."""
    dts, origins, spacing, ts, ws = _packed(supports)
    wsum = max(sum(ws), 1e-12)
    return F.velocity_search(q.contiguous(), segments, observed, dts, origins, spacing, ts, [w / wsum for w in ws],
                             float(tau), NUM_DIRECTIONS, SPEED_STEP, int(round(MAX_SPEED / SPEED_STEP)), LOCAL_STEPS,
                             LOCAL_ROUNDS)


def _packed(supports: list[Support]):
    """The supports as the ``floxels::dt_*`` look-ups take them: (dts, flat origins, spacing,
    time offsets, weights)."""
    spacing = supports[0].spacing
    if any(s.spacing != spacing for s in supports):
        raise ValueError("the support scans' distance transforms must share one sample spacing")
    return ([s.values for s in supports], [float(v) for s in supports for v in s.origin], spacing,
            [s.t for s in supports], [s.w for s in supports])


def one_sided_halves(supports: list[Support]) -> list[list[Support]] | None:
    """A window whose support scans lie on one side of the target (a sequence's first or last
    frame): that side's nearer and farther half (by |t|; the odd scan joins the farther half).
    None where the window has scans on both sides, or one scan.

    The refinement's searched start must explain both halves no worse than the start from the
    flow (:func:`rigid_refine_steps`). The true constant motion explains the near and the far
    scans alike; an alias along the object's own surface fits the near, heavily weighted (1/t^2)
    scans at the far ones' cost: an oncoming bus beside the ego crosses each scan's 3 m crop, its
    front part's true motion lands in the near scans' crop (unmatched), and a motion of ~4.8
    m/frame slides it along its flat side onto its own rear part there (bench/RESULTS.md,
    "`accurate` on one-sided windows"). In a window with both sides, the sides' test judges the
    kept motion on the past and on the future scans instead."""
    if any(s.t < 0 for s in supports) and any(s.t > 0 for s in supports):
        return None
    side = sorted(supports, key=lambda s: abs(s.t))
    half = len(side) // 2
    return [side[:half], side[half:]] if half else None


def _worse_on_a_side(sides, q: torch.Tensor, cid: torch.Tensor, C: int, u: torch.Tensor, ref: torch.Tensor,
                     tau: float) -> torch.Tensor:
    """(C,) bool: the clusters whose per-row motion ``u`` explains some group of ``sides`` (lists of
    support scans; empty ones skipped) worse than ``ref`` does: the summed loss-weighted squared
    robust residuals of the cluster's sample rows ``q`` (grouped by cluster ``cid``)."""
    diffs = []
    for side in sides:
        if side:
            r = _weighted_residuals(side, q, [u, ref], tau, True)
            diffs.append(r[0] - r[1])
    if not diffs:
        return torch.zeros(C, dtype=torch.bool, device=q.device)
    # every side's sums in one pass (each column its own fixed-point sum: the same bits)
    return (~(segment_sum(C, cid, torch.stack(diffs, 1)) <= 0)).any(dim=1)  # (a NaN sum counts as worse)


def _weighted_residuals(supports: list[Support], q: torch.Tensor, us: list[torch.Tensor], tau: float,
                        squared: bool, observed: torch.Tensor | None = None) -> torch.Tensor:
    """(len(us), m): :func:`_weighted_residual` of each per-row motion of ``us`` at the rows ``q``
    (m, 3), in one ``floxels::dt_residual`` launch (the rows stacked; each row's sum is its own,
    so the same bits as one call per motion: fewer launches from the thread that feeds the GPU)."""
    k = len(us)
    ob = None if observed is None else observed.repeat(k)
    return _weighted_residual(supports, q.repeat(k, 1), torch.cat(us), tau, squared, ob).view(k, -1)


def _weighted_residual(supports: list[Support], q: torch.Tensor, u: torch.Tensor, tau: float,
                       squared: bool, observed: torch.Tensor | None = None) -> torch.Tensor:
    """Per point, ``sum_k w_k c(min(DT_k(q + t_k u), tau))`` over the support scans, with
    ``c(d) = d^2`` (``squared``) or ``d``; the weights are the supports' loss weights. One
    ``floxels::dt_residual`` launch for all of them."""
    dts, origins, spacing, ts, ws = _packed(supports)
    return F.dt_residual(q.contiguous(), u.contiguous(), dts, origins, spacing, ts, ws, float(tau), bool(squared),
                         None if observed is None else observed.contiguous())


class _LevenbergMarquardt:
    """``floxels::rigid_lm`` on the sample rows ``q`` (grouped by cluster ``cid``, C clusters); with
    ``level`` every cluster is solved twice in one call, with its vertical velocity and with none
    (its rows repeated as cluster C + c), and the lower cost kept."""

    def __init__(self, q, rel, cid, C: int, packed, tau: float, iters: int, level: bool):
        self.C, self.packed, self.tau, self.iters, self.level = C, packed, float(tau), int(iters), level
        if level:
            q, rel, cid = torch.cat([q, q]), torch.cat([rel, rel]), torch.cat([cid, cid + C])
        self.q, self.rel, self.segments = q, rel, _segments(cid, 2 * C if level else C)

    def solve(self, start: torch.Tensor, vz: torch.Tensor):
        """(theta (C, 3), cost (C,), vertical velocity (C,)) from ``start`` (C, 3)."""
        dts, origins, spacing, ts, wn = self.packed
        if not self.level:
            theta, cur = F.rigid_lm(self.q, self.rel, self.segments, start, vz, dts, origins, spacing, ts, wn,
                                    self.tau, self.iters)
            return theta, cur, vz
        C = self.C
        theta, cur = F.rigid_lm(self.q, self.rel, self.segments, torch.cat([start, start]),
                                torch.cat([vz, torch.zeros_like(vz)]), dts, origins, spacing, ts, wn, self.tau,
                                self.iters)
        flat = cur[C:] < cur[:C]
        return (torch.where(flat[:, None], theta[C:], theta[:C]), torch.where(flat, cur[C:], cur[:C]),
                torch.where(flat, torch.zeros_like(vz), vz))


@dataclass
class RigidMotions:
    """What :func:`rigid_refine` kept: per cluster (C rows) whether its rigid motion was accepted,
    the motion (vx, vy, yaw rate) about its sample points' centroid ``cen`` with vertical velocity
    ``vz``; its sample rows ``q`` (grouped by cluster ``cid``); per point, ``take``: the point's
    flow is its cluster's accepted rigid motion, ``fits``: its cluster's rigid motion passed the
    test against zero flow (accepted or not by the sides' test)."""

    accept: torch.Tensor
    theta: torch.Tensor
    cen: torch.Tensor
    vz: torch.Tensor
    q: torch.Tensor
    cid: torch.Tensor
    take: torch.Tensor
    fits: torch.Tensor

    def motion_at(self, points: torch.Tensor, cluster: torch.Tensor) -> torch.Tensor:
        """Per-point motion (m, 3) of the rigid motions of clusters ``cluster`` (m,) at ``points``."""
        return _planar(self.theta[cluster], points - self.cen[cluster], self.vz[cluster])


def rigid_refine(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None, supports: list[Support],
                 tau: float = TAU, min_speed: float = REFINE_MIN_SPEED, iters: int = REFINE_ITERS,
                 num_clusters: int | None = None, sided: bool = False, search: bool = False,
                 motions: bool = False, level: bool = False):
    """The flow (n, 3) with every moving cluster (mean flow >= ``min_speed`` m/frame)
    replaced by its best planar rigid motion (horizontal translation v and yaw rate w about
    the cluster's centroid c: u(p) = v + w z x (p - c) per frame, the vertical velocity kept
    at the flow's mean), found by Levenberg-Marquardt on the robust squared DT residuals
    started from (mean flow, 0). A cluster keeps its Floxels
    flow unless the rigid motion explains the support scans clearly better than zero flow.
    (Not compared with the Floxels flow itself: a non-rigid flow fits one support scan
    better than the true rigid motion does, by sliding points onto surfaces.)
    ``num_clusters``: ``labels.max() + 1`` if known (saves a host synchronisation).

    ``sided`` (windows of many support scans, ``FloxelsConfig.refine_sided``): the rigid motion
    must also explain each side of the window that has scans (the past ones, t < 0, and the
    future ones, t > 0) no worse than the flow it replaces. A motion that fits one side better
    at the other's cost fits what one side did not see (a car beside the ego, whose past scans
    show another part of it), not the object's motion; a turning car's rigid motion (its yaw,
    which the grid's cluster-mean consistency cannot hold) explains both sides better.
    Not for windows of one or two scans, where the flow can fit a scan better than the true
    motion does (above).

    ``search`` (``FloxelsConfig.refine_search``): the Levenberg-Marquardt loop also starts from
    each moving cluster's best constant velocity of the velocity search (the search of
    :func:`cluster_velocity_search`, over these clusters only), and the cluster takes the motion
    of the two with the lower cost. The loop is local: from a flow stopped short it can settle in
    a partial match, e.g. a far car's points on its own next-frame surface (AV2 pair: 0.30 m/frame
    with a 4 degree/frame yaw, against the label's 0.80 and the scans' 0.84). With ``sided``, in a
    window with one side (a sequence's first or last frame), the searched motion is taken only
    where it also explains that side's nearer and its farther scans each no worse than the
    other start's motion (:func:`one_sided_halves`: an alias trades one for the other).

    Every cluster is solved at once by ``floxels::rigid_lm`` (kernels/rigid_lm.h: per step the
    clusters' normal equations from one look-up per support scan, sums in a fixed order, and a
    closed-form 3 x 3 solve; on CUDA one launch for every cluster and step); the only host
    synchronisation is the number of sample points (plus ``labels.max()`` without ``num_clusters``;
    :func:`rigid_refine_steps` yields it, for reads merged over several problems).

    ``motions``: return ``(flow, RigidMotions or None)`` (what was kept, for
    estimator/spread.py). ``level`` (``FloxelsConfig.refine_level``): each start is also solved
    with no vertical velocity, and the lower cost kept: the optimiser's mean vertical flow of a
    fast, far mover can be off by decimetres a frame (a highway truck: 0.47 m/frame), which no
    horizontal motion then fits."""
    return run_one(rigid_refine_steps(points, flow, labels, supports, tau, min_speed, iters, num_clusters, sided,
                                      search, motions, level))


def rigid_refine_steps(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None,
                       supports: list[Support], tau: float = TAU, min_speed: float = REFINE_MIN_SPEED,
                       iters: int = REFINE_ITERS, num_clusters: int | None = None, sided: bool = False,
                       search: bool = False, motions: bool = False, level: bool = False) -> Steps:
    """:func:`rigid_refine` as steps of ``estimator/host_reads.py``: its host read (the number of
    sample rows) yielded."""
    none = (flow, None) if motions else flow
    if labels is None or points.shape[0] == 0 or not supports:
        return none
    lab = labels.to(torch.int64)
    C = int(num_clusters) if num_clusters is not None else (int(lab.max()) + 1 if lab.numel() else 0)
    if C <= 0:
        return none
    dev, dt = points.device, points.dtype
    mean_flow, size = cluster_means(flow, lab, C)
    sel = (mean_flow[:, :2].norm(dim=1) >= min_speed) & (size >= MIN_CLUSTER_POINTS)
    lab = torch.where((lab >= 0) & sel[lab.clamp_min(0)], lab, torch.full_like(lab, -1))
    order, keep = _subsample_mask(lab, C, torch.where(sel, size, torch.zeros_like(size)).to(torch.int64),
                                  REFINE_POINTS)
    (num_rows,) = yield [keep.sum()]  # (the one host synchronisation)
    if num_rows == 0:
        return none
    rows = order[rows_where(keep, num_rows)]
    q, cid = points[rows], lab[rows]
    segments = _segments(cid, C)
    n = segments.diff().clamp_min(1).to(dt)  # sample points per cluster
    wsum = max(sum(s.w for s in supports), 1e-12)  # all zero (lambda_d = 0): no cost, nothing accepted
    # the centroids' sums and zero flow's cost (the acceptance test's, below) in one pass: each
    # column its own fixed-point sum, the same bits as apart
    r_0 = _weighted_residual(supports, q, torch.zeros_like(q), tau, True) / wsum
    sums = segment_sum(C, cid, torch.cat([q, r_0[:, None].to(q.dtype)], 1))
    cen, zero_cost = sums[:, :3] / n[:, None], sums[:, 3].to(r_0.dtype) / n  # (C, 3), (C,)
    rel = q - cen[cid]
    # planar rigid motion (vx, vy, yaw rate); the vertical velocity stays the flow's mean (the
    # scans of vertical faces hardly constrain it, and road users move on the road)
    theta = torch.cat([mean_flow[:, :2], torch.zeros(C, 1, device=dev, dtype=dt)], 1)  # (C, 3)
    vz = mean_flow[:, 2]
    # Levenberg-Marquardt on every cluster at once (floxels::rigid_lm: one launch on CUDA; the
    # reference is floxels_ext.reference.rigid_lm); the sample rows are grouped by cluster
    dts, origins, spacing, ts, ws = _packed(supports)
    wn = [w / wsum for w in ws]
    rel, vz = rel.contiguous(), vz.contiguous()
    lm = _LevenbergMarquardt(q, rel, cid, C, (dts, origins, spacing, ts, wn), tau, iters, level)
    theta, cur, vz = lm.solve(theta, vz)
    if search:  # the second start: the searched velocity (the search of cluster_velocity_search)
        best = _search(q, segments, None, supports, tau)[0]
        start = torch.cat([best[:, :2].to(dt), torch.zeros(C, 1, device=dev, dtype=dt)], 1)
        theta_s, cur_s, vz_s = lm.solve(start, mean_flow[:, 2].contiguous())
        lower = sel & (cur_s < cur)
        halves = one_sided_halves(supports) if sided else None
        if halves is not None:  # a one-sided window: the searched motion must not trade its halves
            lower &= ~_worse_on_a_side(halves, q, cid, C, _planar(theta_s[cid], rel, vz_s[cid]),
                                       _planar(theta[cid], rel, vz[cid]), tau)
        theta, cur = torch.where(lower[:, None], theta_s, theta), torch.where(lower, cur_s, cur)
        vz = torch.where(lower, vz_s, vz)
    # keep the rigid motion where it is evidence of motion: it explains the scans clearly
    # better than zero flow (the same test as the search); else the cluster keeps its flow
    accept = sel & (cur < (1 - SEARCH_GAIN) * zero_cost)
    fits = accept.clone()
    if sided:
        accept &= ~_worse_on_a_side(([s for s in supports if s.t < 0], [s for s in supports if s.t > 0]), q, cid, C,
                                    _planar(theta[cid], rel, vz[cid]), flow[rows], tau)
    cl = lab.clamp_min(0)
    take = (lab >= 0) & accept[cl]
    rigid = _planar(theta[cl], points - cen[cl], vz[cl])
    out = torch.where(take[:, None], rigid, flow)
    fits = (lab >= 0) & fits[cl]
    return (out, RigidMotions(accept, theta, cen, vz, q, cid, take, fits)) if motions else out
