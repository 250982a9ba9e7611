"""``floxels run INPUT --out OUT_DIR``: scene flow for every frame of a real lidar sequence.

Per frame: read the file (``floxels_ext.io``), crop and remove the ground in the
scan's own sensor frame (``floxels_ext.preprocess``), bring the scans of its window into one
frame with the poses (ego-motion compensation), estimate the flow with the chosen method and
write ``OUT_DIR/<frame name>.npz`` (see :data:`floxels_ext.outputs.OUTPUT`). Frames already
written with the same settings are skipped, so an interrupted run continues where it stopped.
Reading and preprocessing run ahead on worker threads and writing on a writer thread while the
method optimises (:mod:`floxels_ext.pipeline`).

Coordinates: the scans of a window are compensated in a world frame re-centred on the chunk
being processed (world axes, so float32 stays precise with city-scale AV2 coordinates); the
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
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .outputs import OUTPUT, write_output  # noqa: F401  (write_output: re-exported for callers)


def _opt_float(text: str) -> float | None:
    if text.lower() in ("none", "off", "inf"):
        return None
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"expected a number or 'none', got {text!r}") from None
    return v


def add_parser(sub) -> None:
    import argparse
    import textwrap

    from .dataset_run import add_dataset_arguments

    p = sub.add_parser(
        "run", help="estimate scene flow for a whole lidar sequence (resumable)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="\n\n".join(textwrap.fill(t, 92) for t in (
            "Estimate the flow of every frame of INPUT and write one .npz per frame to OUT_DIR.",
            "INPUT: a directory of frame files of one format (.bin .npy .npz .pcd .ply .feather, natural "
            "order), a 'floxels simulate' sequence, or an Argoverse 2 log directory "
            "(sensors/lidar/*.feather + city_SE3_egovehicle.feather).",
            "Ego-motion: --poses FILE, else poses stored with the frames (AV2, .npz 'pose'), else "
            "--odometry kiss-icp (estimated; pip install 'floxels_ext[odometry]'), else --no-ego-motion "
            "if the scans are already in one frame.")) + "\n\n" + OUTPUT)
    p.add_argument("input", metavar="INPUT", nargs="?")
    p.add_argument("--out", metavar="OUT_DIR", help="output directory (created; required)")
    p.add_argument("--poses", metavar="FILE", help="poses: KITTI poses.txt (12/line), 4x4 per line, TUM, "
                   ".npy/.npz (F,4,4), or AV2 city_SE3_egovehicle.feather")
    p.add_argument("--calib", metavar="FILE", help="KITTI calib.txt: turn camera poses into velodyne poses")
    p.add_argument("--odometry", choices=["kiss-icp"], help="estimate poses with KISS-ICP when none are given")
    p.add_argument("--no-ego-motion", action="store_true", help="the scans are already ego-motion compensated")
    p.add_argument("--method", default="floxels", help="scene-flow method (see --list-methods; default floxels)")
    p.add_argument("--list-methods", action="store_true", help="print the available methods and exit")
    p.add_argument("--scans", type=int, default=5, help="scans per window, target in the middle (default 5)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda if available)")
    p.add_argument("--frames", metavar="A:B", help="only these frames (Python slice over the sorted frames); "
                   "neighbours outside still serve as support scans")
    p.add_argument("--max-iters", type=int, help="shortcut for --option max_iters=N")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="method option (Floxels: any FloxelsConfig field, e.g. voxel_size=0.5); repeatable")
    p.add_argument("--no-ground-removal", action="store_true", help="keep ground points")
    p.add_argument("--min-range", type=_opt_float, default=3.0, help="m, drop closer points (default 3; 'none')")
    p.add_argument("--max-range", type=_opt_float, default=50.0, help="m, drop farther points (default 50; 'none')")
    p.add_argument("--max-height", type=_opt_float, default=4.0,
                   help="m above the local ground, drop higher points (default 4; 'none')")
    p.add_argument("--ground-threshold", type=float, default=0.3, help="m above the ground surface that is "
                   "still ground (default 0.3)")
    p.add_argument("--ground-window", type=float, default=8.0, help="m, morphological window (default 8)")
    p.add_argument("--ground-cell", type=float, default=0.5, help="m, ground grid cell (default 0.5)")
    p.add_argument("--bin-columns", type=int, choices=[3, 4, 5, 6], help="float32 columns of .bin frames "
                   "(default: from the file size; 4 KITTI, 5 nuScenes)")
    p.add_argument("--ext", help="frame extension to use when INPUT mixes formats")
    p.add_argument("--points-frame", choices=["auto", "sensor", "world"], default="auto",
                   help="coordinates of the stored points: each scan's sensor frame, or one world frame "
                        "(.npz with the sensor 'pose', as 'floxels simulate' writes); auto: world for a "
                        "'floxels simulate' directory (sequence.json present), else sensor")
    p.add_argument("--chunk", type=int, default=None, help="targets per method call (one re-centred world frame, "
                   "shared distance transforms); default: 8, 16, 32, then 64 (the device starts early)")
    p.add_argument("--force", action="store_true", help="recompute frames already written (also those written "
                   "with other settings)")
    p.add_argument("--dynamic-threshold", type=float, default=0.05, metavar="M",
                   help="m per frame step: optimised points moving faster are flagged 'dynamic' (default 0.05, "
                        "0.5 m/s at 10 Hz as in the Argoverse 2 protocol)")
    p.add_argument("--self-contained", action="store_true", help="also store the input points in every output "
                   "(default: read back from the recorded source file)")
    p.add_argument("--compress", action="store_true", help="zip-compress the outputs (smaller, slower)")
    p.add_argument("--summary", metavar="FILE", help="JSON summary of the run (default OUT_DIR/run_summary.json)")
    p.add_argument("--workers", type=int, default=None, help="reader/preprocessor threads (default: 4 with GPU "
                   "preprocessing, else the CPU cores, at most 16)")
    p.add_argument("--worker-kind", choices=["auto", "thread", "process"], default="auto",
                   help="readers/preprocessors as threads or processes (numpy preprocessing only); auto: threads "
                        "(faster than processes on the hosts measured)")
    p.add_argument("--preprocess-device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="where cropping/ground removal run: numpy on the CPU, or torch on the GPU (same masks; "
                        "worker threads); auto: the GPU when --device is one, else the CPU")
    add_dataset_arguments(p)
    p.set_defaults(func=run)


def _parse_options(items: list[str], max_iters: int | None, config: type | None) -> dict:
    """``--option KEY=VALUE`` items as typed values: parsed for the field's type of the method's
    ``config`` dataclass (bools from true/false/yes/no/on/off/1/0, tuples from a,b); JSON for
    a method without one."""
    from .cli import CLIError
    from .config_fields import parse_option_value

    opts: dict = {}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise CLIError(f"--option expects KEY=VALUE, got {item!r}")
        if config is not None:
            try:
                opts[key] = parse_option_value(config, key, val)
            except (TypeError, ValueError) as e:
                raise CLIError(f"bad --option {item!r}: {e}") from None
            continue
        try:
            opts[key] = json.loads(val)
        except json.JSONDecodeError:
            opts[key] = val  # a bare string such as reg_scale=paper
        if isinstance(opts[key], list):
            opts[key] = tuple(opts[key])
    if max_iters is not None:
        opts["max_iters"] = max_iters
    return opts


def _parse_frames(text: str | None, n: int) -> list[int]:
    from .cli import CLIError

    if not text:
        return list(range(n))
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            sl = slice(int(a) if a.strip() else None, int(b) if b.strip() else None)
        else:
            k = int(text)
            sl = slice(k, k + 1 if k != -1 else None)
    except ValueError:
        raise CLIError(f"--frames expects A:B, A:, :B or A (integers), got {text!r}") from None
    sel = list(range(n))[sl]
    if not sel:
        raise CLIError(f"--frames {text} selects no frame of the {n}")
    return sel


def _resolve_poses(seq, args, out: Path, report):
    """(pose_mode, poses) for the sequence; raises CLIError when ego-motion cannot be resolved."""
    from .cli import CLIError

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
        return "table", _odometry(seq, out, report, int(getattr(args, "verbosity", 0) or 0))
    raise CLIError(f"{seq.root}: no poses for ego-motion compensation. Give one of: --poses FILE (KITTI "
                   f"poses.txt, .npy/.npz (F,4,4), AV2 city_SE3_egovehicle.feather); --odometry kiss-icp "
                   f"(estimate them; needs pip install 'floxels_ext[odometry]'); or --no-ego-motion if the scans "
                   f"are already in one common frame")


def _odometry(seq, out: Path, report, verbosity: int = 0) -> np.ndarray:
    from .io import read_poses
    from .io.poses import PoseFormatError
    from .odometry import kiss_icp_poses
    from .progress import Progress

    cache = out / "poses_kiss_icp.txt"
    if cache.is_file():
        try:
            poses = read_poses(cache)
            if len(poses) == len(seq):
                report(f"reusing odometry poses from {cache}")
                return poses
        except PoseFormatError:
            pass

    def scans():
        for i in range(len(seq)):
            try:
                yield seq.load(i).points
            except ValueError:
                yield np.zeros((0, 3), np.float32)

    bar = Progress(len(seq), "frames (KISS-ICP odometry)", verbosity=verbosity)
    poses = kiss_icp_poses(scans(), progress=lambda i: bar.update())
    bar.close()
    tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
    np.savetxt(tmp, poses[:, :3, :].reshape(len(poses), 12), fmt="%.9g")
    os.replace(tmp, cache)
    report(f"wrote odometry poses to {cache} (KITTI format)")
    return poses


def _check_args(args, torch):
    """Validate the plain arguments; returns (device, options). Raises CLIError."""
    from .cli import CLIError
    from .methods import available_methods, get_method

    if not args.input or not args.out:
        raise CLIError("floxels run needs INPUT and --out OUT_DIR")
    if args.method not in available_methods():
        raise CLIError(f"unknown --method {args.method!r}; available: {', '.join(available_methods())}")
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.chunk is not None and args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    if args.workers is not None and args.workers < 1:
        raise CLIError("--workers must be >= 1")
    if not (np.isfinite(args.dynamic_threshold) and args.dynamic_threshold >= 0):
        raise CLIError(f"--dynamic-threshold must be a finite number >= 0 (m per frame), got {args.dynamic_threshold}")
    if args.calib and not args.poses:
        raise CLIError("--calib turns the camera poses of --poses into lidar poses; it needs --poses FILE")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise CLIError(f"--device must be cpu or cuda, got {device!r}")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise CLIError("--device cuda requested but no CUDA device is available")
    if args.preprocess_device == "cuda" and not torch.cuda.is_available():
        raise CLIError("--preprocess-device cuda requested but no CUDA device is available")
    options = _parse_options(args.option, args.max_iters, get_method(args.method).config)
    if "num_scans" in options and options["num_scans"] != args.scans:
        raise CLIError(f"--option num_scans={options['num_scans']} contradicts --scans {args.scans}; "
                       f"give the window size once, with --scans")
    if args.method == "floxels":  # the baselines estimate from a (frame, next frame) pair
        options = {"num_scans": args.scans, **options}
        from .config import FloxelsConfig  # fail fast on a bad option instead of after reading data
        try:
            FloxelsConfig(**options)
        except (TypeError, ValueError) as e:
            raise CLIError(f"bad --option for floxels: {e}") from None
    return device, options


def _check_out_dir(out: Path, seq) -> None:
    from .cli import CLIError

    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    o = out.resolve()
    frame_dir = seq.frames[0].path.parent.resolve()
    for d, what in ((seq.root.resolve(), "the input directory"), (frame_dir, "the directory of the frame files")):
        if o == d:
            raise CLIError(f"--out {out} is {what}: the outputs would be taken for input frames by the next run; "
                           f"choose another directory")


def _check_resume(out_path: dict, selected: list[int], settings: dict, force: bool) -> list[int]:
    """Frames to estimate: those without an output, and (with --force) all; an output written
    with other settings stops the run (CLIError) unless --force."""
    from .cli import CLIError
    from .outputs import read_settings, settings_mismatch

    if force:
        return list(selected)
    todo, clash = [], None
    for i in selected:
        if not out_path[i].is_file():
            todo.append(i)
            continue
        rec = read_settings(out_path[i])
        if rec is None:  # unreadable (e.g. truncated by a crash of the machine): recompute it
            todo.append(i)
            continue
        diff = settings_mismatch(rec, settings)
        if diff and clash is None:
            clash = (out_path[i], diff)
    if clash is not None:
        raise CLIError(f"{clash[0]} was written with other settings ({'; '.join(clash[1])}); "
                       f"use --force to recompute, or another --out")
    return todo


def _reader_plan(args, device: str) -> tuple[str | None, int, str]:
    """(preprocessing device or None for numpy, reader workers, "thread"/"process").

    Measured on a 16-core H100 host (bench/bench_run.py, bench/RESULTS.md): cropping and ground
    removal on the GPU from 4 reader threads beat numpy on 16 threads or processes by ~1.3-2x
    (more threads contend for the GIL with the optimiser's host work). ``args.cpu_limit`` (set
    by a Ray task: the CPUs it was given) caps the default worker count."""
    cores = os.cpu_count() or 1
    limit = getattr(args, "cpu_limit", None)
    if limit:
        cores = min(cores, max(1, int(limit)))
    pre = args.preprocess_device
    if pre == "auto":  # worker processes preprocess with numpy (CUDA does not survive a fork)
        pre = "cuda" if device.startswith("cuda") and args.worker_kind != "process" else "cpu"
    pre_dev = (device if device.startswith("cuda") else "cuda") if pre == "cuda" else None
    workers = args.workers or (min(4, cores) if pre_dev else max(1, min(16, cores)))
    kind = "thread" if args.worker_kind == "auto" else args.worker_kind
    return pre_dev, workers, kind


def _frame_times(seq, stamps: list, report) -> tuple[list[float] | None, str | None]:
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


def run(args) -> int:
    from .dataset_run import maybe_run_dataset

    rc = maybe_run_dataset(args)
    if rc is not None:
        return rc
    import torch

    from .cli import CLIError
    from .io import MissingDependencyError
    from .io.poses import PoseFormatError
    from .io.sources import InputError, discover_input
    from .methods import available_methods, get_method
    from .outputs import FORMAT_VERSION, cleanup_temps
    from .pipeline import EstimationError, FrameLoader, Stages, run_pipeline, single_threaded_blas
    from .preprocess import Preprocess
    from .progress import Progress

    verbosity = int(getattr(args, "verbosity", 0) or 0)
    if args.list_methods:
        for name in available_methods():
            print(f"{name:<12} {get_method(name).description}")
        return 0
    device, options = _check_args(args, torch)
    try:
        settings = Preprocess(min_range=args.min_range, max_range=args.max_range, max_height=args.max_height,
                              remove_ground=not args.no_ground_removal, ground_cell=args.ground_cell,
                              ground_window=args.ground_window, ground_threshold=args.ground_threshold)
    except ValueError as e:
        raise CLIError(str(e)) from None
    out = Path(args.out)
    try:
        seq = discover_input(args.input, poses_file=args.poses, calib=args.calib, bin_columns=args.bin_columns,
                             ext=args.ext, points_frame=args.points_frame)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    if len(seq) < 2:
        raise CLIError(f"{seq.root} holds {len(seq)} frame; scene flow needs at least 2")
    _check_out_dir(out, seq)
    selected = _parse_frames(args.frames, len(seq))
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
        pose_mode, poses = _resolve_poses(seq, args, out, report)
    except (PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    run_settings = {"method": args.method, "num_scans": args.scans, "options": options,
                    "preprocess": asdict(settings), "ego_motion": pose_mode,
                    "pose_source": str(seq.pose_source) if seq.pose_source else None,
                    "dynamic_threshold": args.dynamic_threshold}
    out_path = {i: out / f"{seq.frames[i].name}.npz" for i in selected}
    todo = _check_resume(out_path, selected, run_settings, args.force)
    skipped = len(selected) - len(todo)
    info(f"{seq.root}: {len(seq)} frames ({seq.kind}), {len(selected)} selected, {skipped} already done, "
         f"{len(todo)} to estimate with {args.method} on {device} "
         f"(ego-motion: {seq.pose_source or {'seqio': 'points already in one frame', 'identity': 'none (--no-ego-motion)', 'frame': 'per-frame poses', 'table': 'KISS-ICP odometry'}[pose_mode]})")

    pre_dev, workers, kind = _reader_plan(args, device)
    if kind == "process" and pre_dev is not None:
        raise CLIError("--preprocess-device cuda runs in worker threads; it contradicts --worker-kind process")
    stages = Stages()
    loader = FrameLoader(seq, settings, poses, pose_mode, report, workers=workers, kind=kind, pre_device=pre_dev,
                         keep_points=args.self_contained, stages=stages,
                         warn=lambda m: report(f"floxels: warning: {m}"))
    # per-frame times in seconds where the input names them (AV2 sweeps: ns timestamps); the
    # pipeline passes them to methods whose estimate_sequence takes ``times``
    stamps = [f.timestamp_ns for f in seq.frames]
    times_s, times_source = _frame_times(seq, stamps, report)
    if times_source is not None:
        info(f"frame times from {times_source}: window offsets follow them, flow stays per frame step")
    meta = {"method": np.str_(args.method), "num_scans": np.int32(args.scans),
            "options": np.str_(json.dumps(options, default=str)),
            "settings": np.str_(json.dumps(run_settings, default=str)),
            "dynamic_threshold": np.float64(args.dynamic_threshold), "format": np.int32(FORMAT_VERSION),
            "bin_columns": np.int32(seq.bin_columns or 0),
            "points_frame": np.str_("world" if seq.kind == "seqio" else "native")}

    def write_one(i, p, flow_kept, elapsed, next_to_world):
        # float32 arithmetic and index (not boolean) assignment: this ran on the writer threads
        # at ~6 ms a frame in float64, a third of a GPU frame's budget (flow differs < 1e-6 m)
        full = np.zeros((p.n, 3), np.float32)
        full[p.nonfinite] = np.nan
        kept = np.flatnonzero(p.mask)
        # world-axes flow -> the frame's native axes: R^T f (row vectors: f @ R)
        native = np.asarray(flow_kept, np.float32) @ p.to_world[:3, :3].astype(np.float32)
        full[kept] = native
        dynamic = np.zeros(len(full), bool)
        thr = args.dynamic_threshold
        dynamic[kept] = np.einsum("ij,ij->i", native, native) > np.float32(thr) * np.float32(thr)
        extra = {}
        if next_to_world is not None:
            extra["ego_motion"] = np.linalg.solve(next_to_world, p.to_world)
        if args.self_contained:
            extra["points"] = p.points
        if stamps[i] is not None:
            extra["timestamp_ns"] = np.int64(stamps[i])
        write_output(out_path[i], compress=args.compress, flow=full, mask=p.mask, dynamic=dynamic,
                     pose=p.to_world, elapsed_s=np.float64(elapsed),
                     source=np.str_(str(seq.frames[i].path.resolve())), **meta, **extra)

    def next_pose(i):
        if i + 1 >= len(seq) or pose_mode == "seqio":
            return None
        if pose_mode == "table":
            return poses[i + 1]
        if pose_mode == "identity":
            return np.eye(4)
        nxt = loader.peek(i + 1)
        return None if nxt is None else nxt.to_world

    bar = Progress(len(todo), verbosity=verbosity)
    t0 = time.perf_counter()
    # with the method on the GPU, numpy's BLAS serves only the per-scan host work: one thread each
    blas = single_threaded_blas() if device.startswith("cuda") else contextlib.nullcontext()
    try:
        with blas:
            res = run_pipeline(loader=loader, method=get_method(args.method), todo=todo, n=len(seq),
                               num_scans=args.scans, chunk=args.chunk, device=device, options=options,
                               write_one=write_one, next_pose=next_pose, times_s=times_s,
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
               "wall_s": round(wall, 4), "frames_per_s": round(written / wall, 3) if wall > 0 and written else None,
               "s_per_frame_mean": round(statistics.mean(times), 6) if times else None,
               "s_per_frame_median": round(statistics.median(times), 6) if times else None,
               "stages_s": stages.as_dict(), "workers": workers, "worker_kind": kind,
               "preprocess_device": pre_dev or "cpu",
               "settings": json.loads(json.dumps(run_settings, default=str))}
    summary_path = Path(args.summary) if args.summary else out / "run_summary.json"
    try:
        tmp = summary_path.with_name(f".{summary_path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
        os.replace(tmp, summary_path)
    except OSError as e:
        report(f"floxels: warning: cannot write the summary {summary_path}: {e}")
    line = f"done: {written} frame(s) written, {skipped} skipped (already done), {len(failed)} failed"
    if times:
        line += (f"; {statistics.mean(times):.2f} s/frame mean, {statistics.median(times):.2f} s median, "
                 f"{sum(times):.1f} s total")
    if verbosity >= 0:
        print(line, file=sys.stderr)
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
