"""The `floxels run` engine without an estimator: frames/s and CPU ms a frame of reading,
preprocessing, the chunk transforms, delivery and writing, with an instant method that answers
zero flow (no GPU, no optimiser). Compares commits on the CPU: run it with each checkout's
package on ``sys.path``.

    python tools/engine_probe.py --repo . --frames 120 [--repeat 3]         # builds a 128-beam sequence
    python tools/engine_probe.py --repo ../other-checkout --seq /tmp/seq120  # the same frames
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", default=".", help="checkout whose python/ package runs")
    ap.add_argument("--seq", type=Path, help="a bench_run sequence root (kitti/velodyne, kitti/poses.txt); made if absent")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    sys.path.insert(0, str(Path(args.repo).resolve() / "python"))
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
    import numpy as np

    from floxels_ext import cli, methods

    seq = args.seq or Path(tempfile.mkdtemp(prefix="engine_probe_")) / "seq"
    if not (seq / "kitti" / "poses.txt").exists():
        from bench_run import build

        build(seq, args.frames, 128, 1800, 0)

    def instant(scans, frames, device, options, callback, times=None):
        for f in frames:
            callback(f, np.zeros((len(scans[f]), 3), np.float32))

    methods._REGISTRY["instant"] = methods.Method("instant", "zero flow at once (tools/engine_probe.py)", instant)
    for _ in range(args.repeat):
        out = Path(tempfile.mkdtemp(prefix="engine_probe_out_"))
        t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        rc = cli.main(["run", str(seq / "kitti" / "velodyne"), "--poses", str(seq / "kitti" / "poses.txt"),
                       "--out", str(out), "--method", "instant", "-q", "--device", "cpu"])
        wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
        n = sum(1 for f in os.listdir(out) if f.endswith(".npz"))
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
        print(f"{args.repo}: rc {rc}, {n} frames, {n / wall:.1f} frames/s, {1e3 * wall / n:.1f} ms a frame wall, "
              f"{1e3 * cpu / n:.1f} ms of CPU a frame", flush=True)
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
