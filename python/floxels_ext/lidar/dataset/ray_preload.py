"""What a Ray worker of ``floxels run --ray`` imports before its first job, for Ray to load into
its idle worker processes ahead of time.

A fresh worker's start is mostly ``import torch`` (1-3 s; ~3 s with four workers starting at
once on a 4-GPU host) before its CUDA context and warm-up. Ray can start idle Python workers
when a node starts and import modules into them (``RAY_enable_worker_prestart=1
RAY_preload_python_modules=floxels_ext.lidar.dataset.ray_preload``, set for ``ray start``);
an actor placed on such a process skips those imports, so the first job on a fresh cluster
starts its workers in about the time of their CUDA context (docs/datasets-and-ray.md).

Importing this module does not touch CUDA: the GPU a worker gets is only known once Ray places
an actor on the process (``CUDA_VISIBLE_DEVICES``), and the CUDA context comes in the worker's
warm-up.
"""

from __future__ import annotations

import time

import torch  # noqa: F401 - the point of this module

import floxels_ext.ops  # noqa: F401 - the compiled ops
from floxels_ext.lidar.dataset.ray_worker import import_pipeline  # the actor class Ray loads

import_pipeline()  # what the worker's warm-up would import

PRELOADED = time.time()  # when the imports ended (the worker's timeline shows it as "preloaded")

# the environment to set for `ray start` (printed by the docs and used by tools/gpu_ray_bench.sh)
RAY_ENV = {"RAY_enable_worker_prestart": "1", "RAY_preload_python_modules": __name__}
