"""The Ray driver of ``floxels run DATASET --ray``: one long-lived worker per GPU (or per
``--gpus-per-task`` share, or per ``--cpus-per-task`` CPUs on a CPU cluster).

Each worker is a Ray actor (:class:`FloxelsWorker`) that keeps its process, its CUDA context,
the loaded extension and one pipeline (``worker.run_tasks``: readers, writers and the
method's stream) for the whole job, so Ray's and CUDA's start are paid once per worker, not
per task. Workers pull tasks (``tasks.Task``: a sequence, or a frame range of a long one)
from a :class:`Dispatcher` actor that the driver starts; a worker asks for the next task as
its read-ahead reaches the end of the current one, so the pipeline never drains between
tasks. Input and output must be on storage every node sees at the same path.

The dispatcher leases each task to one worker at a time. When a worker (or its node) dies,
the driver hands its unfinished leases back to the queue and, while ``--retries`` allows,
starts a replacement; any worker may take them. Frames written before the death stay (the
new holder's resume check skips them: nothing is written twice), frames in flight are
estimated again (nothing is lost). A task left when no worker is left is reported with the
names of the files it did not write; running the same command again writes only those.
Progress is counted from the output files of the leased tasks; sequences done, skipped and
failed from the dispatcher.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections import deque

__all__ = ["run_on_ray", "connect", "task_slots", "Dispatcher", "FloxelsWorker"]


def _ray():
    from floxels_ext.lidar.io._optional import require

    return require("ray", "ray", "ray", "floxels run --ray")


def connect(address: str):
    """ray.init for ``--ray auto|ADDRESS`` unless this process is already connected."""
    from floxels_ext.errors import CLIError

    ray = _ray()
    if not ray.is_initialized():
        try:
            ray.init(address=None if address == "auto" else address, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise CLIError(f"--ray {address}: cannot connect to a Ray cluster: {e}") from None
    return ray


def _alive_nodes(ray) -> list[dict]:
    return [n["Resources"] for n in ray.nodes() if n.get("Alive")]


def task_slots(nodes: list[dict], gpus: float, cpus: float) -> int:
    """How many workers of (gpus, cpus) the nodes hold at once (each node packs its own)."""
    eps = 1e-9
    total = 0
    for r in nodes:
        k = math.floor(r.get("CPU", 0.0) / cpus + eps)
        if gpus > 0:
            k = min(k, math.floor(r.get("GPU", 0.0) / gpus + eps))
        total += k
    return total


def _resources(ray, args) -> tuple[float, float, str]:
    """(GPUs, CPUs) per worker and the workers' --device; CLIError when no node can hold one."""
    from floxels_ext.errors import CLIError

    nodes = _alive_nodes(ray)
    has_gpu = any(r.get("GPU", 0) > 0 for r in nodes)
    gpus = args.gpus_per_task
    if gpus is None:
        gpus = 1.0 if has_gpu and args.device != "cpu" else 0.0
    if gpus == 0 and args.device is not None and args.device.startswith("cuda"):
        raise CLIError("--device cuda on Ray needs GPUs: the cluster has none" if not has_gpu
                       else "--device cuda contradicts --gpus-per-task 0")
    if gpus > 1 and gpus != int(gpus):
        raise CLIError(f"--gpus-per-task above 1 must be a whole number, got {gpus}")
    cpus = args.cpus_per_task
    if cpus is None:  # a GPU node's CPUs shared by the workers it holds (readers and writers need them)
        shares = [r.get("CPU", 0.0) / math.floor(r["GPU"] / gpus + 1e-9) for r in nodes
                  if gpus > 0 and r.get("GPU", 0.0) >= gpus]
        cpus = max(1.0, math.floor(min(shares))) if shares else 1.0
    if task_slots(nodes, gpus, cpus) == 0:
        have = ", ".join(f"{r.get('CPU', 0):g} CPU + {r.get('GPU', 0):g} GPU" for r in nodes) or "no live node"
        raise CLIError(f"no node of the Ray cluster can hold a worker of {gpus:g} GPU + {cpus:g} CPU "
                       f"(nodes: {have}); change --gpus-per-task / --cpus-per-task")
    device = "cuda" if gpus > 0 else "cpu"  # a worker sees only the GPUs Ray gave it, as cuda:0...
    return gpus, cpus, device


def _rewrites(tasks) -> bool:
    """Whether any frame to do already has an output (recomputed: its inputs changed)."""
    present: dict = {}
    for t in tasks:
        if t.out_dir not in present:
            try:
                present[t.out_dir] = {e.name[:-4] for e in os.scandir(t.out_dir) if e.name.endswith(".npz")}
            except OSError:
                present[t.out_dir] = set()
        if any(n in present[t.out_dir] for n in t.todo):
            return True
    return False


def _count_written(task, since: float | None) -> int:
    """Frames of task.todo whose output file exists (written after ``since`` when given: --force)."""
    try:
        present = {e.name[:-4] for e in os.scandir(task.out_dir) if e.name.endswith(".npz")}
    except OSError:
        return 0
    names = [n for n in task.todo if n in present]
    if since is None:
        return len(names)
    n = 0
    for name in names:
        try:
            n += os.stat(task.out_dir / f"{name}.npz").st_mtime >= since
        except OSError:
            pass
    return n


def _missing_report(task, since: float | None, limit: int = 8) -> str:
    """Names the output files (and the first input) of the task's frames left unwritten."""
    def written(name: str) -> bool:
        try:
            mtime = os.stat(task.out_dir / f"{name}.npz").st_mtime
            return since is None or mtime >= since
        except OSError:
            return False

    todo = set(task.todo)
    missing = [(n, p) for n, p in zip(task.names, task.frame_paths) if n in todo and not written(n)]
    if not missing:
        return "all its frames were written"
    shown = ", ".join(str(task.out_dir / f"{n}.npz") for n, _ in missing[:limit])
    more = f" and {len(missing) - limit} more" if len(missing) > limit else ""
    return f"{len(missing)} frame(s) not written: {shown}{more} (first input: {missing[0][1]})"


class Dispatcher:
    """The job's task queue (a Ray actor in the driver's node): leases each task to one worker
    at a time and records how it ended."""

    def __init__(self, tasks: list) -> None:
        self.tasks = tasks
        self.queue = deque(range(len(tasks)))
        self.leases: dict[str, set[int]] = {}
        self.ended: dict[int, tuple[str, list[str]]] = {}

    def lease(self, worker: str):
        """(task id, task) for ``worker``, or None when the queue is empty now."""
        if not self.queue:
            return None
        k = self.queue.popleft()
        self.leases.setdefault(worker, set()).add(k)
        return k, self.tasks[k]

    def finish(self, worker: str, k: int, outcome: str, lines: list[str]) -> None:
        self.leases.get(worker, set()).discard(k)
        self.ended[k] = (outcome, lines)

    def requeue(self, worker: str) -> list[int]:
        """A dead worker's unfinished tasks go back to the front of the queue."""
        ks = sorted(self.leases.pop(worker, set()))
        self.queue.extendleft(reversed(ks))
        return ks

    def state(self, worker: str | None = None) -> str:
        """"work" (tasks queued), "wait" (none queued, some leased: a death may requeue them)
        or "done"."""
        if self.queue:
            return "work"
        return "wait" if any(self.leases.values()) else "done"

    def status(self) -> dict:
        return {"leased": {w: sorted(ks) for w, ks in self.leases.items()}, "ended": dict(self.ended),
                "queued": len(self.queue)}


def task_args(common: dict, device: str | None, threads: int | None):
    """The run's namespace in a worker: the driver's common options, this worker's device and CPUs."""
    from floxels_ext.cli import build_parser

    ns = build_parser().parse_args(["run", "INPUT", "--out", "OUT"])
    for k, v in common.items():
        setattr(ns, k, v)
    ns.device, ns.ray, ns.poses, ns.calib, ns.frames = device, None, None, None, None
    ns.cpu_limit = threads  # the default reader count stays within the worker's CPUs
    return ns


class FloxelsWorker:
    """A Ray actor: one pipeline for the whole job, fed by the dispatcher's tasks."""

    def __init__(self, threads: int | None = None) -> None:
        import torch

        if threads:
            torch.set_num_threads(int(threads))
        self.threads = threads

    def pid(self) -> int:
        return os.getpid()

    def run(self, dispatcher, name: str, common: dict, device: str | None) -> dict:
        import socket

        import ray

        from floxels_ext.lidar.dataset.worker import run_tasks

        args = task_args(common, device, self.threads)
        log: list[str] = []
        out = {"written": 0, "failed": [], "host": socket.gethostname(), "pid": os.getpid(), "streams": 0}

        def report(msg: str) -> None:
            if len(log) < 200:
                log.append(msg)

        def tasks():
            while True:
                got = ray.get(dispatcher.lease.remote(name))
                if got is None:
                    return
                k, task = got
                task.lease = k
                yield task

        def ended(task, outcome, job, lines) -> None:
            dispatcher.finish.remote(name, task.lease, outcome, list(lines))

        while True:
            res = run_tasks(tasks(), args, report=report, on_sequence=ended)
            out["streams"] += 1
            out["written"] += res["written"]
            out["failed"] += res["failed"]
            out["stages"] = res["stages"]
            # the queue is empty: wait while others hold tasks (a death puts theirs back)
            while (state := ray.get(dispatcher.state.remote(name))) == "wait":
                time.sleep(0.25)
            if state == "done":
                out["log"] = log[-30:]
                return out


def run_on_ray(tasks, args, common: dict, n_sequences: int) -> int:
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.outputs import remove_temps
    from floxels_ext.lidar.pipeline.progress import DatasetProgress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    out_dirs = sorted({t.out_dir for t in tasks})
    for d in out_dirs:  # temporaries of an interrupted job; none of ours is running yet
        d.mkdir(parents=True, exist_ok=True)
        stale = remove_temps(d)
        if stale and verbosity >= 0:
            print(f"removed {stale} temporary file(s) left by an interrupted run in {d}", file=sys.stderr)
    todo_tasks = [t for t in tasks if t.todo]
    total = sum(len(t.names) for t in tasks)
    if not todo_tasks:
        print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total} already done, nothing to "
              f"estimate", file=sys.stderr)
        return 0
    ray = connect(args.ray)
    gpus, cpus, device = _resources(ray, args)
    todo = sum(len(t.todo) for t in todo_tasks)
    # frames whose old output is recomputed (--force, inputs changed) count once written again
    since = time.time() - 1.0 if args.force or _rewrites(todo_tasks) else None
    nodes = _alive_nodes(ray)
    cap = task_slots(nodes, gpus, cpus)
    n_workers = max(1, min(cap if args.max_tasks is None else min(args.max_tasks, cap), len(todo_tasks)))
    if verbosity >= 0:
        print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total - todo} already done, {todo} to "
              f"estimate in {len(todo_tasks)} task(s) on Ray ({len(nodes)} node(s), "
              f"{sum(r.get('GPU', 0) for r in nodes):g} GPU, {sum(r.get('CPU', 0) for r in nodes):g} CPU): "
              f"{n_workers} worker(s) of {gpus:g} GPU + {cpus:g} CPU", file=sys.stderr, flush=True)
    threads = max(1, int(cpus))
    dispatcher = ray.remote(Dispatcher).options(num_cpus=0).remote(todo_tasks)
    worker_cls = ray.remote(FloxelsWorker).options(num_gpus=gpus, num_cpus=cpus, max_restarts=0)
    workers: dict = {}   # run ObjectRef -> (name, actor)
    made = 0

    def start_worker() -> None:
        nonlocal made
        name = f"worker-{made}"
        made += 1
        actor = worker_cls.remote(threads)
        workers[actor.run.remote(dispatcher, name, common, device)] = (name, actor)

    for _ in range(n_workers):
        start_worker()
    replacements = args.retries
    bar = DatasetProgress(todo, len(tasks), verbosity=verbosity)
    for _ in range(len(tasks) - len(todo_tasks)):
        bar.sequence("skipped")
    failures: list[str] = []
    deaths: list[str] = []
    results: list[dict] = []
    ended_seen: set[int] = set()
    done_frames = 0   # frames of tasks that ended
    shown = 0
    t0 = time.perf_counter()
    try:
        while workers:
            ready, _ = ray.wait(list(workers), num_returns=1, timeout=0.5)
            for ref in ready:
                name, actor = workers.pop(ref)
                try:
                    results.append(ray.get(ref))
                    ray.kill(actor)  # its GPU is free for the next job at once
                except ray.exceptions.RayError as e:
                    if isinstance(getattr(e, "cause", None), CLIError):
                        raise e.cause from None  # a mistake in the common options: every worker would fail
                    if isinstance(getattr(e, "cause", None), ImportError):
                        raise CLIError(f"a Ray worker cannot import what it needs ({e.cause}); install the same "
                                       f"floxels_ext and its dependencies on every node") from None
                    back = ray.get(dispatcher.requeue.remote(name))
                    lines = str(e).strip().splitlines()
                    deaths.append(f"{name}: {type(e).__name__}: {lines[-1] if lines else e}; "
                                  f"{len(back)} task(s) handed to the other workers")
                    if verbosity >= 0:
                        bar.message(f"floxels: warning: {deaths[-1]}")
                    if replacements > 0:
                        replacements -= 1
                        start_worker()
            st = ray.get(dispatcher.status.remote())
            for k, (outcome, lines) in st["ended"].items():
                if k not in ended_seen:
                    ended_seen.add(k)
                    bar.sequence(outcome)
                    failures += lines
                    done_frames += _count_written(todo_tasks[k], since)
            if not workers and (st["queued"] or any(st["leased"].values())):
                break  # no worker left: what is left is reported below
            if st["queued"] == 0 and not any(st["leased"].values()) and len(ended_seen) == len(todo_tasks):
                # all done: workers return now; one still waiting for resources (its node gone) is not needed
                left, _ = ray.wait(list(workers), num_returns=len(workers), timeout=30.0)
                for ref in left:
                    results.append(ray.get(ref))
                    ray.kill(workers.pop(ref)[1])
                for ref, (_, actor) in list(workers.items()):
                    ray.kill(actor)
                workers.clear()
            leased = [todo_tasks[k] for ks in st["leased"].values() for k in ks]
            done = done_frames + sum(_count_written(t, since) for t in leased)
            if done > shown:
                bar.frames(done - shown)
                shown = done
    except BaseException:
        for _, actor in workers.values():
            ray.kill(actor)
        bar.close()
        print("floxels: job stopped; running the same command again writes only the missing frames",
              file=sys.stderr)
        raise
    bar.close()
    st = ray.get(dispatcher.status.remote())
    unfinished = [todo_tasks[k] for k in range(len(todo_tasks)) if k not in st["ended"]]
    for t in unfinished:
        failures.append(f"{t.label}: no worker left to run it; {_missing_report(t, since)}")
    ray.kill(dispatcher)
    left = sum(remove_temps(d) for d in out_dirs)  # from workers killed mid-write
    wall = time.perf_counter() - t0
    counts = {o: 0 for o in ("done", "skipped", "failed")}
    for outcome, _ in st["ended"].values():
        counts[outcome] += 1
    counts["skipped"] += len(tasks) - len(todo_tasks)
    counts["failed"] += len(unfinished)
    print(f"done: {n_sequences} sequences in {len(tasks)} task(s) ({counts['done']} done, {counts['skipped']} skipped, "
          f"{counts['failed']} failed), {shown} frame(s) written by {made} worker(s) in {wall:.1f} s "
          f"({shown / wall if wall > 0 else 0:.2f} frames/s), {total - todo} skipped (already done), "
          f"{len(failures)} failure(s)" + (f"; {len(deaths)} worker(s) lost" if deaths else "")
          + (f"; removed {left} temporary file(s) of killed workers" if left else ""), file=sys.stderr)
    if failures:
        print("failed:", file=sys.stderr)
        for f in failures:
            print(f"  {f}", file=sys.stderr)
        return 1
    return 0
