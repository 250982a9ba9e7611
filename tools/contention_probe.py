"""Why ``floxels run``'s optimiser computes slower than ``estimate_sequence`` alone (issue 16):
times ``estimate_sequence`` on prepared in-memory scans (the ceiling of bench/bench_run.py)
alone, then while background threads load the host the way the run's readers and writers do,
one kind of load at a time:

* ``op``: the lidar ops in a loop (C++, GIL released for the whole call): hardware contention
  only (cores, memory bandwidth, caches);
* ``numpy``: a .bin read + numpy's isfinite / boolean indexing (short GIL-holding steps between
  GIL-free loops, like the run's Python around the ops);
* ``python``: a pure-Python loop (holds the GIL but for the interpreter's switch interval);
* ``frame``: the run's whole per-frame reader work (``load_frame``).

Each background thread sleeps ``--duty`` of its time so that the load is near the run's (a
reader is busy ~10 ms a frame at ~90 frames/s over 4 threads: ~25 % each).

    python tools/contention_probe.py [--frames 64] [--threads 4] [--duty 0.75]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_run import build  # noqa: E402

from floxels_ext.estimator.api import estimate_sequence  # noqa: E402
from floxels_ext.estimator.config import FloxelsConfig  # noqa: E402
from floxels_ext.lidar.io import read_points, read_poses  # noqa: E402
from floxels_ext.lidar.preprocess import Preprocess, host_rows, preprocess_mask, transform_points  # noqa: E402
from floxels_ext.ops.lidar import lidar_select  # noqa: E402


def loads(files):
    pts = read_points(files[0]).points
    rows = host_rows(pts)
    mask = torch.from_numpy(preprocess_mask(pts))

    def op():
        preprocess_mask(pts)
        lidar_select(rows, mask)

    def numpy_work():
        p = np.ascontiguousarray(read_points(files[0]).points)
        f = np.isfinite(p).all(1)
        p[f & mask.numpy()]

    def python_work():
        s = 0
        for i in range(200_000):
            s += i * i

    def frame():
        from floxels_ext.lidar.pipeline.frame_loader import load_frame

        class Seq:  # the one-file sequence load_frame reads
            frames = [type("F", (), {"path": files[2]})]

            @staticmethod
            def load(i):
                return read_points(files[2])

        load_frame(0, Seq, Preprocess(), "identity", None, False)

    return {"op": op, "numpy": numpy_work, "python": python_work, "frame": frame}


def timed(scans, cfg, device) -> float:
    torch.cuda.synchronize() if device.startswith("cuda") else None
    t0 = time.perf_counter()
    estimate_sequence(scans, cfg, device=device)
    torch.cuda.synchronize() if device.startswith("cuda") else None
    return 1e3 * (time.perf_counter() - t0) / len(scans)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--threads", type=int, default=4)
    ap.add_argument("--duty", type=float, default=0.25, help="fraction of the time each thread works")
    ap.add_argument("--switch-interval", type=float, default=None)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    a = ap.parse_args()
    if a.switch_interval:
        sys.setswitchinterval(a.switch_interval)
    with tempfile.TemporaryDirectory() as tmp:
        kitti, _, _ = build(Path(tmp), a.frames, a.beams, 1800, 0)
        files = sorted((kitti / "velodyne").glob("*.bin"))
        poses = read_poses(kitti / "poses.txt")
        scans = []
        for f, T in zip(files, poses):
            p = read_points(f).points
            T = T.copy()
            T[:3, 3] -= poses[0][:3, 3]
            scans.append(transform_points(np.ascontiguousarray(p)[preprocess_mask(p)], T))
        cfg = FloxelsConfig(num_scans=5)
        estimate_sequence(scans[:8], cfg, device=a.device, frames=[3])  # warm-up
        work = loads(files)
        print(f"estimate_sequence, {a.frames} frames on {a.device}, {a.threads} background threads "
              f"working {100 * a.duty:.0f} % of the time (ms/frame, best of 3)")
        base = min(timed(scans, cfg, a.device) for _ in range(3))
        print(f"  {'alone':8s} {base:7.2f}")
        for name, fn in work.items():
            t0 = time.perf_counter()
            fn()
            cost = time.perf_counter() - t0
            stop = threading.Event()
            done = [0]

            def loop():
                while not stop.is_set():
                    t = time.perf_counter()
                    fn()
                    done[0] += 1
                    stop.wait((time.perf_counter() - t) * (1 / a.duty - 1))

            th = [threading.Thread(target=loop, daemon=True) for _ in range(a.threads)]
            for t in th:
                t.start()
            ms = min(timed(scans, cfg, a.device) for _ in range(3))
            stop.set()
            for t in th:
                t.join()
            print(f"  {name:8s} {ms:7.2f}  {ms / base:5.2f}x alone  (one call {1e3 * cost:.1f} ms, "
                  f"{done[0]} calls)")


if __name__ == "__main__":
    main()
