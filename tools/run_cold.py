"""``floxels run`` in fresh processes (no warm-up in the same process, as a user runs it) on one
simulated 128-beam KITTI-style sequence, once per set of extra arguments; prints frames/s, the
stage times of each run's ``run_summary.json`` and the CPU seconds of the run and its children.
Answers whether a cold process behaves like bench/bench_run.py's warmed-up in-process runs.

    python tools/run_cold.py "" "--worker-kind process" ...
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))


def main() -> None:
    from bench_run import build

    tmp = Path(tempfile.mkdtemp(prefix="run_cold_"))
    kitti, _, npts = build(tmp, 64, 128, 1800, 0)
    print(f"64 frames, {npts} raw points a frame")
    for k, extra in enumerate(sys.argv[1:] or [""]):
        out = tmp / f"out{k}"
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        rc = subprocess.run([sys.executable, "-m", "floxels_ext", "run", str(kitti / "velodyne"), "--poses",
                             str(kitti / "poses.txt"), "--out", str(out), "-q", *extra.split()]).returncode
        wall = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        s = json.loads((out / "run_summary.json").read_text())
        st = {k: round(1e3 * v / 64, 1) for k, v in s["stages_s"].items() if k in
              ("read", "preprocess", "transform", "compute", "write", "wait_input")}
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
        print(f"[{extra or 'defaults'}] rc {rc}: process wall {wall:.2f} s (with start-up), pipeline "
              f"{64 / s['stages_s']['wall']:.1f} frames/s; ms/frame {st}; CPU {cpu:.1f} s "
              f"({1e3 * cpu / 64:.0f} ms a frame)", flush=True)


if __name__ == "__main__":
    main()
