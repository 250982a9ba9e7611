"""The lidar pipeline: from lidar files and poses to flow files, in five sub-packages.

``io`` reads frames and poses, finds sequences on disk and owns the flow-file format
(``io.outputs``); ``preprocess`` crops scans and removes the ground (numpy reference, compiled
op, GPU path), transforms them rigidly and estimates poses (KISS-ICP); ``pipeline`` runs one
sequence (``floxels run SEQ``: reading ahead, estimation, writing, resume); ``dataset`` runs
many (``floxels run DATASET``, here or on Ray); ``viz`` uses the outputs (``floxels show``,
``floxels accumulate``). ``run`` is the ``floxels run`` command: its options, and INPUT sent to
``dataset`` or ``pipeline``.

Imports go one way: ``run`` -> ``dataset`` -> ``pipeline`` -> ``preprocess`` -> ``io``, and
``viz`` -> ``io``. Kept light on import: the CLI imports the command modules when a command runs.
"""
