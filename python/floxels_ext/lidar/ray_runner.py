"""The Ray driver of ``floxels run DATASET --ray``: one Ray task per (sequence, frame range).

Each task asks Ray for ``--gpus-per-task`` GPUs (fractions pack tasks on one GPU) and
``--cpus-per-task`` CPUs, and runs ``dataset_run.floxels_task`` on whichever node Ray picks; input
and output must therefore be on storage all nodes see at the same path. The driver keeps at most
as many tasks in flight as the cluster's resources fit (re-read as nodes join or leave), so every
task in flight is running and the progress line's worker count is true. Progress is counted from
the output files themselves (listing only the directories of running tasks), which also makes a
re-run exact: it plans only the frames whose files are missing.

A worker or node that dies makes Ray re-run the task (``--retries``); the re-run skips the
frames already written. A task that still fails is reported with the names of the files it did
not write, and the exit status is 1; running the same command again writes only what is missing.
"""

from __future__ import annotations

import math
import os
import sys
import time

__all__ = ["run_on_ray", "connect", "task_slots"]


def _ray():
    from floxels_ext.lidar.io._optional import require

    return require("ray", "ray", "ray", "floxels run --ray")


def connect(address: str):
    """ray.init for ``--ray auto|ADDRESS`` unless this process is already connected."""
    from floxels_ext.cli import CLIError

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
    """How many tasks of (gpus, cpus) the nodes hold at once (each node packs its own)."""
    eps = 1e-9
    total = 0
    for r in nodes:
        k = math.floor(r.get("CPU", 0.0) / cpus + eps)
        if gpus > 0:
            k = min(k, math.floor(r.get("GPU", 0.0) / gpus + eps))
        total += k
    return total


def _resources(ray, args) -> tuple[float, float, str]:
    """(GPUs, CPUs) per task and the task's --device; CLIError when no node can hold such a task."""
    from floxels_ext.cli import CLIError

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
    if task_slots(nodes, gpus, args.cpus_per_task) == 0:
        have = ", ".join(f"{r.get('CPU', 0):g} CPU + {r.get('GPU', 0):g} GPU" for r in nodes) or "no live node"
        raise CLIError(f"no node of the Ray cluster can hold a task of {gpus:g} GPU + {args.cpus_per_task:g} CPU "
                       f"(nodes: {have}); change --gpus-per-task / --cpus-per-task")
    device = "cuda" if gpus > 0 else "cpu"  # a task sees only the GPUs Ray gave it, as cuda:0...
    return gpus, args.cpus_per_task, device


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


def run_on_ray(tasks, args, common: dict, n_sequences: int) -> int:
    from floxels_ext.cli import CLIError
    from floxels_ext.lidar.dataset_run import floxels_task, remove_temps, task_job
    from floxels_ext.lidar.progress import Progress

    out_dirs = sorted({t.out_dir for t in tasks})
    for d in out_dirs:  # temporaries of an interrupted job; none of ours is running yet
        d.mkdir(parents=True, exist_ok=True)
        stale = remove_temps(d)
        if stale:
            print(f"removed {stale} temporary file(s) left by an interrupted run in {d}", file=sys.stderr)
    todo_tasks = [t for t in tasks if t.todo]
    if not todo_tasks:
        n = sum(len(t.names) for t in tasks)
        print(f"dataset {args.input}: {n_sequences} sequences, {n} frames, {n} already done, nothing to estimate",
              file=sys.stderr)
        return 0
    ray = connect(args.ray)
    gpus, cpus, device = _resources(ray, args)
    total = sum(len(t.names) for t in tasks)
    todo = sum(len(t.todo) for t in todo_tasks)
    since = time.time() - 1.0 if args.force else None
    nodes = _alive_nodes(ray)
    slots = task_slots(nodes, gpus, cpus) if args.max_tasks is None else min(args.max_tasks, task_slots(nodes, gpus, cpus))
    print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total - todo} already done, {todo} to "
          f"estimate in {len(todo_tasks)} task(s) on Ray ({len(nodes)} node(s), "
          f"{sum(r.get('GPU', 0) for r in nodes):g} GPU, {sum(r.get('CPU', 0) for r in nodes):g} CPU): "
          f"{gpus:g} GPU + {cpus:g} CPU per task, up to {slots} at once", file=sys.stderr, flush=True)
    remote = ray.remote(floxels_task).options(num_gpus=gpus, num_cpus=cpus, max_retries=args.retries,
                                              retry_exceptions=False)
    threads = max(1, int(cpus))
    pending = list(todo_tasks)
    inflight: dict = {}                      # ObjectRef -> Task
    counted_done = 0                         # frames of finished tasks
    failures: list[str] = []
    succeeded = 0
    bar = Progress(todo, "frames")
    shown = 0
    t0 = time.perf_counter()
    t_slots = t_count = t0
    try:
        while pending or inflight:
            now = time.perf_counter()
            if now - t_slots > 10.0:  # nodes may have joined or left
                t_slots = now
                cap = task_slots(_alive_nodes(ray), gpus, cpus)
                slots = max(1, cap if args.max_tasks is None else min(args.max_tasks, cap))
            while pending and len(inflight) < slots:
                t = pending.pop(0)
                inflight[remote.remote(task_job(t, common, device, threads))] = t
            running = len(inflight)
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)  # back as soon as one ends
            if ready:
                ready, _ = ray.wait(list(inflight), num_returns=len(inflight), timeout=0)
            for ref in ready:
                t = inflight.pop(ref)
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as e:
                    if isinstance(getattr(e, "cause", None), ImportError) and succeeded == 0:
                        raise CLIError(f"a Ray worker cannot import what a task needs ({e.cause}); install the "
                                       f"same floxels_ext and its dependencies on every node") from None
                    lines = str(e).strip().splitlines()
                    failures.append(f"{t.label}: {type(e).__name__}: {lines[-1] if lines else e}; "
                                    f"{_missing_report(t, since)}")
                    res = None
                if res is not None:
                    if res["rc"] == 2 and succeeded == 0 and not failures:
                        raise CLIError(res["error"])  # a mistake in the common options: every task would fail
                    if res["rc"] == 0:
                        succeeded += 1
                    elif res["rc"] == 2:
                        failures.append(f"{t.label}: {res['error']}")
                    else:
                        failures += res["failed"] or [f"{t.label} (on {res['host']}): exit {res['rc']}; "
                                                      f"{_missing_report(t, since)}\n{res['log']}"]
                counted_done += _count_written(t, since)
            if time.perf_counter() - t_count < 0.5 and (pending or inflight):
                continue  # list the running tasks' directories twice a second at most
            t_count = time.perf_counter()
            done = counted_done + sum(_count_written(t, since) for t in inflight.values())
            if done > shown:
                el = time.perf_counter() - t0
                bar.update(done - shown, note=f"{done / el:.2f} frames/s, {running} worker(s)")
                shown = done
    except BaseException:
        for ref in inflight:
            ray.cancel(ref, force=True)
        bar.close()
        print("floxels: job stopped; running the same command again writes only the missing frames",
              file=sys.stderr)
        raise
    bar.close()
    left = sum(remove_temps(d) for d in out_dirs)  # from attempts killed mid-write and then retried
    wall = time.perf_counter() - t0
    print(f"done: {shown} frame(s) written by {len(todo_tasks)} task(s) in {wall:.1f} s "
          f"({shown / wall if wall > 0 else 0:.2f} frames/s), {total - todo} skipped (already done), "
          f"{len(failures)} failure(s)" + (f"; removed {left} temporary file(s) of killed attempts" if left else ""),
          file=sys.stderr)
    if failures:
        print("failed:", file=sys.stderr)
        for f in failures:
            print(f"  {f}", file=sys.stderr)
        return 1
    return 0
