"""``floxels_ext.ops``: checked Python wrappers around ``torch.ops.floxels.*``.

Importing this module loads the compiled library and registers the fake (meta) and
autograd implementations, so the raw ops also work under ``torch.compile``/``opcheck``.
"""

from floxels_ext.ops._lib import has_cuda_kernels, ops_ns
from floxels_ext.ops.corners import CompactCorners, compact_corners, corner_gather, corner_scatter
from floxels_ext.ops.cluster import cluster_consistency_fwd_bwd, cluster_consistency_loss, cluster_mean
from floxels_ext.ops.dbscan import dbscan
from floxels_ext.ops.dt_loss import dt_loss, dt_loss_fwd_bwd
from floxels_ext.ops.dt_query import dt_evidence, dt_residual, dt_sample
from floxels_ext.ops.edt import distance_transform, edt, points_to_occupancy
from floxels_ext.ops.grid import DEFAULT_MAX_CELLS, GridTooLargeError, grid_for_points
from floxels_ext.ops.lidar import frame_flow, lidar_keep_mask, lidar_point_classes, lidar_select, rigid_transform
from floxels_ext.ops.nearest import nearest_neighbor
from floxels_ext.ops.rigid_lm import rigid_lm
from floxels_ext.ops.segment_sum import fixed_segment_sum
from floxels_ext.ops.velocity_search import velocity_search
from floxels_ext.ops.setup import ProblemSetup, problem_setup, stage_points
from floxels_ext.ops.trilinear import trilinear_gather, trilinear_scatter

__all__ = [
    "ops_ns", "has_cuda_kernels",
    "trilinear_gather", "trilinear_scatter",
    "edt", "points_to_occupancy", "distance_transform",
    "dt_loss", "dt_loss_fwd_bwd",
    "dt_residual", "dt_sample", "dt_evidence", "rigid_lm", "velocity_search",
    "dbscan",
    "cluster_mean", "cluster_consistency_loss", "cluster_consistency_fwd_bwd",
    "corner_gather", "corner_scatter", "compact_corners", "CompactCorners",
    "grid_for_points", "GridTooLargeError", "DEFAULT_MAX_CELLS",
    "problem_setup", "ProblemSetup", "stage_points",
    "nearest_neighbor",
    "fixed_segment_sum",
    "lidar_keep_mask", "lidar_point_classes", "rigid_transform", "lidar_select", "frame_flow",
]
