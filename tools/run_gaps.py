"""Why does the GPU idle during ``floxels run``? Runs it in this process on a simulated 128-beam
KITTI-style sequence (as bench/bench_run.py builds it) under the torch profiler (with Python
stacks), then attributes every GPU idle gap to the innermost Python frames of the thread that
launches the kernels (the optimiser thread) at the gap's middle, and prints the GPU's busy time
and its largest kernels. The profiler slows the host, so the gaps are larger than in a plain run;
their ranking is what it is for (issue 33: the page-locked staging's reallocations and the
per-scan sight launches were found this way). It runs one engine (``--engines 1``, unless
``--run-args`` names another count): the profiler sees only this process.

    python tools/run_gaps.py [--frames 32] [--run-args "--preset accurate --scans 11"] [--trace T.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))

from _traces import busy_and_gaps, gpu_events  # noqa: E402  (tools/, this script's folder)


def attribute(events: list, gaps: list, min_gap: float, depth: int = 3) -> collections.Counter:
    """Idle microseconds per innermost ``depth`` Python frames of the launching thread; ``gaps``:
    [(start, length)] (``_traces.busy_and_gaps``)."""
    launches = collections.Counter(e["tid"] for e in events if e.get("cat") == "cuda_runtime")
    main = launches.most_common(1)[0][0]
    frames = sorted((e for e in events if e.get("cat") == "python_function" and e["tid"] == main),
                    key=lambda e: (e["ts"], -e["dur"]))
    out: collections.Counter = collections.Counter()
    # one sweep: the thread's Python frames nest, so the frames open at a time form a stack
    # (a scan of every frame for every gap took minutes on `accurate`'s traces)
    wanted = sorted((start + length / 2, length) for start, length in gaps if length >= min_gap)
    stack: list = []
    i = 0
    for mid, length in wanted:
        while i < len(frames) and frames[i]["ts"] <= mid:
            e = frames[i]
            while stack and stack[-1]["ts"] + stack[-1]["dur"] < e["ts"]:
                stack.pop()
            stack.append(e)
            i += 1
        while stack and stack[-1]["ts"] + stack[-1]["dur"] < mid:
            stack.pop()
        names = [e["name"] for e in stack if e["ts"] + e["dur"] >= mid]
        out[" < ".join(s.split("(")[0].split("/")[-1][:60] for s in names[:-depth - 1:-1])] += length
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=32, help="frames profiled (after 8 warm-up frames)")
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--run-args", default="--preset accurate --scans 11")
    ap.add_argument("--min-gap-us", type=float, default=50.0)
    ap.add_argument("--top", type=int, default=20)
    ap.add_argument("--top-kernels", type=int, default=10, help="largest kernels printed (by GPU time)")
    ap.add_argument("--trace", help="keep the Chrome trace here (default: deleted)")
    args = ap.parse_args()
    import torch
    from torch.profiler import ProfilerActivity, profile

    from bench_run import build
    from floxels_ext import cli

    if not torch.cuda.is_available():
        sys.exit("run_gaps.py needs a CUDA device")
    tmp = Path(tempfile.mkdtemp(prefix="run_gaps_"))
    kitti, _, _ = build(tmp, args.frames + 8, args.beams, 1800, 0)
    # one engine: the profiler sees this process's kernels only (another engine's would fill the
    # gaps unseen); with --engines N the GPU's busy share is host_sampler.py's (nvidia-smi)
    engines = [] if "--engines" in args.run_args.split() else ["--engines", "1"]
    base = [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt"), *args.run_args.split(), *engines, "-q"]
    cli.main(["run", *base, "--out", str(tmp / "warm"), "--frames", "0:8"])
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], with_stack=True) as prof:
        cli.main(["run", *base, "--out", str(tmp / "out"), "--frames", f"8:{args.frames + 8}"])
    trace = args.trace or str(tmp / "trace.json")
    prof.export_chrome_trace(trace)
    events = [e for e in json.load(open(trace))["traceEvents"] if e.get("ph") == "X"]
    gpu = gpu_events(events)
    if not gpu:
        sys.exit("run_gaps.py: the trace has no GPU events")
    t0, t1, busy, gaps = busy_and_gaps(gpu)
    print(f"{args.frames} frames ({args.run_args}): GPU span {(t1 - t0) / 1e3:.1f} ms, busy {busy / 1e3:.1f} ms")
    work: collections.Counter = collections.Counter()
    count: collections.Counter = collections.Counter()
    for e in gpu:
        work[e["name"][:80]] += e["dur"]
        count[e["name"][:80]] += 1
    print(f"largest GPU work ({sum(count.values()) / args.frames:.0f} kernels and copies a frame, "
          f"{sum(work.values()) / 1e3 / args.frames:.2f} ms of their time a frame):")
    for name, d in work.most_common(args.top_kernels):
        print(f"  {d / 1e3:7.1f} ms  {count[name] / args.frames:6.1f}/frame  {name}")
    idle = attribute(events, gaps, args.min_gap_us)
    print(f"idle gaps >= {args.min_gap_us:g} us: {sum(idle.values()) / 1e3:.1f} ms, by the optimiser thread's "
          "innermost Python frames:")
    for key, v in idle.most_common(args.top):
        print(f"  {v / 1e3:7.1f} ms  {key}")
    if not args.trace:
        os.remove(trace)


if __name__ == "__main__":
    main()
