"""Tasks of a dataset through one pipeline in this process: the local ``floxels run DATASET``
and each Ray worker (``ray_runner``) run :func:`run_tasks`.

The run's options are checked once (``run_args.check_args``: a mistake there is the user's and
stops the job, CLIError); the readers, transform threads and writers are made once; the tasks
(``tasks.Task``) are opened one ahead of the stream (``sequence.open_sequence``) and
their frames go through ``stream.run_stream``. A task that cannot be opened (its
poses, its output written with other settings) fails alone; the others go on.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable

__all__ = ["run_tasks"]


def run_tasks(tasks: Iterable, args, *, report: Callable[[str], None],
              on_frame: Callable[[object, int], None] = lambda job, i: None,
              on_sequence: Callable[[object, str, object, list], None] = lambda task, outcome, job, lines: None
              ) -> dict:
    """Runs every task of ``tasks`` (an iterable; it may wait for the next task) and returns
    {"written", "failed": [lines], "sequences": {outcome: count}, "stages"}.

    ``on_frame(job, i)``: frame ``i`` of ``job`` written or failed; ``on_sequence(task, outcome,
    job, lines)``: a task ended, ``outcome`` "done", "failed" (``job`` None when it could not be
    opened; ``lines`` name the failures) or "skipped" (nothing to do). Both may run on the
    pipeline's threads."""
    import threading

    import torch

    from floxels_ext.cli import CLIError
    from floxels_ext.evaluation.seqio import SequenceFormatError
    from floxels_ext.lidar.dataset.sequence import DatasetContext, failure_lines, open_sequence, write_sequence_summary
    from floxels_ext.lidar.dataset.stream import run_stream
    from floxels_ext.lidar.pipeline.frame_loader import LoaderPools, Stages, single_threaded_blas
    from floxels_ext.lidar.pipeline.frame_writer import DRAIN_WRITERS, WriterPool
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.pipeline.estimate_loop import EstimationError
    from floxels_ext.lidar.pipeline.run_args import (apply_cpu_default, check_args, host_cores, preprocess_settings,
                                                      reader_plan)
    from floxels_ext.methods import get_method

    device, options = check_args(args, torch)
    # on the CPU, the threads the plain run uses (a Ray worker has set its own: args.cpu_limit)
    apply_cpu_default(args, device, report if int(getattr(args, "verbosity", 0) or 0) > 0 else None)
    settings = preprocess_settings(args)  # the plain run's, --outlier-below/--outlier-above included
    pre_dev, workers, writers, kind = reader_plan(args, device)
    if kind == "process" and pre_dev is not None:
        raise CLIError("--preprocess-device cuda runs in worker threads; it contradicts --worker-kind process")
    stages = Stages()
    result = {"written": 0, "failed": [], "sequences": {"done": 0, "skipped": 0, "failed": 0}}
    lock = threading.Lock()

    def ended(task, outcome: str, job, lines=()) -> None:
        with lock:
            result["sequences"][outcome] += 1
            result["failed"] += list(lines)
            if job is not None:
                result["written"] += job.written
        on_sequence(task, outcome, job, list(lines))

    pools = LoaderPools(workers, kind)
    try:
        writer = WriterPool(None, stages, workers=writers, kind=kind, drain=min(DRAIN_WRITERS, host_cores(args)))
    except BaseException:
        pools.close()
        raise
    ctx = DatasetContext(args=args, device=device, options=options, settings=settings, pools=pools, stages=stages,
                         pre_device=pre_dev, report=report, workers=workers, writers=writers, kind=kind)

    def jobs():
        for task in tasks:
            try:
                job = open_sequence(task, ctx)
            except (CLIError, SequenceFormatError, MissingDependencyError, OSError, ValueError) as e:
                report(f"floxels: error: {task.label}: {e}")
                ended(task, "failed", None, [f"{task.label}: {e}"])
                continue
            yield job

    def finish(job) -> None:
        task = job.info["task"]
        if not job.todo:
            ended(task, "skipped", job)
            return
        write_sequence_summary(job, ctx)
        lines = failure_lines(job)
        ended(task, "failed" if job.failed else "done", job, lines)

    blas = single_threaded_blas() if device.startswith("cuda") else contextlib.nullcontext()
    try:
        with blas:
            run_stream(jobs(), writer=writer, method=get_method(args.method), num_scans=args.scans, chunk=args.chunk,
                       device=device, options=options, stages=stages, tpool=pools.move, on_frame_done=on_frame,
                       on_finish=finish, report=report)
    except EstimationError as e:
        raise CLIError(f"{args.method}: {e}") from None
    except MissingDependencyError as e:
        raise CLIError(str(e)) from None
    finally:
        pools.close()
    result["stages"] = stages.as_dict()
    result["device"] = device
    return result
