"""Ego-motion from the scans themselves, through KISS-ICP (Vizzo et al., RA-L 2023), an established
lidar odometry pipeline published on PyPI as ``kiss-icp``. Optional: ``pip install 'floxels_ext[odometry]'``.

Only used when a sequence comes without poses. KISS-ICP's poses are sensor-to-world with the
world frame being the first scan's sensor frame, which is all that ego-motion compensation needs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from floxels_ext.lidar.io._optional import MissingDependencyError, require

__all__ = ["kiss_icp_poses", "MissingDependencyError"]


def kiss_icp_poses(scans: Iterable[np.ndarray], *, max_range: float = 100.0, min_range: float = 0.0,
                   voxel_size: float | None = None, deskew: bool = False,
                   progress: Callable[[int], None] | None = None) -> np.ndarray:
    """(F, 4, 4) float64 sensor-to-world poses of ``scans`` ((N_i, 3) arrays in their sensor frames,
    consecutive, rows with NaN/inf are ignored) estimated by KISS-ICP. ``voxel_size`` defaults to
    KISS-ICP's own choice (max_range / 100). ``deskew`` needs per-point timestamps, which generic
    frame files lack, so it is off. An empty scan keeps the constant-velocity prediction."""
    require("kiss_icp", "odometry", "kiss-icp", "estimating ego-motion without poses (--odometry kiss-icp)")
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    cfg = load_config(None)
    cfg.data.max_range = float(max_range)
    cfg.data.min_range = float(min_range)
    cfg.data.deskew = bool(deskew)
    cfg.mapping.voxel_size = float(voxel_size) if voxel_size else float(max_range) / 100.0
    odom = KissICP(cfg)
    poses = []
    for i, scan in enumerate(scans):
        pts = np.asarray(scan, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts):
            odom.register_frame(np.ascontiguousarray(pts), np.zeros(0))
        else:  # nothing to register: assume constant velocity
            odom.last_pose = odom.last_pose @ odom.last_delta
        poses.append(np.array(odom.last_pose, dtype=np.float64))
        if progress is not None:
            progress(i)
    return np.stack(poses) if poses else np.zeros((0, 4, 4))
