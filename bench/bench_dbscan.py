"""Benchmark of the exact DBSCAN (torch.ops.floxels.dbscan) against scikit-learn.

Points: simulated LiDAR sweeps of the "crossing" scene with the ground removed (points on
boxes, walls, poles), denser sensors for the larger sizes, randomly subsampled to the
target size and shuffled. Baseline in the same run: sklearn.cluster.DBSCAN(eps,
min_samples).fit(points).labels_ (KD-tree, all cores). The labels are checked to be
identical before timing. CUDA times use torch.cuda.synchronize after warm-up.

    python bench/bench_dbscan.py --device cpu [--quick] [--json PATH] [--threads T]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np
import torch

import floxels_ext  # noqa: E402,F401  (registers torch.ops.floxels.*)
from _timing import timeit  # noqa: E402
from floxels_ext.evaluation.sim import simulate_sequence  # noqa: E402

try:
    from sklearn.cluster import DBSCAN  # noqa: E402
except ImportError:  # GPU machine without scikit-learn: compare with our CPU op instead
    DBSCAN = None

SIZES = (30_000, 100_000, 150_000)
SETTINGS = ((0.5, 4), (0.3, 10))  # (eps, min_samples)


def lidar_points(n, seed=0):
    """>= n non-ground points of a simulated sweep, subsampled to exactly n."""
    for beams, steps in ((64, 2048), (128, 4096), (192, 4096), (256, 8192)):
        frame = simulate_sequence("crossing", num_frames=1, seed=seed, beams=beams, azimuth_steps=steps).frames[0]
        pts = np.asarray(frame.points)[~np.asarray(frame.ground)]
        if pts.shape[0] >= n:
            break
    rng = np.random.default_rng(seed)
    pick = rng.choice(pts.shape[0], size=min(n, pts.shape[0]), replace=False)
    return torch.from_numpy(pts[pick].astype(np.float32))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--quick", action="store_true", help="30k points only, fewer repeats")
    ap.add_argument("--json", default=None, help="output JSON (default bench/results/dbscan_<device>.json)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    a = ap.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
    device = a.device
    if device == "cuda" and not torch.cuda.is_available():
        sys.exit("CUDA requested but not available")
    sizes = SIZES[:1] if a.quick else SIZES
    repeats = 3 if a.quick else (5 if device == "cpu" else 20)
    print(f"dbscan, lidar-like points, device={device}, threads={torch.get_num_threads()}")
    print(f"{'op':<22}{'size':>9}{'ours ms':>11}{'sklearn ms':>12}{'speedup':>9}{'clusters':>10}")
    rows = []
    for n in sizes:
        pts_cpu = lidar_points(n)
        pts = pts_cpu.to(device)
        for eps, ms in SETTINGS:
            if DBSCAN is not None:
                baseline = lambda: DBSCAN(eps=eps, min_samples=ms).fit(pts_cpu.numpy()).labels_  # noqa: E731
            else:
                baseline = lambda: torch.ops.floxels.dbscan(pts_cpu, eps, ms).numpy()  # noqa: E731
            want = baseline()
            got = torch.ops.floxels.dbscan(pts, eps, ms).cpu().numpy()
            if not np.array_equal(got, want):
                sys.exit(f"labels differ from the baseline at n={n}, eps={eps}, min_samples={ms}")
            t_ours = timeit(lambda: torch.ops.floxels.dbscan(pts, eps, ms), device, repeats)
            t_base = timeit(baseline, "cpu",
                            max(1, repeats // 3) if device == "cpu" else 3, warmup=0)
            op = f"dbscan(eps={eps},ms={ms})"
            row = dict(op=op, size=int(pts.shape[0]), eps=eps, min_samples=ms, ours_ms=t_ours, baseline_ms=t_base,
                       speedup=t_base / t_ours, clusters=int(want.max()) + 1, noise=int((want == -1).sum()))
            rows.append(row)
            print(f"{op:<22}{row['size']:>9}{t_ours:>11.2f}{t_base:>12.1f}{row['speedup']:>8.1f}x{row['clusters']:>10}")
    out = Path(a.json) if a.json else Path(__file__).resolve().parent / "results" / f"dbscan_{device}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(device=device, torch=torch.__version__, threads=torch.get_num_threads(), cpu_count=os.cpu_count(),
                machine=platform.processor() or platform.machine(), quick=a.quick, repeats=repeats,
                baseline="sklearn.cluster.DBSCAN (n_jobs=None)" if DBSCAN is not None else "floxels dbscan on CPU",
                gpu=torch.cuda.get_device_name() if device == "cuda" else None)
    out.write_text(json.dumps(dict(meta=meta, rows=rows), indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
