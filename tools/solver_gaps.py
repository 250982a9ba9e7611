"""Where does ``floxels run`` lose GPU time against the ceiling (issue 16)? Times the solver's
work on the GPU itself (CUDA events around every chunk of iterations the estimator enqueues)
during the same KITTI-style run as ``bench/bench_run.py`` and during the ceiling
(``estimate_sequence`` on the prepared scans in memory), and splits each run's wall time into:

* head: from the start of the run to the first solver iteration on the GPU (setup, the first
  frames read, the first batch prepared);
* busy: the GPU running solver chunks;
* gap in: the solver's stream idle between chunks of one batch (the host late topping up its
  queue; the device may run the next batch's preparation meanwhile, on its own streams);
* gap between: the solver's stream idle between one batch's last chunk and the next batch's first (results read
  back and delivered, the next batch's preparation not finished); "side late": how long after
  a batch's last iteration the next batch's preparation (its kernels on the side stream) was
  done, the part of "gap between" the device spent on it;
* tail: from the last iteration to the end of the run (the last results, the last writes);

plus the host time the optimiser's thread spent preparing batches (``prepare_group``) and
finishing them (``Solving.finish``). Measurement-only patches (nothing shipped changes); modes
run interleaved ``--repeat`` times, the table shows medians (ms a frame).

A mode is ``ceiling`` or ``run`` with options joined by "+": ``preread`` (every frame read
before the method starts, see tools/run_isolation.py), ``depthN`` (N solver chunks kept queued
instead of two), ``nice`` (reader and writer threads at nice 10), ``nodrain`` (no extra
writer threads at the run's end).

    python tools/solver_gaps.py [--frames 64] [--repeat 5] [--modes ceiling run run+nodrain run+depth4 ...]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_run import build, prepared_scans, run_cli  # noqa: E402
from run_isolation import configure  # noqa: E402

import floxels_ext.estimator.api as api  # noqa: E402
import floxels_ext.estimator.group as group  # noqa: E402
import floxels_ext.estimator.solver_run as solver_run  # noqa: E402
import floxels_ext.lidar.pipeline.frame_loader as frame_loader  # noqa: E402
import floxels_ext.lidar.pipeline.frame_writer as frame_writer  # noqa: E402
from floxels_ext.lidar.pipeline.frame_writer import WriterPool  # noqa: E402

CHUNKS: list = []  # (run number, start event, end event)
READY: list = []   # (run number of the next SolverRun, event after a batch's preparation on its stream)
HOST = {"prepare": 0.0, "finish": 0.0}
STATE = {"depth": 2, "nice": False, "runs": 0}


def _event() -> torch.cuda.Event:
    ev = torch.cuda.Event(enable_timing=True)
    ev.record()
    return ev


def install() -> None:
    orig_enqueue, orig_init = solver_run.SolverRun._enqueue, solver_run.SolverRun.__init__

    def init(self, packed, chunk=None, depth=2):
        orig_init(self, packed, chunk, STATE["depth"])
        STATE["runs"] += 1
        self._gap_id = STATE["runs"]

    def enqueue(self):
        with torch.cuda.stream(self.stream):
            start = _event()
            orig_enqueue(self)
            CHUNKS.append((self._gap_id, start, _event()))

    solver_run.SolverRun.__init__, solver_run.SolverRun._enqueue = init, enqueue

    def timed(fn, key):
        def wrapper(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                HOST[key] += time.perf_counter() - t0
        return wrapper

    api.prepare_group = timed(api.prepare_group, "prepare")
    orig_pack = api.pack

    def pack(*a, **kw):  # the last step of a pipelined preparation, on its side stream
        out = orig_pack(*a, **kw)
        READY.append((STATE["runs"] + 1, _event()))  # the SolverRun this batch will be
        return out

    api.pack = pack
    group.Solving.finish = timed(group.Solving.finish, "finish")

    orig_load, orig_loop = frame_loader.load_frame, WriterPool._loop

    def lower_priority():
        if STATE["nice"] and not getattr(_TLS, "niced", False):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)
            _TLS.niced = True

    def load(*a, **kw):
        lower_priority()
        return orig_load(*a, **kw)

    def loop(self):
        lower_priority()
        return orig_loop(self)

    frame_loader.load_frame, WriterPool._loop = load, loop


_TLS = threading.local()
SHIPPED_DRAIN = frame_writer.DRAIN_WRITERS


def set_mode(mode: str) -> None:
    opts = set(mode.split("+")[1:])
    configure("preread" if "preread" in opts else "default")
    depth = [int(o[5:]) for o in opts if o.startswith("depth")]
    STATE.update(depth=depth[0] if depth else 2, nice="nice" in opts)
    frame_writer.DRAIN_WRITERS = 0 if "nodrain" in opts else SHIPPED_DRAIN


def measure(fn, frames: int) -> dict:
    """Runs ``fn`` and splits its wall time by the solver chunks' GPU timeline (ms a frame)."""
    torch.cuda.synchronize()
    CHUNKS.clear()
    READY.clear()
    STATE["runs"] = 0
    HOST.update(prepare=0.0, finish=0.0)
    t0 = time.perf_counter()
    first = _event()  # the GPU is idle: completes at once, i.e. at the host's t0
    fn()
    last = _event()
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    rel = [(rid, first.elapsed_time(s), first.elapsed_time(e)) for rid, s, e in CHUNKS]
    busy = sum(e - s for _, s, e in rel)
    gap_in = gap_between = 0.0
    for (r0, _, e0), (r1, s1, _) in zip(rel, rel[1:]):
        gap = max(0.0, s1 - e0)
        if r0 == r1:
            gap_in += gap
        else:
            gap_between += gap
    first_start = {}
    last_end = {}
    for rid, s, e in rel:
        first_start.setdefault(rid, s)
        last_end[rid] = e
    side_late = 0.0
    for rid, ev in READY:  # prepared for run ``rid``: late if done after run rid-1's last iteration
        if rid - 1 in last_end:
            side_late += max(0.0, first.elapsed_time(ev) - last_end[rid - 1])
    head = rel[0][1] if rel else 0.0
    tail = first.elapsed_time(last) - rel[-1][2] if rel else 0.0
    per = 1.0 / frames
    return {"wall": 1e3 * wall * per, "head": head * per, "busy": busy * per, "gap_in": gap_in * per,
            "gap_between": gap_between * per, "side_late": side_late * per, "tail": tail * per, "prepare": 1e3 * HOST["prepare"] * per,
            "finish": 1e3 * HOST["finish"] * per, "fps": frames / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--modes", nargs="+", default=["ceiling", "run", "run+nodrain", "run+preread"])
    a = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("solver_gaps.py times the solver on the GPU: it needs CUDA")
    install()
    from floxels_ext.estimator.api import estimate_sequence
    from floxels_ext.estimator.config import FloxelsConfig

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        kitti, _, npts = build(tmp, a.frames, a.beams, 1800, 0)
        scans, _, _ = prepared_scans(kitti)
        src = [str(kitti / "velodyne"), "--poses", str(kitti / "poses.txt")]
        common = ["--device", "cuda", "-q"]
        run_cli(["run", *src, "--out", str(tmp / "warm"), "--frames", "0:6", *common])
        estimate_sequence(scans[:8], FloxelsConfig(), device="cuda", frames=[3])
        got: dict[str, list] = {m: [] for m in a.modes}
        for rep in range(a.repeat):
            for m in a.modes:
                set_mode(m)
                if m.startswith("ceiling"):
                    fn = lambda: estimate_sequence(scans, FloxelsConfig(), device="cuda")  # noqa: E731
                else:
                    fn = lambda m=m, rep=rep: run_cli(["run", *src, "--out", str(tmp / f"{m}_{rep}"), *common])  # noqa: E731
                got[m].append(measure(fn, a.frames))
        set_mode("run")
    keys = ["fps", "wall", "head", "busy", "gap_in", "gap_between", "side_late", "tail", "prepare", "finish"]
    print(f"{a.frames} frames of {npts} raw points; medians of {a.repeat} runs; ms a frame (fps: frames/s)")
    print(" | ".join([f"{'mode':>{max(11, *(len(m) for m in a.modes))}}"] + [f"{k:>11}" for k in keys]))
    w = max(11, *(len(m) for m in a.modes))
    for m in a.modes:
        vals = [statistics.median(r[k] for r in got[m]) for k in keys]
        print(" | ".join([f"{m:>{w}}"] + [f"{v:11.2f}" for v in vals]))
    for m in a.modes:
        print(f"{m}: frames/s of the runs: " + ", ".join(f"{r['fps']:.1f}" for r in got[m]))
    print("head/busy/gap in/gap between/tail: the run's wall time on the GPU's timeline; prepare/finish: "
          "host time of the optimiser's thread preparing batches and reading them back")


if __name__ == "__main__":
    main()
