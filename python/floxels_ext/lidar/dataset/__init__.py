"""``floxels run DATASET``: many sequences through one pipeline. ``tasks`` finds the sequences
and cuts them into tasks; ``run`` holds the dataset options and runs the tasks here (one
progress bar) or hands them to ``ray_runner`` (one long-lived worker per GPU); ``worker`` runs
tasks through one pipeline in a process; ``sequence`` opens one task as the plain run opens a
sequence; ``stream`` and ``layout`` lay the tasks' chunks end to end in one index space.

Builds on ``pipeline`` (its checks, loader, writer, resume), ``preprocess`` and ``io``; nothing
below imports it."""
