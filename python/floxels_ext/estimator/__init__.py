"""The estimator: configuration, scan staging, the optimisation of one frame or a batch of
frames on top of ``torch.ops.floxels``, and sliding windows over a sequence.

``api`` is the public surface (re-exported by ``floxels_ext``); ``group`` prepares and solves
a group of target frames together, its data steps in execution order; ``schedule`` says where
each step runs on a GPU (streams, events, waits, page-locked staging); ``windows`` slides the
windows over a sequence or a stream of them; ``scans`` validates and uploads the input scans; ``solver_run`` drives the device-resident solver op;
``evidence`` tests after the optimisation whether a group's flow explains the support scans
better than zero flow (``FloxelsConfig.evidence``).
"""

from floxels_ext.estimator.api import (DistanceTransform, Floxels, FloxelsResult, estimate_flow,
                                       estimate_sequence, window_for)
from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.evidence import MotionEvidence, group_ids, motion_evidence

__all__ = ["FloxelsConfig", "Floxels", "FloxelsResult", "DistanceTransform", "estimate_flow",
           "estimate_sequence", "window_for", "MotionEvidence", "motion_evidence", "group_ids"]
