"""Checks of ``floxels run``'s frames (issue 45): whether an estimated frame may be written (one
check for both delivery points: one sequence, ``estimate_loop``; a dataset, ``dataset/stream``),
and what a frame read says about its file (float32 coordinates far out, no ground within the
ground grid's reach), warned about once by the loader.

A frame is not written, and fails with the reason, when the method says it has no estimate
(``fields["failure"]``: Floxels' optimisation diverged) or when none of its support scans
(``Method.support_frames``: Floxels' window, a baseline's pair) could be read: the method then
saw empty scans beside its target and answered zero flow, which was written as "all static"
(``--scans 2`` with the next frame's file broken: 0 moving points instead of 2,652).
"""

from __future__ import annotations

import numpy as np

__all__ = ["frame_failure", "float32_far_message", "beyond_ground_grid", "FLOAT32_FAR"]


def frame_failure(method, options: dict, loader, i: int, n: int, fields=None) -> str | None:
    """Why frame ``i`` (of ``n``; its own scan read) gets no output, or None to write it.
    ``loader.get(j)`` is None for a frame that could not be used (``loader.errors[j]`` says why)."""
    if fields and fields.get("failure"):
        return str(fields["failure"])
    if method.support_frames is None:
        return None
    support = method.support_frames(i, n, options)
    if not support or any(loader.get(j) is not None for j in support):
        return None
    names = [loader.seq.frames[j].path.name for j in support]
    first = loader.errors.get(support[0], "unreadable")
    return (f"no support scan: none of the scans its estimate reads besides its own ({', '.join(names)}) could be "
            f"used, so no flow could be estimated ({first})")


# float32 coordinates beyond this (m) resolve worse than 7.8 mm: such a file is warned about
FLOAT32_FAR = 65536.0


def float32_far_message(path, pts: np.ndarray) -> str | None:
    """A warning for a float32 file whose coordinates lie so far out that float32 has lost
    their precision (judged on <= 4096 rows), else None."""
    sample = np.abs(pts[::max(1, len(pts) // 4096)])
    reach = float(np.max(sample, initial=0.0, where=np.isfinite(sample)))
    if reach <= FLOAT32_FAR:
        return None
    return (f"{path} stores float32 coordinates up to {reach:.4g} m from the origin, where float32 resolves only "
            f"{float(np.spacing(np.float32(reach))):.3g} m: its points lost that precision when the file was "
            f"written; store them as float64 (floxels run reads float64 files in float64), or relative to a "
            f"nearby point")


def beyond_ground_grid(path, pts_sensor: np.ndarray, settings, pose_mode: str) -> str | None:
    """Why no ground was removed from a frame whose points all lie beyond the ground grid's
    reach from its sensor origin (points of a world frame at map scale read with
    ``--no-ego-motion``: the grid is measured from the world origin), else None."""
    p = np.asarray(pts_sensor, np.float64)
    p = p[np.isfinite(p).all(axis=1)]
    if not len(p):
        return None
    r = float(np.hypot(p[:, 0], p[:, 1]).min())
    if r <= settings.grid_distance:
        return None
    return (f"{path}: no ground removed: its points lie {r:.4g} m and more from the sensor origin, beyond the ground "
            f"grid's reach ({settings.grid_distance:g} m)" +
            ("; --no-ego-motion measures from the world origin: give the sensor poses ('pose' in the file with "
             "--points-frame world, or --poses) or --no-ground-removal" if pose_mode == "identity" else
             "; check the poses (--poses/--calib) or the frame of the points"))
