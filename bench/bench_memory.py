"""What one Floxels frame costs on the CPU: peak memory (RSS) and time by number of scans and
points per scan.

    python bench/bench_memory.py [--scans 3 5 9 13] [--points 30000 100000] [--iters 500]

Each (scans, points) cell runs in a fresh process (peak RSS is per process): a simulated
urban sequence (64-beam lidar, ground kept, points within 50 m of the sensor, so a ~100 m
wide scene as in real data), each scan subsampled or repeated with jitter to the given
number of points, the middle scan estimated with the default config. Prints a table and
writes JSON to bench/results/memory_cpu.json. Memory grows with the number of scans mostly
through one distance transform per support scan (0.1 m samples over the scan's extent plus
2 m padding: ~100 m x 100 m x 8 m = 8 M samples = 32 MB each, more for taller scenes).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time


def one(scans: int, points: int, iters: int) -> dict:
    """Run one frame in this process and report its peak RSS."""
    import numpy as np
    import torch

    from floxels_ext import Floxels, FloxelsConfig
    from floxels_ext.evaluation.sim import simulate_sequence

    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    seq = simulate_sequence("urban", num_frames=scans, seed=0)
    rng = np.random.default_rng(0)
    data = []
    for fr in seq.frames:
        keep = np.linalg.norm(fr.points[:, :2] - fr.pose[:2, 3], axis=1) < 50
        p = fr.points[keep]
        idx = rng.choice(len(p), points, replace=len(p) < points)
        q = p[idx] + (rng.normal(0, 0.01, (points, 3)) if len(p) < points else 0)
        data.append(q.astype(np.float32))
    del seq
    ready = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    torch.set_num_threads(os.cpu_count() or 1)
    t0 = time.perf_counter()
    res = Floxels(FloxelsConfig(num_scans=scans, max_iters=iters), "cpu").fit(data, scans // 2)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    ext = np.ptp(np.concatenate(data), axis=0)
    return dict(scans=scans, points=points, iters=res.num_iters, seconds=seconds,
                peak_rss_mb=peak / 1024, data_rss_mb=ready / 1024, start_rss_mb=base / 1024,
                extent_m=[round(float(e), 1) for e in ext], stages={k: round(v, 3) for k, v in res.timings.items()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, nargs="+", default=[3, 5, 9, 13])
    ap.add_argument("--points", type=int, nargs="+", default=[30000, 100000])
    ap.add_argument("--iters", type=int, default=500)
    ap.add_argument("--json", default=os.path.join(os.path.dirname(__file__), "results", "memory_cpu.json"))
    ap.add_argument("--one", nargs=2, type=int, help=argparse.SUPPRESS)  # child process: SCANS POINTS
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(*args.one, args.iters)))
        return
    rows = []
    print(f"{'scans':>5} {'points/scan':>11} {'peak RSS (GB)':>13} {'time (s)':>9} {'iters':>6}  extent (m)")
    for s in args.scans:
        for n in args.points:
            out = subprocess.run([sys.executable, __file__, "--one", str(s), str(n), "--iters", str(args.iters)],
                                 capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{s:>5} {n:>11,} {row['peak_rss_mb'] / 1024:>13.2f} {row['seconds']:>9.1f} {row['iters']:>6}  "
                  f"{' x '.join(str(e) for e in row['extent_m'])}", flush=True)
    os.makedirs(os.path.dirname(args.json) or ".", exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(dict(machine=platform.processor() or platform.machine(), cpus=os.cpu_count(),
                       torch=__import__("torch").__version__, rows=rows), f, indent=2)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
