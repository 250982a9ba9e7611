"""How many engines share one GPU by default: ``floxels run``'s ``--engines`` (local engine
processes, ``run.engine_count``) and the Ray workers a GPU (``ray_runner.gpu_share``) follow
the same rule, measured on the local engines and on Ray (bench/RESULTS.md).
"""

from __future__ import annotations

import math

__all__ = ["default_engines", "gpu_share", "THREE_ENGINE_CORES", "ACCURATE_ENGINES"]

# Default engines on a GPU: each one's readers, writers and optimiser thread keep ~4 cores busy;
# on a host of at least THREE_ENGINE_CORES cores a third engine filled the GPU's remaining gaps
# (one H100, 16 cores, 768 frames: three engines faster in 8 of 8 runs, `paper` 1.02-1.58x,
# `accurate` 1.08-1.38x; bench/RESULTS.md, C5)
THREE_ENGINE_CORES = 16
# `accurate`'s host steps a frame (the refinement, the sights, the evidence: ~1,100 launches and
# ~5 host reads a frame against `paper`'s ~300 and 2) keep three engines waiting on the host: a
# fourth gave 98.8-105.5 frames/s against three's 72.8-102.9 (one H200, 16 cores, 768 frames,
# two runs each; `paper` with four: 230-279 against 246-281, so it keeps three; bench/RESULTS.md)
ACCURATE_ENGINES = 4


def default_engines(device: str, cores: int | None = None, preset: str = "paper") -> int:
    """Engines sharing ``device`` by default on a host of ``cores`` cores (None: this one's; for
    a Ray node, its cores per GPU), running ``preset`` (the Floxels preset in effect; ``paper``
    for other methods): 1 on the CPU; on CUDA 2, or on 16+ cores 3 (4 with ``accurate``)."""
    if not device.startswith("cuda"):
        return 1
    if cores is None:
        from floxels_ext.cpu_threads import usable_cores

        cores = usable_cores()
    if cores < THREE_ENGINE_CORES:
        return 2
    return ACCURATE_ENGINES if preset == "accurate" else 3


# Default GPUs a worker asks for on a GPU cluster: 1/W, W workers sharing each GPU, W the local
# run's engines on a host of the GPU nodes' cores per GPU (:func:`default_engines`: 2, or on 16+
# cores a GPU 3, 4 with `accurate`). One worker leaves its GPU idle while its host steps run
# (reading, set-up, results); the others' kernels fill those gaps (time-sliced contexts).
# Measured (bench/RESULTS.md): two a GPU 1.41x one (2 x H200); three a GPU against two with
# `paper` on 4 x H100, 64 cores, 96 x 150 frames: 1.08x on 1 GPU, 1.06x on 2, 1.16x on 4 ("Ray on
# four H100s", ninth session). Rounded down to Ray's 4 decimals (3 x 0.3333 fit a GPU).
def gpu_share(nodes: list[dict], preset: str) -> float:
    """GPUs a worker asks for by default on a cluster of ``nodes`` (resource dicts) running ``preset``."""
    per_gpu = [r.get("CPU", 0.0) / r["GPU"] for r in nodes if r.get("GPU", 0.0) >= 1]
    w = default_engines("cuda", int(min(per_gpu)) if per_gpu else 0, preset)
    return math.floor(1e4 / w) / 1e4
