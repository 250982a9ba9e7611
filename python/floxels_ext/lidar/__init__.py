"""The lidar pipeline: from lidar files and poses to flow files.

``io`` reads frames and poses; ``preprocess`` (numpy) / ``preprocess_torch`` (GPU) crop and
remove the ground; ``odometry`` estimates poses when none are given; ``run`` is the
``floxels run`` command, ``frame_loader`` and ``pipeline`` overlap reading, preprocessing,
estimation and writing; ``outputs`` is the flow-file format; ``dataset``, ``dataset_run`` and
``ray_runner`` run whole datasets, locally or on a Ray cluster; ``accumulate`` and ``show``
use the outputs (densified clouds, pictures).

Kept light on import: the CLI imports the command modules when a command runs.
"""
