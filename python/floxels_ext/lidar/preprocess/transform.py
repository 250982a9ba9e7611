"""Rigid transforms of scans (ego-motion compensation) with the compiled CPU op, and the
zero-copy view of a numpy array that the lidar ops take.
"""

from __future__ import annotations

import numpy as np

__all__ = ["transform_points", "host_rows", "relative_pose"]


def transform_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points (NaN rows stay NaN), in float64; float32 out.
    (The compiled :func:`floxels_ext.ops.rigid_transform`: numpy's ``p @ R.T + t`` to the last
    bit of the float32 result, without the GIL.)"""
    import torch

    from floxels_ext.ops.lidar import rigid_transform

    out = rigid_transform(host_rows(np.asarray(points).reshape(-1, 3)), torch.from_numpy(np.asarray(T, np.float64)))
    return out.numpy().astype(np.float32, copy=False)


def host_rows(points: np.ndarray):
    """``points`` as a CPU tensor for the lidar ops, without a copy where torch can view it
    (float32/float64, positive strides, writeable; the ops read any strides); other dtypes
    become float64."""
    import torch

    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    if not p.flags.writeable or any(s <= 0 or s % p.itemsize for s in p.strides):
        p = np.ascontiguousarray(p)
        if not p.flags.writeable:
            p = p.copy()
    return torch.from_numpy(p)


def relative_pose(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """Transform taking coordinates of the frame with sensor-to-world pose ``pose_from`` into
    the frame with pose ``pose_to``: ``inv(pose_to) @ pose_from``."""
    return np.linalg.solve(np.asarray(pose_to, np.float64), np.asarray(pose_from, np.float64))
