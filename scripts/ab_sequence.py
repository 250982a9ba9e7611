"""Sequence throughput with and without preparing the next batch during the optimisation
(FLOXELS_PIPELINE), alternating runs on the same frames: python3 scripts/ab_sequence.py"""
import os
import statistics
import time

import torch

from _solver_problems import simulated_scans
from floxels_ext import FloxelsConfig, estimate_sequence

frames = simulated_scans(48)
cfg = FloxelsConfig(patience=10**9)
estimate_sequence(frames[:8], cfg.replace(max_iters=20), device="cuda", batch_size=4)  # warm-up
fps = {"1": [], "0": []}
for rep in range(3):
    for mode in ("1", "0"):
        os.environ["FLOXELS_PIPELINE"] = mode
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        estimate_sequence(frames, cfg, device="cuda", batch_size=16)
        torch.cuda.synchronize()
        fps[mode].append(len(frames) / (time.perf_counter() - t0))
        print(f"pipeline={mode} run {rep}: {fps[mode][-1]:.1f} frames/s", flush=True)
for mode, v in fps.items():
    print(f"pipeline={mode}: median {statistics.median(v):.1f} frames/s over {v}")
