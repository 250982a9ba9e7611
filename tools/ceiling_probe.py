"""bench_run's in-memory ceiling (``estimate_sequence`` on a sequence's prepared scans) timed with
chosen estimator options, then one call under ``torch.profiler``: the CUDA kernels' and copies'
time and count a frame, the largest kernels and host ops. Compares builds or options on one GPU
host (bench/RESULTS.md, "The regression since 37d68ff": the evidence off and on, 37d68ff beside).

    python tools/ceiling_probe.py --seq DIR [--options '{"evidence": "off"}'] [--tag T] [--repeat 3] [--no-profile]

``--seq``: a bench_run sequence root (``kitti/velodyne``, ``kitti/poses.txt``), built here with
bench_run's defaults (64 frames, 128 beams) when missing. Run it with each checkout's package on
``PYTHONPATH`` and that checkout as the working directory (its bench/bench_run.py is used).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", type=Path, required=True)
    ap.add_argument("--options", default="{}", help="FloxelsConfig fields as JSON (default: bench_run's)")
    ap.add_argument("--tag", default="ceiling")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-profile", action="store_true")
    args = ap.parse_args()
    sys.path.insert(0, "bench")
    import torch
    import bench_run

    if not (args.seq / "kitti" / "poses.txt").exists():
        bench_run.build(args.seq, 64, 128, 1800, 0)
    c = bench_run.Ceiling(args.seq / "kitti", 5, "cuda", json.loads(args.options))
    for _ in range(args.repeat):
        c.time()
    s = c.summary()
    print(f"{args.tag}: ceiling {s['frames_per_s']:.1f} frames/s, {1e3 / s['frames_per_s']:.2f} ms/frame; "
          f"repeats {[round(x, 1) for x in s['repeats_frames_per_s']]}", flush=True)
    if args.no_profile:
        return
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t0 = time.perf_counter()
        c.estimate(c.scans, c.cfg, device="cuda")
        torch.cuda.synchronize()
        wall = time.perf_counter() - t0
    n = len(c.scans)
    events = prof.key_averages()
    kernels = [e for e in events if getattr(e, "device_type", None) == torch.autograd.DeviceType.CUDA]
    total = sum(e.self_device_time_total for e in kernels)
    print(f"{args.tag}: profiled wall {1e3 * wall / n:.2f} ms/frame; CUDA kernels+copies {total / 1e3 / n:.2f} "
          f"ms/frame, {sum(e.count for e in kernels) / n:.0f} per frame", flush=True)
    for e in sorted(kernels, key=lambda e: -e.self_device_time_total)[:14]:
        print(f"   {e.self_device_time_total / 1e3 / n:7.3f} ms/frame {e.count / n:6.1f}/frame  {e.key[:110]}")
    host = [e for e in events if getattr(e, "device_type", None) == torch.autograd.DeviceType.CPU]
    print(f"{args.tag}: host ops by self CPU time (ms/frame, calls/frame)")
    for e in sorted(host, key=lambda e: -e.self_cpu_time_total)[:14]:
        print(f"   {e.self_cpu_time_total / 1e3 / n:7.3f} {e.count / n:6.1f}  {e.key[:100]}")


if __name__ == "__main__":
    main()
