"""The Floxels estimator: public API and the optimisation loop on top of torch.ops.floxels.

One frame:
1. an exact distance transform (0.1 m samples) of every support scan, cached per scan so
   sliding windows (:func:`estimate_sequence`) build each one once;
2. DBSCAN clusters of the target scan (our exact op: labels identical to scikit-learn);
3. Adam over the flow-grid vertices touched by the target points (see
   ``floxels_ext.ops.corners``: exactly dense Adam, at a fraction of the cost), each
   iteration being: compact gather of the point flow, fused multi-scan DT loss +
   gradient, fused cluster-consistency loss + gradient, flow-norm term, compact scatter;
4. early stopping; the result is the flow of the lowest loss seen.
"""

from __future__ import annotations

import collections.abc
import contextlib
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from .config import FloxelsConfig
from .ops import distance_transform
from .ops.grid import grid_from_bounds, point_bounds
from .ops.corners import CompactCorners
from .ops.setup import problem_setup
from .ops.solver import MAX_DTS, MAX_PROBLEMS, SEGMENT_TILE, PackedProblems, SolverProblem
from .scans import (PreparedScans, check_times, frame_period_of, prepare_scans, resolve_device,
                    restore_outputs)
from .solver import SolverRun

F = torch.ops.floxels


@dataclass
class DistanceTransform:
    """A support scan's distance transform: float32 (Z, Y, X) metres, sample (0,0,0) at ``origin``."""

    values: torch.Tensor
    origin: list[float]


@dataclass
class FloxelsResult:
    """Everything one optimisation produced."""

    flow: object                       # (N_target, 3): numpy float32 or tensor, like the input
    flow_tensor: torch.Tensor          # (N_kept, 3) float32 on the compute device (finite target rows)
    labels: torch.Tensor | None        # DBSCAN labels of the kept target rows (-1 = noise)
    losses: list[float] = field(default_factory=list)  # total loss per iteration
    best_iter: int = -1                # iteration whose flow is returned
    num_iters: int = 0
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage
    grid_origin: list[float] | None = None
    voxel_size: float = 0.5
    _corners: CompactCorners | None = None
    _params: torch.Tensor | None = None

    @property
    def grid(self) -> torch.Tensor | None:
        """Dense (3, Z, Y, X) flow grid (vertex (iz,iy,ix) at grid_origin + (ix,iy,iz)*voxel_size);
        vertices no point touches hold 0."""
        if self._corners is None:
            return None
        return self._corners.to_dense(self._params)


def _build_dt(points: torch.Tensor, cfg: FloxelsConfig, bounds=None) -> DistanceTransform | None:
    """DT of a validated scan; ``bounds`` (its min/max xyz, see point_bounds) saves a host sync."""
    if points.shape[0] == 0:
        return None
    if bounds is None:
        values, origin = distance_transform(points, cfg.dt_cell, cfg.dt_padding, max_cells=cfg.max_dt_cells)
        return DistanceTransform(values, origin)
    origin, shape = grid_from_bounds(*bounds, cfg.dt_cell, cfg.dt_padding, cfg.max_dt_cells)
    occ = F.points_to_occupancy(points, origin, cfg.dt_cell, shape)
    return DistanceTransform(F.edt(occ, cfg.dt_cell), origin)


class Floxels:
    """Floxels scene-flow estimator.

    >>> est = Floxels(FloxelsConfig(max_iters=300), device="cpu")
    >>> res = est.fit(scans, target=2)      # res.flow, res.losses, res.labels, res.grid, res.timings
    """

    def __init__(self, config: FloxelsConfig | None = None, device=None) -> None:
        if config is not None and not isinstance(config, FloxelsConfig):
            raise TypeError(f"config must be a FloxelsConfig, got {type(config).__name__}")
        self.config = config or FloxelsConfig()
        self.device = device

    # -- public -----------------------------------------------------------------------
    def fit(self, scans: Sequence, target: int | None = None,
            dt_cache: dict[int, DistanceTransform | None] | None = None, *,
            times: Sequence[float] | None = None, frame_period: float | None = None) -> FloxelsResult:
        """Estimate the flow of ``scans[target]`` (default: the middle scan), per frame period.

        ``dt_cache`` maps scan index -> distance transform and is filled in place, so that
        callers optimising several targets over the same scans build each DT once.
        ``times``/``frame_period``: scans not equally spaced, see :func:`estimate_flow`.
        """
        cache = dt_cache if dt_cache is not None else {}
        early = _DtStreams(self.config, cache)
        prep = prepare_scans(scans, target, self.device, on_ready=early, times=times, period=frame_period)
        return self._fit_group([(prep, cache)], early)[0]

    def fit_many(self, windows: Sequence[tuple[Sequence, int | None]]) -> list[FloxelsResult]:
        """Estimate several target frames in one optimisation: ``windows`` is a list of
        ``(scans, target)``. The problems stay independent (each has its own loss, early
        stopping and lowest-loss flow, as when fitted alone) but share every kernel
        launch, which keeps a GPU busy. For sliding windows over one sequence use
        :func:`estimate_sequence`, which also shares the distance transforms."""
        if isinstance(windows, (str, bytes)) or not isinstance(windows, Sequence):
            raise TypeError(f"windows must be a list of (scans, target) pairs, got {type(windows).__name__}")
        if not windows:
            raise ValueError("fit_many needs at least one (scans, target) window")
        for k, w in enumerate(windows):
            # (a list of scans passed as one window has arrays where the scans should be)
            if not (isinstance(w, (tuple, list)) and len(w) == 2 and hasattr(w[0], "__len__")
                    and not hasattr(w[0], "shape") and not isinstance(w[0], str)):
                raise TypeError(f"windows[{k}] must be a (scans, target) pair, e.g. fit_many([(scans, 2)]); "
                                f"got {type(w).__name__}" + (f" of length {len(w)}" if hasattr(w, "__len__") else ""))
        preps = [prepare_scans(scans, target, self.device) for scans, target in windows]
        return self._fit_group([(p, {}) for p in preps])

    # -- internals ----------------------------------------------------------------------
    def _fit_group(self, items: list, early: "_DtStreams | None" = None) -> list[FloxelsResult]:
        """Optimise the targets of ``items`` ([(PreparedScans, dt cache)]) together."""
        return self._solve_group(self._prepare_group(items, early=early)).finish()

    def _prepare_group(self, items: list, pipelined: bool = False, poll: Callable[[], object] | None = None,
                       early: "_DtStreams | None" = None):
        """Everything before the optimisation: the distance transforms still missing from the
        caches, DBSCAN of every target, points sorted by (cluster, voxel) and their compact
        corners. ``pipelined``: all of it is enqueued on the current stream (the caller's
        side stream, while the GPU still optimises other frames) with no device
        synchronisation, and ``poll`` is called between targets to keep that work queued.
        ``early``: the EDTs already started while the scans were uploaded (single frames)."""
        cfg = self.config
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        device = items[0][0].points[0].device

        # Scans were validated by prepare_scans, so the ops are called directly (no
        # re-checks), and every cloud's bounds come back in one host synchronisation.
        t0 = time.perf_counter()
        # DTs still to build, by scan tensor (windows of one sequence share scan tensors,
        # so each scan is built once)
        todo: dict[int, list] = {}  # id -> [points, [(cache, index in window)], bounds or None]
        for prep, cache in items:
            if prep.points[prep.target].shape[0] > 0:
                for i in prep.supports:
                    if i not in cache and prep.points[i].shape[0] > 0:
                        todo.setdefault(id(prep.points[i]), [prep.points[i], [], _known_bounds(prep, i)])[1].append(
                            (cache, i))
        targets = [(prep.points[prep.target], _known_bounds(prep, prep.target)) for prep, _ in items
                   if prep.points[prep.target].shape[0] > 0]
        # bounds not known from the upload (device scans): all in one host synchronisation
        found = iter(point_bounds([v[0] for v in todo.values() if v[2] is None] + [p for p, b in targets if b is None]))
        dt_bounds = [v[2] if v[2] is not None else next(found) for v in todo.values()]
        target_bounds = iter([b if b is not None else next(found) for _, b in targets])
        # On CUDA, DBSCAN and the point sorting run on a side stream while the EDTs (memory
        # bound) run on others: the host synchronisations of DBSCAN and the sorting then
        # wait for their own kernels only. Single frames: one stream per EDT (they overlap
        # each other's tails), the rest on the side stream. Pipelined (the caller's stream is
        # the side stream): EDTs on a third stream. FLOXELS_SERIAL_STAGES=1 runs the stages
        # one after the other (stage timings).
        serial = _serial_stages(device)
        main = torch.cuda.current_stream(device) if device.type == "cuda" else None
        side = dt_stream = None
        if not serial:
            side = None if pipelined else _side_stream(device)
            dt_stream = _dt_stream(device) if pipelined else main
            (side or dt_stream).wait_stream(main)  # the scans are ready
        # single frames on a GPU: a stream per EDT (those already started while the scans were
        # uploaded, and any others here)
        streams = None if serial or pipelined else (early if early is not None else _DtStreams(cfg))
        dt_events = None
        if streams is None and dt_stream is not None and todo:
            dt_events = (torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True))
            dt_events[0].record(dt_stream)
        for (pts, users, _), b in zip(todo.values(), dt_bounds):
            if streams is not None:
                d = streams.launch(pts, b)
            else:
                with torch.cuda.stream(dt_stream) if dt_stream is not None else contextlib.nullcontext():
                    d = _build_dt(pts, cfg, b)
            for cache, i in users:
                cache[i] = d
        if streams is not None and streams.start is not None:
            for st in streams.streams:
                main.wait_stream(st)
            dt_events = (streams.start, torch.cuda.Event(enable_timing=True))
        if dt_events is not None:
            dt_events[1].record(dt_stream)
        supports = []  # per item: (dts, origins, offsets, weights)
        for prep, cache in items:
            dts, origins, offsets, weights = [], [], [], []
            if prep.points[prep.target].shape[0] > 0:
                for i, t in zip(prep.supports, prep.offsets):
                    if i not in cache:  # empty support scan
                        cache[i] = None
                    d = cache[i]
                    if d is None:  # empty support scan: no evidence from it
                        continue
                    dts.append(d.values)
                    origins.append(d.origin)
                    offsets.append(float(t))
                    weights.append(cfg.lambda_d * cfg.time_weight(t))
            supports.append((dts, origins, offsets, weights))
        if serial:
            _sync_device(device)
        timings["dt"] = time.perf_counter() - t0  # serial: wall time; else replaced by GPU time (dt_events)
        stream_ctx = torch.cuda.stream(side) if side is not None else contextlib.nullcontext()
        with stream_ctx:
            labels, problems, orders, grids = self._targets(items, supports, target_bounds, timings, poll)
        work = side if side is not None else (torch.cuda.current_stream(device) if pipelined else None)
        if pipelined and dt_stream is not None:
            # the DTs were made on the EDT stream and are used on the preparing stream's
            # successors: that stream waits for them, and the allocator learns of the use
            work.wait_stream(dt_stream)
            for d in {id(t): t for pr in problems if pr is not None for t in pr.dts}.values():
                d.record_stream(work)
        if side is not None:
            _used_on(main, items, problems, orders, labels)
            main.wait_stream(side)
        return _Prepared(items, labels, problems, orders, grids, timings, t_start, dt_events)

    def _solve_group(self, prepared: "_Prepared", wait_for=None) -> "_Solving":
        """Pack the prepared problems and start their optimisation on the current stream
        (after ``wait_for``, the stream the preparation ran on, if any)."""
        t0 = time.perf_counter()
        packs = prepared.packs if prepared.packs is not None else self._pack(prepared)
        if wait_for is not None:
            main = torch.cuda.current_stream()
            _used_on(main, prepared.items, prepared.problems, prepared.orders, prepared.labels)
            for _, packed in packs:
                packed.record_stream(main)
            main.wait_stream(wait_for)
        runs = []
        for group, packed in packs:
            run = SolverRun(packed)
            run.poll()
            runs.append((group, packed, run))
        return _Solving(self, prepared, runs, t0)

    def _pack(self, prepared: "_Prepared") -> list:
        """The solver calls of a prepared group: [(indices of its problems, PackedProblems)]."""
        live = [k for k, p in enumerate(prepared.problems) if p is not None]
        return [(group, PackedProblems([prepared.problems[k] for k in group], self.config))
                for group in _groups(live, prepared.problems)]

    def _targets(self, items, supports, target_bounds, timings, poll=None):
        """DBSCAN of every target, then its points sorted by (cluster, voxel) with their
        compact corners: the per-target part of :meth:`_fit_group` before the solver."""
        cfg = self.config
        t0 = time.perf_counter()
        labels = []
        for prep, _ in items:
            if poll is not None:
                poll()
            labels.append(F.dbscan(prep.points[prep.target], cfg.dbscan_eps, cfg.dbscan_min_samples)
                          if cfg.cluster_loss and prep.points[prep.target].shape[0] else None)
        timings["dbscan"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        problems, orders, grids = [], [], []
        for (prep, _), lab, (dts, origins, offsets, weights) in zip(items, labels, supports):
            if poll is not None:
                poll()
            P = prep.points[prep.target]
            if P.shape[0] == 0:
                problems.append(None)
                orders.append(None)
                grids.append(None)
                continue
            g_origin, g_shape = grid_from_bounds(*next(target_bounds), cfg.voxel_size, cfg.voxel_size,
                                                 max_cells=1 << 40)
            # One op, one host synchronisation: points sorted by (cluster, voxel) (neighbouring
            # points touch neighbouring memory, a block of points meets few clusters, and the
            # solver's segments, one cluster inside one cell, are long runs), their compact
            # corners and the solver's segment tables (built here, while the EDTs run, rather
            # than when packing), and the number of clusters.
            st = problem_setup(P, lab, g_origin, cfg.voxel_size, g_shape, SEGMENT_TILE)
            problems.append(SolverProblem(st.points, st.corners, st.labels, dts, origins, offsets, weights,
                                          cfg.regulariser_scale(len(prep.supports)), st.num_clusters, st.segments))
            orders.append(st.order)
            grids.append(g_origin)
        timings["setup"] = time.perf_counter() - t0
        return labels, problems, orders, grids


@dataclass
class _Prepared:
    """What :meth:`Floxels._prepare_group` hands to :meth:`Floxels._solve_group`."""

    items: list
    labels: list
    problems: list
    orders: list
    grids: list
    timings: dict
    t_start: float
    dt_events: tuple | None = None  # CUDA events around the EDT launches (their GPU time)
    packs: list | None = None       # Floxels._pack, if packed during the preparation


class _Solving:
    """Optimisations under way for one prepared group: ``poll()`` keeps them queued,
    ``finish()`` waits for them and builds the results."""

    def __init__(self, est: Floxels, prepared: _Prepared, runs: list, t0: float) -> None:
        self.est, self.prepared, self.runs, self.t0 = est, prepared, runs, t0

    def poll(self) -> None:
        for _, _, run in self.runs:
            run.poll()

    def finish(self) -> list[FloxelsResult]:
        pr, cfg = self.prepared, self.est.config
        solved: dict[int, tuple] = {}
        hosts = []
        for group, packed, run in self.runs:
            run.finish(wait=False)  # the read-backs below queue behind the last iterations
            hosts.append(packed.summaries_start())
        for group, packed, run in self.runs:
            for b, k in enumerate(group):
                solved[k] = packed.best_params(b).clone()
        flows, parts = [], []  # flow of the kept rows, (labels, fields of the result) per frame
        for k, (prep, _) in enumerate(pr.items):
            if pr.problems[k] is None:
                flows.append(prep.points[prep.target].new_zeros(0, 3))
                continue
            corners = pr.problems[k].corners
            flow_s = F.corner_gather(solved[k], corners.corner_idx, corners.corner_w)
            flow = torch.empty_like(flow_s)
            flow[pr.orders[k]] = flow_s
            flows.append(flow)
        # every frame's output in one transfer (numpy outputs of CUDA flows), then the one
        # synchronisation of the read-backs
        outs = restore_outputs(flows, [prep for prep, _ in pr.items])
        for _, packed, run in self.runs:
            if run.cuda:
                run.stream.synchronize()
        summaries: dict[int, tuple] = {}
        for (group, packed, _), host in zip(self.runs, hosts):
            for k, summary in zip(group, packed.summaries(host)):
                summaries[k] = summary
        timings = dict(pr.timings)
        if pr.dt_events is not None:  # the EDTs overlapped other work: their GPU time
            timings["dt"] = 1e-3 * pr.dt_events[0].elapsed_time(pr.dt_events[1])
        timings["optimise"] = time.perf_counter() - self.t0
        timings["total"] = time.perf_counter() - pr.t_start
        if len(pr.items) > 1:
            timings["group_size"] = float(len(pr.items))
        for k, lab in enumerate(pr.labels):
            if pr.problems[k] is None:
                parts.append((None, [], -1, 0, dict(timings), None, cfg.voxel_size, None, None))
                continue
            losses, best_iter = summaries[k]
            parts.append((lab, losses, best_iter, len(losses), dict(timings), pr.grids[k], cfg.voxel_size,
                          pr.problems[k].corners, solved[k]))
        return [FloxelsResult(out, flow, *fields) for out, flow, fields in zip(outs, flows, parts)]


def _used_on(stream, items, problems, orders, labels) -> None:
    """Tensors made on another stream and used on ``stream``: keep the caching allocator
    from handing their memory out again while ``stream`` may still use it."""
    for pr, order in zip(problems, orders):
        if pr is not None:
            for t in (pr.points, pr.corners.corner_idx, pr.corners.corner_w, pr.corners.vertices, order, pr.labels,
                      *pr.dts, *(pr.segments or ())):
                if t is not None:
                    t.record_stream(stream)
    for lab in labels:
        if lab is not None:
            lab.record_stream(stream)
    for prep, _ in items:
        prep.finite_masks[prep.target].record_stream(stream)


def _groups(live: list[int], problems: list) -> list[list[int]]:
    """Split problems into op calls: at most MAX_PROBLEMS each and MAX_DTS distinct DTs."""
    groups, cur, dts = [], [], set()
    for k in live:
        ids = {id(d) for d in problems[k].dts}
        if cur and (len(cur) == MAX_PROBLEMS or len(dts | ids) > MAX_DTS):
            groups.append(cur)
            cur, dts = [], set()
        cur.append(k)
        dts |= ids
    if cur:
        groups.append(cur)
    return groups


class _WindowCache:
    """A window's view (index in the window -> DT) of a sequence-wide cache (frame -> DT)."""

    def __init__(self, cache: dict, start: int) -> None:
        self.cache, self.start = cache, start

    def __contains__(self, i) -> bool:
        return self.start + i in self.cache

    def __getitem__(self, i):
        return self.cache[self.start + i]

    def __setitem__(self, i, value) -> None:
        self.cache[self.start + i] = value


class _DtStreams:
    """EDTs of a single frame on a GPU, each on a stream of its own (they overlap each
    other's tails). As ``prepare_scans``' on_ready hook (:meth:`__call__`), it queues each
    support scan's EDT as soon as its upload is queued, so the EDTs (the longest work before
    the optimiser) start while later scans are still being copied; ``FLOXELS_EARLY_DT=0``
    leaves them to :meth:`Floxels._prepare_group` (measurements)."""

    def __init__(self, cfg: FloxelsConfig, cache: dict | None = None) -> None:
        self.cfg, self.cache = cfg, cache  # cache: where __call__ puts the DTs
        self.start: torch.cuda.Event | None = None  # on the main stream, before the first EDT
        self.streams: list = []  # the streams used, for the main stream to wait for

    def launch(self, points: torch.Tensor, bounds) -> DistanceTransform | None:
        """Queue the EDT of ``points`` (on a CUDA device) after the current stream's work."""
        main = torch.cuda.current_stream(points.device)
        if self.start is None:
            self.start = torch.cuda.Event(enable_timing=True)
            self.start.record(main)
        st = _side_stream(points.device, f"dt{len(self.streams) % 4}")
        st.wait_stream(main)  # the upload
        with torch.cuda.stream(st):
            d = _build_dt(points, self.cfg, bounds)
        self.streams.append(st)
        return d

    def __call__(self, i: int, points: torch.Tensor, bounds, is_target: bool) -> None:
        dev = points.device
        if dev.type != "cuda" or _serial_stages(dev) or is_target or i in self.cache or points.shape[0] == 0:
            return
        if os.environ.get("FLOXELS_EARLY_DT", "1") == "0":
            return
        self.cache[i] = self.launch(points, bounds)


def _known_bounds(prep: PreparedScans, i: int):
    return prep.bounds[i] if prep.bounds is not None else None


_SIDE_STREAMS: dict = {}


def _side_stream(device: torch.device, kind: str = "side"):
    """Persistent side streams per device (a new stream per frame would strand cached
    allocator blocks on streams never used again). "side" (DBSCAN, sorting: short kernels
    whose results the host waits for) has high priority, so that its kernels are scheduled
    ahead of the optimiser's queued blocks; "dt" (the EDTs, long and memory bound) has
    normal priority."""
    key = (device.index if device.index is not None else torch.cuda.current_device(), kind)
    if key not in _SIDE_STREAMS:
        # (a priority beyond the device's range maps to its highest)
        _SIDE_STREAMS[key] = torch.cuda.Stream(device=torch.device("cuda", key[0]),
                                               priority=-8 if kind == "side" else 0)
    return _SIDE_STREAMS[key]


def _dt_stream(device: torch.device):
    return _side_stream(device, "dt")


def _serial_stages(device: torch.device) -> bool:
    return device.type != "cuda" or os.environ.get("FLOXELS_SERIAL_STAGES", "0") == "1"


def _sync_device(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def estimate_flow(scans: Sequence, target: int | None = None, config: FloxelsConfig | None = None, device=None,
                  *, times: Sequence[float] | None = None, frame_period: float | None = None,
                  flow_unit: str = "frame"):
    """Flow of every point of ``scans[target]``.

    ``scans``: 2 to 13 (N_i, 3) float arrays/tensors in one ego-motion-compensated frame;
    ``target`` defaults to the middle scan (negative indices count from the end). Without
    ``times`` the scans are taken as consecutive at the sensor rate: support scan ``i`` is at
    time offset ``i - target``. ``times``: the scans' timestamps in seconds (one per scan,
    finite, strictly increasing; e.g. a dropped frame leaves a gap): offsets are then
    ``(t_i - t_target) / period`` with ``period = frame_period`` or, by default, the median
    step of ``times``. ``flow_unit``: ``"frame"`` (default: metres per frame period) or
    ``"m/s"`` (needs ``times`` or ``frame_period``). Returns (N_target, 3): numpy float32 for
    numpy input, else a tensor of the input's dtype on the input's device. Rows with NaN/inf
    coordinates are dropped (with a warning) and get NaN flow.
    """
    if flow_unit not in ("frame", "m/s"):  # argument mistakes before any work
        raise ValueError(f"flow_unit must be 'frame' or 'm/s', got {flow_unit!r}")
    if flow_unit == "m/s" and times is None and frame_period is None:
        raise ValueError("flow_unit='m/s' needs the scans' times= (seconds) or frame_period= (seconds)")
    frame_period_of(None, frame_period)  # checks it
    flow = Floxels(config, device).fit(scans, target, times=times, frame_period=frame_period).flow
    to_unit = _unit_factor(flow_unit, None if times is None else check_times(times, len(scans)), frame_period)
    return flow if to_unit == 1.0 else flow * to_unit


def _unit_factor(flow_unit: str, times, frame_period) -> float:
    """Factor from metres per frame period to ``flow_unit``; ``times`` already checked."""
    if flow_unit not in ("frame", "m/s"):
        raise ValueError(f"flow_unit must be 'frame' or 'm/s', got {flow_unit!r}")
    if flow_unit == "frame":
        return 1.0
    if times is None and frame_period is None:
        raise ValueError("flow_unit='m/s' needs the scans' times= (seconds) or frame_period= (seconds)")
    return 1.0 / frame_period_of(times, frame_period)


def _batches(frames: list[int], size: int, ramp: bool) -> list[list[int]]:
    """Consecutive batches of at most ``size`` frames. ``ramp`` (pipelined sequences): the
    first batches are smaller (4, 8, ... frames) so the GPU starts optimising after a short
    first preparation, and each later batch is prepared while a batch about half its size is
    optimised; results do not depend on the batching."""
    out, k, cur = [], 0, min(size, 4) if ramp else size
    while k < len(frames):
        out.append(frames[k:k + cur])
        k += cur
        cur = min(size, 2 * cur)
    return out


def window_for(frame: int, num_frames: int, num_scans: int) -> tuple[int, int]:
    """[start, stop) of the window of ``num_scans`` scans used for ``frame``: centred on it,
    shifted inwards at the ends of the sequence (so the target may be the first/last scan)."""
    w = min(num_scans, num_frames)
    start = min(max(frame - w // 2, 0), num_frames - w)
    return start, start + w


def estimate_sequence(scans: Sequence, config: FloxelsConfig | None = None, device=None,
                      frames: Sequence[int] | None = None,
                      callback: Callable[[int, FloxelsResult], None] | None = None,
                      batch_size: int | None = None, *, times: Sequence[float] | None = None,
                      frame_period: float | None = None, flow_unit: str = "frame") -> list:
    """Flow of every frame of a sequence (or of ``frames``) with a sliding window of
    ``config.num_scans`` scans. Each scan's distance transform is built once and reused by
    every window that needs it (and freed once no later window does).

    ``batch_size`` target frames are optimised together (default: 16 on CUDA, where
    sharing kernel launches raises throughput, 1 on the CPU); each frame's result is the
    same as optimising it alone. On CUDA the next batch is prepared (distance transforms,
    DBSCAN, sorting) while the GPU optimises the current one; the first batches are then
    smaller (4, 8, ... up to ``batch_size``) so that the GPU starts early.

    ``frames``: indices into ``scans``; negative ones count from the end, like ``target``.
    ``times``/``frame_period``/``flow_unit``: scans not equally spaced and the unit of the
    flow, as in :func:`estimate_flow` (the period is the median step of the whole sequence's
    times; each window's offsets come from its scans' times).

    Returns a list with one flow per requested frame (numpy float32 for numpy input).
    ``callback(frame, result)`` is called after each frame (e.g. to write it to disk), with
    ``result.flow`` in ``flow_unit``.
    """
    if config is not None and not isinstance(config, FloxelsConfig):
        raise TypeError(f"config must be a FloxelsConfig, got {type(config).__name__}")
    cfg = config or FloxelsConfig()
    if getattr(scans, "ndim", None) == 2:
        raise TypeError(f"scans must be a sequence of (N_i, 3) arrays, not a single {tuple(scans.shape)} array")
    if not isinstance(scans, collections.abc.Sequence):
        scans = list(scans)  # an iterator or a stacked array: materialise it
    # a Sequence is read lazily, window by window (``floxels run`` passes scans that are still
    # being read and preprocessed; the first batch starts as soon as its windows are ready)
    n = len(scans)
    if n < 2:
        raise ValueError(f"a sequence needs at least 2 scans, got {n}")
    if times is not None:
        times = check_times(times, n)
    period = frame_period_of(times, frame_period)
    to_unit = _unit_factor(flow_unit, times, frame_period)
    if frames is None:
        frames = list(range(n))
    else:
        given = list(frames)
        for f in given:
            if isinstance(f, bool) or not isinstance(f, (int, np.integer)):
                raise TypeError(f"frames must hold integer indices, got {f!r}")
        frames = [int(f) + n if int(f) < 0 else int(f) for f in given]
        for f, g in zip(frames, given):
            if not 0 <= f < n:
                raise IndexError(f"frame {g} is out of range for {n} scans (valid: {-n} .. {n - 1})")
    est = Floxels(cfg, device)
    dev = resolve_device(device, scans[0])
    if batch_size is None:
        batch_size = MAX_PROBLEMS if dev.type == "cuda" else 1
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    cache: dict[int, DistanceTransform | None] = {}
    converted: dict = {}  # sequence index -> scan on the device (converted and NaN-checked once)
    # On CUDA, the next batch is prepared (scans, distance transforms, DBSCAN, sorting: mostly
    # host-bound work) on a side stream while the GPU optimises this one.
    # FLOXELS_PIPELINE=0 turns this off, FLOXELS_RAMP=0 the smaller first batches (measurements).
    pipelined = (dev.type == "cuda" and len(frames) > batch_size and not _serial_stages(dev)
                 and os.environ.get("FLOXELS_PIPELINE", "1") != "0")
    batches = _batches(frames, batch_size, ramp=pipelined and os.environ.get("FLOXELS_RAMP", "1") != "0")
    if not batches:
        return []
    side = _side_stream(dev) if pipelined else None

    def prepare(batch, poll=None):
        def items():
            out = []
            for f in batch:
                start, stop = window_for(f, n, cfg.num_scans)
                out.append((prepare_scans(scans[start:stop], f - start, device, converted, start,
                                          times=None if times is None else times[start:stop], period=period),
                            _WindowCache(cache, start)))
            return out
        if side is None:
            return est._prepare_group(items())
        with torch.cuda.stream(side):
            prepared = est._prepare_group(items(), pipelined=True, poll=poll)
            prepared.packs = est._pack(prepared)  # packing, too, before the current batch ends
            return prepared

    out = []
    prepared = prepare(batches[0])
    for k, batch in enumerate(batches):
        solving = est._solve_group(prepared, wait_for=side)
        error = None
        if k + 1 < len(batches):
            try:
                prepared = prepare(batches[k + 1], poll=solving.poll)
            except BaseException as e:  # deliver this batch's flows first, then raise
                error = e
        results = solving.finish()
        del solving
        # free the DTs and device scans that no later window will use
        later = [window_for(g, n, cfg.num_scans)[0] for b in batches[k + 1:] for g in b]
        horizon = min(later) if later else math.inf
        for d in (cache, converted):
            for i in [i for i in d if i < horizon]:
                del d[i]
        for f, res in zip(batch, results):
            if to_unit != 1.0:
                res.flow = res.flow * to_unit
            out.append(res.flow)
            if callback is not None:
                callback(f, res)
        if error is not None:
            raise error
    return out
