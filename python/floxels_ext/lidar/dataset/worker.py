"""Tasks through the engine in this process: ``floxels run SEQ`` (one task), the local ``floxels
run DATASET`` and each Ray worker (``ray_runner``).

The run's options are checked once (:func:`run_context`: ``run_args.check_args``; a mistake
there is the user's and stops the run, CLIError); the readers, transform threads and writers
are made once; the tasks (``tasks.Task``) are opened one ahead of the stream
(``sequence.open_sequence``) and their frames go through ``stream.run_stream``
(:func:`run_jobs`). In a dataset (:func:`run_tasks`) a task that cannot be opened (its poses,
its output written with other settings) fails alone; the others go on.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterable

__all__ = ["run_context", "run_jobs", "run_tasks"]


def run_context(args, report: Callable[[str], None], *, shared_pools: bool = True):
    """The run's checked options as a ``sequence.DatasetContext``: device, the method's options,
    the preprocessing settings, the reader plan and, with ``shared_pools``, the reader and
    transform threads every sequence uses (a run of one sequence lets its loader make its own).
    Raises CLIError."""
    import torch

    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.dataset.sequence import DatasetContext
    from floxels_ext.lidar.pipeline.frame_loader import LoaderPools
    from floxels_ext.lidar.pipeline.frame_writer import DRAIN_WRITERS
    from floxels_ext.lidar.pipeline.run_args import (apply_cpu_default, check_args, host_cores, preprocess_settings,
                                                      reader_plan)
    from floxels_ext.lidar.pipeline.stages import Stages
    from floxels_ext.methods import get_method

    device, options = check_args(args, torch)
    # on the CPU, the threads every command uses (a Ray worker has set its own: args.cpu_limit)
    apply_cpu_default(args, device, report if int(getattr(args, "verbosity", 0) or 0) > 0 else None)
    settings = preprocess_settings(args)  # --outlier-below/--outlier-above included
    pre_dev, workers, writers, kind = reader_plan(args, device)
    if kind == "process" and pre_dev is not None:
        raise CLIError("--preprocess-device cuda runs in worker threads; it contradicts --worker-kind process")
    return DatasetContext(args=args, device=device, options=options, settings=settings,
                          pools=LoaderPools(workers, kind) if shared_pools else None, stages=Stages(),
                          pre_device=pre_dev, report=report, workers=workers, writers=writers, kind=kind,
                          drain=min(DRAIN_WRITERS, host_cores(args)),
                          keep_ground=get_method(args.method).wants_ground(options))


def run_jobs(jobs: Iterable, ctx, *, on_frame: Callable[[object, int], None],
             on_finish: Callable[[object], None], write_one=None) -> None:
    """Every job of ``jobs`` (``stream.SeqJob``; an iterable that may open the next one as it
    goes) through the engine with ``ctx``'s readers and a pool of writers; ``on_frame(job, i)``
    and ``on_finish(job)`` as ``stream.run_stream`` calls them. ``write_one``: the one job's
    output writer, held by writer processes from their start (a run of one sequence). Closes
    the shared pools at the end. Raises CLIError for a method that rejects its input."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.dataset.stream import EstimationError, run_stream
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.pipeline.frame_loader import single_threaded_blas
    from floxels_ext.lidar.pipeline.frame_writer import WriterPool
    from floxels_ext.methods import get_method

    args = ctx.args
    try:
        writer = WriterPool(write_one, ctx.stages, workers=ctx.writers, kind=ctx.kind, drain=ctx.drain)
        # with the method on the GPU, numpy's BLAS serves only the per-scan host work: one thread each
        blas = single_threaded_blas() if ctx.device.startswith("cuda") else contextlib.nullcontext()
        with blas:
            run_stream(jobs, writer=writer, method=get_method(args.method), num_scans=args.scans, chunk=args.chunk,
                       device=ctx.device, options=ctx.options, stages=ctx.stages, on_frame_done=on_frame,
                       on_finish=on_finish, report=ctx.report)
    except EstimationError as e:
        raise CLIError(f"{args.method}: {e}") from None
    except MissingDependencyError as e:
        raise CLIError(str(e)) from None
    finally:
        if ctx.pools is not None:
            ctx.pools.close()


def run_tasks(tasks: Iterable, args, *, report: Callable[[str], None],
              on_frame: Callable[[object, int], None] = lambda job, i: None,
              on_sequence: Callable[[object, str, object, list], None] = lambda task, outcome, job, lines: None,
              engine: int | None = None) -> dict:
    """Runs every task of ``tasks`` (an iterable; it may wait for the next task) and returns
    {"written", "failed": [lines], "sequences": {outcome: count}, "stages", "device"}.

    ``on_frame(job, i)``: frame ``i`` of ``job`` written or failed; ``on_sequence(task, outcome,
    job, lines)``: a task ended, ``outcome`` "done", "failed" (``job`` None when it could not be
    opened; ``lines`` name the failures) or "skipped" (nothing to do); each ended task but a
    skipped one has written its ``run_summary.json``. Both may run on the pipeline's threads.
    ``engine``: this pipeline is one of the run's engines (``engines``): a task's summary is
    not written but left in ``job.info["summary"]`` (``summary.summary_part``, also for a
    skipped task) for the run to merge with the other tasks of its sequence."""
    from floxels_ext.errors import CLIError
    from floxels_ext.evaluation.seqio import SequenceFormatError
    from floxels_ext.lidar.dataset.sequence import failure_lines, open_sequence, write_sequence_summary
    from floxels_ext.lidar.io import MissingDependencyError

    ctx = run_context(args, report)
    result = {"written": 0, "failed": [], "sequences": {"done": 0, "skipped": 0, "failed": 0}}
    lock = threading.Lock()

    def ended(task, outcome: str, job, lines=()) -> None:
        with lock:
            result["sequences"][outcome] += 1
            result["failed"] += list(lines)
            if job is not None:
                result["written"] += job.written
        on_sequence(task, outcome, job, list(lines))

    def jobs():
        for task in tasks:
            try:
                # a task of a sequence whose start lines the run has said (engines) says none
                job = open_sequence(task, ctx, say=(lambda msg: None) if task.said else None)
            except (CLIError, SequenceFormatError, MissingDependencyError, OSError, ValueError) as e:
                report(f"floxels: error: {task.label}: {e}")
                ended(task, "failed", None, [f"{task.label}: {e}"])
                continue
            yield job

    def finish(job) -> None:
        task = job.info["task"]
        if engine is not None:
            from floxels_ext.lidar.dataset.summary import summary_part

            job.info["summary"] = summary_part(job, ctx, engine)  # its failures settled
        if not job.todo:
            ended(task, "skipped", job)
            return
        if engine is None:
            write_sequence_summary(job, ctx)
        ended(task, "failed" if job.failed else "done", job, failure_lines(job))

    run_jobs(jobs(), ctx, on_frame=on_frame, on_finish=finish)
    result["stages"] = ctx.stages.as_dict()
    result["device"] = ctx.device
    return result
