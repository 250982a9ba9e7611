"""``floxels run`` on this machine: one sequence (:func:`run_sequence`) or a dataset
(:func:`run_dataset`), both through the engine (``worker``); they differ only in what they
print. One sequence: its start line, a progress bar naming each frame, ``done: ...`` and the
failed frames; a dataset: one progress bar counting frames and sequences, ``dataset done: ...``.
With ``--engines N`` (``engines``) both print the same from what every engine reports, and a
sequence's one summary is merged over its tasks (``summary``).

Per frame: read the file (``floxels_ext.lidar.io``), crop and remove the ground in the scan's own
sensor frame (``floxels_ext.lidar.preprocess``), bring the scans of its window into one frame
with the poses (ego-motion compensation), estimate the flow with the chosen method and write
``OUT_DIR/<frame name>.npz`` (see :data:`floxels_ext.lidar.io.outputs.OUTPUT`). Frames already
written with the same settings from the same inputs are skipped, so an interrupted run continues
where it stopped; frames whose window's scans, poses or times changed are recomputed
(:mod:`floxels_ext.lidar.pipeline.resume`).

Coordinates: the scans of a window are compensated in a world frame re-centred near the chunk
being processed (world axes, so float32 stays precise with city-scale AV2 coordinates; the
origin on a 10 m grid, so the flow does not depend on where chunks start: ``layout``); the
flow is then rotated into the target frame's *native* coordinates, those its file stores (the
sensor frame for plain files, the ego frame for AV2, the world frame for a ``floxels simulate``
sequence). Flow is ego-motion compensated: static points have zero flow. ``ego_motion`` holds
the rigid motion of the frame itself to the next one, for those who need raw displacements.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

__all__ = ["run_sequence", "run_dataset"]


def run_sequence(args, engines=None, task_frames: int = 0, align: int = 1) -> int:
    """``floxels run SEQ``: one task of the sequence's selected frames through the engine; with
    ``engines`` (``engines.Engines``), cut into tasks of ``task_frames`` frames for them
    (:func:`_sequence_on_engines`) when more than one of them has frames to do; fewer frames a
    task where the frames to do are few for the engines (``tasks.balanced_task_size``, multiples
    of ``align``), unless ``--task-frames`` says."""
    from floxels_ext.lidar.dataset.sequence import failure_lines, open_sequence, write_sequence_summary
    from floxels_ext.lidar.dataset.worker import run_context, run_jobs
    from floxels_ext.lidar.pipeline.progress import Progress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    bar: Progress | None = None

    def report(msg: str) -> None:  # errors and warnings: shown at every verbosity
        (bar.message(msg) if bar is not None else print(msg, file=sys.stderr, flush=True))

    def info(msg: str) -> None:
        if verbosity >= 0:
            report(msg)

    def frame_report(msg: str) -> None:  # with -q a frame's error is said once, in the final list
        if verbosity >= 0 or not msg.startswith("floxels: error:"):
            report(msg)

    ctx = run_context(args, frame_report, shared_pools=False)
    task = _sequence_task(args)
    job = open_sequence(task, ctx, say=info)  # the start lines, temporaries swept, what is left to do
    if engines is not None:
        from floxels_ext.lidar.dataset.tasks import balanced_task_size, split_task

        todo = {job.seq.frames[i].name for i in job.todo}
        if getattr(args, "task_frames", None) is None:
            task_frames = balanced_task_size(len(todo), engines.n, task_frames, align)
        planned = split_task(task, task_frames)
        run = [t for t in planned if todo.intersection(t.names)]
        if len(run) > 1:
            job.loader.close()
            return _sequence_on_engines(args, ctx, run, planned, len(todo), engines)
    try:
        bar = Progress(len(job.todo), verbosity=verbosity)
        t0 = time.perf_counter()
        try:
            run_jobs([job], ctx, on_frame=lambda job, i: bar.update(note=job.seq.frames[i].name),
                     on_finish=lambda job: None, write_one=job.write_one)
        finally:
            bar.close()
    finally:
        job.loader.close()  # its own readers
    wall = time.perf_counter() - t0
    summary_path = write_sequence_summary(job, ctx, wall=wall)
    line = _done_line(job.written, job.info["skipped"], len(job.failed), len(job.loader.empty_crop), job.times)
    return _finish(line, verbosity, "stages (s)", ctx.stages.as_dict(), summary_path, "failed frames:",
                   failure_lines(job))


def _done_line(written: int, skipped: int, failed: int, empty_crop: int, times: list) -> str:
    """``floxels run SEQ``'s final line."""
    line = f"done: {written} frame(s) written, {skipped} skipped (already done), {failed} failed"
    if empty_crop:
        line += f" ({empty_crop} with no point left after cropping)"
    if times:
        line += (f"; {statistics.mean(times):.2f} s/frame mean, {statistics.median(times):.2f} s median, "
                 f"{sum(times):.1f} s total")
    return line


def _finish(line: str, verbosity: int, stages_label: str, stages: dict | None, summary_path, header: str,
            failures: list) -> int:
    """Prints the final line (also with -q: the help promises it), the stage times with -v and
    the failures; returns the exit status."""
    print(line, file=sys.stderr)
    if verbosity >= 1 and stages is not None:
        print(f"{stages_label}: " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
              + f"; summary: {summary_path}", file=sys.stderr)
    return _failures(header, failures)


def _failures(header: str, lines: list) -> int:
    """Prints the failures under ``header``; the exit status (1 if any)."""
    if not lines:
        return 0
    print(header, file=sys.stderr)
    for msg in lines:
        print(f"  {msg}", file=sys.stderr)
    return 1


def _sequence_on_engines(args, ctx, run: list, planned: list, todo: int, engines) -> int:
    """``floxels run SEQ`` on several engines (``engines``): the same progress bar, ``done:``
    line, failed frames and one ``run_summary.json`` for the whole run, whichever engine ran
    which frames."""
    from floxels_ext.lidar.dataset.summary import SequenceParts, render, write_summary
    from floxels_ext.lidar.pipeline.progress import Progress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    parts = SequenceParts(run, planned)
    got: list = [None, []]  # the merged part, the failures of tasks that could not be opened
    bar = Progress(todo, verbosity=verbosity)

    def on_ended(task, outcome, lines, part):
        if part is None:
            got[1] += lines
        done = parts.add(task, outcome, part)
        if done is not None:
            got[0] = done[1]

    def say(msg: str) -> None:  # with -q a frame's error is said once, in the final list
        if verbosity >= 0 or not msg.startswith("floxels: error:"):
            bar.message(msg)

    t0 = time.perf_counter()
    try:
        res = engines.run(run, args, report=say, on_frame=lambda task, name, ok: bar.update(note=name),
                          on_ended=on_ended)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    merged, unopened = got
    if merged is None:  # no task could be opened
        merged = {"written": 0, "skipped": 0, "failures": {}, "empty_crop": {}, "times": [], "stages": {}}
    if res["stages"]:  # the whole run's (the parts have each engine's up to its last task's end)
        merged["stages"] = res["stages"]
    merged["engines_start"] = res["start"]
    summary_path = write_summary(merged, say, wall=wall) if "path" in merged else None
    failures = [line for _, (_, line) in sorted(merged["failures"].items())] + unopened
    line = _done_line(merged["written"], merged["skipped"], len(failures), len(merged["empty_crop"]), merged["times"])
    line += f"; {res['engines']} engine(s), {merged['written'] / wall if wall > 0 else 0:.2f} frames/s"
    if res["lost"]:
        line += f"; {len(res['lost'])} engine(s) lost, their tasks redone by the others"
    stages = render(merged, wall)["stages_s"] if "path" in merged else None
    return _finish(line, verbosity, "stages (s, summed over the engines)", stages, summary_path, "failed frames:",
                   failures)


def _sequence_task(args):
    """The task of ``floxels run SEQ``: the sequence's frames that ``--frames`` selects, with
    the checks made before any frame is read (the sequence found, at least 2 frames, --out and
    --summary usable). Raises CLIError."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.dataset.tasks import SequenceSpec, Task
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.io.sources import InputError, discover_input
    from floxels_ext.lidar.pipeline.run_args import check_out_dir, parse_frame_range
    from floxels_ext.output_paths import check_output_file

    try:
        seq = discover_input(args.input, poses_file=args.poses, calib=args.calib, bin_columns=args.bin_columns,
                             ext=args.ext, points_frame=args.points_frame)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    if len(seq) < 2:
        raise CLIError(f"{seq.root} holds {len(seq)} frame; scene flow needs at least 2")
    out = Path(args.out)
    check_out_dir(out, seq)
    if args.summary:  # checked before the work, like every output path
        check_output_file(args.summary, "--summary", "run_summary.json")
    start, stop = parse_frame_range(args.frames, len(seq))
    spec = SequenceSpec(Path(args.input), Path("."), Path(args.poses) if args.poses else None,
                        Path(args.calib) if args.calib else None)
    return Task(spec, out, start, stop, [f.name for f in seq.frames[start:stop]],
                frame_paths=[str(f.path) for f in seq.frames[start:stop]],
                summary=Path(args.summary) if args.summary else None, selection=(start, stop), found=seq)


def run_dataset(tasks, args, n_sequences: int, engines=None) -> int:
    """Every sequence of a dataset through one pipeline in this process (``worker.run_tasks``),
    with one progress bar for the dataset; with ``engines`` (``engines.Engines``) and more than
    one task to do, through them, one summary per sequence."""
    from floxels_ext.lidar.dataset.worker import run_tasks
    from floxels_ext.lidar.pipeline.progress import DatasetProgress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    total = sum(len(t.names) for t in tasks)
    todo = sum(len(t.todo) for t in tasks)
    if verbosity >= 0:
        print(f"dataset {args.input}: {n_sequences} sequences, {total} frames, {total - todo} already done",
              file=sys.stderr, flush=True)
    run = [t for t in tasks if t.todo]
    bar = DatasetProgress(todo, n_sequences, verbosity=verbosity)

    def report(msg: str) -> None:  # with -q a frame's or task's error is said once, in the final list
        if verbosity >= 0 or not msg.startswith("floxels: error:"):
            bar.message(msg)

    for _ in range(n_sequences - len({(t.out_dir, t.summary) for t in run})):  # nothing left to do
        bar.sequence("skipped")
    t0 = time.perf_counter()
    try:
        if engines is not None and len(run) > 1:
            res = _dataset_on_engines(run, tasks, args, engines, report, bar)
        else:
            res = run_tasks(run, args, report=report, on_frame=lambda job, i: bar.frames(1),
                            on_sequence=lambda task, outcome, job, lines: bar.sequence(outcome))
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    seqs = dict(res["sequences"])
    seqs["skipped"] += n_sequences - sum(res["sequences"].values())
    print(f"dataset done: {n_sequences} sequences ({seqs['done']} done, {seqs['skipped']} skipped, {seqs['failed']} "
          f"failed), {res['written']} frame(s) written in {wall:.1f} s"
          + (f" ({res['written'] / wall:.2f} frames/s)" if wall > 0 and res["written"] else "")
          + f", {len(res['failed'])} failure(s)" + (f"; {res['engines']} engine(s)" if "engines" in res else "")
          + (f", {len(res['lost'])} lost (their tasks redone by the others)" if res.get("lost") else "")
          + f"; outputs in {args.out}", file=sys.stderr)
    return _failures("failed:", res["failed"])


def _dataset_on_engines(run: list, planned: list, args, engines, report, bar) -> dict:
    """The tasks of a dataset on several engines: a sequence's summary is written, and counted
    on the bar, once its last task has ended. Returns what ``worker.run_tasks`` returns, plus
    the engines and those lost."""
    from floxels_ext.lidar.dataset.summary import SequenceParts, write_summary

    parts = SequenceParts(run, planned)
    res = {"written": 0, "failed": [], "sequences": {"done": 0, "skipped": 0, "failed": 0}}

    def on_ended(task, outcome, lines, part):
        if part is None:  # it could not be opened; an opened task's lines are its sequence's below
            res["failed"] += lines
        done = parts.add(task, outcome, part)
        if done is None:
            return
        seq_outcome, merged = done
        if merged is not None:
            res["written"] += merged["written"]
            res["failed"] += [line for _, (_, line) in sorted(merged["failures"].items())]
            if seq_outcome != "skipped":
                write_summary(merged, report)
        res["sequences"][seq_outcome] += 1
        bar.sequence(seq_outcome)

    r = engines.run(run, args, report=report, on_frame=lambda task, name, ok: bar.frames(1), on_ended=on_ended)
    return res | r
