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
        self.engines = None  # the run's Engines (their start stamps) and when it was made (time.time())
        self.made = 0.0
        self.first_frame: dict[int, float] = {}  # engine -> its first frame written (perf_counter)

    def install(self) -> None:
        rec, H, E = self, engines_mod.Handout, engines_mod.Engines
        take, end, run, init = H.take, H.end, E.run, E.__init__

        def init_(e, *a, **kw):
            rec.engines, rec.made = e, time.time()
            return init(e, *a, **kw)

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

        def run_(e, tasks, *a, on_frame, **kw):
            rec.tasks = tasks

            def frame_(task, name, ok):  # the engine that holds the task wrote it
                k = next((i for i, t in enumerate(rec.tasks) if t is task), None)
                holder = next((en for _, kind, en, kk in reversed(rec.events) if kind == "take" and kk == k), None)
                if holder is not None:
                    rec.first_frame.setdefault(holder, time.perf_counter())
                return on_frame(task, name, ok)
            return run(e, tasks, *a, on_frame=frame_, **kw)
        H.take, H.end, E.run, E.__init__ = take_, end_, run_, init_


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
                rec.first_frame.clear()
                rec.engines = None
                argv = ["run", args.input, "--out", str(Path(tmp) / "out"), "-q",
                        *shlex.split(args.run_args), *shlex.split(extra)]
                t0, w0 = time.perf_counter(), time.time()
                rc = cli.main(argv)
                wall = time.perf_counter() - t0
            ev = sorted(rec.events)
            per: dict[int, dict] = {}
            held: dict[tuple, float] = {}
            spans: dict[int, list] = {}  # engine -> [take, end] of its tasks (a stream holds several at once)
            for t, kind, e, k in ev:
                d = per.setdefault(e, {"first_take_s": t - t0, "busy_s": 0.0, "tasks": 0, "frames": 0, "last_end_s": 0.0})
                if kind == "take":
                    held[(e, k)] = t
                else:
                    spans.setdefault(e, []).append((held.pop((e, k), t), t))
                    d["tasks"] += 1
                    d["frames"] += frames_of(rec.tasks[k]) if k < len(rec.tasks) else 0
                    d["last_end_s"] = t - t0
            for e, sp in spans.items():  # busy: the union of its tasks' spans, not their sum
                end = -1.0
                for a, b in sorted(sp):
                    per[e]["busy_s"] += max(0.0, b - max(a, end))
                    end = max(end, b)
            for e, t in rec.first_frame.items():
                per.setdefault(e, {})["first_frame_s"] = t - t0
            # engines 1..: their start, step by step, from the Engines' creation (s after the run's start)
            for en in (rec.engines.engines if rec.engines is not None else []):
                d = per.setdefault(en.index, {})
                d["made_s"] = rec.made - w0
                for key, v in en.stamps.items():
                    if isinstance(v, float) and v > 1e9:
                        d[key + "_s"] = v - w0
            row = {"label": label, "repeat": rep, "rc": rc, "wall_s": wall, "tasks": len(rec.tasks), "engines": per}
            out.append(row)
            print(f"\n{label} (run {rep + 1}): rc {rc}, wall {wall:.2f} s, {len(rec.tasks)} tasks")
            cols = ["process", "warm_imports", "cuda_context", "warm_done", "first_take", "first_frame"]
            print(f"{'engine':>6} " + " ".join(f"{c + ' s':>13}" for c in cols)
                  + f" {'busy s':>8} {'tasks':>6} {'frames':>7} {'last end s':>11}")
            for e in sorted(per):
                d = per[e]
                print(f"{e:>6} " + " ".join(f"{d.get(c + '_s', float('nan')):>13.2f}" for c in cols)
                      + f" {d.get('busy_s', 0):>8.2f} {d.get('tasks', 0):>6} {d.get('frames', 0):>7}"
                      f" {d.get('last_end_s', float('nan')):>11.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
