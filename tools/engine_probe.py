"""The `floxels run` engine without an estimator: frames/s and CPU ms a frame of reading,
preprocessing, the chunk transforms, delivery and writing, with an instant method that answers
zero flow (no GPU, no optimiser). Compares commits on the CPU: run it with each checkout's
package on ``sys.path``.

    python tools/engine_probe.py --repo . --frames 120 [--repeat 3]         # builds a 128-beam sequence
    python tools/engine_probe.py --repo ../other-checkout --seq /tmp/seq120  # the same frames
    python tools/engine_probe.py --seq /tmp/seq120 --parts --repeat 3       # CPU ms a frame per part
    python tools/engine_probe.py --repo /tmp/ab/main --seq /tmp/seq120 --parts  # a tools/ab_bench.py build

``--parts``: CPU ms a frame of each part of the engine (the calling thread's CPU time around
the functions that do the work, summed over their threads), and of each kind of thread (the
kernel's per-thread CPU time, ``/proc/self/task/*/schedstat``, sampled; threads without a
Python name are the ops' or the interpreter's own). Nested parts are listed indented under
the part that calls them.
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
    ap.add_argument("--repo", default=".", help="checkout whose python/ package runs (or a directory holding floxels_ext)")
    ap.add_argument("--seq", type=Path, help="a bench_run sequence root (kitti/velodyne, kitti/poses.txt); made if absent")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--parts", action="store_true", help="CPU ms a frame per part and per thread kind")
    args = ap.parse_args()
    repo = Path(args.repo).resolve()
    # a checkout (its python/), or a directory the package is installed in (tools/ab_bench.py's /tmp/ab/NAME)
    sys.path.insert(0, str(repo / "python" if (repo / "python").is_dir() else repo))
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
    parts = _Parts() if args.parts else None
    for _ in range(args.repeat):
        if parts is not None:
            parts.start()
        out = Path(tempfile.mkdtemp(prefix="engine_probe_out_"))
        t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        rc = cli.main(["run", str(seq / "kitti" / "velodyne"), "--poses", str(seq / "kitti" / "poses.txt"),
                       "--out", str(out), "--method", "instant", "-q", "--device", "cpu"])
        wall, c1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
        n = sum(1 for f in os.listdir(out) if f.endswith(".npz"))
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
        print(f"{args.repo}: rc {rc}, {n} frames, {n / wall:.1f} frames/s, {1e3 * wall / n:.1f} ms a frame wall, "
              f"{1e3 * cpu / n:.1f} ms of CPU a frame", flush=True)
        if parts is not None:
            parts.report(n, cpu)
        shutil.rmtree(out, ignore_errors=True)


# (module, attribute, part name): the functions the engine's work goes through; where a caller
# imports a function by name at module level, that module's name is the one patched
_PARTS = [
    ("floxels_ext.lidar.pipeline.frame_loader", "load_frame", "read+preprocess (load_frame)"),
    ("floxels_ext.lidar.io.readers", "read_bin", "  read_bin"),
    ("floxels_ext.lidar.io.readers", "_check_bin_plausible", "    .bin plausibility check"),
    ("floxels_ext.lidar.preprocess.masks", "preprocess_classes", "  crop + ground (preprocess_classes)"),
    ("floxels_ext.ops.lidar", "lidar_select", "  lidar_select (kept rows, non-finite)"),
    ("floxels_ext.lidar.io.outputs", "points_crc32", "  points_crc32"),
    ("floxels_ext.lidar.pipeline.frame_loader", "far_outliers", "  far_outliers"),
    ("floxels_ext.lidar.pipeline.frame_checks", "float32_far_message", "  float32_far_message"),
    ("floxels_ext.lidar.dataset.layout", "StreamScans._make", "transform (StreamScans._make)"),
    ("floxels_ext.lidar.pipeline.frame_writer", "FrameOutput.__call__", "write (FrameOutput)"),
    ("floxels_ext.ops.lidar", "frame_flow", "  frame_flow"),
    ("floxels_ext.lidar.pipeline.frame_writer", "write_output", "  write_output (.npz)"),
]


class _Parts:
    """CPU time per part (wrapped functions, thread CPU time) and per thread kind (sampled)."""

    def __init__(self) -> None:
        import functools
        import importlib
        import threading

        self.lock = threading.Lock()
        self.cpu: dict = {}
        for mod, attr, name in _PARTS:
            owner = importlib.import_module(mod)
            cls, _, fn = attr.rpartition(".")
            if cls:
                owner = getattr(owner, cls)
            orig = getattr(owner, fn)

            def wrap(*a, _orig=orig, _name=name, **kw):
                t0 = time.thread_time_ns()
                try:
                    return _orig(*a, **kw)
                finally:
                    dt = time.thread_time_ns() - t0
                    with self.lock:
                        self.cpu[_name] = self.cpu.get(_name, 0) + dt

            setattr(owner, fn, functools.wraps(orig)(wrap))

    def start(self) -> None:
        import threading

        self.cpu = {}
        self.threads: dict = {}  # tid -> [name, first ns, last ns]
        self.stop = threading.Event()
        self.sampler = threading.Thread(target=self._sample, name="probe-sampler", daemon=True)
        self.base = self._tasks()
        self.sampler.start()

    @staticmethod
    def _tasks() -> dict:
        out = {}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/schedstat") as fh:
                    out[int(tid)] = int(fh.read().split()[0])
            except OSError:
                pass
        return out

    def _sample(self) -> None:
        import threading

        while not self.stop.wait(0.02):
            names = {t.native_id: t.name for t in threading.enumerate()}
            for tid, ns in self._tasks().items():
                rec = self.threads.setdefault(tid, [None, self.base.get(tid, 0), ns])
                rec[2] = ns
                if rec[0] is None and tid in names:
                    rec[0] = names[tid]

    def report(self, n: int, cpu: float) -> None:
        import re

        self.stop.set()
        self.sampler.join()
        for tid, ns in self._tasks().items():  # the threads still alive: their last value
            if tid in self.threads:
                self.threads[tid][2] = ns
        kinds: dict = {}
        for name, a, b in self.threads.values():
            kind = "(no Python name: ops, interpreter)" if name is None else re.sub(r"[_-]?\d+$", "", name)
            kinds[kind] = kinds.get(kind, 0) + (b - a)
        print(f"  per part (CPU ms a frame; {1e3 * cpu / n:.2f} in all):")
        for _, _, name in _PARTS:
            print(f"    {name:<44} {self.cpu.get(name, 0) / 1e6 / n:6.2f}")
        print("  per thread kind (CPU ms a frame):")
        for kind, ns in sorted(kinds.items(), key=lambda kv: -kv[1]):
            print(f"    {kind:<44} {ns / 1e6 / n:6.2f}")


if __name__ == "__main__":
    main()
