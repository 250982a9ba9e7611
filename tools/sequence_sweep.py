"""Sequence throughput of estimate_sequence on the simulated ~100k-point sequence under
several schedules (batch size, pipelining, smaller first batches), each the median of a few
passes over the same frames:  python3 tools/sequence_sweep.py [--frames 40] [--passes 3]"""
import argparse
import os
import statistics
import time

import torch

from _solver_problems import simulated_scans
from floxels_ext import FloxelsConfig, estimate_sequence

ap = argparse.ArgumentParser()
ap.add_argument("--frames", type=int, default=40)
ap.add_argument("--passes", type=int, default=3)
args = ap.parse_args()
frames = simulated_scans(args.frames)
cfg = FloxelsConfig(patience=10**9)
estimate_sequence(frames[:8], cfg.replace(max_iters=20), device="cuda", batch_size=4)  # warm-up
configs = [("batch 16", 16, {}), ("batch 16, no ramp", 16, {"FLOXELS_RAMP": "0"}),
           ("batch 16, not pipelined", 16, {"FLOXELS_PIPELINE": "0"}), ("batch 8", 8, {}), ("batch 12", 12, {})]
for name, batch, env in configs:
    os.environ.update(env)
    fps = []
    for _ in range(args.passes):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        estimate_sequence(frames, cfg, device="cuda", batch_size=batch)
        torch.cuda.synchronize()
        fps.append(len(frames) / (time.perf_counter() - t0))
    for k in env:
        del os.environ[k]
    print(f"{name:<26} median {statistics.median(fps):6.1f} frames/s  ({', '.join(f'{v:.1f}' for v in fps)})",
          flush=True)
