"""Benchmark: exact EDT of lidar-like occupancy grids, ours vs scipy (and cupyx on CUDA).

    python bench/bench_edt.py --device cpu [--quick] [--json PATH]
    python bench/bench_edt.py --device cuda
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np
import torch
from scipy import ndimage

import floxels_ext.ops as F  # noqa: E402

SIZES = {"small": (20, 120, 120), "medium": (40, 500, 500), "large": (60, 1000, 1000)}
TARGET_OCCUPIED = {"small": 3_000, "medium": 30_000, "large": 150_000}


def lidar_like(shape, n_occupied, seed=0):
    """Ground plane near the bottom plus box-shaped objects (walls, cars, poles), like a
    voxelised lidar sweep: most of the volume is empty, occupancy sits on surfaces."""
    rng = np.random.default_rng(seed)
    Z, Y, X = shape
    occ = np.zeros(shape, dtype=bool)
    n_ground = int(n_occupied * 0.6)
    # ground: sparse rings-like density falloff from the sensor at the centre
    r = np.abs(rng.normal(0, 0.35, n_ground)) * min(X, Y)
    th = rng.uniform(0, 2 * np.pi, n_ground)
    gx = np.clip(X / 2 + r * np.cos(th), 0, X - 1).astype(int)
    gy = np.clip(Y / 2 + r * np.sin(th), 0, Y - 1).astype(int)
    gz = np.clip(1 + rng.integers(0, 2, n_ground), 0, Z - 1)
    occ[gz, gy, gx] = True
    while occ.sum() < n_occupied:
        h = rng.integers(2, max(3, Z // 2))
        w, d = rng.integers(2, max(3, X // 25)), rng.integers(2, max(3, Y // 25))
        x0, y0 = rng.integers(0, X - w), rng.integers(0, Y - d)
        face = rng.integers(0, 2)  # one visible face, sparsely sampled
        k = int(w * h * 0.5) + 1
        zz = rng.integers(1, min(Z, 1 + h), k)
        if face:
            xx = rng.integers(x0, x0 + w, k)
            yy = np.full(k, y0)
        else:
            xx = np.full(k, x0)
            yy = rng.integers(y0, y0 + d, k)
        occ[zz, yy, xx] = True
    return torch.from_numpy(occ)


def time_cpu(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts) * 1e3


def time_cuda(fn, repeats):
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    ts = []
    for _ in range(repeats):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        fn()
        b.record()
        torch.cuda.synchronize()
        ts.append(a.elapsed_time(b))
    return statistics.median(ts)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--quick", action="store_true", help="small and medium sizes only, fewer repeats")
    ap.add_argument("--json", default=None)
    ap.add_argument("--spacing", type=float, default=0.1)
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("--device cuda: no CUDA device")
    path = args.json or os.path.join(os.path.dirname(__file__), "results", f"edt_{args.device}.json")
    names = ["small", "medium"] if args.quick else ["small", "medium", "large"]
    repeats = 3 if args.quick else 7
    try:
        import cupy
        import cupyx.scipy.ndimage as cndi
    except Exception:  # noqa: BLE001 - any import failure just skips the baseline
        cupy = cndi = None
    if args.device == "cuda" and cndi is None:
        print("cupy not importable: skipping the cupyx baseline")

    rows = []
    for name in names:
        shape = SIZES[name]
        occ = lidar_like(shape, TARGET_OCCUPIED[name])
        n_occ = int(occ.sum())
        inv = ~occ.numpy()
        t = time.perf_counter()
        ref = ndimage.distance_transform_edt(inv, sampling=args.spacing).astype(np.float32)
        scipy_ms = (time.perf_counter() - t) * 1e3  # one run: scipy is seconds at the large size
        ref = torch.from_numpy(ref)
        s = args.spacing
        if args.device == "cpu":
            occ_d = occ
            ours_ms = time_cpu(lambda: F.edt(occ_d, s), repeats)
        else:
            occ_d = occ.cuda()
            ours_ms = time_cuda(lambda: F.edt(occ_d, s), repeats)
        ours = F.edt(occ_d, s).cpu()
        ulp = int((ours.view(torch.int32).long() - ref.view(torch.int32).long()).abs().max())
        row = {"op": "edt", "size": "x".join(map(str, shape)), "occupied": n_occ, "device": args.device,
               "threads": torch.get_num_threads(), "ours_ms": ours_ms, "scipy_ms": scipy_ms,
               "speedup_vs_scipy": scipy_ms / ours_ms, "max_ulp_vs_scipy": ulp}
        if args.device == "cuda" and cndi is not None:
            inv_c = cupy.asarray(inv)
            row["cupyx_ms"] = time_cuda(lambda: cndi.distance_transform_edt(inv_c, sampling=s), repeats)
            row["speedup_vs_cupyx"] = row["cupyx_ms"] / ours_ms
            del inv_c
        rows.append(row)
        print(f"done {name}", flush=True)

    hdr = f"{'op':<5}{'size':>14}{'occupied':>10}{'ours ms':>10}{'scipy ms':>11}{'speedup':>9}"
    if any("cupyx_ms" in r for r in rows):
        hdr += f"{'cupyx ms':>10}{'vs cupyx':>9}"
    print(hdr + f"{'max ulp':>8}")
    for r in rows:
        line = (f"{r['op']:<5}{r['size']:>14}{r['occupied']:>10}{r['ours_ms']:>10.2f}{r['scipy_ms']:>11.1f}"
                f"{r['speedup_vs_scipy']:>8.1f}x")
        if "cupyx_ms" in r:
            line += f"{r['cupyx_ms']:>10.2f}{r['speedup_vs_cupyx']:>8.1f}x"
        print(line + f"{r['max_ulp_vs_scipy']:>8}")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(rows, fh, indent=2)
    print(json.dumps(rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
