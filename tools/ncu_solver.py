"""A few eager solver iterations on the estimator's problems (PDL off), for hardware-counter
profiling of the solver kernels, e.g.

    ncu --clock-control none -k regex:'points_kernel|vertex_kernel' \
        --launch-skip 15 --launch-count 3 python3 tools/ncu_solver.py --batch 1

Small batches run the persistent loop kernel by default: profile it with -k regex:loop_kernel,
or set FLOXELS_SOLVER_PERSISTENT=0 for the two-kernel iteration above.
"""
import argparse
import os

import torch

from _solver_problems import problems_of, simulated_scans
from floxels_ext import FloxelsConfig
from floxels_ext.ops.solver import PackedProblems

ap = argparse.ArgumentParser()
ap.add_argument("--batch", type=int, default=1)
ap.add_argument("--iters", type=int, default=10)
args = ap.parse_args()
os.environ.setdefault("FLOXELS_SOLVER_PDL", "0")
cfg = FloxelsConfig(max_iters=args.iters, patience=10**9)
probs = problems_of(simulated_scans(args.batch + 4), cfg, args.batch)
p = PackedProblems(probs, cfg)
p.run(args.iters)
torch.cuda.synchronize()
print("ran", args.iters, "iterations on", p.points.shape[0], "points")
