"""Where a run's ego-motion and frame times come from: pose tables, poses in the frames, KISS-ICP
odometry (cached next to the outputs with what it was computed from: ``odometry_cache.py``), a
KITTI ``times.txt``, AV2 timestamps or gaps in the frame numbering."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["resolve_poses", "frame_times", "run_settings", "output_meta", "next_pose_reader"]


def resolve_poses(seq, args, out: Path, report):
    """(pose_mode, poses) for the sequence; raises CLIError when ego-motion cannot be resolved."""
    from floxels_ext.cli import CLIError

    if args.no_ego_motion and (args.poses or args.odometry):
        raise CLIError("--no-ego-motion contradicts --poses/--odometry")
    if seq.kind == "seqio":
        if args.poses or args.odometry:
            raise CLIError(f"{seq.root}: the points are already in one world frame (floxels simulate layout / "
                           f"--points-frame world); --poses and --odometry do not apply")
        return "seqio", None
    if seq.poses is not None:
        return "table", seq.poses
    if args.no_ego_motion:
        return "identity", None
    if seq.frames[0].path.suffix.lower() == ".npz":
        for i in range(len(seq)):  # the first readable frame decides
            try:
                if seq.load(i).pose is not None:
                    return "frame", None
                break
            except ValueError:
                continue
    if args.odometry == "kiss-icp":
        from floxels_ext.lidar.pipeline.odometry_cache import odometry_poses

        return "table", odometry_poses(seq, out, report, int(getattr(args, "verbosity", 0) or 0),
                                       force=bool(getattr(args, "force", False)))
    raise CLIError(f"{seq.root}: no poses for ego-motion compensation. Give one of: --poses FILE (KITTI "
                   f"poses.txt, .npy/.npz (F,4,4), AV2 city_SE3_egovehicle.feather); --odometry kiss-icp "
                   f"(estimate them; needs pip install 'floxels_ext[odometry]'); or --no-ego-motion if the scans "
                   f"are already in one common frame")


def frame_times(seq, stamps: list, report) -> tuple[list[float] | None, str | None]:
    """Per-frame times for methods that take them (unequally spaced scans), and where they came
    from: the frames' own timestamps (AV2 sweeps), a KITTI ``times.txt`` (seconds, one line per
    scan) next to the frames, or gaps in numbered frame names (000004 missing between 000003
    and 000005: a dropped scan; offsets in frame steps). None when frames are evenly spaced or
    nothing says otherwise."""
    if all(t is not None for t in stamps):
        return [(t - stamps[0]) * 1e-9 for t in stamps], None
    n = len(seq.frames)
    parent = seq.frames[0].path.parent
    for cand in dict.fromkeys((parent / "times.txt", parent.parent / "times.txt")):
        if not cand.is_file():
            continue
        try:
            t = np.loadtxt(cand, ndmin=1, dtype=np.float64)
        except ValueError as e:
            report(f"floxels: warning: {cand} is not one time (s) per line ({e}); frames taken as evenly spaced")
            return None, None
        if t.ndim != 1 or len(t) != n or not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
            report(f"floxels: warning: {cand} holds {t.size} values for {n} frames (or not increasing); "
                   f"frames taken as evenly spaced")
            return None, None
        return [float(v - t[0]) for v in t], str(cand)
    names = [f.path.stem for f in seq.frames]
    if all(s.isdigit() for s in names):
        num = np.array([int(s) for s in names], np.int64)
        steps = np.diff(num)
        if len(steps) and np.all(steps > 0) and len(set(steps.tolist())) > 1:
            return [float(v - num[0]) for v in num], "gaps in the frame numbers"
    return None, None


# What a sequence's outputs record of the run: one definition for the plain run (run.py) and
# the dataset pipeline (dataset/sequence.py), so a resume compares like with like.

def run_settings(args, options: dict, settings, pose_mode: str, seq) -> dict:
    """The settings an output was computed with (``settings`` in every frame; a resume with
    others stops): method, window, the method's options, preprocessing, ego-motion source."""
    from dataclasses import asdict

    return {"method": args.method, "num_scans": args.scans, "options": options,
            "preprocess": asdict(settings), "ego_motion": pose_mode,
            # resolved: a resume names the same file by another path (relative, a link)
            "pose_source": str(Path(seq.pose_source).resolve()) if seq.pose_source else None,
            "dynamic_threshold": args.dynamic_threshold}


def output_meta(args, options: dict, settings: dict, seq) -> dict:
    """The fields every output frame of a sequence carries besides its own (lidar/io/outputs.py)."""
    import json

    from floxels_ext.lidar.io.outputs import FORMAT_VERSION

    return {"method": np.str_(args.method), "num_scans": np.int32(args.scans),
            "options": np.str_(json.dumps(options, default=str)),
            "settings": np.str_(json.dumps(settings, default=str)),
            "dynamic_threshold": np.float64(args.dynamic_threshold), "format": np.int32(FORMAT_VERSION),
            "bin_columns": np.int32(seq.bin_columns or 0),
            "points_frame": np.str_("world" if seq.kind == "seqio" else "native")}


def next_pose_reader(seq, pose_mode: str, poses, loader):
    """``next_pose(i)``: the world pose of frame i + 1 (outputs record the ego motion to it), or
    None where there is none; per-frame poses are read from the loader's prepared frame."""
    def next_pose(i):
        if i + 1 >= len(seq) or pose_mode == "seqio":
            return None
        if pose_mode == "table":
            return poses[i + 1]
        if pose_mode == "identity":
            return np.eye(4)
        nxt = loader.peek(i + 1)
        return None if nxt is None else nxt.to_world
    return next_pose

