"""A group of target frames optimised together, its data steps in the order they run: the
distance transforms still missing, DBSCAN, points sorted by (cluster, voxel) with their
compact corners (:func:`prepare_group`), the packed solver calls (:func:`solve_group`), and
the flows, their motion evidence and refinement, read back (:meth:`Solving.finish`). Each
frame's result is the same as when it is optimised alone; the group shares kernel launches
(and, in :func:`~floxels_ext.estimator.api.estimate_sequence`, the distance transforms of the
scans its windows share). Where each step runs on a GPU (streams, events, waits) is
``schedule.py``'s."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.distance import build_dt
from floxels_ext.estimator.post import after_optimisation_all, problem_evidence, problem_observed
from floxels_ext.estimator.refine import cluster_velocity_search, supports_of, vertex_init
from floxels_ext.estimator.result import FloxelsResult
from floxels_ext.estimator.scans import PreparedScans, restore_outputs
from floxels_ext.estimator.solver_run import SolverRun
from floxels_ext.estimator.schedule import EdtStreams, GpuMarks, PrepareSchedule, receive
from floxels_ext.ops.grid import grid_from_bounds, point_bounds
from floxels_ext.ops.setup import problem_setup
from floxels_ext.ops.solver import MAX_DTS, MAX_PROBLEMS, SEGMENT_TILE, PackedProblems, SolverProblem

__all__ = ["Prepared", "Solving", "Finishing", "fit_group", "prepare_group", "solve_group", "pack", "problem_evidence"]

F = torch.ops.floxels


def fit_group(cfg: FloxelsConfig, items: list, early: EdtStreams | None = None) -> list[FloxelsResult]:
    """Optimise the targets of ``items`` ([(PreparedScans, dt cache)]) together."""
    prepared = prepare_group(cfg, items, early=early)
    return solve_group(cfg, prepared).finish()


def prepare_group(cfg: FloxelsConfig, items: list, pipelined: bool = False,
                  poll: Callable[[], object] | None = None, early: EdtStreams | None = None) -> Prepared:
    """Everything before the optimisation: the distance transforms still missing from the
    caches, DBSCAN of every target, points sorted by (cluster, voxel) and their compact
    corners. ``pipelined``: all of it is enqueued on the current stream (the caller's
    side stream, while the GPU still optimises other frames) with no device
    synchronisation, and ``poll`` is called between targets to keep that work queued.
    ``early``: the EDTs already started while the scans were uploaded (single frames).
    Where each step runs on a GPU: ``schedule.PrepareSchedule``."""
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    device = items[0][0].points[0].device

    # Scans were validated by prepare_scans, so the ops are called directly (no
    # re-checks), and every cloud's bounds come back in one host synchronisation.
    t0 = time.perf_counter()
    # DTs still to build, by scan tensor (windows of one sequence share scan tensors,
    # so each scan is built once)
    todo: dict[int, list] = {}  # id -> [points, [(cache, index in window)], bounds or None, sensor, ground_of]
    for prep, cache in items:
        if prep.points[prep.target].shape[0] > 0:
            for i in prep.supports:
                if i not in cache and prep.points[i].shape[0] > 0:
                    todo.setdefault(id(prep.points[i]), [prep.points[i], [], known_bounds(prep, i),
                                                         prep.sensor(i), prep.ground_of(i)])[1].append((cache, i))
    targets = [(prep.points[prep.target], known_bounds(prep, prep.target)) for prep, _ in items
               if prep.points[prep.target].shape[0] > 0]
    # bounds not known from the upload (device scans): all in one host synchronisation
    found = iter(point_bounds([v[0] for v in todo.values() if v[2] is None] + [p for p, b in targets if b is None]))
    dt_bounds = [v[2] if v[2] is not None else next(found) for v in todo.values()]
    target_bounds = iter([b if b is not None else next(found) for _, b in targets])
    sched = PrepareSchedule(device, pipelined, early)
    sched.begin_dts(len(todo))
    for (pts, users, _, sensor, ground_of), b in zip(todo.values(), dt_bounds):
        with sched.dt():
            d = build_dt(pts, cfg, b, sensor, ground_of)
        for cache, i in users:
            cache[i] = d
    sched.end_dts()
    supports = []  # per item: (dts, origins, offsets, weights, sights or None)
    for prep, cache in items:
        dts, origins, offsets, weights, sights = [], [], [], [], []
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
                sights.append(d.sight)
        # sights where some support scan has one (a scan without counts everywhere)
        supports.append((dts, origins, offsets, weights, sights if any(s is not None for s in sights) else None))
    timings["dt"] = timings["dt_host"] = time.perf_counter() - t0  # "dt": replaced by GPU time (dt_events)
    with sched.targets():
        labels, problems, orders, grids = _targets(cfg, items, supports, target_bounds, timings, poll)
    sched.hand_over(items, problems, orders, labels)
    return Prepared(items, labels, problems, orders, grids, timings, t_start, sched.dt_events)


def solve_group(cfg: FloxelsConfig, prepared: Prepared, wait_for=None) -> Solving:
    """Pack the prepared problems and start their optimisation on the current stream
    (after ``wait_for``, the stream the preparation ran on, if any)."""
    t0 = time.perf_counter()
    packs = prepared.packs if prepared.packs is not None else pack(cfg, prepared)
    receive(prepared, packs, wait_for)
    marks = GpuMarks(prepared.items[0][0].points[0].device)
    marks.mark("solver")
    runs = []
    for group, packed in packs:
        run = SolverRun(packed)
        run.poll()
        runs.append((group, packed, run))
    prepared.timings["pack"] = time.perf_counter() - t0
    return Solving(cfg, prepared, runs, t0, marks)


def pack(cfg: FloxelsConfig, prepared: Prepared) -> list:
    """The solver calls of a prepared group: [(indices of its problems, PackedProblems)]."""
    live = [k for k, p in enumerate(prepared.problems) if p is not None]
    packs = [(group, PackedProblems([prepared.problems[k] for k in group], cfg))
             for group in _groups(live, prepared.problems)]
    if cfg.velocity_search:
        for group, packed in packs:
            for b, k in enumerate(group):
                packed.theta[packed.vertex_ranges[b]:packed.vertex_ranges[b + 1]] = _searched_start(
                    cfg, prepared.problems[k])
    return packs


def _searched_start(cfg: FloxelsConfig, p: SolverProblem) -> torch.Tensor:
    """Grid parameters started from each cluster's searched velocity (refine.py)."""
    sup = supports_of(p.dts, p.origins, p.time_offsets, p.weights, cfg.dt_cell)
    vel = cluster_velocity_search(p.points, p.labels, sup, observed=problem_observed(p), num_clusters=p.num_clusters)
    return vertex_init(vel, p.corners.corner_idx, p.corners.corner_w, p.corners.num_params)


def _targets(cfg: FloxelsConfig, items, supports, target_bounds, timings, poll=None):
    """DBSCAN of every target, then its points sorted by (cluster, voxel) with their
    compact corners: the per-target part of :func:`prepare_group`."""
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
    for (prep, _), lab, (dts, origins, offsets, weights, sights) in zip(items, labels, supports):
        if poll is not None:
            poll()  # keeps the solver's queue topped up while the device optimises the batch before
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
        # than when packing), and the number of clusters. (One synchronisation for a whole
        # group was tried and measured no faster: bench/RESULTS.md "Where floxels run waits".)
        st = problem_setup(P, lab, g_origin, cfg.voxel_size, g_shape, SEGMENT_TILE)
        problems.append(SolverProblem(st.points, st.corners, st.labels, dts, origins, offsets, weights,
                                      cfg.regulariser_scale(len(prep.supports), prep.offsets), st.num_clusters, st.segments,
                                      sights))
        orders.append(st.order)
        grids.append(g_origin)
    timings["setup"] = time.perf_counter() - t0
    return labels, problems, orders, grids


@dataclass
class Prepared:
    """What :func:`prepare_group` hands to :func:`solve_group`."""

    items: list
    labels: list
    problems: list
    orders: list
    grids: list
    timings: dict
    t_start: float
    dt_events: tuple | None = None  # CUDA events around the EDT launches (their GPU time)
    packs: list | None = None       # pack(), if packed during the preparation


class Solving:
    """Optimisations under way for one prepared group: ``poll()`` keeps them queued,
    ``finish()`` waits for them and builds the results."""

    def __init__(self, cfg: FloxelsConfig, prepared: Prepared, runs: list, t0: float,
                 marks: GpuMarks | None = None) -> None:
        self.cfg, self.prepared, self.runs, self.t0 = cfg, prepared, runs, t0
        self.marks = marks

    def poll(self) -> None:
        for _, _, run in self.runs:
            run.poll()

    def finish(self) -> list[FloxelsResult]:
        """Wait for the optimisations and build the results."""
        return self.queue_results().results()

    def queue_results(self) -> "Finishing":
        """Queue everything the results need on the device (the flows at the points, the steps
        after the optimiser, the one read-back) behind the optimisations, without waiting: work
        queued on the stream afterwards (the next group's optimisation) runs while the host
        waits for this group's read-back alone (:meth:`Finishing.results`)."""
        pr, cfg = self.prepared, self.cfg
        t_solve = time.perf_counter()
        solved: dict[int, tuple] = {}
        hosts = []
        for group, packed, run in self.runs:
            run.finish(wait=False)  # the read-backs below queue behind the last iterations
            hosts.append(packed.summaries_start())
        if self.marks is not None:
            self.marks.mark("results")
        t_results = time.perf_counter()
        for group, packed, run in self.runs:
            for b, k in enumerate(group):
                solved[k] = packed.best_params(b).clone()
        flows = []  # flow of the kept rows per frame
        evidence = [] if cfg.evidence != "off" else None  # (N_kept, 2): score, explained (0/1)
        # the evidence test and the refinement of every problem, their host reads merged
        live = [k for k, p in enumerate(pr.problems) if p is not None]
        after = dict(zip(live, after_optimisation_all(
            cfg, [pr.problems[k] for k in live],
            [F.corner_gather(solved[k], pr.problems[k].corners.corner_idx, pr.problems[k].corners.corner_w)
             for k in live])))
        for k, (prep, _) in enumerate(pr.items):
            if pr.problems[k] is None:
                flows.append(prep.points[prep.target].new_zeros(0, 3))
                if evidence is not None:
                    evidence.append(prep.points[prep.target].new_zeros(0, 2))
                continue
            flow_s, ev = after[k]
            if evidence is not None:
                ev_k = torch.empty(len(flow_s), 2, dtype=torch.float32, device=flow_s.device)
                ev_k[pr.orders[k], 0] = ev.score
                ev_k[pr.orders[k], 1] = ev.explained.to(torch.float32)
                evidence.append(ev_k)
            flow = torch.empty_like(flow_s)
            flow[pr.orders[k]] = flow_s
            flows.append(flow)
        # every frame's output in one transfer (numpy outputs of CUDA flows), queued; an event
        # behind it and the summaries' copies, which the host waits for instead of the stream
        if self.marks is not None:
            self.marks.mark("end")
        t_readback = time.perf_counter()
        outputs = restore_outputs(flows, [prep for prep, _ in pr.items], evidence, wait=False)
        done = []
        for _, packed, run in self.runs:
            if run.cuda:
                done.append(torch.cuda.Event())
                done[-1].record(run.stream)
        return Finishing(self, solved, flows, hosts, outputs, done, (t_solve, t_results, t_readback))


class Finishing:
    """A group whose results are queued (:meth:`Solving.queue_results`); :meth:`results` waits
    for them and builds the :class:`FloxelsResult` of each target."""

    def __init__(self, solving: Solving, solved: dict, flows: list, hosts: list, outputs, done: list,
                 times: tuple) -> None:
        self.solving, self.solved, self.flows, self.hosts = solving, solved, flows, hosts
        self.outputs, self.done, self.times = outputs, done, times

    def results(self) -> list[FloxelsResult]:
        sv = self.solving
        pr, cfg, solved, flows = sv.prepared, sv.cfg, self.solved, self.flows
        t_solve, t_results, t_readback = self.times
        outs, ev_outs = self.outputs()
        for ev in self.done:
            ev.synchronize()
        t_finish = time.perf_counter()
        summaries: dict[int, tuple] = {}
        for (group, packed, _), host in zip(sv.runs, self.hosts):
            for k, summary in zip(group, packed.summaries(host)):
                summaries[k] = summary
        timings = dict(pr.timings)
        if pr.dt_events is not None:  # the EDTs overlapped other work: their GPU time
            timings["dt"] = 1e-3 * pr.dt_events[0].elapsed_time(pr.dt_events[1])
        # host time, in order (bench_speed names every part of a frame): the result kernels'
        # launches; the read-back, which waits for the solver's and those kernels' GPU work;
        # the summaries and results built after it
        timings["solve"] = t_results - t_solve  # CPU: the optimisation; CUDA: its last launches
        timings["results"] = t_readback - t_results
        timings["readback"] = t_finish - t_readback
        timings["finish"] = time.perf_counter() - t_finish
        if sv.marks is not None:  # GPU time from the solver's enqueue on (no synchronisation)
            timings.update(sv.marks.spans())
        timings["optimise"] = time.perf_counter() - sv.t0
        timings["total"] = time.perf_counter() - pr.t_start
        if len(pr.items) > 1:
            timings["group_size"] = float(len(pr.items))
        parts = []  # (labels, fields of the result) per frame
        for k, lab in enumerate(pr.labels):
            if pr.problems[k] is None:
                parts.append((None, [], -1, 0, dict(timings), None, cfg.voxel_size, None, None))
                continue
            losses, best_iter = summaries[k]
            rc = pr.items[k][0].recentring  # the origin in the caller's coordinates
            origin = rc.restore(pr.grids[k]) if rc is not None else pr.grids[k]
            parts.append((lab, losses, best_iter, len(losses), dict(timings), origin, cfg.voxel_size,
                          pr.problems[k].corners, solved[k]))
        results = [FloxelsResult(out, flow, *fields) for out, flow, fields in zip(outs, flows, parts)]
        if ev_outs is not None:
            for res, (score, explained) in zip(results, ev_outs):
                res.evidence, res.explained = score, explained
        return results


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


def known_bounds(prep: PreparedScans, i: int):
    return prep.bounds[i] if prep.bounds is not None else None
