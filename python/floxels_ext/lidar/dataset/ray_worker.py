"""The Ray actor of ``floxels run DATASET --ray`` (:class:`FloxelsWorker`, several per GPU by default) and its
side of the driver's task hand-out (:class:`Channel`).

A worker keeps its process, CUDA context, loaded extension and pinned buffers across tasks and,
in the warm pool (``ray_pool``), across jobs. Its start is split so that the slow parts overlap
the driver's own work: ``__init__`` (run as soon as the driver asks for the actor, before it lists
the dataset) sets the CPU threads and starts :meth:`FloxelsWorker._warm_up` on a thread of its
own (the pipeline's imports, the CUDA context, one tiny estimate that loads the kernels);
:meth:`FloxelsWorker.run` starts the pipeline (``worker.run_tasks``) once the driver has planned
the job and the warm-up is done (the estimator's host state is not shared between threads). Every step is stamped (``time.time()``) so the driver can print where a worker's
start went (``-v``, ``ray_job_summary.json``).

Task hand-out (no dispatcher process): the pipeline's task iterator asks for a task
(:meth:`Channel.tasks` emits "need" and waits); the driver always holds one long poll
(:meth:`FloxelsWorker.poll`) per worker, which returns at once with the question, the tasks that
ended and the frames written since the last poll, or after ``timeout`` with nothing new; the
driver answers with :meth:`FloxelsWorker.offer` (a task, or None: the job is over). A worker
whose driver stops polling for ``OWNER_TIMEOUT`` seconds (the driver died; only a pooled,
detached worker outlives it) ends its run: the tasks it holds are finished, none is taken.
"""

from __future__ import annotations

import os
import queue
import socket
import sys
import threading
import time

__all__ = ["FloxelsWorker", "Channel", "worker_threads", "warm_up", "import_pipeline", "PIPELINE_MODULES",
           "process_start_time", "task_args", "OWNER_TIMEOUT"]

_IMPORTED = time.time()  # Ray imports this module to load the actor class (torch comes in __init__)

OWNER_TIMEOUT = 60.0  # s without a poll from the job's driver: it is gone
HANDOVER_S = 4.0  # how long a claim waits for the release of a worker whose starting job dropped it


def worker_threads(cpus: float, gpu: bool) -> dict:
    """CPU threads of one worker given the ``cpus`` Ray reserved for it (``--cpus-per-task``).

    The rule (issue 44): a GPU worker's speed is set by its main thread (the optimiser's Python
    that feeds the GPU, ~0.85 of a core on an H200) and by reader threads that keep frames
    ready (the compiled preprocessing op, a few ms a scan without the GIL); measured, a worker
    at ~130 frames/s used ~3.2 cores in all. torch's intra-op pool serves only the small CPU
    tensor ops of the GPU path: with one OpenMP team per calling thread, 16-64 threads per
    worker only add barrier waits and, with 4-8 workers a host, runnable threads beyond the
    cores (a descheduled team member stalls the main thread). So a GPU worker gets
    ``torch = min(4, cpus)`` intra-op threads, ``readers = clamp(cpus - 2, 1, 6)`` (one core
    for the main thread, one for the transform and writer threads; 6 was the best on a 16-core
    host, bench/RESULTS.md) and 2 writers. A CPU worker computes in torch's ops: ``torch =
    cpus``, ``readers = min(6, cpus)``. With the default ``--cpus-per-task`` (a node's CPUs
    shared by its GPU workers) 4 workers on 64 cores use ~4 busy cores each, leaving the rest
    idle rather than contended."""
    c = max(1, int(cpus))
    if gpu:
        return {"cpus": c, "torch": min(4, c), "readers": max(1, min(6, c - 2)), "writers": 2}
    return {"cpus": c, "torch": c, "readers": min(6, c), "writers": 2}


def process_start_time() -> float | None:
    """When this process started (``time.time()`` scale; Linux /proc, else None)."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return time.time() - (uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


# the modules a worker's pipeline runs on: imported by its warm-up, or before it by Ray (ray_preload)
PIPELINE_MODULES = ("floxels_ext.lidar.dataset.worker", "floxels_ext.lidar.pipeline.run_args", "floxels_ext.methods")


def import_pipeline() -> None:
    """Imports :data:`PIPELINE_MODULES`."""
    import importlib

    for name in PIPELINE_MODULES:
        importlib.import_module(name)


def warm_up(device: str, stamps: dict) -> None:
    """The pipeline's imports, the CUDA context and one tiny estimate (the kernels' lazy
    loading, the allocator's first blocks), each step stamped in ``stamps`` (``time.time()``);
    a failure is stamped as ``warm_error`` (it only costs the first task its start). Ray
    workers and the local engine processes (``engine_process``) start with it."""
    try:
        import_pipeline()
        stamps["warm_imports"] = time.time()
        if device.startswith("cuda"):
            import numpy as np
            import torch

            from floxels_ext import FloxelsConfig, estimate_flow

            torch.zeros(1, device=device)
            torch.cuda.synchronize()
            stamps["cuda_context"] = time.time()
            # more than Ray gave it: CUDA was initialised before Ray set CUDA_VISIBLE_DEVICES (the driver warns)
            stamps["cuda_devices"] = torch.cuda.device_count()
            rng = np.random.default_rng(0)
            scans = [(rng.random((400, 3)) * [8, 8, 1] + [0.2 * i, 0, 0]).astype(np.float32) for i in range(3)]
            estimate_flow(scans, config=FloxelsConfig(max_iters=3), device=device)
            torch.cuda.synchronize()
        stamps["warm_done"] = time.time()
    except Exception as e:  # noqa: BLE001 - a failed warm-up only costs the first task its start
        stamps["warm_error"] = f"{type(e).__name__}: {e}"[:300]


def _empty_cache() -> None:
    import torch

    torch.cuda.empty_cache()


class Channel:
    """One job's hand-out between a worker's pipeline and the driver (module docstring)."""

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.events: list[tuple] = []
        self.frames: dict[int, int] = {}   # task id -> frames written since the last poll
        self.answers: queue.Queue = queue.Queue()
        self.seen = time.monotonic()        # the driver's last poll
        self.closed = False
        self.over = False                   # the driver said the job is over

    def emit(self, *event) -> None:
        with self.cv:
            self.events.append(event)
            self.cv.notify_all()

    def count(self, k: int) -> None:
        with self.cv:  # reported with the next poll (no wake-up per frame)
            self.frames[k] = self.frames.get(k, 0) + 1

    def poll(self, timeout: float) -> tuple[list, dict]:
        with self.cv:
            self.seen = time.monotonic()
            self.cv.wait_for(lambda: self.events or self.closed, timeout)
            events, self.events = self.events, []
            frames, self.frames = self.frames, {}
            if self.closed and not events:
                events = [("closed",)]
            self.seen = time.monotonic()
        return events, frames

    def close(self) -> None:
        with self.cv:
            self.closed = True
            self.cv.notify_all()

    def ask(self, what: str):
        """Emits ``what`` ("need": the stream wants its next task; "idle": the stream has drained)
        and waits for the driver's answer: (task id, task), "wait" (none queued now) or None
        (the job is over; also when the driver has stopped polling)."""
        self.emit(what)
        while True:
            try:
                return self.answers.get(timeout=1.0)
            except queue.Empty:
                if time.monotonic() - self.seen > OWNER_TIMEOUT:
                    return None

    def tasks(self, first=None):
        """The tasks of one stream: ``first``, then one per "need" until the driver answers
        "wait" (the stream drains; the worker then asks again as "idle", see ``run``) or None
        (``self.over``)."""
        if first is not None:
            yield first
        while True:
            item = self.ask("need")
            if item is None:
                self.over = True
                return
            if item == "wait":
                return
            yield item


class FloxelsWorker:
    """A Ray actor (threaded: ``poll``/``offer`` run beside ``run``): one pipeline per job, fed
    by the driver. ``keep_s``: seconds it waits idle for the next job before it exits (the warm
    pool; None: it is killed by its job's driver)."""

    def __init__(self, cpus: float, device: str, keep_s: float | None = None, job: str | None = None) -> None:
        self.stamps = {"process": process_start_time(), "imported": _IMPORTED, "init": time.time()}
        preload = sys.modules.get("floxels_ext.lidar.dataset.ray_preload")  # Ray loaded it before this actor came
        if preload is not None and hasattr(preload, "PRELOADED"):
            self.stamps["preloaded"] = preload.PRELOADED
        import torch  # (importing floxels_ext does not import torch; the compiled ops load with it)

        import floxels_ext.ops  # noqa: F401

        self.stamps["torch"] = time.time()

        self.device, self.keep_s = device, keep_s
        self.threads = worker_threads(cpus, device.startswith("cuda"))
        torch.set_num_threads(self.threads["torch"])
        self.lock = threading.Lock()
        self.handed = threading.Condition(self.lock)  # notified when a job releases it
        self.owner: str | None = job  # the job that started it holds it
        self.started_for = job
        self.owner_seen = time.monotonic()
        self.idle_since = time.monotonic()
        self.running = False
        self.retiring = False
        self.retire_asked = False  # a job asked while another held it: it exits once released
        self.jobs = 0
        self.tasked = False  # the job that started it has given it a task (it is that job's for good)
        self.withdrawn: list[str] = []  # jobs whose release came before their claim (see release)
        self.channels: dict[str, Channel] = {}
        self.warm = threading.Thread(target=self._warm_up, name="floxels-warm-up", daemon=True)
        self.warm.start()
        if keep_s:
            threading.Thread(target=self._watch, name="floxels-idle", daemon=True).start()
        self.stamps["init_done"] = time.time()

    # -- start -------------------------------------------------------------------------------
    def _warm_up(self) -> None:
        """The pipeline's imports, the CUDA context and one tiny estimate while the driver
        lists and plans the job (:func:`warm_up`)."""
        warm_up(self.device, self.stamps)

    # -- the warm pool -----------------------------------------------------------------------
    def claim(self, job: str) -> bool:
        """Makes this worker ``job``'s, when no job holds it (and no job asked it to leave).

        A worker that a job started and dropped before it was up (that job had fewer tasks, or
        ended first) gets that job's ``run`` (answered "no task"), its release and the next job's
        claim queued together behind its ``__init__``; a threaded actor runs them in either order,
        and ``run`` first waits for the worker's warm-up (~0.5-1 s on a GPU). So a claim that
        finds it held by the job it was started for, which has given it no task, waits up to
        ``HANDOVER_S`` for that release (without it, the next job skipped such workers and started
        new ones ~6-7 s late: A5, E6). The claiming job does not wait for the answer: it takes
        the worker when it comes (``ray_pool.Workers.take_late``)."""
        with self.handed:
            if (self.owner is not None and self.owner == self.started_for and not self.tasked
                    and not (self.retiring or self.retire_asked)):
                self.handed.wait_for(lambda: self.owner != self.started_for or self.tasked, timeout=HANDOVER_S)
            if self.owner is not None or self.retiring or self.retire_asked or job in self.withdrawn:
                return False
            self.owner, self.owner_seen = job, time.monotonic()
            return True

    def _took_task(self) -> None:
        """A task came: a claim waiting for this worker's hand-over gives up at once."""
        with self.handed:
            if not self.tasked:
                self.tasked = True
                self.handed.notify_all()

    def release(self, job: str) -> None:
        """The job is done with this worker: it waits for the next one (its GPU memory cache
        freed, its context and kernels kept)."""
        with self.lock:
            if self.owner != job:
                # a job that gave up on a claim still queued here (it ended first): the claim,
                # when it runs, is refused rather than holding this worker for OWNER_TIMEOUT
                self.withdrawn = [*self.withdrawn[-15:], job]
                return
            self.owner, self.idle_since = None, time.monotonic()
            self.channels.pop(job, None)
            self.handed.notify_all()
            leave = self._leave_if_asked()
        if leave:
            return
        if self.device.startswith("cuda"):
            # on a thread of its own: freeing the cached blocks takes ~0.1-0.3 s on a busy host,
            # and the release sits between the job's last frame and its end (E6: the 4-GPU row's
            # workers ended 0.25 s after the driver knew every task had ended)
            threading.Thread(target=_empty_cache, name="floxels-empty-cache", daemon=True).start()

    def retire(self) -> bool:
        """Exits when idle (another job needs its resources). False when a job holds it: then it
        exits as soon as that job releases it (a job still finishing its last frames, or one that
        started it and is gone), instead of holding its GPU for the pool's idle time while the
        asking job waits for it."""
        with self.lock:
            if self.owner is not None:
                self.retire_asked = True
                return False
            self.retiring = True
        threading.Thread(target=self._exit, daemon=True).start()
        return True

    def _leave_if_asked(self) -> bool:
        """(Under the lock, just released.) Starts the exit a retire asked for while it was held."""
        if not self.retire_asked or self.retiring:
            return False
        self.retiring = True
        threading.Thread(target=self._exit, daemon=True).start()
        return True

    def _exit(self) -> None:
        import ray

        time.sleep(0.05)  # the caller's reply first
        ray.kill(ray.get_runtime_context().current_actor, no_restart=True)

    def _watch(self) -> None:
        """Gives an abandoned claim back (its driver never ran a job on it) and exits after
        ``keep_s`` seconds without a job (its GPU free for others)."""
        while True:
            time.sleep(1.0)
            with self.lock:
                now = time.monotonic()
                if self.owner is not None and not self.running:
                    ch = self.channels.get(self.owner)
                    seen = max(self.owner_seen, ch.seen if ch else 0.0)
                    if now - seen > OWNER_TIMEOUT:
                        self.channels.pop(self.owner, None)
                        self.owner, self.idle_since = None, now
                        if self._leave_if_asked():
                            return
                idle = self.owner is None and now - self.idle_since > self.keep_s
                if idle:
                    self.retiring = True
            if idle:
                self._exit()
                return

    # -- one job -----------------------------------------------------------------------------
    def _channel(self, job: str) -> Channel:
        with self.lock:
            if job not in self.channels:
                self.channels[job] = Channel()
            return self.channels[job]

    def info(self) -> dict:
        import ray

        ctx = ray.get_runtime_context()
        try:
            gpus = [str(g) for g in ctx.get_accelerator_ids().get("GPU", [])]
        except Exception:  # noqa: BLE001 - informational only
            gpus = []
        return {"host": socket.gethostname(), "pid": os.getpid(), "node": ctx.get_node_id(), "gpus": gpus,
                "jobs": self.jobs, "idle": self.owner is None and not self.running, "threads": dict(self.threads),
                "stamps": dict(self.stamps)}

    def poll(self, job: str, timeout: float = 1.0) -> tuple[list, dict]:
        """The driver's long poll: ([events], {task id: frames written}) (module docstring)."""
        return self._channel(job).poll(timeout)

    def offer(self, job: str, item) -> None:
        """The driver's answer to "need": (task id, task), or None (no more tasks)."""
        self._channel(job).answers.put(item)

    def run(self, job: str, spec: dict) -> dict:
        """Runs the job's tasks through one pipeline until the driver answers None.
        ``spec``: {"common": the run's options, "device", "t0": the job's start (time.time())}."""
        stamps = {"run": time.time()}
        with self.lock:
            if self.owner not in (None, job) or self.retiring:
                raise RuntimeError("this pooled worker was given to another job (its driver had stopped polling)")
            self.running, self.owner, self.owner_seen = True, job, time.monotonic()
            warm_jobs = self.jobs
            self.jobs += 1
        ch = self._channel(job)
        log: list[str] = []

        def report(msg: str) -> None:
            if len(log) < 200:
                log.append(msg)

        def on_frame(j, i) -> None:
            now = time.time()
            stamps.setdefault("first_output", now)
            stamps["last_output"] = now
            if i not in j.failed:
                ch.count(j.info["task"].lease)

        def ended(task, outcome, j, lines) -> None:  # with the task's summary part: the driver merges a sequence's
            stamps["task_ended"] = time.time()  # its last task's end (the timeline's "tasks ended")
            ch.emit("ended", task.lease, outcome, list(lines), j.info.get("summary") if j is not None else None)

        def tasks(first):
            for k, task in ch.tasks(first):
                self._took_task()
                stamps.setdefault("first_task", time.time())
                task.lease = k
                yield task

        res = {"written": 0, "failed": [], "stages": {}, "streams": 0}
        try:
            # the estimator's host state (page-locked staging buffers, streams) is not shared
            # between threads: the pipeline starts once the warm-up is done
            self.warm.join()
            from floxels_ext.lidar.dataset.worker import run_tasks

            args = task_args(spec["common"], spec["device"], self.threads)
            stamps["pipeline"] = time.time()
            first = None
            while True:  # one stream while tasks are queued; after it drains, wait for requeued ones
                # engine: a task's summary part goes back to the driver, which writes each sequence's
                # run_summary.json once from the parts of all its tasks (whichever worker ran them)
                r = run_tasks(tasks(first), args, report=report, on_frame=on_frame, on_sequence=ended,
                              engine=f"{socket.gethostname()}:{os.getpid()}")
                res["written"] += r["written"]
                res["failed"] += r["failed"]
                res["stages"], res["streams"] = r["stages"], res["streams"] + 1
                if ch.over:
                    break
                first = ch.ask("idle")
                if first is None:
                    break
        finally:
            ch.close()
            with self.lock:
                self.running, self.owner_seen = False, time.monotonic()
            if self.keep_s:
                self.release(job)  # back to the pool (the driver does not wait for a worker still starting)
        stamps["end"] = time.time()
        out = self.info()
        t0 = spec["t0"]
        rel = {k: round(v - t0, 3) for k, v in {**self.stamps, **stamps}.items() if isinstance(v, float)}
        out.update(written=res["written"], failed=res["failed"], stages=res["stages"], streams=res["streams"], log=log[-30:],
                   warm=warm_jobs > 0, timeline=rel, warm_error=self.stamps.get("warm_error"),
                   cuda_devices=self.stamps.get("cuda_devices"))
        return out


def task_args(common: dict, device: str | None, threads: dict):
    """The run's namespace in a worker: the driver's common options, this worker's device and
    threads (readers and writers unless the user set them)."""
    from floxels_ext.cli import build_parser

    ns = build_parser().parse_args(["run", "INPUT", "--out", "OUT"])
    for k, v in common.items():
        setattr(ns, k, v)
    ns.device, ns.ray, ns.poses, ns.calib, ns.frames = device, None, None, None, None
    ns.cpu_limit = threads["cpus"]  # caps the drain writers; the plain run's CPU default stays off (threads set)
    ns.workers = ns.workers or threads["readers"]
    ns.writers = ns.writers or threads["writers"]
    return ns
