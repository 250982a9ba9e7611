"""The lidar pipeline: from lidar files and poses to flow files.

``io`` reads frames and poses; ``preprocess`` (numpy) / ``preprocess_torch`` (GPU) crop and
remove the ground; ``odometry`` estimates poses when none are given; ``run`` is the
``floxels run`` command, ``frame_loader`` and ``pipeline`` overlap reading, preprocessing,
estimation and writing; ``outputs`` is the flow-file format; ``dataset`` (finding sequences,
tasks), ``dataset_run`` (options, the local run), ``dataset_worker`` / ``dataset_sequence`` /
``dataset_stream`` (every sequence through one pipeline) and ``ray_runner`` (one worker per
GPU on a Ray cluster) run whole datasets; ``accumulate`` and ``show`` use the outputs
(densified clouds, pictures).

Kept light on import: the CLI imports the command modules when a command runs.
"""
