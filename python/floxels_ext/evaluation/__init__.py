"""Evaluation: the lidar simulator with exact ground truth (``sim``), its sequence format
(``seqio``), the scene-flow metrics (``metrics``) and benchmark protocols (``protocol``:
Argoverse 2 classes, evaluation box), the ``floxels eval`` and ``floxels simulate`` commands,
and the demo (``floxels demo``)."""
