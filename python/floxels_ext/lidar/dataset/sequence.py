"""One sequence of ``floxels run DATASET`` in the shared pipeline (``stream``): opening
it as the plain ``floxels run SEQ --frames A:B`` does (frames, poses, resume, output metadata;
the same checks, the same files) and, once its frames are done, its ``run_summary.json`` and
failure lines, as the plain run writes them.

:class:`DatasetContext` holds what every sequence of the job shares: the parsed options, the
method's options, the preprocessing settings, the reader pools and stage times.
"""

from __future__ import annotations

import json
import os
import statistics
from dataclasses import dataclass, field
from pathlib import Path

from floxels_ext.lidar.dataset.stream import SeqJob

__all__ = ["DatasetContext", "open_sequence", "resume_todo", "write_sequence_summary", "failure_lines"]


@dataclass
class DatasetContext:
    args: object           # the run's parsed arguments (the options every sequence shares)
    device: str
    options: dict          # the method's options (check_args)
    settings: object       # Preprocess
    pools: object          # LoaderPools
    stages: object         # Stages
    pre_device: str | None
    report: object         # message -> None (errors and warnings)
    workers: int = 0
    writers: int = 0
    kind: str = "thread"
    extra: dict = field(default_factory=dict)


def open_sequence(task, ctx: DatasetContext) -> SeqJob:
    """The job of ``task`` (``tasks.Task``: a sequence's frames [start, stop) and its output
    directory). Raises CLIError (or the readers' errors) when the sequence cannot run; only
    this task's own temporaries are removed (tasks of one sequence may share its directory)."""
    from floxels_ext.lidar.io.sources import absolute_sources
    from floxels_ext.lidar.pipeline.frame_loader import FrameLoader
    from floxels_ext.lidar.pipeline.frame_writer import FrameOutput
    from floxels_ext.lidar.pipeline.run_inputs import next_pose_reader, output_meta
    from floxels_ext.methods import get_method

    args = ctx.args
    st = _resume_state(task, args, ctx.options, ctx.settings, ctx.report, sweep=True)
    seq, todo = st["seq"], st["todo"]
    meta = output_meta(args, ctx.options, st["settings"], seq)
    write_one = FrameOutput(out_path=st["out_path"], sources=absolute_sources(seq, todo), stamps=st["stamps"],
                            meta=meta, dynamic_threshold=args.dynamic_threshold, compress=args.compress,
                            self_contained=args.self_contained, inputs=st["inputs"])
    loader = FrameLoader(seq, ctx.settings, st["poses"], st["pose_mode"], ctx.report, pools=ctx.pools,
                         pre_device=ctx.pre_device, keep_points=args.self_contained, stages=ctx.stages,
                         keep_ground=get_method(args.method).wants_ground(ctx.options),
                         warn=lambda m: ctx.report(f"floxels: warning: {m}"))

    next_pose = next_pose_reader(seq, st["pose_mode"], st["poses"], loader)

    info = {"out": st["out"], "selected": st["selected"], "skipped": len(st["selected"]) - len(todo),
            "settings": st["settings"], "task": task}
    return SeqJob(label=task.label, seq=seq, loader=loader, todo=todo, write_one=write_one, next_pose=next_pose,
                  times_s=st["times_s"], info=info)


def resume_todo(task, args, options: dict, settings) -> list[str]:
    """The names of ``task``'s frames to estimate by the check :func:`open_sequence` (and
    ``floxels run SEQ``) makes: outputs missing, unreadable, written from other inputs (their
    window's scans, poses or times changed: ``pipeline/resume.py``), or all with --force. Said
    nothing; raises as :func:`open_sequence` does (other settings: CLIError). The driver asks it
    for the tasks whose outputs all exist, which it would otherwise skip unchecked."""
    st = _resume_state(task, args, options, settings, lambda msg: None, sweep=False)
    return [st["seq"].frames[i].name for i in st["todo"]]


def _resume_state(task, args, options: dict, settings, report, *, sweep: bool) -> dict:
    """The sequence of ``task`` opened as the plain run opens one (frames, output directory,
    poses, times, settings) and the frames left to do; ``sweep``: remove this task's own
    temporaries first."""
    from floxels_ext.cli import CLIError
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.io.outputs import cleanup_temps
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.io.sources import InputError, discover_input
    from floxels_ext.lidar.pipeline.run_args import check_out_dir, resume_plan
    from floxels_ext.lidar.pipeline.run_inputs import resolve_poses

    spec = task.seq
    out = Path(task.out_dir)
    try:
        seq = discover_input(spec.path, poses_file=spec.poses, calib=spec.calib, bin_columns=args.bin_columns,
                             ext=args.ext, points_frame=args.points_frame)
        check_out_dir(out, seq)
        selected = list(range(task.start, min(task.stop, len(seq))))
        out.mkdir(parents=True, exist_ok=True)
        if sweep:
            cleanup_temps(out, {f"{seq.frames[i].name}.npz" for i in selected})
        args_seq = _with(args, poses=str(spec.poses) if spec.poses else None,
                         calib=str(spec.calib) if spec.calib else None)
        pose_mode, poses = resolve_poses(seq, args_seq, out, report)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    plan = resume_plan(seq, selected, out, args, options, settings, pose_mode, poses, report, sweep=sweep)
    return {"seq": seq, "out": out, "selected": selected, "pose_mode": pose_mode, "poses": poses, **plan}


def _with(args, **changes):
    import argparse

    ns = argparse.Namespace(**vars(args))
    for k, v in changes.items():
        setattr(ns, k, v)
    return ns


def failure_lines(job: SeqJob) -> list[str]:
    """One line per failed frame, naming its file (as the plain run lists them)."""
    out = []
    for i in sorted(job.failed):
        path = str(job.seq.frames[i].path)
        msg = job.failed[i]
        out.append(msg if msg.startswith(path) else f"{path}: {msg}")
    return out


def write_sequence_summary(job: SeqJob, ctx: DatasetContext) -> Path | None:
    """The sequence's ``run_summary.json`` with the plain run's keys; the stage times are the
    whole stream's so far (the stages are shared by its sequences), its wall time is from the
    moment the stream took the sequence to its last frame written."""
    args, seq, info = ctx.args, job.seq, job.info
    for i, msg in job.loader.errors.items():  # unreadable support scans count as failures too
        if i in info["selected"]:
            job.failed.setdefault(i, msg)
    todo = set(job.todo)
    nonfinite = {i: k for i, k in job.loader.nonfinite.items() if i in todo}
    if nonfinite:
        first = sorted(nonfinite)[:3]
        ctx.report(f"floxels: warning: {len(nonfinite)} frame(s) have rows with NaN/inf coordinates (their flow "
                   f"is NaN): " + ", ".join(f"{seq.frames[i].path.name} ({nonfinite[i]} rows)" for i in first)
                   + (" ..." if len(nonfinite) > 3 else ""))
    wall = max(0.0, job.t_end - job.t_start)
    times = job.times
    lines = failure_lines(job)
    summary = {"input": str(seq.root), "out": str(info["out"]), "method": args.method, "device": ctx.device,
               "frames": len(seq), "selected": len(info["selected"]), "written": job.written,
               "skipped": info["skipped"], "failed": len(job.failed),
               "failures": [{"frame": seq.frames[i].name, "message": m} for i, m in zip(sorted(job.failed), lines)],
               "nonfinite_rows": {seq.frames[i].name: k for i, k in sorted(nonfinite.items())},
               # as the plain run: frames with points but none left to optimise (also in "failed"),
               # frames whose few far points blow up a distance transform
               "no_points_after_crop": [seq.frames[i].name for i in sorted(job.loader.empty_crop) if i in todo],
               "far_outliers": [seq.frames[i].name for i in sorted(job.loader.stray) if i in todo],
               "wall_s": round(wall, 4),
               "frames_per_s": round(job.written / wall, 3) if wall > 0 and job.written else None,
               "s_per_frame_mean": round(statistics.mean(times), 6) if times else None,
               "s_per_frame_median": round(statistics.median(times), 6) if times else None,
               "stages_s": ctx.stages.as_dict(), "workers": ctx.workers, "writers": ctx.writers,
               "worker_kind": ctx.kind, "writer_kind": ctx.kind, "preprocess_device": ctx.pre_device or "cpu",
               "settings": json.loads(json.dumps(info["settings"], default=str)),
               "dataset_stream": True}
    path = Path(info["out"]) / "run_summary.json"
    try:
        from floxels_ext.output_paths import replace_atomically

        text = json.dumps(summary, indent=2) + "\n"
        replace_atomically(path.with_name(f".{path.name}.{os.getpid()}.tmp"), path, lambda t: t.write_text(text))
    except OSError as e:
        ctx.report(f"floxels: warning: cannot write the summary {path}: {e}")
        return None
    return path
