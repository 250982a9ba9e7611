"""``floxels run --engines N``: N engines on this machine's one device, fed from one queue of
tasks.

Why: one engine leaves its GPU idle 35-60 % of the time (its host steps: reading,
preprocessing, problem set-up, reading results back). Two engine processes on one GPU
(time-sliced CUDA contexts) fill each other's gaps: measured on Ray with two workers a GPU, the
GPU ran 97-100 % busy at 1.41x the frames/s of one (bench/RESULTS.md, "Two workers a GPU").

How: the run's own process is engine 0 and starts at once, exactly as with one engine; engines
1..N-1 are processes from the fork server (``engine_process``) that start in parallel (imports,
CUDA context, a tiny warm-up) and take tasks once ready. The tasks (``tasks.Task``: a
sequence's frames [A, B), cut at ``--task-frames``) are handed out in order from one queue
(:class:`Handout`) to whichever engine asks, so engine 0 never waits for the others, and a
short run is never slower than one engine. Outputs do not depend on which engine ran which
task: ``layout`` lays every window and anchor out the same whatever the cut.

An engine process that dies: its unfinished tasks go back to the front of the queue and
another engine (engine 0 at least, which lives as long as the run) runs them; the frames it
had written stay (the new holder's resume check skips them, nothing is written twice), its
temporaries are removed, and the run says which engine was lost and which tasks were handed
over. Ctrl-C: the engines are stopped (SIGTERM: each writes what it had computed) and
``floxels: interrupted``; running the same command again writes only the missing frames.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import wait as wait_for
from pathlib import Path

__all__ = ["Handout", "Engines", "early_engines", "engine_threads"]

_WAIT = "wait"
STOP_S = 15.0    # how long an interrupted engine may take to write what it computed
DRAIN_S = 2.0    # how long the run waits for the engines to end their streams once all tasks have


class Handout:
    """The run's queue of task ids, handed out in order; each task is leased to one engine
    until it ends. ``load(n)`` fills it once the run is planned (engines start before that).
    ``take(engine, wait)``: the next id; None when every task has ended (or the run stopped);
    without ``wait``, "wait" while the queue is empty but tasks are still leased (one may come
    back from an engine that dies)."""

    def __init__(self) -> None:
        self.n: int | None = None
        self.cv = threading.Condition()
        self.queue: deque = deque()
        self.leases: dict[int, set] = {}
        self.ended: set[int] = set()
        self.stopped = False

    def load(self, n: int) -> None:
        with self.cv:
            self.n = n
            self.queue.extend(range(n))
            self.cv.notify_all()

    def loaded(self) -> bool:
        """Waits until the tasks are loaded (True) or the run stopped (False)."""
        with self.cv:
            while self.n is None and not self.stopped:
                self.cv.wait(0.5)
            return not self.stopped

    def take(self, engine: int, wait: bool):
        with self.cv:
            while True:
                if self.stopped or self.n is not None and len(self.ended) == self.n:
                    return None
                if self.queue:
                    k = self.queue.popleft()
                    self.leases.setdefault(engine, set()).add(k)
                    return k
                if not wait and self.n is not None:
                    return _WAIT
                self.cv.wait(0.5)

    def end(self, engine: int, k: int) -> None:
        with self.cv:
            self.leases.get(engine, set()).discard(k)
            self.ended.add(k)
            self.cv.notify_all()

    def hand_back(self, engine: int) -> list[int]:
        """The unfinished tasks of an engine that died, back at the front of the queue."""
        with self.cv:
            back = sorted(self.leases.pop(engine, set()) - self.ended)
            self.queue.extendleft(reversed(back))
            self.cv.notify_all()
            return back

    def stop(self) -> None:
        with self.cv:
            self.stopped = True
            self.cv.notify_all()

    @property
    def over(self) -> bool:
        with self.cv:
            return self.stopped or self.n is not None and len(self.ended) == self.n


def engine_threads(cores: int, engines: int, gpu: bool) -> dict:
    """CPU threads of each engine: the host's cores shared by the engines, each with the thread
    plan of a Ray worker given that share (``ray_worker.worker_threads``: on a GPU at most 4
    torch threads, not an OpenMP team per core in every engine)."""
    from floxels_ext.lidar.dataset.ray_worker import worker_threads

    return worker_threads(max(1, cores // engines), gpu)


@dataclasses.dataclass
class _Engine:
    index: int
    proc: object = None
    conn: object = None
    pid: int | None = None
    ready: bool = False
    done: bool = False
    stopping: bool = False
    error: str | None = None
    stamps: dict = dataclasses.field(default_factory=dict)  # its start, step by step (time.time(), warm_up's)
    thread: threading.Thread | None = None
    ended: threading.Event = dataclasses.field(default_factory=threading.Event)  # said "done", or gone


class Engines:
    """Engines 1..N-1 and the hand-out (module docstring). Started early (:func:`early_engines`:
    before the run lists its input, so their start overlaps it), on a thread (each start waits
    for the fork server's imports, which ``run._run_input`` set going before the run imported
    torch: seconds on a CUDA image); each is served by a thread of its own that answers its
    questions and passes on what it says. :meth:`run` loads the tasks and runs engine 0 here."""

    def __init__(self, n: int, device: str, threads: dict) -> None:
        self.device, self.threads = device, threads
        self.handout = Handout()
        self.engines = [_Engine(i) for i in range(1, n)]
        self.n = n
        self.lock = threading.Lock()
        self.closing = False
        self.tasks: list = []
        self.common: dict = {}
        self.on_message: Callable = lambda e, msg: None
        self.on_lost: Callable = lambda e, why, back: None
        self.starter = threading.Thread(target=self._start_all, name="floxels-engines", daemon=True)
        self.starter.start()

    def _start_all(self) -> None:
        from floxels_ext.lidar.dataset.engine_process import engine_main
        from floxels_ext.lidar.pipeline.worker_processes import forkserver_context

        ctx = forkserver_context()
        for e in self.engines:
            if self.closing or self.handout.over:
                return  # the run is over (a short run): no engine is started for nothing
            mine, theirs = ctx.Pipe()
            proc = ctx.Process(target=engine_main, args=(theirs, e.index, self.device, self.threads),
                               name=f"floxels-engine-{e.index}", daemon=True)
            try:
                proc.start()
            except OSError as err:
                self.on_lost(e, f"could not start: {err}", [])
                return
            theirs.close()  # its end lives in the child: a dead child reads as the end of the pipe
            with self.lock:
                if self.closing:  # the run ended while it started
                    _signal(proc, signal.SIGKILL)
                    return
                e.proc, e.conn, e.pid = proc, mine, proc.pid
            e.thread = threading.Thread(target=self._serve, args=(e,), name=f"floxels-engine-{e.index}-pipe",
                                        daemon=True)
            e.thread.start()

    def _answer(self, e: _Engine, kind: str):
        if kind == "options":  # the run's options, once it has planned its tasks
            return self.common if self.handout.loaded() else None
        k = self.handout.take(e.index, wait=kind == "idle")
        return (k, dataclasses.replace(self.tasks[k], found=None)) if isinstance(k, int) else k

    def _serve(self, e: _Engine) -> None:
        conn = e.conn
        while True:
            try:
                wait_for([conn, e.proc.sentinel])
                if not conn.poll():
                    break  # the process ended and said all it had to say
                msg = conn.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            if kind in ("options", "need", "idle"):
                try:
                    conn.send(self._answer(e, kind))
                except OSError:
                    break
            elif kind == "ready":
                e.stamps = msg[2]
                e.ready = True
            elif kind == "done":
                e.done = True
                e.ended.set()
            elif kind == "error":
                e.error = msg[1]
            else:
                self.on_message(e, msg)
        e.ended.set()
        e.proc.join(timeout=5.0)
        back = self.handout.hand_back(e.index)
        if not e.done and not (e.stopping and not back):
            code = e.proc.exitcode
            why = e.error or (f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}")
            self.on_lost(e, why, back)

    def close(self, interrupted: bool) -> list[int]:
        """Stops the engines and returns their pids; the run never waits for one still
        starting (it holds no task). Interrupted: the ones running get SIGTERM and write what
        they computed, within ``STOP_S``. Else every task has ended, its outputs written: the
        engines are killed without waiting for them to take their CUDA contexts down."""
        with self.lock:
            self.closing = True
            started = [e for e in self.engines if e.proc is not None]
            for e in started:
                e.stopping = True
        self.handout.stop()  # engines waiting for a task get None
        for e in started:
            _signal(e.proc, signal.SIGTERM if interrupted and e.ready else signal.SIGKILL)
        if interrupted:
            for e in started:
                e.proc.join(timeout=STOP_S if e.ready else 1.0)
                if e.proc.exitcode is None:
                    _signal(e.proc, signal.SIGKILL)
                    e.proc.join(timeout=5.0)
        return [e.pid for e in started]

    def run(self, tasks: list, args, *, report: Callable[[str], None],
            on_frame: Callable[[object, str, bool], None],
            on_ended: Callable[[object, str, list, dict | None], None]) -> dict:
        """Runs ``tasks`` on the engines, engine 0 here; returns {"lost": [lines], "engines":
        how many took a task, "stages": {engine: its stage times (s)}, those engines', "start":
        when they joined (``engine_start.JoinClock.summary``)}. ``on_frame(task, name, ok)``: a frame written (or failed);
        ``on_ended(task, outcome, lines, part)``: a task ended (``worker.run_tasks``'s outcome
        and failure lines; ``part``: its ``summary`` part, None when it could not be opened;
        its ``written`` counts the frames an engine lost on it had written). Both run on
        whichever thread heard of it, under one lock."""
        import argparse

        import torch

        from floxels_ext.lidar.dataset.engine_start import JoinClock
        from floxels_ext.lidar.dataset.tasks import common_options
        from floxels_ext.lidar.dataset.worker import run_tasks

        lock = threading.Lock()
        clock = JoinClock(self.n)  # when each engine joined (the summary's engines_start)
        before: dict[int, int] = {}      # task -> frames written by holders lost before it ended
        written_by: dict[int, int] = {}  # task -> frames written by its current holder
        took: set[int] = set()
        lost: list[str] = []
        stages: dict[int, dict] = {}     # engine -> its streams' stage times (s), summed

        def add_stages(engine: int, st: dict) -> None:
            with lock:
                mine = stages.setdefault(engine, {})
                for key, v in st.items():
                    mine[key] = mine.get(key, 0.0) + v

        def frame(engine: int, k: int, name: str, ok: bool) -> None:
            with lock:
                took.add(engine)
                clock.frame(engine, ok)
                written_by[k] = written_by.get(k, 0) + ok
                on_frame(tasks[k], name, ok)

        def ended(engine: int, k: int, outcome: str, lines: list, part: dict | None) -> None:
            with lock:
                took.add(engine)
                if part is not None and before.get(k):  # what a lost holder wrote, its resume skipped
                    part = dict(part, written=part["written"] + before[k], skipped=part["skipped"] - before[k])
                on_ended(tasks[k], outcome, lines, part)
            self.handout.end(engine, k)

        def message(e: _Engine, msg) -> None:
            if msg[0] == "frame":
                frame(e.index, *msg[1:])
            elif msg[0] == "ended":
                ended(e.index, *msg[1:])
            elif msg[0] == "report":
                report(msg[1])
            elif msg[0] == "stages":
                add_stages(e.index, msg[1])

        def on_lost(e: _Engine, why: str, back: list[int]) -> None:
            with lock:
                for k in back:
                    before[k] = before.get(k, 0) + written_by.pop(k, 0)
                names = ", ".join(f"{tasks[k].seq.path.name} frames {tasks[k].start}:{tasks[k].stop}" for k in back)
                lost.append(f"engine {e.index} (pid {e.pid}) lost: {why}; "
                            + (f"its task(s) {names} handed to the other engines" if back else "it held no task"))
            report(f"floxels: warning: {lost[-1]}")

        self.tasks, self.common, self.on_message, self.on_lost = tasks, common_options(args), message, on_lost
        self.handout.load(len(tasks))
        # engine 0: this process, as the plain run but with its share of the CPU threads
        own = argparse.Namespace(**vars(args))
        own.frames = own.poses = own.calib = None  # each task carries its range and its files
        own.cpu_limit = self.threads["cpus"]
        torch_threads = torch.get_num_threads()
        torch.set_num_threads(self.threads["torch"])
        state = {"over": False}

        def own_tasks(first):
            k = first
            while isinstance(k, int):
                tasks[k].lease = k
                yield tasks[k]
                k = self.handout.take(0, wait=False)
            state["over"] = k is None

        try:
            k = self.handout.take(0, wait=False)
            while k is not None:
                if k != _WAIT:
                    r = run_tasks(own_tasks(k), own, report=report, engine=0,
                              on_frame=lambda job, i: frame(0, job.info["task"].lease, job.seq.frames[i].name,
                                                            i not in job.failed),
                              on_sequence=lambda task, outcome, job, lines: ended(
                                  0, task.lease, outcome, lines, None if job is None else job.info.get("summary")))
                    add_stages(0, r["stages"])
                    if state["over"]:
                        break
                k = self.handout.take(0, wait=True)  # tasks other engines still hold may come back
        finally:
            torch.set_num_threads(torch_threads)
        # every task has ended: the engines that ran some end their streams (their stage times
        # come with that) a few ms later; the run waits for that, at most DRAIN_S
        self.handout.stop()
        deadline = time.monotonic() + DRAIN_S
        for e in self.engines:
            if e.index in took:
                e.ended.wait(max(0.0, deadline - time.monotonic()))
        return {"lost": lost, "engines": len(took), "stages": {e: st for e, st in stages.items() if e in took},
                "start": clock.summary()}


def _signal(proc, sig: int) -> None:
    try:
        if sig and proc.exitcode is None:
            os.kill(proc.pid, sig)
    except (OSError, ValueError, AttributeError):
        pass


def _remove_temps(dirs, pids: list[int]) -> int:
    """The temporary outputs (``.<frame>.npz.<pid>.tmp``) the engines ``pids`` left (killed
    mid-write); other runs' temporaries are left alone."""
    pat = re.compile(r"^\..+\.npz\.(\d+)\.tmp$")
    n = 0
    for d in dirs:
        try:
            names = os.listdir(d)
        except OSError:
            continue
        for name in names:
            m = pat.match(name)
            if m and int(m.group(1)) in pids:
                Path(d, name).unlink(missing_ok=True)
                n += 1
    return n


@contextlib.contextmanager
def early_engines(args, n: int, device: str):
    """Engines 1..n-1 started now (before the run lists and plans its input) for
    :meth:`Engines.run`; stopped on the way out (SIGTERM when the run fails or is interrupted:
    each writes what it computed), their temporaries removed. Yields None for one engine."""
    if n <= 1:
        yield None
        return
    from floxels_ext.lidar.pipeline.run_args import host_cores

    engines = Engines(n, device, engine_threads(host_cores(args), n, device.startswith("cuda")))
    ok = False
    try:
        yield engines
        ok = True
    finally:
        pids = engines.close(interrupted=not ok)
        left = _remove_temps({t.out_dir for t in engines.tasks}, pids)
        if left:
            print(f"removed {left} temporary file(s) of stopped engines", file=sys.stderr)
