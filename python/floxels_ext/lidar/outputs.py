"""Moved to :mod:`floxels_ext.lidar.io.outputs` (issue 32's split of the lidar package).

The README documented ``floxels_ext.lidar.outputs.read_flow_output`` before the split, so user
scripts may import it from here; this name stays, with a DeprecationWarning on import."""

import warnings

from floxels_ext.lidar.io.outputs import *  # noqa: F401,F403
from floxels_ext.lidar.io.outputs import __all__  # noqa: F401

warnings.warn("floxels_ext.lidar.outputs moved to floxels_ext.lidar.io.outputs", DeprecationWarning, stacklevel=2)
