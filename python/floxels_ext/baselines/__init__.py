"""Baselines in the Floxels framework: NSFP (Li et al., NeurIPS 2021) and Fast Neural Scene
Flow (Li et al., ICCV 2023), for side-by-side comparisons (``bench/compare.py``) and
``floxels run --method nsfp|fastnsf``.

>>> flow = estimate_flow_nsfp(scan_t, scan_t1, NSFPConfig(max_iters=1000), device="cuda")
>>> flow = estimate_flow_fastnsf(scan_t, scan_t1)
"""

from floxels_ext.baselines import registry  # noqa: F401  (registers "nsfp" and "fastnsf" in floxels_ext.methods)
from floxels_ext.baselines._common import BaselineResult
from floxels_ext.baselines.chamfer import nearest_neighbors, nn_distances, truncated_chamfer
from floxels_ext.baselines.config import FastNSFConfig, NSFPConfig
from floxels_ext.baselines.fastnsf import estimate_flow_fastnsf, fit_fastnsf
from floxels_ext.baselines.mlp import CoordinateMLP
from floxels_ext.baselines.nsfp import estimate_flow_nsfp, fit_nsfp

__all__ = [
    "NSFPConfig", "FastNSFConfig", "BaselineResult", "CoordinateMLP",
    "estimate_flow_nsfp", "fit_nsfp", "estimate_flow_fastnsf", "fit_fastnsf",
    "truncated_chamfer", "nearest_neighbors", "nn_distances",
]
