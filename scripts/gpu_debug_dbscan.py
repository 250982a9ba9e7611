"""Reproduces bench_dbscan's failing CUDA case: repeated calls on 150k lidar-like points."""
import sys

import torch

import floxels_ext  # noqa: F401

sys.path.insert(0, "bench")
from bench_dbscan import lidar_points  # noqa: E402

n = int(sys.argv[1]) if len(sys.argv) > 1 else 150_000
reps = int(sys.argv[2]) if len(sys.argv) > 2 else 5
pts = lidar_points(n).cuda()
for eps, ms in [(0.5, 4), (0.3, 10)]:
    ref = torch.ops.floxels.dbscan(pts.cpu(), eps, ms)
    for r in range(reps):
        lab = torch.ops.floxels.dbscan(pts, eps, ms)
        torch.cuda.synchronize()
        print(n, eps, ms, r, "equal to CPU:", bool((lab.cpu() == ref).all()), flush=True)
