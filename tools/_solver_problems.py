"""The solver problems the estimator builds for a simulated ~100k-point sequence, shared by
the profiling scripts (tools/profile_solver.py, tools/ncu_solver.py)."""
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "bench"))
from bench_speed import _frames  # noqa: E402

import floxels_ext.estimator.group as E  # noqa: E402  (where the estimator packs its problems)
from floxels_ext import estimate_sequence  # noqa: E402


def simulated_scans(num_frames: int, beams: int = 128, scene: str = "urban"):
    return _frames(scene, 0, num_frames, beams, 2048)[0]


def problems_of(scans, cfg, batch: int):
    """SolverProblems of targets 2 .. 2 + batch - 1 (one call group, DTs shared)."""
    captured = {}
    orig = E.PackedProblems

    def grab(problems, c):
        captured["problems"] = problems
        return orig(problems, c)

    E.PackedProblems = grab
    try:
        estimate_sequence(scans[:batch + 4], cfg.replace(max_iters=2), device="cuda",
                          frames=list(range(2, 2 + batch)), batch_size=batch)
    finally:
        E.PackedProblems = orig
    return captured["problems"]
