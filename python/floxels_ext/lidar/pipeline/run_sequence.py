"""``floxels run SEQ --out OUT_DIR``: scene flow for every frame of one real lidar sequence (the
command's options are in ``floxels_ext.lidar.run``; a dataset goes to ``lidar.dataset.run``).

Per frame: read the file (``floxels_ext.lidar.io``), crop and remove the ground in the
scan's own sensor frame (``floxels_ext.lidar.preprocess``), bring the scans of its window into one
frame with the poses (ego-motion compensation), estimate the flow with the chosen method and
write ``OUT_DIR/<frame name>.npz`` (see :data:`floxels_ext.lidar.io.outputs.OUTPUT`). Frames already
written with the same settings from the same inputs are skipped, so an interrupted run continues
where it stopped; frames whose window's scans, poses or times changed are recomputed
(:mod:`floxels_ext.lidar.pipeline.resume`).
Reading and preprocessing run ahead on reader threads and writing on writer threads while the
method optimises (:mod:`floxels_ext.lidar.pipeline.estimate_loop`).

Coordinates: the scans of a window are compensated in a world frame re-centred near the chunk
being processed (world axes, so float32 stays precise with city-scale AV2 coordinates; the
origin on a 10 m grid, so the flow does not depend on where chunks start); the
flow is then rotated into the target frame's *native* coordinates, those its file stores (the
sensor frame for plain files, the ego frame for AV2, the world frame for a ``floxels simulate``
sequence). Flow is ego-motion compensated: static points have zero flow. ``ego_motion`` holds
the rigid motion of the frame itself to the next one, for those who need raw displacements.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

__all__ = ["run_sequence"]


def run_sequence(args) -> int:
    """``floxels run SEQ``: one sequence (``lidar.run`` sends a dataset to ``dataset.run`` first)."""
    import torch

    from floxels_ext.lidar.pipeline.run_args import (apply_cpu_default, check_args, check_out_dir, host_cores,
                                                      parse_frames, preprocess_settings, reader_plan, resume_plan)
    from floxels_ext.lidar.pipeline.run_inputs import next_pose_reader, output_meta, resolve_poses

    from floxels_ext.cli import CLIError
    from floxels_ext.lidar.io import MissingDependencyError
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.io.sources import InputError, absolute_sources, discover_input
    from floxels_ext.methods import available_methods, get_method
    from floxels_ext.lidar.pipeline.frame_writer import DRAIN_WRITERS, FrameOutput, WriterPool
    from floxels_ext.lidar.io.outputs import cleanup_temps
    from floxels_ext.lidar.pipeline.frame_loader import FrameLoader, Stages, single_threaded_blas
    from floxels_ext.lidar.pipeline.estimate_loop import EstimationError, run_pipeline
    from floxels_ext.lidar.pipeline.progress import Progress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    if args.list_methods:
        for name in available_methods():
            print(f"{name:<12} {get_method(name).description}")
        return 0
    device, options = check_args(args, torch)
    apply_cpu_default(args, device, (lambda m: print(m, file=sys.stderr)) if verbosity > 0 else None)
    settings = preprocess_settings(args)
    out = Path(args.out)
    try:
        seq = discover_input(args.input, poses_file=args.poses, calib=args.calib, bin_columns=args.bin_columns,
                             ext=args.ext, points_frame=args.points_frame)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    if len(seq) < 2:
        raise CLIError(f"{seq.root} holds {len(seq)} frame; scene flow needs at least 2")
    check_out_dir(out, seq)
    if args.summary:  # checked before the work, like every output path
        from floxels_ext.output_paths import check_output_file

        check_output_file(args.summary, "--summary", "run_summary.json")
    selected = parse_frames(args.frames, len(seq))
    out.mkdir(parents=True, exist_ok=True)
    stale = cleanup_temps(out, {f"{seq.frames[i].name}.npz" for i in selected})
    bar: Progress | None = None

    def report(msg: str) -> None:  # errors and warnings: shown at every verbosity
        (bar.message(msg) if bar is not None else print(msg, file=sys.stderr, flush=True))

    def info(msg: str) -> None:
        if verbosity >= 0:
            report(msg)

    if stale:
        info(f"removed {stale} temporary file(s) left by an interrupted run")
    try:
        pose_mode, poses = resolve_poses(seq, args, out, report)
    except (PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    plan = resume_plan(seq, selected, out, args, options, settings, pose_mode, poses, report, resume_report=info)
    run_settings, out_path, stamps, times_s, times_source, inputs, todo = (
        plan[k] for k in ("settings", "out_path", "stamps", "times_s", "times_source", "inputs", "todo"))
    skipped = len(selected) - len(todo)
    info(f"{seq.root}: {len(seq)} frames ({seq.kind}), {len(selected)} selected, {skipped} already done, "
         f"{len(todo)} to estimate with {args.method} on {device} "
         f"(ego-motion: {seq.pose_source or {'seqio': 'points already in one frame', 'identity': 'none (--no-ego-motion)', 'frame': 'per-frame poses', 'table': 'KISS-ICP odometry'}[pose_mode]})")

    if times_source is not None:
        info(f"frame times from {times_source}: window offsets follow them, flow stays per frame step")
    meta = output_meta(args, options, run_settings, seq)
    write_one = FrameOutput(out_path=out_path, sources=absolute_sources(seq, todo), stamps=stamps, meta=meta,
                            dynamic_threshold=args.dynamic_threshold, compress=args.compress,
                            self_contained=args.self_contained, inputs=inputs)

    pre_dev, workers, writers, kind = reader_plan(args, device)
    if kind == "process" and pre_dev is not None:
        raise CLIError("--preprocess-device cuda runs in worker threads; it contradicts --worker-kind process")
    stages = Stages()
    writer = WriterPool(write_one, stages, workers=writers, kind=kind, drain=min(DRAIN_WRITERS, host_cores(args)))
    try:
        # a frame's error as it happens; with -q the final list is the one place that names it
        loader = FrameLoader(seq, settings, poses, pose_mode, info, workers=workers, kind=kind, pre_device=pre_dev,
                             keep_points=args.self_contained, stages=stages,
                             keep_ground=get_method(args.method).wants_ground(options),
                             warn=lambda m: report(f"floxels: warning: {m}"))
    except BaseException:
        writer.close()
        raise

    next_pose = next_pose_reader(seq, pose_mode, poses, loader)

    bar = Progress(len(todo), verbosity=verbosity)
    t0 = time.perf_counter()
    # with the method on the GPU, numpy's BLAS serves only the per-scan host work: one thread each
    blas = single_threaded_blas() if device.startswith("cuda") else contextlib.nullcontext()
    try:
        with blas:
            res = run_pipeline(loader=loader, writer=writer, method=get_method(args.method), todo=todo, n=len(seq),
                               num_scans=args.scans, chunk=args.chunk, device=device, options=options,
                               next_pose=next_pose, times_s=times_s,
                               on_written=lambda i: bar.update(note=seq.frames[i].name))
    except EstimationError as e:
        raise CLIError(f"{args.method}: {e}") from None
    except MissingDependencyError as e:
        raise CLIError(str(e)) from None
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    failed = res["failed"]
    for i, msg in loader.errors.items():  # unreadable support scans count as failures too
        failed.setdefault(i, msg)
    written = res["written"]
    nonfinite = {i: k for i, k in loader.nonfinite.items() if i in set(todo)}
    if nonfinite:
        first = sorted(nonfinite)[:3]
        report(f"floxels: warning: {len(nonfinite)} frame(s) have rows with NaN/inf coordinates (their flow is "
               f"NaN): " + ", ".join(f"{seq.frames[i].path.name} ({nonfinite[i]} rows)" for i in first)
               + (" ..." if len(nonfinite) > 3 else ""))
    times = res["times"]
    msgs = {}
    for i in sorted(failed):
        path = str(seq.frames[i].path)
        msgs[i] = failed[i] if failed[i].startswith(path) else path + ": " + failed[i]
    summary = {"input": str(seq.root), "out": str(out), "method": args.method, "device": device,
               "frames": len(seq), "selected": len(selected), "written": written, "skipped": skipped,
               "failed": len(failed), "failures": [{"frame": seq.frames[i].name, "message": msgs[i]} for i in msgs],
               "nonfinite_rows": {seq.frames[i].name: k for i, k in sorted(nonfinite.items())},
               # frames with points but none left to optimise (counted in "failed" too)
               "no_points_after_crop": [seq.frames[i].name for i in sorted(loader.empty_crop)],
               # frames whose few far points blow up a distance transform (warned about once)
               "far_outliers": [seq.frames[i].name for i in sorted(loader.stray)],
               # per estimated frame: points kept (optimised), removed as ground, removed as
               # outliers (far below the ground / far above the sensor), cropped (or non-finite)
               "point_classes": {seq.frames[i].name: c for i, c in sorted(loader.counts.items()) if i in set(todo)},
               "outliers": sum(c["outlier"] for i, c in loader.counts.items() if i in set(todo)),
               "wall_s": round(wall, 4), "frames_per_s": round(written / wall, 3) if wall > 0 and written else None,
               "s_per_frame_mean": round(statistics.mean(times), 6) if times else None,
               "s_per_frame_median": round(statistics.median(times), 6) if times else None,
               "stages_s": stages.as_dict(), "workers": workers, "writers": writers, "worker_kind": kind,
               "writer_kind": kind, "preprocess_device": pre_dev or "cpu",
               "settings": json.loads(json.dumps(run_settings, default=str))}
    summary_path = Path(args.summary) if args.summary else out / "run_summary.json"
    try:
        from floxels_ext.output_paths import replace_atomically

        text = json.dumps(summary, indent=2) + "\n"
        replace_atomically(summary_path.with_name(f".{summary_path.name}.{os.getpid()}.tmp"), summary_path,
                           lambda t: t.write_text(text))
    except OSError as e:
        report(f"floxels: warning: cannot write the summary {summary_path}: {e}")
    line = f"done: {written} frame(s) written, {skipped} skipped (already done), {len(failed)} failed"
    if loader.empty_crop:
        line += f" ({len(loader.empty_crop)} with no point left after cropping)"
    if times:
        line += (f"; {statistics.mean(times):.2f} s/frame mean, {statistics.median(times):.2f} s median, "
                 f"{sum(times):.1f} s total")
    print(line, file=sys.stderr)  # also with -q: its help promises the final summary
    if verbosity >= 1:
        st = stages.as_dict()
        print("stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in st.items()) + f"; summary: {summary_path}",
              file=sys.stderr)
    if failed:
        print("failed frames:", file=sys.stderr)
        for i in msgs:
            print(f"  {msgs[i]}", file=sys.stderr)
        return 1
    return 0
