"""floxels_ext: fast unsupervised voxel-based scene flow (Floxels, CVPR 2025).

torch is imported before the compiled ``_C`` module, which links libtorch.

Layout (docs/architecture.md): ``ops`` (the compiled ops and their Python registration),
``estimator`` (the Floxels optimiser), ``lidar`` (files to flow files: ``floxels run``),
``evaluation`` (simulator, metrics, protocols), ``baselines`` (NSFP, FastNSF), ``reference``
(pure-PyTorch oracles), ``methods`` (the registry ``floxels run`` picks methods from) and
``cli`` (the ``floxels`` command, which only dispatches).
"""

import torch  # noqa: F401

from floxels_ext import ops, reference  # noqa: F401  (loads _C and registers torch.ops.floxels.*)
from floxels_ext.estimator import (DistanceTransform, Floxels, FloxelsConfig, FloxelsResult, estimate_flow,
                                   estimate_sequence)

__all__ = ["FloxelsConfig", "Floxels", "FloxelsResult", "DistanceTransform", "estimate_flow",
           "estimate_sequence", "ops", "reference"]

__version__ = "0.1.0"
