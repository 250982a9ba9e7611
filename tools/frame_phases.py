"""Host timeline of whole frames: when each step of ``Floxels.fit`` starts and ends on the
host (perf_counter), and when the GPU reaches the optimiser (CUDA events), without a
profiler's overhead. Prints the median frame's timeline (ms from the start of fit).

    python tools/frame_phases.py [--frames 9]
"""
import argparse
import statistics
import time

import torch

import floxels_ext.estimator.api as api_mod
import floxels_ext.estimator.distance as dist_mod
import floxels_ext.estimator.group as est_mod
import floxels_ext.estimator.scans as scans_mod
import floxels_ext.estimator.schedule as sched_mod
import floxels_ext.estimator.solver_run as solver_mod
from _solver_problems import simulated_scans
from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.ops import solver as opsolver

ap = argparse.ArgumentParser()
ap.add_argument("--frames", type=int, default=9)
ap.add_argument("--device", default="cuda")
ap.add_argument("--iters", type=int, default=500)
args = ap.parse_args()

EVENTS: list = []  # (label, depth, t_start, t_end)
DEPTH = [0]


def wrap(owner, name, label=None):
    fn = getattr(owner, name)
    label = label or name

    def inner(*a, **k):
        t0 = time.perf_counter()
        DEPTH[0] += 1
        try:
            return fn(*a, **k)
        finally:
            DEPTH[0] -= 1
            EVENTS.append((label, DEPTH[0], t0, time.perf_counter()))
    setattr(owner, name, inner)


class _OpsProxy:
    """torch.ops.floxels with every op call timed."""

    def __init__(self, ns):
        self.ns = ns

    def __getattr__(self, name):
        op = getattr(self.ns, name)

        def call(*a, **k):
            t0 = time.perf_counter()
            try:
                return op(*a, **k)
            finally:
                EVENTS.append(("op " + name, DEPTH[0], t0, time.perf_counter()))
        return call


wrap(api_mod, "prepare_scans")
for name in ("point_bounds", "build_dt", "problem_setup", "restore_outputs", "prepare_group", "_targets",
             "solve_group", "pack"):
    wrap(est_mod, name)
wrap(dist_mod, "build_dt", "build_dt (early EDT)")
wrap(scans_mod, "_finite_rows")
wrap(sched_mod, "stage_points")
wrap(sched_mod._STAGER, "take", "_STAGER.take")
wrap(sched_mod._STAGER, "used", "_STAGER.used")
wrap(sched_mod.HostCopy, "arrays", "HostCopy.arrays (read-back wait)")
wrap(Floxels, "fit")
wrap(est_mod.Solving, "finish", "Solving.finish")
wrap(opsolver.PackedProblems, "__init__", "PackedProblems()")
wrap(opsolver.PackedProblems, "summaries")
wrap(opsolver.PackedProblems, "summaries_start")
wrap(opsolver.PackedProblems, "run", "solver_run (enqueue)")
wrap(solver_mod.SolverRun, "finish", "SolverRun.finish (wait)")
est_mod.F = _OpsProxy(torch.ops.floxels)
# GPU side: an event on the current stream when the solver is enqueued and after the frame
GPU: dict = {}
_run = opsolver.PackedProblems.run


def run_with_events(self, n):
    if not CUDA:
        return _run(self, n)
    a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    a.record()
    _run(self, n)
    b.record()
    GPU["solver"] = (a, b)


opsolver.PackedProblems.run = run_with_events

scans = simulated_scans(5)
cfg = FloxelsConfig(patience=10**9, max_iters=args.iters)
fl = Floxels(cfg, args.device)
CUDA = args.device == "cuda"
for _ in range(3):
    fl.fit(scans, 2)
frames = []
for _ in range(args.frames):
    EVENTS.clear()
    if CUDA:
        torch.cuda.synchronize()
        start = torch.cuda.Event(enable_timing=True)
        start.record()
    t0 = time.perf_counter()
    fl.fit(scans, 2)
    if CUDA:
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    gpu = (0.0, 0.0)
    if CUDA:
        a, b = GPU["solver"]
        gpu = (start.elapsed_time(a), start.elapsed_time(b))
    frames.append((wall, t0, list(EVENTS), gpu))
frames.sort(key=lambda f: f[0])
print("frame wall ms:", [round(1e3 * f[0], 2) for f in frames])
wall, t0, events, gpu = frames[len(frames) // 2]
print(f"\nmedian frame {1e3 * wall:.2f} ms; GPU: solver starts {gpu[0]:.2f} ms, ends {gpu[1]:.2f} ms after the frame's "
      f"first event (solver GPU span {gpu[1] - gpu[0]:.2f} ms)")
print(f"{'step':<34} {'start':>8} {'end':>8} {'ms':>7}")
for label, depth, s, e in sorted(events, key=lambda x: (x[2], x[1])):
    print(f"{'  ' * depth + label:<34} {1e3 * (s - t0):8.3f} {1e3 * (e - t0):8.3f} {1e3 * (e - s):7.3f}")
# medians over frames of each top-level label's total duration
tot: dict = {}
for _, f0, evs, _ in frames:
    per: dict = {}
    for label, depth, s, e in evs:
        per[label] = per.get(label, 0.0) + (e - s)
    for k, v in per.items():
        tot.setdefault(k, []).append(v)
print("\nmedian total per step over frames (ms):")
for k, v in sorted(tot.items(), key=lambda x: -statistics.median(x[1])):
    print(f"  {k:<34} {1e3 * statistics.median(v):7.3f}")
