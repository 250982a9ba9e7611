"""When does each engine of ``floxels run --engines N`` start, and when does it end (issue 42: a
run's wall against its engines' own pipeline time)? Runs ``floxels run`` in this process (as
bench/bench_run.py does: a warm engine 0, engines 1.. from the fork server) and records every
hand-out of a task and every task's end, by engine, from the run's ``Handout``; prints, per
run, each engine's first task (its start), busy time, frames, last end, and the run's wall.

    python tools/engine_timeline.py DATASET_INPUT [--repeat 2] [--variant LABEL=ARGS ...] [--json PATH]
    (e.g. bench_run.py --data /tmp/ab_data's /tmp/ab_data/kitti/velodyne)
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import threading
import time
from pathlib import Path

from floxels_ext import cli
from floxels_ext.lidar.dataset import engines as engines_mod


class Recorder:
    def __init__(self) -> None:
        self.events: list[tuple] = []
        self.lock = threading.Lock()
        self.tasks: list = []

    def install(self) -> None:
        rec, H, E = self, engines_mod.Handout, engines_mod.Engines
        take, end, run = H.take, H.end, E.run

        def take_(h, engine, wait):
            k = take(h, engine, wait)
            if isinstance(k, int):
                with rec.lock:
                    rec.events.append((time.perf_counter(), "take", engine, k))
            return k

        def end_(h, engine, k):
            with rec.lock:
                rec.events.append((time.perf_counter(), "end", engine, k))
            return end(h, engine, k)

        def run_(e, tasks, *a, **kw):
            rec.tasks = tasks
            return run(e, tasks, *a, **kw)
        H.take, H.end, E.run = take_, end_, run_


def frames_of(task) -> int:
    return int(task.stop) - int(task.start)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input")
    ap.add_argument("--run-args", default="", help="floxels run arguments for every run (quoted)")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=ARGS")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    variants = [("default", "")] + [tuple(v.split("=", 1)) for v in args.variant]
    rec = Recorder()
    rec.install()
    out = []
    for rep in range(args.repeat):
        for label, extra in variants:
            with tempfile.TemporaryDirectory(prefix="engine_timeline_") as tmp:
                rec.events.clear()
                argv = ["run", args.input, "--out", str(Path(tmp) / "out"), "-q",
                        *shlex.split(args.run_args), *shlex.split(extra)]
                t0 = time.perf_counter()
                rc = cli.main(argv)
                wall = time.perf_counter() - t0
            ev = sorted(rec.events)
            per: dict[int, dict] = {}
            held: dict[tuple, float] = {}
            for t, kind, e, k in ev:
                d = per.setdefault(e, {"first_take_s": t - t0, "busy_s": 0.0, "tasks": 0, "frames": 0, "last_end_s": 0.0})
                if kind == "take":
                    held[(e, k)] = t
                else:
                    d["busy_s"] += t - held.pop((e, k), t)
                    d["tasks"] += 1
                    d["frames"] += frames_of(rec.tasks[k]) if k < len(rec.tasks) else 0
                    d["last_end_s"] = t - t0
            row = {"label": label, "repeat": rep, "rc": rc, "wall_s": wall, "tasks": len(rec.tasks), "engines": per}
            out.append(row)
            print(f"\n{label} (run {rep + 1}): rc {rc}, wall {wall:.2f} s, {len(rec.tasks)} tasks")
            print(f"{'engine':>6} {'first task s':>12} {'busy s':>8} {'tasks':>6} {'frames':>7} {'last end s':>11}")
            for e in sorted(per):
                d = per[e]
                print(f"{e:>6} {d['first_take_s']:>12.2f} {d['busy_s']:>8.2f} {d['tasks']:>6} {d['frames']:>7}"
                      f" {d['last_end_s']:>11.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
