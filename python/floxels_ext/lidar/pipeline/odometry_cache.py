"""KISS-ICP poses of ``floxels run --odometry kiss-icp``, cached next to the outputs with a
record of what they were computed from (issue 45, item 1).

Poses derived from the scans are inputs like the scans: the cache ``OUT/poses_kiss_icp.txt``
(KITTI format) is reused only while ``OUT/poses_kiss_icp.json`` says it was computed from the
same frames (each file's name, size and modification time, as the resume record of
:mod:`floxels_ext.lidar.pipeline.resume` compares them) with the same odometry settings and the
same reading of the files (``--bin-columns``). Anything else (a re-exported sequence, a frame
added or removed, a cache without its record, ``--force``) computes them again; the resume then
recomputes the frames whose poses changed. Before, the cache was reused whenever its line count
matched the frames, also after the sweeps were re-exported rotated by 0.3 rad (70-93 % of the
kept points came out moving instead of 47-49 %).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

__all__ = ["ODOMETRY_SETTINGS", "odometry_record", "odometry_poses"]

#: What ``kiss_icp_poses`` is called with (recorded: another setting computes them again).
ODOMETRY_SETTINGS = {"max_range": 100.0, "min_range": 0.0, "voxel_size": None, "deskew": False}
CACHE_NAME = "poses_kiss_icp.txt"
RECORD_NAME = "poses_kiss_icp.json"


def odometry_record(seq) -> dict:
    """What the poses of ``seq`` are computed from: the odometry, its settings, how the files
    are read, and each frame file's [name, size, mtime_ns] (null where it cannot be stat'ed)."""
    frames = []
    for f in seq.frames:
        try:
            st = os.stat(f.path)
            frames.append([f.path.name, int(st.st_size), int(st.st_mtime_ns)])
        except OSError:
            frames.append([f.path.name, None, None])
    return {"odometry": "kiss-icp", "settings": dict(ODOMETRY_SETTINGS),
            "bin_columns": seq.bin_columns, "frames": frames}


def _record_diff(old: dict | None, new: dict) -> str | None:
    """None when ``old`` matches ``new``, else why the cached poses are stale (for the message)."""
    if old is None:
        return f"no {RECORD_NAME} says what they were computed from"
    if {k: v for k, v in old.items() if k != "frames"} != {k: v for k, v in new.items() if k != "frames"}:
        return "they were computed with other odometry settings or another --bin-columns"
    a, b = {r[0]: r[1:] for r in old.get("frames", [])}, {r[0]: r[1:] for r in new["frames"]}
    if set(a) != set(b):
        return f"the sequence holds other frames now ({len(a)} then, {len(b)} now)"
    changed = [nm for nm in b if a[nm] != b[nm]]
    if changed:
        return f"{len(changed)} frame file(s) changed since ({', '.join(changed[:3])}{' ...' if len(changed) > 3 else ''})"
    return None


def _read_record(path: Path) -> dict | None:
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def odometry_poses(seq, out: Path, report, verbosity: int = 0, force: bool = False) -> np.ndarray:
    """(F, 4, 4) poses of ``seq``'s frames: the cache in ``out`` when its record matches and not
    ``force``, else KISS-ICP over every frame (an unreadable frame: an empty scan), written to
    the cache with its record. The poses returned are those read back from the cache, so a
    resumed run compares the same values."""
    from floxels_ext.lidar.io import read_poses
    from floxels_ext.lidar.io.poses import PoseFormatError
    from floxels_ext.lidar.pipeline.progress import Progress
    from floxels_ext.lidar.preprocess.odometry import kiss_icp_poses
    from floxels_ext.output_paths import replace_atomically

    cache, record_path = out / CACHE_NAME, out / RECORD_NAME
    record = odometry_record(seq)
    if cache.is_file():
        why = "--force" if force else _record_diff(_read_record(record_path), record)
        if why is None:
            try:
                poses = read_poses(cache)
                if len(poses) == len(seq):
                    report(f"reusing odometry poses from {cache} (computed from these frames)")
                    return poses
                why = f"it holds {len(poses)} poses for {len(seq)} frames"
            except PoseFormatError as e:
                why = f"it cannot be read ({e})"
        report(f"recomputing the odometry poses in {cache}: {why}")

    def scans():
        for i in range(len(seq)):
            try:
                yield seq.load(i).points
            except ValueError:
                yield np.zeros((0, 3), np.float32)

    bar = Progress(len(seq), "frames (KISS-ICP odometry)", verbosity=verbosity)
    poses = kiss_icp_poses(scans(), progress=lambda i: bar.update(), **ODOMETRY_SETTINGS)
    bar.close()
    record_path.unlink(missing_ok=True)  # no record until the new poses are in place
    pid = os.getpid()
    replace_atomically(cache.with_name(f".{cache.name}.{pid}.tmp"), cache,
                       lambda t: np.savetxt(t, poses[:, :3, :].reshape(len(poses), 12), fmt="%.17g"))
    text = json.dumps(record) + "\n"
    replace_atomically(record_path.with_name(f".{record_path.name}.{pid}.tmp"), record_path,
                       lambda t: t.write_text(text))
    report(f"wrote odometry poses to {cache} (KITTI format; what they were computed from: {record_path.name})")
    return read_poses(cache)
