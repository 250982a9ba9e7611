"""Profile the device optimiser loop on ~100k-point frames: wall time per iteration (with
and without programmatic dependent launch), the persistent
loop's per-phase times printed by the kernel (FLOXELS_SOLVER_TRACE=1; with --skip, parts left
out, FLOXELS_SOLVER_SKIP) and the GPU time of each kernel measured with PDL off (with PDL on,
a kernel's span includes its wait for the previous one, so the profiler's figures overlap).

    python tools/profile_solver.py [--beams 128] [--iters 100] [--batch 1 16] [--skip MASK...]

The phase trace and --skip need a profiling build (release builds compile that code out, and
this script refuses to run on one; --no-trace measures the rest on any build):

    FLOXELS_PROFILING=ON FLOXELS_CUDA=ON pip install --no-build-isolation .   # installed package
    PYTHON=python3 tools/dev_build.sh -DFLOXELS_PROFILING=ON                    # in-place build
    FLOXELS_PROFILING=ON tools/gpu_run.sh build                                 # device machine

(torch.ops.floxels.has_profiling() tells which kind is loaded; rebuild without the option, or
with -DFLOXELS_PROFILING=OFF for the in-place build, before measuring anything else.)
"""
import argparse
import os
import sys
import time

import torch

from _solver_problems import problems_of, simulated_scans
from floxels_ext import FloxelsConfig
from floxels_ext.ops.solver import PackedProblems
from floxels_ext.estimator.solver_run import run_solver

ap = argparse.ArgumentParser()
ap.add_argument("--beams", type=int, default=128)
ap.add_argument("--iters", type=int, default=100)
ap.add_argument("--scene", default="urban")
ap.add_argument("--batch", type=int, nargs="+", default=[1, 16])
ap.add_argument("--skip", type=int, nargs="*", default=[],
                help="also trace the persistent loop with these FLOXELS_SOLVER_SKIP masks (parts left out: "
                     "1 DT, 2 segment sums, 4 cluster u sums, 8 loss reduction, 16 flow gather, "
                     "32 vertex gradient gather, 64 next means)")
ap.add_argument("--no-trace", action="store_true",
                help="leave out the phase trace (and --skip): runs on builds without FLOXELS_PROFILING")
args = ap.parse_args()


def has_profiling() -> bool:
    try:
        return bool(torch.ops.floxels.has_profiling())
    except (AttributeError, RuntimeError):  # a library built before the op existed
        return False


if not args.no_trace and not has_profiling():
    sys.exit("profile_solver: this floxels_ext build has no profiling code (built without FLOXELS_PROFILING), "
             "so FLOXELS_SOLVER_TRACE / FLOXELS_SOLVER_SKIP would do nothing. Rebuild with "
             "FLOXELS_PROFILING=ON (pip install) or `tools/dev_build.sh -DFLOXELS_PROFILING=ON`, "
             "or pass --no-trace to measure only the wall and per-kernel times.")

scans = simulated_scans(max(args.batch) + 4, args.beams, args.scene)
cfg = FloxelsConfig(max_iters=args.iters, patience=10**9)


def wall_per_iter(probs) -> float:
    best = float("inf")
    for _ in range(3):
        p = PackedProblems(probs, cfg)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        run_solver(p)
        torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / args.iters


for batch in args.batch:
    probs = problems_of(scans, cfg, batch)
    npts = sum(p.points.shape[0] for p in probs)
    print(f"\n=== batch {batch}: {npts} points, {sum(p.corners.num_params for p in probs)} vertices, "
          f"{sum(int(p.labels.max()) + 1 for p in probs)} clusters")
    for pers in ("auto", "1", "0"):
        if pers == "auto":
            os.environ.pop("FLOXELS_SOLVER_PERSISTENT", None)
        else:
            os.environ["FLOXELS_SOLVER_PERSISTENT"] = pers
        blocks = PackedProblems(probs, cfg).loop_blocks()
        for pdl in (("1", "0") if pers == "0" else ("0",)):
            os.environ["FLOXELS_SOLVER_PDL"] = pdl
            us = wall_per_iter(probs)
            print(f"persistent={pers} (loop blocks {blocks}) pdl={pdl}: {us:8.1f} us/iteration "
                  f"({us / batch:6.1f} per problem)")
    if not args.no_trace:
        # phase times inside the persistent loop (printed by the kernel; profiling builds)
        os.environ["FLOXELS_SOLVER_PERSISTENT"] = "1"
        os.environ["FLOXELS_SOLVER_TRACE"] = "1"
        run_solver(PackedProblems(probs, cfg))
        torch.cuda.synchronize()
        # the same with parts left out (measurement only; FLOXELS_SOLVER_SKIP bits in
        # csrc/common/env_switches.h)
        for mask in args.skip:
            os.environ["FLOXELS_SOLVER_SKIP"] = str(mask)
            print(f"skip mask {mask}:", flush=True)
            run_solver(PackedProblems(probs, cfg))
            torch.cuda.synchronize()
        os.environ.pop("FLOXELS_SOLVER_SKIP", None)
        del os.environ["FLOXELS_SOLVER_TRACE"]
    os.environ["FLOXELS_SOLVER_PERSISTENT"] = "0"
    os.environ["FLOXELS_SOLVER_PDL"] = "0"
    p = PackedProblems(probs, cfg)
    p.run(5)
    torch.cuda.synchronize()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        p.run(20)
        torch.cuda.synchronize()
    for ev in prof.key_averages():
        if getattr(ev, "device_time_total", 0) > 0 and ev.count >= 1:
            name = (ev.key.replace("floxels::cuda::(anonymous namespace)::", "")
                    .replace("floxels::cuda::solver_detail::", ""))[:40]
            print(f"  {name:<42} {ev.device_time_total / ev.count:8.1f} us x {ev.count}")
    del os.environ["FLOXELS_SOLVER_PDL"]
    del os.environ["FLOXELS_SOLVER_PERSISTENT"]
