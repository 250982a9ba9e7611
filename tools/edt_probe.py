"""GPU time of the distance transforms of a frame's support scans (the estimator's grids),
per kernel, from the torch profiler; and the whole op with CUDA events.

    python tools/edt_probe.py [--scans 4]
"""
import argparse

import torch

from _solver_problems import simulated_scans  # also puts bench/ on sys.path
from _timing import timeit
from floxels_ext import FloxelsConfig
from floxels_ext.ops.grid import grid_from_bounds

F = torch.ops.floxels
ap = argparse.ArgumentParser()
ap.add_argument("--scans", type=int, default=4)
ap.add_argument("--reps", type=int, default=5)
args = ap.parse_args()
cfg = FloxelsConfig()
pts = [torch.as_tensor(s, device="cuda") for s in simulated_scans(args.scans)]
grids = []
for p in pts:
    lo, hi = p.min(0).values.tolist(), p.max(0).values.tolist()
    grids.append(grid_from_bounds(lo, hi, cfg.dt_cell, cfg.dt_padding, cfg.max_dt_cells))
print("grids:", [g[1] for g in grids])


def one_pass():
    out = []
    for p, (origin, shape) in zip(pts, grids):
        occ = F.points_to_occupancy(p, origin, cfg.dt_cell, shape)
        out.append(F.edt(occ, cfg.dt_cell))
    return out


streams = [torch.cuda.Stream() for _ in pts]


def streamed_pass():
    """Each scan's DT on its own stream (they run concurrently)."""
    main = torch.cuda.current_stream()
    out = []
    for s, p, (origin, shape) in zip(streams, pts, grids):
        s.wait_stream(main)
        with torch.cuda.stream(s):
            occ = F.points_to_occupancy(p, origin, cfg.dt_cell, shape)
            out.append(F.edt(occ, cfg.dt_cell))
    for s in streams:
        main.wait_stream(s)
    return out


def timed(fn, label):
    ms = timeit(fn, "cuda", args.reps)
    print(f"{args.scans} DTs (occupancy + edt), {label}: median {ms:.3f} ms")


timed(one_pass, "one stream")
timed(streamed_pass, "a stream each")
with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
    one_pass()
    torch.cuda.synchronize()
print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=12))
