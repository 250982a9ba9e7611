"""Pure-PyTorch references: one per op (``ops``, re-exported here, so that
``floxels_ext.reference.trilinear_gather`` is the reference of
``torch.ops.floxels.trilinear_gather``) and the whole estimator (``estimator``: scipy EDT,
scikit-learn DBSCAN, ``grid_sample``, ``torch.optim.Adam``). Tests compare the ops and the
estimator against them; they are slow by design."""

from floxels_ext.reference.ops import *  # noqa: F401,F403
from floxels_ext.reference.ops import __all__  # noqa: F401
