"""Per-scan preprocessing: cropping and ground removal (``masks``: numpy reference and the
dispatch to the compiled op; ``masks_torch``: the GPU path; ``settings``: what they share;
``ground_plane`` and ``ground_outliers``: two steps of the ground removal), rigid transforms
(``transform``) and KISS-ICP odometry (``odometry``, when a sequence has no poses)."""

from floxels_ext.lidar.preprocess.masks import (crop_mask, ground_estimate, ground_mask, ground_surface,
                                                preprocess_classes, preprocess_classes_numpy, preprocess_mask,
                                                preprocess_mask_numpy)
from floxels_ext.lidar.preprocess.settings import CROPPED, GROUND, KEPT, MAX_GROUND_CELLS, OUTLIER, Preprocess
from floxels_ext.lidar.preprocess.transform import host_rows, relative_pose, transform_points

__all__ = ["Preprocess", "preprocess_mask", "preprocess_mask_numpy", "preprocess_classes", "preprocess_classes_numpy",
           "ground_estimate", "ground_surface", "ground_mask", "crop_mask", "transform_points", "host_rows",
           "relative_pose", "CROPPED", "KEPT", "GROUND", "OUTLIER", "MAX_GROUND_CELLS"]
