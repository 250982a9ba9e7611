"""Where the time of one whole frame (and of a sequence) goes on the GPU: runs them under
torch.profiler, writes Chrome traces, and prints a condensed timeline (host regions of the
estimator, GPU busy time per stream, idle gaps before the optimiser starts).

    python tools/frame_timeline.py --out DIR [--seq-frames 40] [--batch 16]
"""
import argparse
import gzip
import json
import os
import time

import torch

from _solver_problems import simulated_scans
from _traces import busy_and_gaps, gpu_events
from floxels_ext import Floxels, FloxelsConfig, estimate_sequence

ap = argparse.ArgumentParser()
ap.add_argument("--out", default=os.environ.get("OUT", "/tmp"))
ap.add_argument("--seq-frames", type=int, default=40)
ap.add_argument("--batch", type=int, default=16)
args = ap.parse_args()

scans = simulated_scans(max(args.seq_frames, 5))
cfg = FloxelsConfig(patience=10**9)
frame = scans[:5]
Floxels(cfg.replace(max_iters=60), "cuda").fit(frame, 2)
for _ in range(2):
    Floxels(cfg, "cuda").fit(frame, 2)
torch.cuda.synchronize()


def summarise(trace_path: str, label: str) -> None:
    with gzip.open(trace_path, "rt") as fh:
        events = json.load(fh)["traceEvents"]
    kernels = gpu_events(events)
    if not kernels:
        print(label, "no GPU events")
        return
    t0, t1, busy, gaps = busy_and_gaps(kernels)
    by_stream: dict = {}
    for e in kernels:
        by_stream.setdefault(e.get("tid"), []).append(e)
    print(f"\n== {label}: GPU span {1e-3 * (t1 - t0):.2f} ms")
    for sid, evs in by_stream.items():
        busy = sum(e["dur"] for e in evs)
        print(f"  stream {sid}: {len(evs)} events, busy {1e-3 * busy:.2f} ms")
    # busy: the union of the intervals over all streams
    print(f"  any stream busy {1e-3 * busy:.2f} ms; idle {1e-3 * (t1 - t0 - busy):.2f} ms")
    for at, g in sorted(gaps, key=lambda x: -x[1])[:12]:
        print(f"    gap {g:8.1f} us at {1e-3 * (at - t0):8.2f} ms")
    # first solver kernel, and the GPU time by kernel name before it
    solver = [e for e in kernels if "points_kernel" in e["name"]]
    if solver:
        s0 = min(e["ts"] for e in solver)
        print(f"  first points_kernel at {1e-3 * (s0 - t0):.2f} ms; last GPU event ends {1e-3 * (t1 - t0):.2f} ms")
        names: dict = {}
        for e in kernels:
            if e["ts"] < s0:
                k = e["name"].split("<")[0].replace("floxels::cuda::(anonymous namespace)::", "")[:50]
                names[k] = names.get(k, 0.0) + e["dur"]
        for k, v in sorted(names.items(), key=lambda x: -x[1])[:15]:
            print(f"    before solver: {k:<50} {v:9.1f} us")
    # host: the estimator's python-level ops (cpu_op) longer than 200 us
    cpu = [e for e in events if e.get("cat") == "cpu_op" and e.get("dur", 0) > 200]
    hs = min((e["ts"] for e in events if e.get("cat") == "cpu_op"), default=t0)
    for e in sorted(cpu, key=lambda e: e["ts"])[:25]:
        print(f"    host op {e['name'][:40]:<40} at {1e-3 * (e['ts'] - hs):8.2f} ms for {1e-3 * e['dur']:.2f} ms")


acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
with torch.profiler.profile(activities=acts) as prof:
    t0 = time.perf_counter()
    res = Floxels(cfg, "cuda").fit(frame, 2)
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
path = os.path.join(args.out, "frame_trace.json.gz")
prof.export_chrome_trace(path)
print(f"frame wall {1e3 * wall:.2f} ms under the profiler; timings "
      + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in res.timings.items()))
summarise(path, "frame")

seq = scans[:args.seq_frames]
estimate_sequence(seq[:8], cfg.replace(max_iters=20), device="cuda", batch_size=4)
torch.cuda.synchronize()
t0 = time.perf_counter()
estimate_sequence(seq, cfg, device="cuda", batch_size=args.batch)
torch.cuda.synchronize()
print(f"\nsequence without profiler: {len(seq) / (time.perf_counter() - t0):.1f} frames/s")
with torch.profiler.profile(activities=acts) as prof:
    t0 = time.perf_counter()
    estimate_sequence(seq, cfg, device="cuda", batch_size=args.batch)
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
path = os.path.join(args.out, "sequence_trace.json.gz")
prof.export_chrome_trace(path)
print(f"sequence under the profiler: {len(seq) / wall:.1f} frames/s")
summarise(path, "sequence")
