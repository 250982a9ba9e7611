"""Motion evidence: does a group of points' estimated flow explain the support scans better
than zero flow?

The optimiser can leave motion on static structure that the scans do not support: a wall
parallel to the ego motion slides along itself at almost no cost in the distance-transform
loss, facade fragments and vegetation pick up the flow of their neighbours through the flow
grid (issue 29). After the optimisation, each *group* of target points (a DBSCAN cluster;
unclustered points grouped by the flow-grid cell they fall in) is tested on the scans and the
distance transforms the loss used:

    R_flow = mean over the group's points and the support scans (weights w_t of the loss) of
             min(DT_t(p + t f(p)), truncation)
    R_zero = the same with f = 0
    gain   = R_zero - R_flow                                  (metres)
    explained  <=>  gain > max(margin, ratio * R_zero)

A rigid object moving 0.5 m a frame leaves R_zero of tens of centimetres that its flow removes
almost entirely; a wall sliding along itself has gain ~ 0; a group whose flow is ~0 has gain ~0
too and is "unexplained" (zeroing its flow changes nothing).

``margin`` (metres; default 0.02, about the range noise of automotive lidar: a smaller gain is
no evidence) and ``ratio`` (default 0.05: the share of the zero-flow residual the flow must also
remove, which matters for far, sparse or partly occluded groups whose residual is large) are
the same for all data. They are deliberately permissive: walls and facades sliding along
themselves remove 0-9 % of their residual (gain < 1 cm), rigid movers 40-90 %, but slow or
under-estimated movers (pedestrians, a long vehicle seen from its side) only 10-25 %, and
zeroing those cost more dynamic EPE than it saved static EPE (bench/RESULTS.md, "Motion
evidence"). Not caught: motion that does explain the scans, e.g. static structure following
the sensor's ring pattern.

Cost: one ``floxels::dt_evidence`` call (csrc/cuda/dt_query.cu): two trilinear DT look-ups
per point and support scan (the optimiser does one per scan and iteration) and the group sums,
in 4 CUDA kernels whatever the number of support scans (the groups are runs of the solver's
point order; CUDA: float64 prefix sums differenced at each run's ends, CPU: each run summed in
order in float64; no atomics, so the same bits on every run; no host synchronisation). The
look-ups use the loss's own interpolation (kernels/dt_loss.h). Works with any device the ops
support.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from floxels_ext.estimator.sight import self_occluded_bits
from floxels_ext.ops._small import device_values

__all__ = ["MotionEvidence", "motion_evidence", "run_evidence", "seen_evidence", "sensor_velocity", "group_ids",
           "EVIDENCE_MODES", "FOLLOW_RATIO"]

F = torch.ops.floxels

# FloxelsConfig.evidence: "off" (the paper's output, nothing computed), "score" (the evidence is
# computed and returned, the flow untouched), "zero" (also the flow of unexplained groups set to 0)
EVIDENCE_MODES = ("off", "score", "zero")

# seen_evidence: a group's flow follows the sensor where it points along the sensors' velocity:
# its part across that direction at most this share of its length (30 degrees)
FOLLOW_RATIO = 0.5

# Unclustered points' grouping key: cell coordinates packed 20 bits an axis; clustered points
# get this bit set plus their label, so the two kinds never share a key.
_AXIS_BITS = 20
_CLUSTER_BIT = 1 << 62


@dataclass
class MotionEvidence:
    """Per point (rows of the points given): ``score`` float32, metres of distance-transform
    residual the group's flow removes compared with zero flow (its ``gain``; negative: the
    flow explains the scans worse than zero); ``explained`` bool, the group passes the test;
    ``residual_flow`` / ``residual_zero``: the group's R_flow and R_zero (metres); ``hidden``
    (``keep_unseen``, else None): explained only because no support scan saw the group, each
    showing something in front of it (a verdict the rigid refinement must confirm)."""

    score: torch.Tensor
    explained: torch.Tensor
    residual_flow: torch.Tensor
    residual_zero: torch.Tensor
    hidden: torch.Tensor | None = None

    def apply(self, flow: torch.Tensor) -> torch.Tensor:
        """``flow`` with the rows of unexplained groups set to (+)0, the others unchanged."""
        return torch.where(self.explained[:, None], flow, flow.new_zeros(()))


def group_ids(points: torch.Tensor, labels: torch.Tensor | None, cell: float,
              cell_origin: Sequence[float] | None = None, presorted: bool = False,
              cells: torch.Tensor | None = None) -> torch.Tensor:
    """(N,) int64 group of each point: its DBSCAN label (``labels`` >= 0), or for unclustered
    points (-1, or no labels) the cell of side ``cell`` metres it falls in (cells counted from
    ``cell_origin``, default the points' minimum; or ``cells``, any integer id per point of its
    cell, e.g. the compact index of its lower flow-grid corner). Ids are not dense: any values
    in [0, N). ``presorted``: points of one group are already contiguous (the solver's
    (cluster, cell) order with the same cells), so groups are runs and nothing is sorted."""
    n = points.shape[0]
    if cells is not None:
        key = cells.long()
    else:
        if cell_origin is None:
            o = points.amin(0)
        else:  # (no blocking copy: it would wait for the work queued on the stream)
            o = torch.as_tensor([float(v) for v in cell_origin], dtype=points.dtype).to(points.device,
                                                                                      non_blocking=True)
        ic = ((points - o) / cell).floor().clamp_(0, (1 << _AXIS_BITS) - 1).long()
        key = (ic[:, 2] << (2 * _AXIS_BITS)) | (ic[:, 1] << _AXIS_BITS) | ic[:, 0]
    if labels is not None:
        lab = labels.long()
        key = torch.where(lab >= 0, lab + _CLUSTER_BIT, key)
    order = None
    if not presorted:
        key, order = torch.sort(key, stable=True)
    start = torch.ones(n, dtype=torch.bool, device=points.device)
    if n > 1:
        torch.ne(key[1:], key[:-1], out=start[1:])
    gid = torch.cumsum(start, 0)
    gid -= 1
    if order is not None:
        gid = torch.empty_like(gid).scatter_(0, order, gid)
    return gid


def motion_evidence(points: torch.Tensor, flow: torch.Tensor, groups: torch.Tensor,
                    dts: Sequence[torch.Tensor], origins: Sequence[Sequence[float]], offsets: Sequence[float],
                    weights: Sequence[float], *, dt_cell: float, truncation: float, margin: float = 0.02,
                    ratio: float = 0.05, runs: bool = False, observed: torch.Tensor | None = None) -> MotionEvidence:
    """The motion evidence of ``flow`` (N, 3; metres per frame period) at ``points`` (N, 3,
    float32, finite) for the groups ``groups`` ((N,) int64 in [0, N), e.g. :func:`group_ids`).

    ``dts``/``origins``/``offsets``/``weights``: the support scans' distance transforms
    ((Z, Y, X) float32, sample spacing ``dt_cell``, sample (0,0,0) at the origin), their time
    offsets in frame periods and their weights in the loss (as the estimator builds them).
    Look-ups clamp at the DT border like the loss; values are capped at ``truncation``.
    Without support scans every group is unexplained with score 0. ``runs``: the groups are
    contiguous runs (``group_ids(..., presorted=True)``), used as they are; otherwise the
    points are sorted by group first (a stable sort and its inverse). Either way the group sums
    are float64 and the same bits on every run of a device (no atomics). ``observed`` ((N,)
    int32, estimator/sight.py): bit k set where support scan k counts for the point (it could
    see the point's own position)."""
    if runs or points.shape[0] == 0 or not dts:
        return run_evidence(points, flow, None, groups, dts, origins, offsets, weights, dt_cell=dt_cell,
                            truncation=truncation, margin=margin, ratio=ratio, observed=observed)
    key, order = torch.sort(groups, stable=True)
    ev = run_evidence(points[order], flow[order], None, key, dts, origins, offsets, weights, dt_cell=dt_cell,
                      truncation=truncation, margin=margin, ratio=ratio,
                      observed=None if observed is None else observed[order])

    def back(x):
        out = torch.empty_like(x)
        out[order] = x
        return out

    return MotionEvidence(back(ev.score), back(ev.explained), back(ev.residual_flow), back(ev.residual_zero),
                          None if ev.hidden is None else back(ev.hidden))


def run_evidence(points: torch.Tensor, flow: torch.Tensor, labels: torch.Tensor | None, cells: torch.Tensor,
                 dts: Sequence[torch.Tensor], origins: Sequence[Sequence[float]], offsets: Sequence[float],
                 weights: Sequence[float], *, dt_cell: float, truncation: float, margin: float = 0.02,
                 ratio: float = 0.05, observed: torch.Tensor | None = None, seen_mean: bool = False,
                 keep_unseen: bool = False, occluded: torch.Tensor | None = None,
                 sensor_velocity: torch.Tensor | None = None, sights=None) -> MotionEvidence:
    """:func:`motion_evidence` for groups that are runs of consecutive points: equal ``labels``
    (DBSCAN, (N,) int32/int64) and, for label -1 (or ``labels`` None), equal ``cells`` ((N,)
    int32/int64, any stride: e.g. the compact index of each point's lower flow-grid corner) --
    the groups of :func:`group_ids` on points in the solver's (cluster, cell) order, without
    computing the ids. One ``floxels::dt_evidence`` call (no input checks here: the estimator's
    points are validated, at most 32 support scans).

    With ``observed`` (the sights): ``seen_mean`` judges each group on the support scans that saw
    its points (:func:`seen_evidence`; ``sensor_velocity``: the sensors' (3,) velocity over the
    window, :func:`sensor_velocity`), ``keep_unseen`` marks the groups no support scan saw
    because something stood in front of them (``occluded``: the sights' bits of the scans with a
    nearer return; no evidence either way). ``sights``: the support scans' sights
    (estimator/sight.py), with which a following group in a one-sided window whose old place its
    own moved points hide awaits the rigid refinement (:func:`seen_evidence`)."""
    n = points.shape[0]
    dev = points.device
    if n == 0 or not dts:
        zeros = torch.zeros(n, dtype=torch.float32, device=dev)
        return MotionEvidence(zeros, torch.zeros(n, dtype=torch.bool, device=dev), zeros, zeros.clone())
    wsum = max(float(sum(weights)), 1e-12)  # all zero (lambda_d = 0): no residual, nothing explained
    norm = [float(w) / wsum for w in weights]
    score, explained, rf, rz = F.dt_evidence(
        points.to(torch.float32).contiguous(), flow.to(torch.float32).contiguous(), labels, cells, list(dts),
        [float(x) for o in origins for x in o], float(dt_cell), [float(t) for t in offsets],
        norm, float(truncation), float(margin), float(ratio), observed)
    if observed is not None and (seen_mean or keep_unseen):
        return seen_evidence(score, explained, rf, rz, labels, cells, observed, norm,
                             margin=margin, ratio=ratio, seen_mean=seen_mean, keep_unseen=keep_unseen,
                             occluded=occluded, flow=flow, sensor_velocity=sensor_velocity,
                             one_sided=all(float(t) > 0 for t in offsets) or all(float(t) < 0 for t in offsets),
                             points=points, sights=sights, offsets=offsets)
    return MotionEvidence(score, explained, rf, rz)


_RUN_SPARE = 1024  # seen_evidence's spare slots of its run tables


def seen_evidence(score, explained, rf, rz, labels, cells, observed, weights, *, margin: float, ratio: float,
                  seen_mean: bool, keep_unseen: bool, occluded: torch.Tensor | None = None,
                  flow: torch.Tensor | None = None, sensor_velocity: torch.Tensor | None = None,
                  one_sided: bool = False, points: torch.Tensor | None = None, sights=None,
                  offsets: Sequence[float] | None = None) -> MotionEvidence:
    """The evidence of :func:`run_evidence` judged on what the support scans saw.

    ``floxels::dt_evidence`` sums each point's residual over the scans that saw it, weighted by
    the loss weights normalised over *all* support scans: a group seen only by some scans gets a
    residual, and a gain, a fraction of one seen by all of them, and fails the margin whatever
    share of its residual the flow removes (a pedestrian 4 m from the sensor at a sequence's last
    frame: 84 % of it, but 0.016 m). ``seen_mean``: a group that fails is judged again on its
    residuals divided by its points' mean weight share of the scans that saw them (a weighted
    mean over what was seen), and passes if that test passes and its flow does not follow the
    sensor (``flow`` pointing along ``sensor_velocity``, the sensors' velocity over the window,
    m/frame: its part across that direction at most ``FOLLOW_RATIO`` of its length). Why that
    condition: the part of a barrier that a lidar sees travels with the sensor (its beams meet
    the barrier in a band of ranges); in the scans that saw it the sensor's motion, or a part of
    it, explains it, and the scans that would show it standing still did not see it (highway: a
    197-point barrier group at the ego's 2.52 m/frame passed; a band 5.8 m beside the sensor at
    0.54 of the ego's 2.68 m/frame too, when the test compared the speeds). Vehicles driving
    along the ego keep today's verdict (the all-scans test). ``keep_unseen``: a group that no support scan saw, most of whose points some scan
    shows hidden behind a nearer return (``occluded`` bits; every group no scan saw without
    them), is marked ``hidden`` and explained (estimator/post.py keeps its flow only where a
    rigid motion fits the scans): a car approaching the sensor from behind, at a sequence's
    first frame, hides its own old place in every later scan. Not a group out of the beams'
    reach (empty directions): the band of a barrier that follows the sensor lies between a
    32-beam lidar's rings in the other scans. ``one_sided`` (the support scans all on one side of
    the target: a sequence's first or last frame) with ``points``, ``sights`` and ``offsets`` (the
    support scans' time offsets): a following group most of whose points the scans show hidden
    only behind the group itself, moved by its flow (estimator/sight.py's ``self_occluded_bits``:
    in some scan, and in every scan that shows the place behind a nearer return), is not
    cut from the weak evidence that awaits the refinement (a pedestrian walking the ego's way hides
    its old place behind itself). ``weights``: the op's (normalised) weights. Groups
    are runs (as the op's); float64 prefix sums differenced at the run ends, so the same bits on
    every run."""
    n = rf.shape[0]
    k = len(weights)
    bits = (observed[:, None] >> torch.arange(k, dtype=torch.int32, device=observed.device)) & 1
    # each point's share of the window's weight that saw it, and the sum of those scans' squared
    # weights (the seen mean's noise, below): one product
    w = [float(v) for v in weights]
    seen_w = bits.to(torch.float64) @ device_values(w + [v * v for v in w], torch.float64, observed.device).view(2, k).T
    share = seen_w[:, 0]
    lab = labels.long() if labels is not None else torch.full((n,), -1, dtype=torch.long, device=rf.device)
    same = (lab[1:] == lab[:-1]) & ((lab[1:] >= 0) | (cells[1:] == cells[:-1]))
    one = torch.ones(min(n, 1), dtype=torch.bool, device=rf.device)
    idx = torch.arange(n, device=rf.device)
    # each point's run [first, last] (no host synchronisation): the runs numbered by a prefix
    # count of their starts; each run's first (last) row written by its start (end) row alone
    # into a table, the other rows into spare slots (never read; spread so that no slot is
    # contended). torch.cummax / cummin with their indices took ~0.24 ms each a frame on an
    # H200 (tools/run_gaps.py), and a scatter_reduce of minima ~0.13 ms (its int64 atomics all
    # on a large run's one slot).
    cut = ~same
    starts, ends = torch.cat([one, cut]), torch.cat([cut, one])
    run = torch.cumsum(starts, 0) - 1
    spare = n + (idx & (_RUN_SPARE - 1))
    table = torch.empty(2, n + _RUN_SPARE, dtype=idx.dtype, device=idx.device)
    table[0].scatter_(0, torch.where(starts, run, spare), idx)
    table[1].scatter_(0, torch.where(ends, run, spare), idx)
    first, last = table[:, run]
    count = (last - first + 1).to(torch.float64)
    # each run's sum: the prefix sum at its last point less the one before its first (shared by
    # every run_mean: a few launches fewer on CUDA)
    after_first, before = first > 0, (first - 1).clamp_min(0)
    zeros = torch.zeros(n, dtype=torch.float64, device=rf.device)

    def run_mean(v: torch.Tensor) -> torch.Tensor:  # each point's group mean of v (float64)
        cs = torch.cumsum(v, 0)
        return (cs[last] - torch.where(after_first, cs[before], zeros)) / count

    mean_share = run_mean(share)
    seen = mean_share > 0
    hidden = None
    # most of the group's points shown behind a nearer return by some support scan
    occl = None if occluded is None else run_mean((occluded != 0).to(torch.float64)) >= 0.5
    if seen_mean:
        div = torch.where(seen, mean_share, torch.ones_like(mean_share))
        gain_n = (score.to(torch.float64) / div).to(score.dtype)
        rz_n = (rz.to(torch.float64) / div).to(rz.dtype)
        # the margin is the noise of the whole window's weighted mean (each scan's residual noisy
        # alike: sigma * sqrt(sum w_t^2) with the weights normalised); the mean over the scans that
        # saw the group is sqrt(sum_seen w_t^2 / sum w_t^2) / share times as noisy, and its margin
        # grows so. Without it (the whole window's margin), static structure beside the sensor at a
        # sequence's end, seen by the nearest scan only in part (between a 32-beam lidar's rings),
        # passed on sampling-level gains (bench/RESULTS.md, "Where the static error lives"). A group
        # between the two margins (weak evidence) keeps its flow only where the rigid refinement
        # confirms it, as a hidden group does (``keep_unseen``; estimator/post.py): a moving
        # fragment a few scans saw is refined and fits, static structure at a few cm/frame is not
        noise = (run_mean(seen_w[:, 1]) / max(sum(v * v for v in w), 1e-300)).sqrt() / div
        above = seen & ~explained & (gain_n > torch.maximum(rz_n * ratio, torch.full_like(rz_n, margin)))
        rescued = above & (gain_n > torch.maximum(rz_n * ratio, (margin * noise).to(rz_n.dtype)))
        if sensor_velocity is not None and flow is not None:
            f = flow.to(torch.float64)
            v = sensor_velocity.to(f)
            speed = v.norm()
            unit = v / speed.clamp_min(1e-9)
            along = f @ unit
            across = (f - along[:, None] * unit).norm(dim=1)
            follows = (speed > 0.05) & (along > 0) & (across <= FOLLOW_RATIO * f.norm(dim=1))
            not_following = run_mean(follows.to(torch.float64)) < 0.5
            rescued &= not_following
            # in a one-sided window, a following group whose own old place the scans show hidden
            # behind *itself* is not a band the beams' reach carries with the sensor (that band's
            # old place has no return at all): a mover travelling the sensor's way hides its old
            # place behind itself in every scan of the side it moves to (a pedestrian walking the
            # ego's way behind it at a sequence's first frame; issue 47, the movers of 0.5-1
            # m/frame). Most of its points must be hidden, in some scan, by the group's own points
            # moved by its flow (sight.self_occluded_bits: in front along the same line of sight,
            # where the scan has its nearer return): static structure behind passing traffic is
            # hidden by another object (held-out highway last frames: static EPE 0.013 -> 0.110
            # when any nearer return counted), and its own moved points slide along its surface.
            # Like a group no scan saw, its flow is kept only where the rigid refinement confirms
            # it. Not in a window with both sides, whose other side would see the place left
            # (tuning seeds' middle frames: static EPE 0.004 -> 0.015 when every window took it)
            if one_sided and occl is not None and points is not None and sights is not None and offsets is not None:
                cand = above & occl & ~not_following
                own = self_occluded_bits(points, flow, run, cand, occluded, sights, offsets)
                # a point counts where every scan that hides its place hides it behind the moved
                # group: a thick static object's own front face hides its rear in every scan, and
                # with a flow that follows the sensor its moved rear meets that face in the nearest
                # scan only (tuning seed 2, urban, 11 frames, first frame: 25 static points at
                # 0.62 m/frame)
                mine = (own != 0) & (own == occluded)
                not_following = not_following | (cand & (run_mean(mine.to(torch.float64)) >= 0.5))
            above &= not_following
        explained = explained | rescued
    if keep_unseen:
        hidden = ~seen & ~explained
        if occl is not None:
            hidden &= occl
        if seen_mean:
            hidden |= above & ~rescued
        explained = explained | hidden
    return MotionEvidence(score, explained, rf, rz, hidden)


def sensor_velocity(sensors: list[torch.Tensor | None], offsets: Sequence[float]) -> torch.Tensor | None:
    """The sensors' velocity (3,) over a window (m/frame): the least-squares line through the known
    support scans' sensor positions against their time offsets; None with fewer than two, or all at
    one offset. No host synchronisation."""
    known = [(s, float(t)) for s, t in zip(sensors, offsets) if s is not None]
    if len(known) < 2:
        return None
    ts = [t for _, t in known]
    tm = sum(ts) / len(ts)
    var = sum((t - tm) ** 2 for t in ts)
    if var <= 0:
        return None
    pos = torch.stack([s for s, _ in known]).to(torch.float64)  # (float32 -> float64: exact in any order)
    w = device_values([(t - tm) / var for t in ts], torch.float64, pos.device)
    return (w[:, None] * (pos - pos.mean(0))).sum(0)
