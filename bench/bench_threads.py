"""CPU threads against the machine's load: one Floxels frame (the demo's: `crossing`, 5 scans,
the paper's protocol) with 1, 2, ... torch threads, each in a fresh process, interleaved, with
``--busy K`` extra CPU-bound processes (spinning Python loops) competing, and the 1-minute load
average recorded at each start. The choice of ``floxels_ext.cpu_threads`` rests on it.

    python bench/bench_threads.py [--threads 1 2] [--busy 0 2] [--repeat 2] [--small]

Prints a table (s/frame per setting) and writes JSON (bench/results/threads.json).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import statistics
import subprocess
import sys
import time

_CHILD = r"""
import sys, time, torch
torch.set_num_threads(int(sys.argv[1]))
from floxels_ext import Floxels, FloxelsConfig
from floxels_ext.evaluation.demo import prepare_demo_scans
from floxels_ext.evaluation.metrics import flow_metrics
scans, target, gt, dyn = prepare_demo_scans("crossing", 0, 5, small=sys.argv[2] == "1")
Floxels(FloxelsConfig(max_iters=2), "cpu").fit([s[:2000] for s in scans], target)  # warm-up
res = Floxels(FloxelsConfig(), "cpu").fit(scans, target)
print(res.timings["total"], flow_metrics(res.flow, gt, dyn)["dynamic_epe"], len(scans[target]))
"""


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        x += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--busy", type=int, nargs="+", default=[0], help="extra CPU-bound processes competing")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--small", action="store_true", help="32-beam lidar (faster)")
    ap.add_argument("--json", default=os.path.join(os.path.dirname(__file__), "results", "threads.json"))
    args = ap.parse_args()
    env = dict(os.environ)
    env.pop("OMP_NUM_THREADS", None)
    env["PYTHONPATH"] = os.pathsep.join(p for p in [os.path.join(os.path.dirname(__file__), "..", "python"),
                                                    env.get("PYTHONPATH", "")] if p)
    rows = []
    for busy in args.busy:
        stop = mp.Event()
        spinners = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(busy)]
        for p in spinners:
            p.start()
        try:
            for rep in range(args.repeat):
                for n in args.threads:
                    load = os.getloadavg()[0]
                    t0 = time.perf_counter()
                    out = subprocess.run([sys.executable, "-c", _CHILD, str(n), "1" if args.small else "0"], env=env,
                                         capture_output=True, text=True, check=True).stdout.split()
                    rows.append(dict(busy=busy, threads=n, rep=rep, load1=load, s_frame=float(out[0]),
                                     dyn_epe=float(out[1]), points=int(out[2]),
                                     process_s=time.perf_counter() - t0))
                    print(f"busy {busy} threads {n} rep {rep}: {float(out[0]):.2f} s/frame (load {load:.1f}, "
                          f"dyn EPE {float(out[1]):.4f})", flush=True)
        finally:
            stop.set()
            for p in spinners:
                p.join()
    print(f"\n{'busy':>5} {'threads':>8} {'s/frame (median)':>17} {'min':>7} {'max':>7} {'load1':>12}")
    for busy in args.busy:
        for n in args.threads:
            r = [x for x in rows if x["busy"] == busy and x["threads"] == n]
            s = [x["s_frame"] for x in r]
            ld = [x["load1"] for x in r]
            print(f"{busy:>5} {n:>8} {statistics.median(s):>17.2f} {min(s):>7.2f} {max(s):>7.2f} "
                  f"{min(ld):>5.1f}-{max(ld):<5.1f}")
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(dict(host=platform.node(), cores=os.cpu_count(), rows=rows), f, indent=2)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
