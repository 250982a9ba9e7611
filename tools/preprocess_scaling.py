"""How preprocessing (read + crop + ground removal, numpy) scales with worker processes on this
host: frames/s for 1, 2, 4, ... workers on one simulated 128-beam frame written as a KITTI .bin.
Answers "is floxels run's host side bound by the cores, by BLAS threads or by something else?"

    python tools/preprocess_scaling.py [--workers 1 2 4 8 16] [--frames 64]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def _job(args):
    path, blas1 = args
    from floxels_ext.lidar.io import read_points
    from floxels_ext.lidar.pipeline.frame_loader import single_threaded_blas
    from floxels_ext.lidar.preprocess import Preprocess, preprocess_mask

    t0 = time.perf_counter()
    pts = read_points(path).points
    t1 = time.perf_counter()
    if blas1:
        with single_threaded_blas():
            preprocess_mask(pts, Preprocess())
    else:
        preprocess_mask(pts, Preprocess())
    return t1 - t0, time.perf_counter() - t1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    ap.add_argument("--frames", type=int, default=64)
    args = ap.parse_args()
    from floxels_ext.lidar.preprocess import transform_points
    from floxels_ext.evaluation.sim import simulate_sequence

    fr = simulate_sequence("urban", 1, 0, beams=128, azimuth_steps=1800).frames[0]
    p = transform_points(fr.points, np.linalg.inv(fr.pose)).astype(np.float32)
    tmp = Path(tempfile.mkdtemp())
    path = tmp / "000000.bin"
    np.c_[p, np.zeros(len(p), np.float32)].astype(np.float32).tofile(path)
    try:
        import threadpoolctl

        info = [(d.get("internal_api"), d.get("num_threads")) for d in threadpoolctl.threadpool_info()]
    except ImportError:
        info = "threadpoolctl missing"
    print(f"{len(p)} points/frame; os.cpu_count {os.cpu_count()}, sched_getaffinity {len(os.sched_getaffinity(0))}; "
          f"thread pools {info}")
    print(f"{'workers':>8}{'blas1':>7}{'frames/s':>10}{'read ms':>9}{'pre ms':>8}{'scaling':>9}")
    base = {}
    for blas1 in (True, False):
        for w in args.workers:
            with mp.get_context("fork").Pool(w) as pool:
                pool.map(_job, [(path, blas1)] * w)  # warm
                t0 = time.perf_counter()
                res = pool.map(_job, [(path, blas1)] * args.frames, chunksize=1)
                wall = time.perf_counter() - t0
            fps = args.frames / wall
            base.setdefault(blas1, fps / w)
            print(f"{w:>8}{str(blas1):>7}{fps:>10.1f}{1e3 * np.mean([r[0] for r in res]):>9.1f}"
                  f"{1e3 * np.mean([r[1] for r in res]):>8.1f}{fps / (w * base[blas1]):>9.2f}")


if __name__ == "__main__":
    main()
