"""Baselines in the Floxels framework: NSFP (Li et al., NeurIPS 2021) and Fast Neural Scene
Flow (Li et al., ICCV 2023), for side-by-side comparisons (``bench/compare.py``) and
``floxels run --method nsfp|fastnsf``.

>>> flow = estimate_flow_nsfp(scan_t, scan_t1, NSFPConfig(max_iters=1000), device="cuda")
>>> flow = estimate_flow_fastnsf(scan_t, scan_t1)
"""

from . import registry  # noqa: F401  (registers "nsfp" and "fastnsf" in floxels_ext.methods)
from ._common import BaselineResult
from .chamfer import nearest_neighbors, nn_distances, truncated_chamfer
from .config import FastNSFConfig, NSFPConfig
from .fastnsf import estimate_flow_fastnsf, fit_fastnsf
from .mlp import CoordinateMLP
from .nsfp import estimate_flow_nsfp, fit_nsfp

__all__ = [
    "NSFPConfig", "FastNSFConfig", "BaselineResult", "CoordinateMLP",
    "estimate_flow_nsfp", "fit_nsfp", "estimate_flow_fastnsf", "fit_fastnsf",
    "truncated_chamfer", "nearest_neighbors", "nn_distances",
]
