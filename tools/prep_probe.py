"""Serial cost (host + GPU, synchronised around each step) of the per-target preparation
before the optimiser, on one ~100k-point frame: upload and checks, DBSCAN, the fused
problem_setup (sorting, compact corners, segment tables) against its former pieces, and a
whole frame for reference.

    python tools/prep_probe.py [--reps 10]
"""
import argparse
import time

import torch

from _solver_problems import simulated_scans
from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.ops import compact_corners, problem_setup, stage_points
from floxels_ext.ops.grid import grid_from_bounds
from floxels_ext.ops.solver import PackedProblems, problem_segments
from floxels_ext.reference.ops import cell_key
from floxels_ext.estimator.scans import prepare_scans

F = torch.ops.floxels
ap = argparse.ArgumentParser()
ap.add_argument("--reps", type=int, default=10)
args = ap.parse_args()
cfg = FloxelsConfig(patience=10**9)
scans = simulated_scans(5)


def timed(label, fn):
    fn()
    torch.cuda.synchronize()
    ts = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        out = fn()
        torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    print(f"{label:34s} {1e3 * sorted(ts)[len(ts) // 2]:7.3f} ms")
    return out


prep = timed("prepare_scans (upload, checks)", lambda: prepare_scans(scans, 2, "cuda"))
buf = torch.empty(scans[2].size, dtype=torch.float32, pin_memory=True)
src = torch.from_numpy(scans[2])
timed(f"  stage_points, one scan ({src.dtype})", lambda: stage_points([src], [buf]))
timed("  numpy copy into page-locked, one scan", lambda: buf.numpy().reshape(-1, 3).__setitem__(slice(None), scans[2]))
P = prep.points[2]
lab = timed("dbscan", lambda: F.dbscan(P, cfg.dbscan_eps, cfg.dbscan_min_samples))
ncl = int(lab.max()) + 1
lo, hi = P.min(0).values.tolist(), P.max(0).values.tolist()
g_origin, g_shape = grid_from_bounds(lo, hi, cfg.voxel_size, cfg.voxel_size, max_cells=1 << 40)
cells = g_shape[0] * g_shape[1] * g_shape[2]
timed("problem_setup (all of the below)", lambda: problem_setup(P, lab, g_origin, cfg.voxel_size, g_shape, 32))
order = timed("  sort (cluster, voxel)", lambda: torch.argsort(
    (lab.to(torch.int64) + 1) * cells + cell_key(P, g_origin, cfg.voxel_size, g_shape)))
Ps = P[order].contiguous()
lab_s = lab[order].contiguous()
corners = timed("  compact_corners", lambda: compact_corners(Ps, g_origin, cfg.voxel_size, g_shape))
timed("  problem_segments", lambda: problem_segments(corners.corner_idx, lab_s, corners.num_params))
fl = Floxels(cfg, "cuda")
for _ in range(2):
    fl.fit(scans, 2)
timed("whole frame (fit)", lambda: fl.fit(scans, 2))
res = fl.fit(scans, 2)
print("frame timings (ms):", {k: round(1e3 * v, 3) for k, v in res.timings.items()})
