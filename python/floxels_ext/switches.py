"""Every ``FLOXELS_*`` environment variable in one place: its default, who reads it, and why.

Build switches choose what is compiled. Runtime switches only change how work is scheduled
or which kernel runs; results stay the same (to float tolerance), except where a row says
otherwise, and those exist in profiling builds only. Python reads its runtime switches with
:func:`flag` when the work starts (so tests and benchmarks may set them per run); the C++
ones are read in ``csrc/common/env_switches.h``. ``tests/test_switches.py`` checks that every
``FLOXELS_*`` name in the sources is listed here and in the table of docs/switches.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

__all__ = ["Switch", "SWITCHES", "flag"]


@dataclass(frozen=True)
class Switch:
    name: str
    default: str
    read_by: str
    meaning: str


SWITCHES: tuple[Switch, ...] = (
    # build
    Switch("FLOXELS_CUDA", "AUTO", "build (CMakeLists.txt)",
           "compile the CUDA kernels: AUTO (iff the installed torch has CUDA), ON (required), OFF"),
    Switch("FLOXELS_PROFILING", "OFF", "build (CMakeLists.txt)",
           "profiling build: compiles the solver's phase trace and skip masks in (tools/profile_solver.py); "
           "release builds do not contain them"),
    Switch("FLOXELS_SOLVER_TRACE", "0", "C++ solver launcher, profiling builds only",
           "1 = the persistent solver kernel prints per-phase times from the GPU clock"),
    Switch("FLOXELS_SOLVER_SKIP", "0", "C++ solver launcher, profiling builds only",
           "bit mask of solver parts left out to attribute time; results are WRONG (measurement only)"),
    # runtime, C++
    Switch("FLOXELS_SOLVER_PERSISTENT", "auto", "C++ solver launcher, every call",
           "1 / 0 force the persistent loop kernel / the two-kernel iteration (tests cover both)"),
    Switch("FLOXELS_SOLVER_MAX_GRID", "unset", "C++ solver launcher, every call",
           "caps the persistent kernel's grid, so that each block walks many point and vertex blocks (tests)"),
    Switch("FLOXELS_SOLVER_PDL", "1", "C++ solver launcher, every call",
           "programmatic dependent launch in the two-kernel iteration (sm_90); 0 = off (e.g. under ncu)"),
    Switch("FLOXELS_CPU_DBSCAN", "0", "CUDA DBSCAN binding, once per process",
           "1 = DBSCAN of CUDA input runs on the CPU (escape hatch; same labels)"),
    # runtime, Python (measurement switches of optimisations that are on by default)
    Switch("FLOXELS_SERIAL_STAGES", "0", "estimator (estimator/schedule.py), every group",
           "1 = the preparation stages run one after another with synchronisations, for per-stage "
           "timings (bench/bench_speed.py)"),
    Switch("FLOXELS_EARLY_DT", "1", "estimator (estimator/schedule.py), every frame",
           "0 = support-scan EDTs wait for the whole upload instead of starting scan by scan"),
    Switch("FLOXELS_PIPELINE", "1", "estimate_sequence, every call",
           "0 = the next batch is not prepared while the GPU optimises the current one"),
    Switch("FLOXELS_RAMP", "1", "estimate_sequence, every call",
           "0 = full-size first batches instead of 4, 8, ... frames"),
    # tests and CI
    Switch("FLOXELS_AV2_PAIR", "unset", "tests/conftest.py (the tests on the Argoverse 2 pair)",
           "path of the shared Argoverse 2 pair (.npz) when it is not under ../shared/data"),
    Switch("FLOXELS_REQUIRE_SHARED", "0", "tests (tests/shared_data.py); .ci/run sets 1",
           "1 = tests that read ../shared (the paper, the real data) fail where it is missing instead of skipping"),
    Switch("FLOXELS_CI_VENV", "/tmp/floxels-ci-venv", ".ci/run", "the virtual environment CI creates"),
)

_BY_NAME = {s.name: s for s in SWITCHES}


def flag(name: str) -> bool:
    """A Python-read 0/1 runtime switch: True unless it is "0" (default "1") or True only when
    it is "1" (default "0")."""
    sw = _BY_NAME[name]
    value = os.environ.get(name, sw.default)
    return value != "0" if sw.default == "1" else value == "1"
