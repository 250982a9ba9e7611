"""A few solver iterations on two small simulated frames, to run under compute-sanitizer:

    compute-sanitizer --tool memcheck python3 tools/sanitize_solver.py
    compute-sanitizer --tool racecheck --kernel-name kns=points_kernel python3 tools/sanitize_solver.py

These small problems run the persistent loop kernel by default; FLOXELS_SOLVER_PERSISTENT=0
selects the two-kernel iteration, and FLOXELS_SOLVER_PERSISTENT=1 FLOXELS_SOLVER_MAX_GRID=7
makes every loop block walk several point and vertex blocks (racecheck: kns=loop_kernel).
"""
import torch

from _solver_problems import problems_of, simulated_scans
from floxels_ext import FloxelsConfig
from floxels_ext.ops.solver import PackedProblems

cfg = FloxelsConfig(max_iters=4, patience=10**9)
probs = problems_of(simulated_scans(6, beams=32), cfg, 2)
for cluster in (True, False):
    p = PackedProblems(probs, cfg.replace(cluster_loss=cluster))
    p.run(3)
    torch.cuda.synchronize()
    print("cluster" if cluster else "no cluster", "losses", [p.losses(b) for b in range(p.num_problems)])
