"""Lidar frame readers and pose files (see ``readers`` and ``poses``)."""

from ._optional import MissingDependencyError
from .poses import PoseFormatError, read_av2_poses, read_kitti_calib, read_poses
from .readers import SUFFIXES, LidarFormatError, LidarScan, natural_key, read_points

__all__ = ["LidarScan", "LidarFormatError", "PoseFormatError", "MissingDependencyError", "SUFFIXES",
           "read_points", "read_poses", "read_av2_poses", "read_kitti_calib", "natural_key"]
