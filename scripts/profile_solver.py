"""Profile the device optimiser loop on a ~100k-point frame: per-kernel GPU time (torch
profiler) and wall time per iteration with and without CUDA graphs.

    python scripts/profile_solver.py [--beams 128] [--iters 100]
"""
import argparse
import time

import torch

from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.demo import prepare_demo_scans  # noqa: F401  (import check)
from floxels_ext.ops.solver import PackedProblems
from floxels_ext.solver import run_solver

ap = argparse.ArgumentParser()
ap.add_argument("--beams", type=int, default=128)
ap.add_argument("--iters", type=int, default=100)
ap.add_argument("--scene", default="urban")
args = ap.parse_args()

import sys, os
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
from bench_speed import _frames  # noqa: E402

scans, _, _ = _frames(args.scene, 0, 5, args.beams, 2048)
cfg = FloxelsConfig(max_iters=args.iters, patience=10**9)
est = Floxels(cfg, "cuda")
# capture the problem the estimator builds
captured = {}
import floxels_ext.estimator as E
orig = E.PackedProblems
def grab(problems, c):
    p = orig(problems, c)
    captured["problems"] = problems
    return p
E.PackedProblems = grab
est.fit(scans, 2)
E.PackedProblems = orig
probs = captured["problems"]
print("points", probs[0].points.shape[0], "vertices", probs[0].corners.num_params,
      "clusters", int(probs[0].labels.max()) + 1, "dt shapes", [tuple(d.shape) for d in probs[0].dts])

for graph in (False, True):
    for _ in range(2):
        p = PackedProblems(probs, cfg)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        run_solver(p, use_graph=graph)
        torch.cuda.synchronize()
        dt = time.perf_counter() - t0
    print(f"graph={graph}: {1e6 * dt / args.iters:.1f} us/iteration (wall, {args.iters} iterations)")

p = PackedProblems(probs, cfg)
with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
    p.run(20)
    torch.cuda.synchronize()
print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=12))

# Whole frame: where the host time of the non-optimiser stages goes (syncs, copies, launches).
est = Floxels(cfg.replace(max_iters=50), "cuda")
est.fit(scans, 2)
torch.cuda.synchronize()
with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                        torch.profiler.ProfilerActivity.CUDA]) as prof:
    res = est.fit(scans, 2)
    torch.cuda.synchronize()
print("frame stages (ms):", {k: round(1e3 * v, 2) for k, v in res.timings.items()})
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
