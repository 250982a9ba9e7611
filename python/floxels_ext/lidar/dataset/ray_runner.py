"""The Ray driver of ``floxels run DATASET --ray``: long-lived workers, several per GPU by default (one per
``--gpus-per-task`` share, or per ``--cpus-per-task`` CPUs on a CPU cluster).

Each worker is a Ray actor (``ray_worker.FloxelsWorker``) that keeps its process, its CUDA
context, the loaded extension and one pipeline (``worker.run_tasks``: readers, writers and the
method's stream) for the whole job, so Ray's and CUDA's start are paid once per worker, not per
task, and, with the warm pool (``ray_pool``, ``--keep-workers``), once per cluster for the jobs
that follow within the idle timeout. The driver asks for its workers first
(:func:`early_workers`, before it lists and plans the dataset), so their start (process,
imports, CUDA context, a tiny warm-up estimate) overlaps the driver's own work.

The driver hands out the tasks (``tasks.Task``: a sequence, or a frame range of a long one)
itself: each worker's pipeline asks for its next task as its read-ahead nears the end of the
current one, through a long poll the driver always holds per worker (``ray_worker.Channel``),
so the pipeline never drains between tasks and no dispatcher process sits between them. Input
and output must be on storage every node sees at the same path.

Each task is leased to one worker at a time. When a worker (or its node) dies, the driver puts
its unfinished leases back in the queue and, while ``--retries`` allows, starts a replacement;
any worker may take them. Frames written before the death stay (the new holder's resume check
skips them: nothing is written twice), frames in flight are estimated again (nothing is lost).
A task left when no worker is left is reported with the names of the files it did not write;
running the same command again writes only those. Progress counts the frames the workers
report; the final count, sequences done, skipped and failed come from the output files and the
workers' reports. ``OUT/ray_job_summary.json`` records the job: counts, wall time and each
worker's start timeline (``-v`` prints it).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import time
from collections import deque
from pathlib import Path

from floxels_ext.lidar.dataset.engine_counts import gpu_share
from floxels_ext.lidar.dataset.ray_report import report_workers, write_job_summary
from floxels_ext.lidar.dataset.ray_tail import TailShare, first_part, near_end

__all__ = ["run_on_ray", "early_workers", "connect", "task_slots"]

POLL_S = 1.0  # a worker's long poll returns at once on news, else after this (the driver's heartbeat)
TAIL_SPLIT_FRAMES = 16  # a task handed out near the job's end is cut while each part keeps this many


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
        from floxels_ext.lidar.pipeline.run_args import preset_name

        gpus = gpu_share(nodes, preset_name(args)) if has_gpu and args.device != "cpu" else 0.0
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
    from floxels_ext.lidar.dataset.tasks import written_names

    present: dict = {}
    for t in tasks:
        if t.out_dir not in present:
            present[t.out_dir] = written_names(t.out_dir)
        if any(n in present[t.out_dir] for n in t.todo):
            return True
    return False


def _count_written(task, since: float | None) -> int:
    """Frames of task.todo whose output file exists (written after ``since`` when given: --force)."""
    from floxels_ext.lidar.dataset.tasks import written_names

    present = written_names(task.out_dir)
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




@contextlib.contextmanager
def early_workers(args):
    """Connects and asks for the job's workers before the driver lists the dataset (their start
    overlaps its listing and planning); yields the ``ray_pool.Workers`` that ``run_on_ray``
    uses and gives them back at the end (killed when the job failed or was interrupted)."""
    from floxels_ext.lidar.dataset.ray_pool import Workers

    t0 = time.time()
    ray = connect(args.ray)
    gpus, cpus, device = _resources(ray, args)
    cap = task_slots(_alive_nodes(ray), gpus, cpus)
    n = cap if args.max_tasks is None else min(args.max_tasks, cap)
    workers = Workers(ray, gpus, cpus, device, keep_s=args.keep_workers, t0=t0)
    ok = False
    try:
        workers.start(max(1, n))
        yield workers
        ok = True
    finally:
        workers.close(ok)


def run_on_ray(tasks, args, common: dict, n_sequences: int, workers, align: int = 0) -> int:
    """``align`` > 0: a task handed out near the job's end is cut at a multiple of ``align``
    (``tasks.halve_task``; 1: anywhere, the outputs do not depend on the cut) to the worker's
    share of the work left, the last tasks also halved (``ray_tail``), the rest queued first, so
    that the workers end together; 0: tasks are never cut (whole sequences asked for, KISS-ICP)."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io.outputs import remove_temps
    from floxels_ext.lidar.dataset.summary import SequenceParts, write_summary
    from floxels_ext.lidar.dataset.tasks import halve_task
    from floxels_ext.lidar.pipeline.progress import DatasetProgress

    ray = workers.ray
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
    todo = sum(len(t.todo) for t in todo_tasks)
    # frames whose old output is recomputed (--force, inputs changed) count once written again
    since = time.time() - 1.0 if args.force or _rewrites(todo_tasks) else None
    for slot in workers.slots[len(todo_tasks):]:  # more workers than tasks
        workers.drop(slot)
    workers.target = min(workers.target, len(todo_tasks))  # (late claims beyond it are given back)
    nodes = _alive_nodes(ray)
    warm = sum(s.claimed for s in workers.slots)
    late = len(workers.late)
    if verbosity >= 0:
        print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total - todo} already done, {todo} to "
              f"estimate in {len(todo_tasks)} task(s) on Ray ({len(nodes)} node(s), "
              f"{sum(r.get('GPU', 0) for r in nodes):g} GPU, {sum(r.get('CPU', 0) for r in nodes):g} CPU): "
              f"{len(workers.slots)} worker(s) of {workers.gpus:g} GPU + {workers.cpus:g} CPU"
              + (f", {warm} of them warm from the pool" if warm else "")
              + (f", {late} more of the pool joining once up" if late else ""), file=sys.stderr, flush=True)
    job, spec = workers.job, {"common": common, "device": workers.device, "t0": workers.t0}
    runs: dict = {}    # run ObjectRef -> Slot
    polls: dict = {}   # poll ObjectRef -> Slot

    def launch(slot) -> None:
        slot.launched = True
        runs[slot.actor.run.remote(job, spec)] = slot
        polls[slot.actor.poll.remote(job, POLL_S)] = slot

    for slot in list(workers.slots):
        launch(slot)
    queue = deque(range(len(todo_tasks)))
    waiting: list = []     # (worker, "need" | "idle"): its stream asked for a task / has drained
    ended: dict[int, tuple[str, list]] = {}
    live: dict[int, int] = {}   # frames the workers reported for tasks not ended yet
    replacements = args.retries
    skipped_tasks = len(tasks) - len(todo_tasks)  # nothing to do; the others: todo_tasks (it grows where tasks are cut)
    bar = DatasetProgress(todo, n_sequences, verbosity=verbosity)  # sequences counted once all their tasks ended
    for _ in {SequenceParts.key(t) for t in tasks} - {SequenceParts.key(t) for t in todo_tasks}:
        bar.sequence("skipped")
    failures: list[str] = []
    deaths: list[str] = []
    # each sequence's run_summary.json, written once from the parts of all its tasks (a sequence
    # longer than a task had the summary of whichever task ended last: its frames only)
    parts = SequenceParts(todo_tasks, tasks)

    def task_ended(k: int, outcome: str, part: dict | None) -> None:
        done = parts.add(todo_tasks[k], outcome, part)
        if done is None:
            return
        bar.sequence(done[0])
        if done[1] is not None and done[0] != "skipped":
            write_summary(done[1], lambda msg: bar.message(msg) if verbosity >= 0 else None)
    results: list[dict] = []
    ran: list[dict] = []  # each task that ended: its frames, its worker (the job summary's "tasks_run")
    done_frames = shown = 0
    t_all_ended = None  # when the driver learnt that every task had ended

    def on_poll(slot, events, frames) -> bool:
        nonlocal done_frames
        slot.alive = True
        tail.written(slot.name, sum(frames.values()), time.time())
        for k, n in frames.items():
            if k not in ended:
                live[k] = live.get(k, 0) + n
        for ev in events:
            if ev[0] in ("need", "idle"):
                waiting.append((slot, ev[0]))
            elif ev[0] == "ended":
                _, k, outcome, lines, part = ev
                task_ended(k, outcome, part)
                slot.leases.discard(k)
                ended[k] = (outcome, lines)
                ran.append({"task": todo_tasks[k].label, "worker": slot.name, "outcome": outcome,
                            "ended_s": round(time.time() - workers.t0, 3)})  # the tail, read afterwards
                live.pop(k, None)
                failures.extend(lines)
                done_frames += _count_written(todo_tasks[k], since)
            elif ev[0] == "closed":
                return False
        return True

    def on_death(slot, e) -> None:
        nonlocal replacements
        if isinstance(getattr(e, "cause", None), CLIError):
            raise e.cause from None  # a mistake in the common options: every worker would fail
        if isinstance(getattr(e, "cause", None), ImportError):
            raise CLIError(f"a Ray worker cannot import what it needs ({e.cause}); install the same floxels_ext "
                           f"and its dependencies on every node") from None
        back = sorted(slot.leases)
        queue.extendleft(reversed(back))
        slot.leases.clear()
        for k in back:  # their next holder reports its own frames (resume skips the written ones)
            live.pop(k, None)
        workers.drop(slot, ok=False)
        lines = str(e).strip().splitlines()
        deaths.append(f"{slot.name}: {type(e).__name__}: {lines[-1] if lines else e}; {len(back)} task(s) handed "
                      f"to the other workers")
        if verbosity >= 0:
            bar.message(f"floxels: warning: {deaths[-1]}")
        if replacements > 0 and len(ended) < len(todo_tasks):
            replacements -= 1
            launch(workers.add())

    tail = TailShare()  # the workers' rates: each one's share of the work left (ray_tail)

    def cut_at(slot, k: int) -> float | None:
        """Where task ``k``, handed to ``slot`` now, is cut (ray_tail.first_part; None: whole)."""
        if not align or not near_end(len(queue), len(runs)):
            return None  # whole, as first_part would say (without a list of the whole queue each time)
        held = {s.name: sum(max(0, len(todo_tasks[j].todo) - live.get(j, 0)) for j in s.leases) for s in runs.values()}
        queued = [len(todo_tasks[j].todo) for j in queue]
        return first_part(tail, slot.name, len(todo_tasks[k].todo), queued, held, time.time())

    def workers_left() -> bool:  # running, or claimed from the pool and still coming while tasks remain
        return bool(runs) or bool(workers.late) and len(ended) < len(todo_tasks)

    try:
        while workers_left():
            refs = list(runs) + list(polls) + list(workers.late)
            ready, _ = ray.wait(refs, num_returns=1, timeout=2.0)
            if ready:  # everything else ready by now as well
                rest = [r for r in refs if r not in ready]
                ready += ray.wait(rest, num_returns=len(rest), timeout=0)[0] if rest else []
            for ref in ready:
                if ref in workers.late:  # a pooled worker that was still starting: it joins now
                    slot = workers.take_late(ref)
                    if slot is not None and len(ended) < len(todo_tasks):
                        launch(slot)
                    elif slot is not None:
                        workers.drop(slot)
                    elif len(ended) < len(todo_tasks) and not workers_left():
                        launch(workers.add())  # refused, and no worker left: one of the job's own
                elif ref in polls:
                    slot = polls.pop(ref)
                    try:
                        events, frames = ray.get(ref)
                    except ray.exceptions.RayError:
                        continue  # its run's result says what happened
                    if on_poll(slot, events, frames) and slot in runs.values():
                        polls[slot.actor.poll.remote(job, POLL_S)] = slot
                elif ref in runs:
                    slot = runs.pop(ref)
                    for r in [r for r, s in polls.items() if s is slot]:
                        del polls[r]
                    waiting[:] = [w for w in waiting if w[0] is not slot]
                    try:
                        res = ray.get(ref) | {"name": slot.name, "claimed": slot.claimed}
                        res["timeline"]["requested"] = round(slot.requested - workers.t0, 3)
                        results.append(res)
                        workers.finished(slot)
                    except ray.exceptions.RayError as e:
                        on_death(slot, e)
            all_ended = len(ended) == len(todo_tasks)
            if all_ended and t_all_ended is None:
                t_all_ended = time.time()
            for w in sorted(waiting, key=lambda w: len(w[0].leases)):  # a worker holding none first
                slot, what = w
                if queue:
                    k = queue.popleft()
                    first = cut_at(slot, k)
                    if first is not None and (h := halve_task(todo_tasks[k], align, TAIL_SPLIT_FRAMES, first)):
                        todo_tasks[k] = h[0]
                        todo_tasks.append(h[1])
                        parts.add_task(h[1])
                        queue.appendleft(len(todo_tasks) - 1)
                    slot.leases.add(k)
                    answer = (k, todo_tasks[k])
                else:  # a stream asking drains now (its tasks end); a drained one waits for a death's
                    answer = None if all_ended else "wait" if what == "need" else False
                if answer is not False:
                    slot.actor.offer.remote(job, answer)
                    waiting.remove(w)
            if all_ended:  # workers still starting (or waiting for resources: a lost node's) are not needed
                for ref, slot in [(r, s) for r, s in runs.items() if not s.alive]:
                    del runs[ref]
                    for r in [r for r, s in polls.items() if s is slot]:
                        del polls[r]
                    workers.drop(slot)
            if not workers_left():
                break  # all done, or no worker left (none coming): what is left is reported below
            done = done_frames + sum(live.values())
            if done > shown:
                bar.frames(done - shown)
                shown = done
    except BaseException:
        workers.close(ok=False)
        bar.close()
        print("floxels: job stopped; running the same command again writes only the missing frames",
              file=sys.stderr)
        raise
    bar.close()
    unfinished = [todo_tasks[k] for k in range(len(todo_tasks)) if k not in ended]
    for k in range(len(todo_tasks)):  # the summaries of sequences with a task no worker finished: what ran
        if k not in ended:
            task_ended(k, "failed", None)
    for t in unfinished:
        failures.append(f"{t.label}: no worker left to run it; {_missing_report(t, since)}")
    left = sum(remove_temps(d) for d in out_dirs)  # from workers killed mid-write
    wall = time.time() - workers.t0  # from the job's start: the workers' start is in it
    counts = {o: 0 for o in ("done", "skipped", "failed")}
    for outcome, _ in ended.values():
        counts[outcome] += 1
    counts["skipped"] += skipped_tasks
    counts["failed"] += len(unfinished)
    written = done_frames
    print(f"done: {n_sequences} sequences in {skipped_tasks + len(todo_tasks)} task(s) ({counts['done']} done, {counts['skipped']} skipped, "
          f"{counts['failed']} failed), {written} frame(s) written by {len(results) + len(deaths)} worker(s) in "
          f"{wall:.1f} s ({written / wall if wall > 0 else 0:.2f} frames/s), {total - todo} skipped (already done), "
          f"{len(failures)} failure(s)" + (f"; {len(deaths)} worker(s) lost" if deaths else "")
          + (f"; removed {left} temporary file(s) of killed workers" if left else ""), file=sys.stderr)
    report_workers(results, verbosity)
    write_job_summary(Path(args.out) / "ray_job_summary.json", {
        "input": str(args.input), "started": workers.t0, "wall_s": round(wall, 3), "frames_written": written,
        "all_tasks_ended_s": None if t_all_ended is None else round(t_all_ended - workers.t0, 3),
        "frames_per_s": round(written / wall, 3) if wall > 0 else None, "tasks": counts, "tasks_run": ran, "failures": len(failures),
        "lost_workers": deaths, "pool": {"keep_s": workers.keep_s, "key": workers.key, "retired": workers.retired},
        "resources": {"gpus": workers.gpus, "cpus": workers.cpus, "device": workers.device},
        "workers": [{k: v for k, v in r.items() if k != "log"} for r in results]})
    if failures:
        print("failed:", file=sys.stderr)
        for f in failures:
            print(f"  {f}", file=sys.stderr)
        return 1
    return 0
