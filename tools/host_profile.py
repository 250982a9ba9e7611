"""Where the host time of whole frames goes (cProfile over several Floxels.fit calls on a
~100k-point frame; a synchronisation shows up in the function that waits). cProfile adds a
little time per Python call, so compare the figures with each other, not with bench_speed.

    python tools/host_profile.py [--frames 5] [--top 35]
"""
import argparse
import cProfile
import pstats

import torch

from _solver_problems import simulated_scans
from floxels_ext import Floxels, FloxelsConfig

ap = argparse.ArgumentParser()
ap.add_argument("--frames", type=int, default=5)
ap.add_argument("--top", type=int, default=35)
args = ap.parse_args()
scans = simulated_scans(5)
fl = Floxels(FloxelsConfig(patience=10**9), "cuda")
for _ in range(2):
    fl.fit(scans, 2)
torch.cuda.synchronize()
prof = cProfile.Profile()
prof.enable()
for _ in range(args.frames):
    fl.fit(scans, 2)
prof.disable()
st = pstats.Stats(prof)
st.sort_stats("cumulative").print_stats(args.top)
st.sort_stats("tottime").print_stats(args.top)
