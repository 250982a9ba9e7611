"""Lidar files: frame readers (``readers``, ``pcd_ply``, ``scan``), pose files (``poses``), sequences
on disk (``sources``), point-cloud writers (``writers``) and the flow-file format of ``floxels run``
(``outputs``). The bottom of the lidar package: imports nothing else of it."""

from floxels_ext.lidar.io._optional import MissingDependencyError
from floxels_ext.lidar.io.poses import PoseFormatError, read_av2_poses, read_kitti_calib, read_poses
from floxels_ext.lidar.io.readers import SUFFIXES, LidarFormatError, LidarScan, natural_key, read_points

__all__ = ["LidarScan", "LidarFormatError", "PoseFormatError", "MissingDependencyError", "SUFFIXES",
           "read_points", "read_poses", "read_av2_poses", "read_kitti_calib", "natural_key"]
