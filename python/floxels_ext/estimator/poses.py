"""Each scan's pose as users have it (``poses=``: (n, 4, 4) world-from-sensor matrices, the
matrices that compensated the ego-motion, as ``floxels run`` reads them from pose files), turned
into what the estimator reads: each scan's sensor position in the scans' frame (the pose's
translation), the ``sensor_origins=`` of ``range_mask`` and ``visibility`` (the ``accurate``
preset's sights, estimator/sight.py).

A pose must be a rigid motion (orthonormal rotation of determinant +1, last row (0, 0, 0, 1),
finite); a matrix that is not one is a mistake of the caller (a sensor-from-world matrix is still
rigid, but then its translation is not the sensor's position: docs/api.md says which one to pass).
Both ``poses=`` and ``sensor_origins=`` may be given only where they agree.
"""

from __future__ import annotations

import numpy as np
import torch

from floxels_ext.estimator.scans import check_sensors

__all__ = ["check_poses", "resolve_sensors", "RIGID_TOL", "AGREE_TOL"]

RIGID_TOL = 1e-3   # max |R^T R - I| and |det R - 1| of a pose's rotation (float32 poses: ~1e-7)
AGREE_TOL = 1e-3   # m: a sensor_origins row and its pose's translation must agree this well


def check_poses(poses, n: int) -> list[np.ndarray | None]:
    """``poses`` (one (4, 4) world-from-sensor matrix per scan: an (n, 4, 4) array or tensor, or a
    sequence of (4, 4) matrices with None for a scan whose pose is unknown) as float64 (4, 4)
    arrays (or None); ValueError/TypeError naming the scan and the problem."""
    if isinstance(poses, (str, bytes)) or not hasattr(poses, "__len__"):
        raise TypeError(f"poses must be one (4, 4) world-from-sensor matrix per scan, e.g. an (n, 4, 4) array; "
                        f"got {type(poses).__name__}")
    if isinstance(poses, torch.Tensor):
        poses = poses.detach().cpu().numpy()
    if isinstance(poses, np.ndarray) and poses.dtype != object and poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (n, 4, 4) (one world-from-sensor matrix per scan), "
                         f"got {poses.shape}")
    if len(poses) != n:
        raise ValueError(f"poses must hold one (4, 4) matrix per scan: got {len(poses)} for {n} scans")
    return [None if p is None else _check_pose(p, i) for i, p in enumerate(poses)]


def _check_pose(p, i: int) -> np.ndarray:
    if isinstance(p, torch.Tensor):
        p = p.detach().cpu().numpy()
    try:
        a = np.asarray(p, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"poses[{i}] must be a (4, 4) matrix of numbers, got {type(p).__name__}") from None
    if a.shape != (4, 4):
        raise ValueError(f"poses[{i}] must be a (4, 4) world-from-sensor matrix, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"poses[{i}] is not finite: {a.tolist()}")
    if np.abs(a[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        raise ValueError(f"poses[{i}] is not a rigid motion: its last row is {a[3].tolist()}, not [0, 0, 0, 1]")
    r = a[:3, :3]
    ortho = float(np.abs(r.T @ r - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if ortho > RIGID_TOL or abs(det - 1.0) > RIGID_TOL:
        what = "a reflection" if det < 0 else f"not orthonormal (|R^T R - I| up to {ortho:.3g})"
        raise ValueError(f"poses[{i}] is not a rigid motion: its rotation is {what}; pass world-from-sensor "
                         f"matrices [R t; 0 0 0 1] with R a rotation")
    return a


def resolve_sensors(sensor_origins, poses, n: int):
    """The sensor positions the estimator reads: ``sensor_origins`` as given when there are no
    ``poses``, else the poses' translations (checked, as :func:`check_poses`); where both are given
    they must agree (within ``AGREE_TOL`` metres, and unknown for the same scans)."""
    if poses is None:
        return sensor_origins
    from_poses = [None if p is None else p[:3, 3].copy() for p in check_poses(poses, n)]
    if sensor_origins is not None:
        given = check_sensors(sensor_origins, n)
        for i, (a, b) in enumerate(zip(given, from_poses)):
            if (a is None) != (b is None):
                raise ValueError(f"poses and sensor_origins contradict each other at scan {i}: one of them "
                                 f"is None; give only poses=")
            if a is not None and np.abs(a - b).max() > AGREE_TOL:
                raise ValueError(f"poses and sensor_origins contradict each other at scan {i}: sensor_origins "
                                 f"{a.tolist()} but the pose's translation is {b.tolist()}; give only poses= "
                                 f"(its translations are the sensor positions)")
    return from_poses
