"""The device-resident optimiser op (``floxels::solver_run``): fake registration and a packer.

:class:`SolverProblem` describes one target frame (sorted points, compact corners,
cluster labels, support scans); :func:`pack_problems` concatenates several of them into the
op's flat arguments once per call group; :meth:`PackedProblems.run` enqueues iterations.
The op mutates its state tensors in place and never synchronises with the host, so the
CUDA path can capture it into a CUDA graph (``floxels_ext.estimator.solver_run``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from floxels_ext.ops._lib import ops_ns
from floxels_ext.ops._small import device_values
from floxels_ext.ops.corners import CompactCorners

MAX_PROBLEMS = 16  # csrc/kernels/solver.h kMaxProblems
MAX_SUPPORT = 12   # kMaxSupport
MAX_DTS = 32       # kMaxDts
STATE_COLS = 10    # kStateCols
COL_ACTIVE, COL_ITER, COL_BEST_LOSS, COL_BEST_ITER = 0, 1, 2, 5


@torch.library.register_fake("floxels::solver_run")
def _fake(points, corner_idx, corner_w, seg_ptr, vtx_ptr, vtx_entry, labels, cluster_count, dts, dt_origins, point_ranges,
          vertex_ranges, support_ranges, support_dt, support_t, support_w, reg_scale, hyper, theta, adam_m, adam_v,
          best, state, history, num_iters):
    return None


@dataclass
class SolverProblem:
    """One target frame. ``points`` (n, 3) float32 in the order the corners were built for;
    ``labels`` (n,) int64 DBSCAN labels (-1 noise) or None (no cluster term); ``dts``: one
    float32 (Z, Y, X) distance transform per support scan with its ``origins`` [x0, y0, z0],
    time offset and weight (lambda_d * w(t)); ``reg_scale`` multiplies both regularisers."""

    points: torch.Tensor
    corners: CompactCorners
    labels: torch.Tensor | None
    dts: list[torch.Tensor]
    origins: list[list[float]]
    time_offsets: list[float]
    weights: list[float]
    reg_scale: float
    num_clusters: int | None = None  # labels.max() + 1 if known (saves a host synchronisation)
    # (seg_ptr, vtx_ptr, vtx_entry) of this problem alone (problem_segments), if already built:
    # the estimator builds them while the distance transforms are still running, so packing
    # needs no host synchronisation
    segments: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    # per support scan what it could see (estimator/sight.py Sight, or None), or None: not used by
    # the solver, only by the evidence test and the velocity search (range_mask, visibility)
    sights: list | None = None


def solver_hyper(cfg) -> list[float]:
    """``hyper`` of the op from a FloxelsConfig (layout documented in csrc/ops.cpp)."""
    lg0, lg1 = (cfg.lambda_g_start, cfg.lambda_g_end) if cfg.flow_norm_loss else (0.0, 0.0)
    ms = tuple(cfg.lr_milestones)
    return [cfg.dt_cell, cfg.truncation, cfg.lr, cfg.adam_betas[0], cfg.adam_betas[1], cfg.adam_eps,
            cfg.lambda_c if cfg.cluster_loss else 0.0, lg0, lg1, float(cfg.lambda_g_decay_iters),
            float(cfg.patience), float(cfg.max_iters), cfg.min_delta,
            # faithfulness readings (FloxelsConfig): truncation mode, lr schedule, and whether
            # reg_scale carries per-problem cluster normalisers
            1.0 if cfg.truncation_mode == "clamp" else 0.0, float(cfg.lr_gamma), float(len(ms)),
            *[float(m) for m in ms], *[0.0] * (4 - len(ms)),
            1.0 if cfg.cluster_loss_mean == "clustered" else 0.0]


class PackedProblems:
    """Flat op arguments and the mutable optimiser state of several problems."""

    def __init__(self, problems: Sequence[SolverProblem], cfg) -> None:
        if not 1 <= len(problems) <= MAX_PROBLEMS:
            raise ValueError(f"solver: 1 to {MAX_PROBLEMS} problems per call, got {len(problems)}")
        dev = problems[0].points.device
        self.cfg = cfg
        self.num_problems = len(problems)
        pts, idx, w, labels = [], [], [], []
        self.point_ranges, self.vertex_ranges = [0], [0]
        ncl = 0
        slots: dict[int, int] = {}
        self.dts: list[torch.Tensor] = []
        self.dt_origins: list[float] = []
        self.support_ranges, self.support_dt, self.support_t, self.support_w = [0], [], [], []
        use_cluster = cfg.cluster_loss and any(p.labels is not None for p in problems)
        for p in problems:
            if p.points.device != dev:
                raise ValueError("solver: all problems must be on one device")
            n, m = p.points.shape[0], p.corners.num_params
            pts.append(p.points.to(torch.float32))
            off = self.vertex_ranges[-1]  # vertex rows are numbered per problem: offset them
            idx.append(p.corners.corner_idx if off == 0 else p.corners.corner_idx.to(torch.int64) + off)
            w.append(p.corners.corner_w.to(torch.float32))
            if use_cluster:
                lab = p.labels if p.labels is not None else torch.full((n,), -1, dtype=torch.int64, device=dev)
                k = p.num_clusters if p.num_clusters is not None else (int(lab.max()) + 1 if n else 0)
                labels.append(lab if ncl == 0 else torch.where(lab >= 0, lab + ncl, lab))
                ncl += max(k, 0)
            self.point_ranges.append(self.point_ranges[-1] + n)
            self.vertex_ranges.append(self.vertex_ranges[-1] + m)
            if len(p.dts) > MAX_SUPPORT:
                raise ValueError(f"solver: at most {MAX_SUPPORT} support scans per problem, got {len(p.dts)}")
            for d, o, t, wt in zip(p.dts, p.origins, p.time_offsets, p.weights):
                key = id(d)
                if key not in slots:
                    slots[key] = len(self.dts)
                    self.dts.append(d.contiguous())
                    self.dt_origins.extend(float(v) for v in o)
                self.support_dt.append(slots[key])
                self.support_t.append(float(t))
                self.support_w.append(float(wt))
            self.support_ranges.append(len(self.support_dt))
        if len(self.dts) > MAX_DTS:
            raise ValueError(f"solver: at most {MAX_DTS} distinct distance transforms per call, got {len(self.dts)}")
        self.reg_scale = [float(p.reg_scale) for p in problems]
        if cfg.cluster_loss_mean == "clustered":
            # the cluster term's normaliser: each problem's clustered points (a host sync;
            # only for this non-default reading)
            self.reg_scale += [float(int((p.labels >= 0).sum())) if p.labels is not None else 0.0
                               for p in problems]
        one = len(problems) == 1  # (no concatenation: fewer kernels and host calls per frame)
        self.points = (pts[0] if one else torch.cat(pts)).contiguous()
        N = self.points.shape[0]
        M = self.vertex_ranges[-1]
        self.corner_idx = (idx[0] if one else torch.cat(idx)).to(torch.int32).reshape(N, 8).contiguous()
        self.corner_w = (w[0] if one else torch.cat(w)).contiguous()
        if use_cluster and ncl > 0:
            lab_all = labels[0] if one else torch.cat(labels)
        else:
            lab_all = None
        own = [p.segments for p in problems]
        # a problem's own segments are only valid with the labels they were built from
        if all(sg is not None for sg in own) and all((p.labels is not None) == (lab_all is not None) for p in problems):
            self.seg_ptr, self.vtx_ptr, self.vtx_entry = _concat_segments(own, self.point_ranges)
        else:
            self.seg_ptr, self.vtx_ptr, self.vtx_entry = _segments(self.corner_idx, lab_all, self.point_ranges, M)
        if lab_all is not None:
            lab = lab_all
            self.labels = lab.to(torch.int32).contiguous()
            # points per cluster, without bincount's host synchronisation
            self.cluster_count = torch.zeros(ncl, dtype=torch.float32, device=dev).index_add_(
                0, lab.clamp_min(0), (lab >= 0).to(torch.float32))
        else:
            self.labels = self.cluster_count = None
        self.hyper = solver_hyper(cfg)
        # theta, Adam's moments and the best copy in one allocation (one fill)
        self._params = torch.zeros(4, M, 3, dtype=torch.float32, device=dev)
        self.theta, self.adam_m, self.adam_v, self.best = self._params.unbind(0)
        row = [0.0] * STATE_COLS
        row[COL_ACTIVE], row[COL_BEST_LOSS], row[3], row[COL_BEST_ITER] = 1.0, float("inf"), float("inf"), -1.0
        # 3: early stopping's reference loss
        self.state = device_values([row] * self.num_problems, torch.float64, dev)
        self.history = torch.full((self.num_problems, cfg.max_iters), float("nan"), dtype=torch.float64, device=dev)

    def record_stream(self, stream) -> None:
        """Mark every device tensor of the call as used on ``stream`` (packed on another one)."""
        for t in (self.points, self.corner_idx, self.corner_w, self.seg_ptr, self.vtx_ptr, self.vtx_entry, self.labels,
                  self.cluster_count, self._params, self.state, self.history, *self.dts):
            if t is not None and t.is_cuda:
                t.record_stream(stream)

    def op_args(self, num_iters: int) -> tuple:
        """The arguments of ``torch.ops.floxels.solver_run`` for ``num_iters`` iterations."""
        return (self.points, self.corner_idx, self.corner_w, self.seg_ptr, self.vtx_ptr, self.vtx_entry, self.labels,
                self.cluster_count, self.dts, self.dt_origins, self.point_ranges, self.vertex_ranges,
                self.support_ranges, self.support_dt, self.support_t, self.support_w, self.reg_scale, self.hyper,
                self.theta, self.adam_m, self.adam_v, self.best, self.state, self.history, int(num_iters))

    def loop_blocks(self) -> int:
        """Blocks of the persistent loop kernel a call would launch (0: two kernels per iteration)."""
        return int(ops_ns.solver_loop_blocks(self.points, self.point_ranges, self.vertex_ranges,
                                             self.labels is not None))

    def run(self, num_iters: int) -> None:
        """Enqueue ``num_iters`` iterations (no host synchronisation on CUDA)."""
        ops_ns.solver_run(*self.op_args(num_iters))

    # -- results (these synchronise) ------------------------------------------------------
    def best_params(self, b: int) -> torch.Tensor:
        return self.best[self.vertex_ranges[b]:self.vertex_ranges[b + 1]]

    def losses(self, b: int) -> list[float]:
        n = int(self.state[b, COL_ITER].item())
        return self.history[b, :n].tolist()

    def summaries_start(self) -> torch.Tensor:
        """Queue the read-back of the state and loss history (into page-locked memory on
        CUDA); pass the result to :meth:`summaries` once the stream has been synchronised."""
        both = torch.cat([self.state, self.history], dim=1)
        if not both.is_cuda:
            return both
        host = torch.empty(both.shape, dtype=both.dtype, pin_memory=True)
        host.copy_(both, non_blocking=True)
        return host

    def summaries(self, host: torch.Tensor | None = None) -> list[tuple[list[float], int]]:
        """(losses, best iteration) of every problem, read back in one host synchronisation
        (or from ``host``, see :meth:`summaries_start`)."""
        both = host if host is not None else torch.cat([self.state, self.history], dim=1).cpu()
        out = []
        for row in both:
            n = int(row[COL_ITER])
            out.append((row[STATE_COLS:STATE_COLS + n].tolist(), int(row[COL_BEST_ITER])))
        return out

    def best_iter(self, b: int) -> int:
        return int(self.state[b, COL_BEST_ITER].item())


SEGMENT_TILE = 32  # points per warp of the CUDA solver's point phase (kTile in csrc/cuda/solver_params.cuh)


def problem_segments(corner_idx: torch.Tensor, labels: torch.Tensor | None, num_vertices: int,
                     tile: int = SEGMENT_TILE):
    """(seg_ptr, vtx_ptr, vtx_entry) of one problem (see :func:`_segments`), for
    :attr:`SolverProblem.segments`."""
    return _segments(corner_idx, labels, [0, corner_idx.shape[0]], num_vertices, tile)


def _concat_segments(own: list, point_ranges: list[int]):
    """The segment tables of several problems from each problem's own (segments, entries
    and vertices are numbered per problem; offsets make them global)."""
    if len(own) == 1:
        return own[0]
    seg_ptr, vtx_ptr, vtx_entry = [], [], []
    segs = ents = 0
    for (sp, vp, ve), p0 in zip(own, point_ranges):
        seg_ptr.append(sp[:-1] + p0)
        vtx_ptr.append(vp[:-1] + ents)
        vtx_entry.append(ve + 8 * segs)
        segs += sp.shape[0] - 1
        ents += ve.shape[0]
    dev = own[0][0].device
    seg_ptr.append(device_values([point_ranges[-1]], torch.int32, dev))
    vtx_ptr.append(device_values([ents], torch.int32, dev))
    return (torch.cat(seg_ptr).contiguous(), torch.cat(vtx_ptr).contiguous(), torch.cat(vtx_entry).contiguous())


def _segments(corner_idx: torch.Tensor, labels: torch.Tensor | None, point_ranges: list[int], num_vertices: int,
              tile: int = SEGMENT_TILE):
    """Segments (runs of points with equal corner rows and labels inside one problem and one
    tile of ``tile`` points) and,
    per vertex, its (segment * 8 + corner) entries: the vertex gradient is then a gather of
    per-segment sums with a small fan-in. Points sorted by (label, voxel) make each segment
    the part of one cluster inside one flow-grid cell."""
    N, dev = corner_idx.shape[0], corner_idx.device
    if N == 0:
        zeros = torch.zeros(1, dtype=torch.int32, device=dev)
        return zeros, torch.zeros(num_vertices + 1, dtype=torch.int32, device=dev), zeros[:0]
    new = torch.ones(N, dtype=torch.bool, device=dev)
    new[1:] = (corner_idx[1:] != corner_idx[:-1]).any(1)
    if labels is not None:
        new[1:] |= labels[1:] != labels[:-1]
    # problem boundaries, and every SEGMENT_TILE-th point of a problem: the CUDA solver sums
    # a segment's points in one warp; a segment that crosses those tiles is summed there by
    # atomics (correct, slower: larger tiles are for tests) (slicing: no host synchronisation)
    for b, e in zip(point_ranges[:-1], point_ranges[1:]):
        new[b:e:tile] = True
    first = torch.nonzero(new).reshape(-1)
    seg_ptr = torch.cat([first, first.new_full((1,), N)]).to(torch.int32).contiguous()
    flat = corner_idx[first].reshape(-1).to(torch.int64)  # (8S) vertex of each (segment, corner)
    order = torch.argsort(flat.to(torch.int32), stable=True)  # (int32: half the radix passes, same order)
    # entries per vertex (index_add_: bincount would synchronise with the host)
    counts = torch.zeros(num_vertices, dtype=torch.int64, device=dev).index_add_(0, flat, torch.ones_like(flat))
    vtx_ptr = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)]).to(torch.int32).contiguous()
    return seg_ptr, vtx_ptr, order.to(torch.int32).contiguous()
