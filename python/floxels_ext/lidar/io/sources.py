"""What ``floxels run`` reads: the frames of one sequence and how their coordinates relate.

Three kinds of INPUT directory:

* ``av2``: an Argoverse 2 sensor log (``sensors/lidar/<timestamp_ns>.feather`` sweeps in the
  ego-vehicle frame, ``city_SE3_egovehicle.feather`` poses matched by timestamp);
* ``seqio``: a sequence written by ``floxels simulate`` (``000000.npz`` ... and
  ``sequence.json``, or any .npz frames with ``--points-frame world``): points already in one
  world frame, ``pose`` the sensor pose used for cropping and ground removal;
* ``files``: frame files of one supported format (``.bin``, ``.npy``, ``.npz``, ``.pcd``,
  ``.ply``, ``.feather``) sorted in natural order, points in each scan's sensor frame. An
  ``.npz`` frame's ``pose`` key, when present, gives its sensor-to-world pose.

Each frame has *native* coordinates (those its file stores); flow is reported in them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path

import numpy as np

from floxels_ext.lidar.io.poses import PoseFormatError, match_timestamps, read_av2_poses, read_poses
from floxels_ext.lidar.io.readers import SUFFIXES, LidarFormatError, LidarScan, natural_key, read_points

__all__ = ["FrameSource", "SequenceInput", "discover_input", "InputError", "absolute_sources"]


class InputError(ValueError):
    """The INPUT directory (as a whole) cannot be used; a user error."""


@dataclass
class FrameSource:
    name: str                      # output file stem
    path: Path
    timestamp_ns: int | None = None


@dataclass
class SequenceInput:
    kind: str                                      # "files", "seqio" or "av2"
    root: Path
    frames: list[FrameSource]
    poses: np.ndarray | None = None                # (F, 4, 4) native-to-world, when known up front
    pose_source: str | None = None                 # where the poses came from (for messages)
    bin_columns: int | None = None
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def points_in_world(self) -> bool:
        """Whether the stored points are already ego-motion compensated (a seqio sequence)."""
        return self.kind == "seqio"

    def load(self, i: int) -> LidarScan:
        return read_points(self.frames[i].path, bin_columns=self.bin_columns)


def _lidar_files(d: Path, ext: str | None) -> list[Path]:
    # a broken link is a frame that fails by name, not a dropped frame (a gap in the numbering)
    # scandir's entries know their type without a stat per file (a dataset lists 12,000 of them
    # before its first task); the suffix test by os.path.splitext, Path's comes as Path(e.path)
    with os.scandir(d) as it:
        files = [Path(e.path) for e in it if not e.name.startswith(".")
                 and os.path.splitext(e.name)[1].lower() in SUFFIXES and (e.is_file() or e.is_symlink())]
    if ext:
        ext = ext.lower() if ext.startswith(".") else "." + ext.lower()
        if ext not in SUFFIXES:
            raise InputError(f"--ext {ext!r} is not a supported lidar extension ({', '.join(SUFFIXES)})")
        files = [p for p in files if p.suffix.lower() == ext]
    kinds = sorted({p.suffix.lower() for p in files})
    if len(kinds) > 1:
        raise InputError(f"{d} holds frames of several formats ({', '.join(kinds)}); choose one with --ext")
    stems = [os.path.splitext(p.name)[0] for p in files]
    if stems and all(t.isdigit() and len(t) == len(stems[0]) for t in stems):
        # KITTI's and most datasets' zero-padded numbers: natural order is the names' order, without
        # a regular expression a file (a dataset lists 12,000 names before its first task)
        return sorted(files, key=lambda f: f.name)
    return sorted(files, key=lambda p: natural_key(p.name))


def discover_input(path, *, poses_file=None, calib=None, bin_columns: int | None = None,
                   ext: str | None = None, points_frame: str = "auto") -> SequenceInput:
    """Inspect INPUT and list its frames (nothing is read yet except pose files).

    ``points_frame``: ``"world"`` if the frames' points are already in one world frame (seqio
    convention, .npz with the sensor ``pose``), ``"sensor"`` if each is in its sensor frame,
    ``"auto"``: world for a seqio directory (000000.npz ... plus sequence.json), else sensor."""
    root = Path(path)
    if not root.exists():
        raise InputError(f"input {root} does not exist")
    if not root.is_dir():
        raise InputError(f"input {root} is not a directory (give the directory holding the frame files)")
    lidar_dir = root / "sensors" / "lidar"
    if lidar_dir.is_dir():
        files = sorted(lidar_dir.glob("*.feather"), key=lambda p: natural_key(p.name))
        if not files:
            raise InputError(f"{lidar_dir} holds no .feather sweeps")
        frames = [FrameSource(p.stem, p, int(p.stem) if p.stem.isdigit() else None) for p in files]
        seq = SequenceInput("av2", root, frames, bin_columns=bin_columns)
        pose_path = Path(poses_file) if poses_file else root / "city_SE3_egovehicle.feather"
        if pose_path.exists() or poses_file:
            if pose_path.suffix.lower() == ".feather":
                if any(f.timestamp_ns is None for f in frames):
                    bad = next(f.path for f in frames if f.timestamp_ns is None)
                    raise InputError(f"{bad}: AV2 sweep names must be their timestamps in ns")
                t, P = read_av2_poses(pose_path)
                seq.poses = match_timestamps(t, P, [f.timestamp_ns for f in frames], str(pose_path))
            else:
                seq.poses = _frame_poses(read_poses(pose_path, calib=calib), len(frames), pose_path, root)
            seq.pose_source = str(pose_path)
        return seq
    files = _lidar_files(root, ext)
    if not files:
        raise InputError(f"{root} holds no lidar frames (looked for {', '.join('*' + s for s in SUFFIXES)}; "
                         f"an Argoverse 2 log needs sensors/lidar/)")
    if points_frame not in ("auto", "sensor", "world"):
        raise InputError(f"points_frame must be 'auto', 'sensor' or 'world', got {points_frame!r}")
    kind = "files"
    seqio_names = all(p.suffix == ".npz" and len(p.stem) == 6 and p.stem.isdigit() for p in files)
    if points_frame == "world" or (points_frame == "auto" and seqio_names and (root / "sequence.json").is_file()):
        if not all(p.suffix == ".npz" for p in files):
            raise InputError("--points-frame world needs .npz frames (their 'pose' locates the sensor)")
        kind = "seqio"  # floxels simulate / seqio layout: points in the world frame
    frames = [FrameSource(p.stem, p, int(p.stem) if p.suffix.lower() == ".feather" and p.stem.isdigit() else None)
              for p in files]
    seq = SequenceInput(kind, root, frames, bin_columns=bin_columns)
    if poses_file:
        pose_path = Path(poses_file)
        if pose_path.suffix.lower() == ".feather" and all(f.timestamp_ns is not None for f in frames):
            t, P = read_av2_poses(pose_path)
            seq.poses = match_timestamps(t, P, [f.timestamp_ns for f in frames], str(pose_path))
        else:
            seq.poses = _frame_poses(read_poses(pose_path, calib=calib), len(frames), pose_path, root)
        seq.pose_source = str(pose_path)
    return seq


def _frame_poses(poses: np.ndarray, n: int, pose_path, root) -> np.ndarray:
    if len(poses) != n:
        raise PoseFormatError(f"{pose_path}: {len(poses)} poses but {root} has {n} frames "
                              f"(one pose per frame, in the frames' sorted order)")
    return poses


# re-exported for callers that catch everything an input can raise
INPUT_ERRORS = (InputError, PoseFormatError, LidarFormatError)


def absolute_sources(seq, frames) -> dict[int, str]:
    """The absolute path of each frame's file, as outputs record it (``source``): each
    directory resolved once (resolving every path took ~0.1 ms a frame of system calls)."""
    dirs: dict = {}
    out = {}
    for i in frames:
        path = seq.frames[i].path
        if path.parent not in dirs:
            dirs[path.parent] = path.parent.resolve()
        out[i] = str(dirs[path.parent] / path.name)
    return out
