"""``floxels run INPUT --out OUT_DIR``: scene flow for every frame of a real lidar sequence.

Per frame, in order: read the file (``floxels_ext.io``), crop and remove the ground in the
scan's own sensor frame (``floxels_ext.preprocess``), bring the scans of its window into one
frame with the poses (ego-motion compensation), estimate the flow with the chosen method and
write ``OUT_DIR/<frame name>.npz`` (see ``OUTPUT`` below). Frames already written are skipped,
so an interrupted run continues where it stopped.

Coordinates: the scans of a window are compensated in a world frame re-centred on the chunk
being processed (world axes, so float32 stays precise with city-scale AV2 coordinates); the
flow is then rotated into the target frame's *native* coordinates, those its file stores (the
sensor frame for plain files, the ego frame for AV2, the world frame for a ``floxels simulate``
sequence). Flow is ego-motion compensated: static points have zero flow. ``ego_motion`` holds
the rigid motion of the frame itself to the next one, for those who need raw displacements.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

OUTPUT = """\
Output: OUT_DIR/<frame name>.npz per frame with
  flow        (N,3) float32  motion to the next frame (metres per frame step), in the frame
                             file's own coordinates and point order; ego-motion compensated
                             (static = 0). Points not optimised (cropped, ground) get 0,
                             rows with NaN/inf input coordinates get NaN.
  mask        (N,)  bool     points that passed cropping and ground removal and were optimised
                             (the points the paper evaluates)
  points      (N,3) float32  the input points (same order)
  pose        (4,4) float64  the frame's coordinates -> the sequence's world frame
  ego_motion  (4,4) float64  the frame's coordinates -> the next frame's (when known)
  method, num_scans, elapsed_s, source, options (JSON)  metadata
"""

_TMP_RE = re.compile(r"^\..+\.npz\.\d+\.tmp$")


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
    p.add_argument("--chunk", type=int, default=16, help="targets estimated together (shared distance "
                   "transforms; default 16)")
    p.add_argument("--force", action="store_true", help="recompute frames already written")
    add_dataset_arguments(p)
    p.set_defaults(func=run)


def _parse_options(items: list[str], max_iters: int | None) -> dict:
    from .cli import CLIError

    opts: dict = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise CLIError(f"--option expects KEY=VALUE, got {item!r}")
        try:
            opts[key.strip()] = json.loads(val)
        except json.JSONDecodeError:
            opts[key.strip()] = val  # a bare string such as reg_scale=paper
        if isinstance(opts[key.strip()], list):
            opts[key.strip()] = tuple(opts[key.strip()])
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


@dataclass
class _Prepared:
    points: np.ndarray       # (N, 3) float32, native coordinates, file order
    mask: np.ndarray         # (N,) bool: optimised points
    to_world: np.ndarray     # (4, 4) native -> world


class _Frames:
    """Reads and preprocesses frames on demand, keeping the ones still needed (an LRU by index)."""

    def __init__(self, seq, settings, poses, pose_mode: str, report) -> None:
        self.seq, self.settings, self.poses, self.pose_mode, self.report = seq, settings, poses, pose_mode, report
        self.cache: dict[int, _Prepared | None] = {}
        self.errors: dict[int, str] = {}
        self._warned_no_pose = False

    def get(self, i: int) -> _Prepared | None:
        if i not in self.cache:
            self.cache[i] = self._load(i)
        return self.cache[i]

    def evict_below(self, lo: int) -> None:
        for k in [k for k in self.cache if k < lo]:
            del self.cache[k]

    def _load(self, i: int) -> _Prepared | None:
        from .io import LidarFormatError, MissingDependencyError
        from .preprocess import preprocess_mask, transform_points

        if i in self.errors:
            return None
        try:
            scan = self.seq.load(i)
            sensor_from_native = np.eye(4)
            if self.pose_mode == "seqio":
                to_world = np.eye(4)
                if scan.pose is not None:
                    sensor_from_native = np.linalg.inv(scan.pose)
                elif not self._warned_no_pose:
                    self._warned_no_pose = True
                    self.report(f"floxels: warning: {self.seq.frames[i].path} has no 'pose': ranges and heights "
                                f"are measured from the world origin")
            elif self.pose_mode == "frame":
                if scan.pose is None:
                    raise LidarFormatError(f"{self.seq.frames[i].path}: no 'pose' in this frame, but other frames "
                                           f"of the sequence have one (give --poses)")
                to_world = scan.pose
            elif self.pose_mode == "identity":
                to_world = np.eye(4)
            else:  # "table": seq.poses or odometry
                to_world = self.poses[i]
        except MissingDependencyError:
            raise
        except (LidarFormatError, ValueError, OSError) as e:
            msg = str(e)
            self.errors[i] = msg
            self.report(f"floxels: error: {msg}")
            return None
        pts = scan.points
        pts_sensor = pts if self.pose_mode != "seqio" else transform_points(pts, sensor_from_native)
        mask = preprocess_mask(pts_sensor, self.settings) if self.settings is not None else \
            np.isfinite(pts).all(axis=1)
        return _Prepared(pts, mask, np.asarray(to_world, np.float64))


def _cleanup_temps(out: Path) -> int:
    n = 0
    for p in out.iterdir():
        if _TMP_RE.match(p.name):
            p.unlink(missing_ok=True)
            n += 1
    return n


def write_output(path: Path, **arrays) -> Path:
    """Atomic .npz write: a temporary name in the same directory, then os.replace."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


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
        return "table", _odometry(seq, out, report)
    raise CLIError(f"{seq.root}: no poses for ego-motion compensation. Give one of: --poses FILE (KITTI "
                   f"poses.txt, .npy/.npz (F,4,4), AV2 city_SE3_egovehicle.feather); --odometry kiss-icp "
                   f"(estimate them; needs pip install 'floxels_ext[odometry]'); or --no-ego-motion if the scans "
                   f"are already in one common frame")


def _odometry(seq, out: Path, report) -> np.ndarray:
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

    bar = Progress(len(seq), "frames (KISS-ICP odometry)")
    poses = kiss_icp_poses(scans(), progress=lambda i: bar.update())
    bar.close()
    tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
    np.savetxt(tmp, poses[:, :3, :].reshape(len(poses), 12), fmt="%.9g")
    os.replace(tmp, cache)
    report(f"wrote odometry poses to {cache} (KITTI format)")
    return poses


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
    from .preprocess import Preprocess
    from .progress import Progress

    if args.list_methods:
        for name in available_methods():
            print(f"{name:<12} {get_method(name).description}")
        return 0
    if not args.input or not args.out:
        raise CLIError("floxels run needs INPUT and --out OUT_DIR")
    if args.method not in available_methods():
        raise CLIError(f"unknown --method {args.method!r}; available: {', '.join(available_methods())}")
    if not 2 <= args.scans <= 13:
        raise CLIError(f"--scans must be in [2, 13], got {args.scans}")
    if args.chunk < 1:
        raise CLIError("--chunk must be >= 1")
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise CLIError(f"--device must be cpu or cuda, got {device!r}")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise CLIError("--device cuda requested but no CUDA device is available")
    options = _parse_options(args.option, args.max_iters)
    if args.method == "floxels":  # the baselines estimate from a (frame, next frame) pair
        options = {"num_scans": args.scans, **options}
    if args.method == "floxels":  # fail fast on a bad option instead of after reading data
        from .config import FloxelsConfig
        try:
            FloxelsConfig(**options)
        except (TypeError, ValueError) as e:
            raise CLIError(f"bad --option for floxels: {e}") from None
    try:
        settings = Preprocess(min_range=args.min_range, max_range=args.max_range, max_height=args.max_height,
                              remove_ground=not args.no_ground_removal, ground_cell=args.ground_cell,
                              ground_window=args.ground_window, ground_threshold=args.ground_threshold)
    except ValueError as e:
        raise CLIError(str(e)) from None

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out {out} exists and is not a directory")
    try:
        seq = discover_input(args.input, poses_file=args.poses, calib=args.calib, bin_columns=args.bin_columns,
                             ext=args.ext, points_frame=args.points_frame)
    except (InputError, PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    if len(seq) < 2:
        raise CLIError(f"{seq.root} holds {len(seq)} frame; scene flow needs at least 2")
    selected = _parse_frames(args.frames, len(seq))
    out.mkdir(parents=True, exist_ok=True)
    stale = _cleanup_temps(out)
    bar: Progress | None = None

    def report(msg: str) -> None:
        (bar.message(msg) if bar is not None else print(msg, file=sys.stderr, flush=True))

    if stale:
        report(f"removed {stale} temporary file(s) left by an interrupted run")
    try:
        pose_mode, poses = _resolve_poses(seq, args, out, report)
    except (PoseFormatError, MissingDependencyError) as e:
        raise CLIError(str(e)) from None
    out_path = {i: out / f"{seq.frames[i].name}.npz" for i in selected}
    todo = [i for i in selected if args.force or not out_path[i].is_file()]
    skipped = len(selected) - len(todo)
    print(f"{seq.root}: {len(seq)} frames ({seq.kind}), {len(selected)} selected, {skipped} already done, "
          f"{len(todo)} to estimate with {args.method} on {device} "
          f"(ego-motion: {seq.pose_source or {'seqio': 'points already in one frame', 'identity': 'none (--no-ego-motion)', 'frame': 'per-frame poses', 'table': 'KISS-ICP odometry'}[pose_mode]})",
          file=sys.stderr, flush=True)

    frames = _Frames(seq, settings, poses, pose_mode, report)
    method = get_method(args.method)
    times: list[float] = []
    failed: dict[int, str] = {}
    written = 0
    bar = Progress(len(todo))
    n = len(seq)
    pad = args.scans - 1
    k = 0
    while k < len(todo):
        chunk = todo[k:k + args.chunk]
        k += len(chunk)
        lo, hi = max(0, chunk[0] - pad), min(n, chunk[-1] + pad + 1)
        frames.evict_below(lo)
        prepared = {i: frames.get(i) for i in range(lo, hi)}
        targets = []
        for i in chunk:
            if prepared[i] is None:
                failed[i] = frames.errors.get(i, "unreadable")
                bar.update()
            else:
                targets.append(i)
        if not targets:
            continue
        anchor = next(p for p in prepared.values() if p is not None).to_world[:3, 3].copy()
        scans = []
        for i in range(lo, hi):
            p = prepared[i]
            if p is None:
                scans.append(np.zeros((0, 3), np.float32))  # keeps the time offsets of the others right
                continue
            T = p.to_world.copy()
            T[:3, 3] -= anchor
            kept = p.points[p.mask].astype(np.float64)
            scans.append((kept @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
        t_last = [time.perf_counter()]

        def on_frame(f_local: int, flow_kept, lo=lo) -> None:
            nonlocal written
            i = lo + int(f_local)
            p = prepared[i]
            flow_kept = np.asarray(flow_kept, np.float32).reshape(-1, 3)
            full = np.zeros_like(p.points)
            full[~np.isfinite(p.points).all(axis=1)] = np.nan
            # world-axes flow -> the frame's native axes: R^T f (row vectors: f @ R)
            full[p.mask] = (flow_kept.astype(np.float64) @ p.to_world[:3, :3]).astype(np.float32)
            now = time.perf_counter()
            elapsed = now - t_last[0]
            t_last[0] = now
            extra = {}
            nxt = prepared.get(i + 1) if i + 1 < hi else (frames.cache.get(i + 1) if i + 1 < n else None)
            if nxt is not None and pose_mode != "seqio":
                extra["ego_motion"] = np.linalg.solve(nxt.to_world, p.to_world)
            write_output(out_path[i], flow=full, mask=p.mask, points=p.points, pose=p.to_world,
                         method=np.str_(args.method), num_scans=np.int32(args.scans),
                         elapsed_s=np.float64(elapsed), source=np.str_(str(seq.frames[i].path)),
                         options=np.str_(json.dumps(options, default=str)), **extra)
            times.append(elapsed)
            written += 1
            bar.update(note=seq.frames[i].name)

        try:
            method.estimate_sequence(scans, [i - lo for i in targets], device, dict(options), on_frame)
        except (ValueError, TypeError) as e:
            if written == 0 and not failed:
                bar.close()
                raise CLIError(f"{args.method}: {e}") from None
            for i in targets:
                if not out_path[i].is_file() or args.force:
                    failed.setdefault(i, f"estimation failed: {e}")
            report(f"floxels: error: frames {seq.frames[targets[0]].name}..{seq.frames[targets[-1]].name}: {e}")
        except RuntimeError as e:  # e.g. out of GPU memory: lose this chunk, keep going
            for i in targets:
                failed.setdefault(i, f"estimation failed: {e}")
            report(f"floxels: error: frames {seq.frames[targets[0]].name}..{seq.frames[targets[-1]].name}: {e}")
    bar.close()
    for i, msg in frames.errors.items():  # unreadable support scans count as failures too
        failed.setdefault(i, msg)

    summary = f"done: {written} frame(s) written, {skipped} skipped (already done), {len(failed)} failed"
    if times:
        summary += (f"; {statistics.mean(times):.2f} s/frame mean, {statistics.median(times):.2f} s median, "
                    f"{sum(times):.1f} s total")
    print(summary, file=sys.stderr)
    if failed:
        print("failed frames:", file=sys.stderr)
        for i in sorted(failed):
            path = str(seq.frames[i].path)
            print(f"  {failed[i] if failed[i].startswith(path) else path + ': ' + failed[i]}", file=sys.stderr)
        return 1
    return 0
