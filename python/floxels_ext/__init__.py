"""floxels_ext: fast unsupervised voxel-based scene flow (Floxels, CVPR 2025).

torch is imported before the compiled ``_C`` module, which links libtorch.
"""

import torch  # noqa: F401

from . import ops, reference  # noqa: F401  (loads _C and registers torch.ops.floxels.*)
from .config import FloxelsConfig
from .estimator import DistanceTransform, Floxels, FloxelsResult, estimate_flow, estimate_sequence

__all__ = ["FloxelsConfig", "Floxels", "FloxelsResult", "DistanceTransform", "estimate_flow",
           "estimate_sequence", "ops", "reference"]

__version__ = "0.1.0"
