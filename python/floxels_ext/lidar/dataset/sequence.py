"""One sequence of ``floxels run`` in the engine (``stream``): opening it (frames, poses,
resume, output metadata, the reader), its failures and, once its frames are done, its
``run_summary.json``. ``floxels run SEQ`` and every sequence (or frame range of one) of a
dataset go through these functions, so both check, resume and summarise alike.

:class:`DatasetContext` holds what every sequence of the run shares: the parsed options, the
method's options, the preprocessing settings, the reader pools and stage times.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from floxels_ext.lidar.dataset.stream import SeqJob
from floxels_ext.lidar.dataset.summary import failure_lines, settle_failures  # noqa: F401 (this module's API)

__all__ = ["DatasetContext", "open_sequence", "resume_todo", "settle_failures", "failure_lines",
           "write_sequence_summary"]

# what the start line says of the ego-motion when no pose file names it
_EGO_MOTION = {"seqio": "points already in one frame", "identity": "none (--no-ego-motion)",
               "frame": "per-frame poses", "table": "KISS-ICP odometry"}


@dataclass
class DatasetContext:
    args: object           # the run's parsed arguments (the options every sequence shares)
    device: str
    options: dict          # the method's options (check_args)
    settings: object       # Preprocess
    pools: object          # LoaderPools shared by the sequences; None: each loader makes its own
    stages: object         # Stages
    pre_device: str | None
    report: object         # message -> None (errors and warnings)
    workers: int = 0
    writers: int = 0
    kind: str = "thread"
    drain: int = 0         # writer threads that write what is queued at the end
    keep_ground: bool = False  # the method reads each scan's removed ground
    extra: dict = field(default_factory=dict)


def open_sequence(task, ctx: DatasetContext, say=None) -> SeqJob:
    """The job of ``task`` (``tasks.Task``: a sequence's frames [start, stop) and its output
    directory). Raises CLIError (or the readers' errors) when the sequence cannot run; only
    this task's own temporaries are removed (tasks of one sequence may share its directory).
    ``say(line)``: the sequence's start lines (temporaries removed, resume notes, what is to
    do, where frame times come from), as ``floxels run SEQ`` prints them; without it, resume
    notes go to ``ctx.report`` and the rest is not said."""
    from floxels_ext.lidar.io.sources import absolute_sources
    from floxels_ext.lidar.pipeline.frame_loader import FrameLoader
    from floxels_ext.lidar.pipeline.frame_writer import FrameOutput
    from floxels_ext.lidar.pipeline.run_inputs import next_pose_reader, output_meta

    args = ctx.args
    st = _resume_state(task, args, ctx.options, ctx.settings, ctx.report, sweep=True, say=say)
    seq, todo, selected = st["seq"], st["todo"], st["selected"]
    if say is not None:
        say(f"{seq.root}: {len(seq)} frames ({seq.kind}), {len(selected)} selected, {len(selected) - len(todo)} "
            f"already done, {len(todo)} to estimate with {args.method} on {ctx.device} "
            f"(ego-motion: {seq.pose_source or _EGO_MOTION[st['pose_mode']]})")
        if st["times_source"] is not None:
            say(f"frame times from {st['times_source']}: window offsets follow them, flow stays per frame step")
    meta = output_meta(args, ctx.options, st["settings"], seq)
    write_one = FrameOutput(out_path=st["out_path"], sources=absolute_sources(seq, todo), stamps=st["stamps"],
                            meta=meta, dynamic_threshold=args.dynamic_threshold, compress=args.compress,
                            self_contained=args.self_contained, inputs=st["inputs"])
    loader = FrameLoader(seq, ctx.settings, st["poses"], st["pose_mode"], ctx.report, pools=ctx.pools,
                         workers=ctx.workers, kind=ctx.kind, pre_device=ctx.pre_device,
                         keep_points=args.self_contained, stages=ctx.stages, keep_ground=ctx.keep_ground,
                         warn=lambda m: ctx.report(f"floxels: warning: {m}"))

    next_pose = next_pose_reader(seq, st["pose_mode"], st["poses"], loader)

    info = {"out": st["out"], "selected": selected, "skipped": len(selected) - len(todo),
            "settings": st["settings"], "task": task}
    return SeqJob(label=task.label, seq=seq, loader=loader, todo=todo, write_one=write_one, next_pose=next_pose,
                  times_s=st["times_s"], info=info)


def resume_todo(task, args, options: dict, settings) -> list[str]:
    """The names of ``task``'s frames to estimate by the check :func:`open_sequence` makes:
    outputs missing, unreadable, written from other inputs (their window's scans, poses or
    times changed: ``pipeline/resume.py``), or all with --force. Said nothing; raises as
    :func:`open_sequence` does (other settings: CLIError). The dataset driver asks it for the
    tasks whose outputs all exist, which it would otherwise skip unchecked."""
    st = _resume_state(task, args, options, settings, lambda msg: None, sweep=False)
    return [st["seq"].frames[i].name for i in st["todo"]]


def _resume_state(task, args, options: dict, settings, report, *, sweep: bool, say=None) -> dict:
    """The sequence of ``task`` opened (frames, output directory, poses, times, settings) and
    the frames left to do; ``sweep``: remove this task's own temporaries first."""
    from floxels_ext.errors import CLIError
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.io.outputs import cleanup_temps
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.io.sources import InputError, discover_input
    from floxels_ext.lidar.pipeline.resume import resume_plan
    from floxels_ext.lidar.pipeline.run_args import check_out_dir, parse_frame_range
    from floxels_ext.lidar.pipeline.run_inputs import resolve_poses

    spec = task.seq
    out = Path(task.out_dir)
    try:
        seq = task.found if task.found is not None else \
            discover_input(spec.path, poses_file=spec.poses, calib=spec.calib, bin_columns=args.bin_columns,
                           ext=args.ext, points_frame=args.points_frame)
        check_out_dir(out, seq)
        selected = list(range(task.start, min(task.stop, len(seq))))
        out.mkdir(parents=True, exist_ok=True)
        if sweep:
            stale = cleanup_temps(out, {f"{seq.frames[i].name}.npz" for i in selected})
            if stale and say is not None:
                say(f"removed {stale} temporary file(s) left by an interrupted run")
        args_seq = _with(args, poses=str(spec.poses) if spec.poses else None,
                         calib=str(spec.calib) if spec.calib else None)
        pose_mode, poses = resolve_poses(seq, args_seq, out, report)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    plan = resume_plan(seq, selected, out, args, options, settings, pose_mode, poses, report, resume_report=say,
                       sweep=sweep)
    # the frames the run selects (--frames) of which this task is a part (a Ray task's range)
    run_range = parse_frame_range(getattr(args, "frames", None), len(seq))
    return {"seq": seq, "out": out, "selected": selected, "pose_mode": pose_mode, "poses": poses,
            "run_range": run_range, **plan}


def _with(args, **changes):
    import argparse

    ns = argparse.Namespace(**vars(args))
    for k, v in changes.items():
        setattr(ns, k, v)
    return ns


def write_sequence_summary(job: SeqJob, ctx: DatasetContext, wall: float | None = None) -> Path | None:
    """The sequence's ``run_summary.json`` (``task.summary``, default in its output directory)
    from this one job (``summary``: the format, and the merge of several tasks' parts); returns
    its path (None when it could not be written: said as a warning). The stage times are the
    whole stream's so far (the sequences of a dataset share them); ``wall``: the run's seconds,
    default from the moment the stream took the sequence to its last frame written."""
    from floxels_ext.lidar.dataset.summary import summary_part, write_summary

    return write_summary(summary_part(job, ctx), ctx.report, wall=wall)
