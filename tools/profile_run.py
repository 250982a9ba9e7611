"""Where ``floxels run`` spends its host time: runs it in this process on a simulated 128-beam
KITTI-style sequence (as bench/bench_run.py builds it) while a sampler thread records every
thread's Python stack every few milliseconds; prints, per thread, the functions it was in most
often, and the CPU seconds of this process and of its worker processes against the wall time.

    python tools/profile_run.py [--frames 64] [--run-args "--preprocess-device cuda"]
"""

from __future__ import annotations

import argparse
import collections
import os
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))


def sample(stop: threading.Event, counts: dict, period: float) -> None:
    me = threading.get_ident()
    names = {}
    while not stop.is_set():
        for t in threading.enumerate():
            names[t.ident] = t.name
        for ident, frame in sys._current_frames().items():
            if ident == me:
                continue
            name = names.get(ident, str(ident))
            name = name.rsplit("_", 1)[0] if name.startswith(("floxels-", "ThreadPoolExecutor")) else name
            stack = []
            f = frame
            while f is not None and len(stack) < 4:
                co = f.f_code
                stack.append(f"{Path(co.co_filename).name}:{f.f_lineno} {co.co_name}")
                f = f.f_back
            counts[name][" <- ".join(stack[:2])] += 1
        time.sleep(period)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--run-args", default="")
    ap.add_argument("--period", type=float, default=0.002)
    ap.add_argument("--top", type=int, default=8)
    args = ap.parse_args()
    from bench_run import build

    from floxels_ext import cli

    tmp = Path(tempfile.mkdtemp(prefix="profile_run_"))
    kitti, _, npts = build(tmp, args.frames, args.beams, 1800, 0)
    base = [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt"), *args.run_args.split()]
    cli.main(["run", *base, "--out", str(tmp / "warm"), "--frames", "0:6", "-q"])
    counts: dict = collections.defaultdict(collections.Counter)
    stop = threading.Event()
    th = threading.Thread(target=sample, args=(stop, counts, args.period), daemon=True)
    r0, c0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    th.start()
    cli.main(["run", *base, "--out", str(tmp / "out"), "-q"])
    wall = time.perf_counter() - t0
    stop.set()
    th.join()
    r1, c1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = lambda a, b: (b.ru_utime - a.ru_utime) + (b.ru_stime - a.ru_stime)  # noqa: E731
    print(f"{args.frames} frames, {npts} raw points/frame, {args.frames / wall:.1f} frames/s; wall {wall:.2f} s; "
          f"CPU s: this process {cpu(r0, r1):.1f}, worker processes {cpu(c0, c1):.1f} "
          f"(of {os.cpu_count()} cores x wall = {os.cpu_count() * wall:.1f})")
    for name, c in sorted(counts.items(), key=lambda kv: -sum(kv[1].values())):
        tot = sum(c.values())
        print(f"\n[{name}] {tot} samples")
        for k, v in c.most_common(args.top):
            print(f"  {100 * v / tot:5.1f}%  {k}")


if __name__ == "__main__":
    main()
