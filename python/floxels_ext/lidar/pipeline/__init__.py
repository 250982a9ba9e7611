"""One sequence through ``floxels run``: the run (``run_sequence``; its checks ``run_args``, its
poses and times ``run_inputs``, what each output was computed from ``resume``), the machinery
that overlaps reading, estimation and writing (``frame_loader``: readers and preprocessing
ahead; ``estimate_loop``: the method's calls chunk by chunk; ``frame_writer``: writers;
``worker_processes``: ``--worker-kind process``) and the progress bars (``progress``).

Imports ``io`` and ``preprocess``, never ``dataset``, ``viz`` or ``lidar.run``."""
