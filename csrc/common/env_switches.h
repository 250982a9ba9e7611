// Every environment variable the C++/CUDA code reads, one documented function each, and the
// FLOXELS_PROFILING build option. The kernels and launchers call these functions; nothing
// else in csrc/ calls getenv. (Switches of the Python package are read and documented there.)
//
// Plain C++ (no torch, no CUDA headers): included by .cpp and .cu files alike.
#pragma once
#include <cstdlib>
#include <cstring>

// FLOXELS_PROFILING: 1 in a profiling build (CMake option FLOXELS_PROFILING=ON, see
// CMakeLists.txt), 0 otherwise. Only a profiling build contains the measurement-only code
// (the traced persistent loop kernel, FLOXELS_SOLVER_TRACE and FLOXELS_SOLVER_SKIP), so a
// release build cannot be made to print or to compute wrong results by an environment
// variable. torch.ops.floxels.has_profiling() tells which build is loaded.
#ifndef FLOXELS_PROFILING
#define FLOXELS_PROFILING 0
#endif

namespace floxels::env {

inline constexpr bool kProfiling = FLOXELS_PROFILING != 0;

namespace detail {
// Unset: `dflt`; exactly "0": false; any other value (the empty string included): true.
inline bool flag(const char* name, bool dflt) {
  const char* v = std::getenv(name);
  return v == nullptr ? dflt : !(v[0] == '0' && v[1] == '\0');
}
}  // namespace detail

// --- CUDA solver (csrc/cuda/solver.cu) ------------------------------------------------------

enum class Persistent { kAuto, kOff, kOn };

// FLOXELS_SOLVER_PERSISTENT: which iteration solver_run uses on CUDA. "0": always two kernels
// per iteration; "1": the persistent cooperative loop kernel whenever the device can run it
// at all (even when the point blocks do not all fit at once); unset or any other value: auto
// (the loop when every point block fits on the GPU at once). Default auto. Read on every
// solver_run and solver_loop_blocks call (tests and tools/profile_solver.py set it).
inline Persistent solver_persistent() {
  const char* v = std::getenv("FLOXELS_SOLVER_PERSISTENT");
  if (v != nullptr && v[0] == '0' && v[1] == '\0') return Persistent::kOff;
  if (v != nullptr && v[0] == '1' && v[1] == '\0') return Persistent::kOn;
  return Persistent::kAuto;
}

// FLOXELS_SOLVER_MAX_GRID: a cap on the persistent loop kernel's grid (blocks), as parsed by
// atoi; 0 (unset, not a positive number): no cap. Tests use it to make every block walk many
// point and vertex blocks, as large batches do. Read on every solver_run and
// solver_loop_blocks call.
inline int solver_max_grid() {
  const char* v = std::getenv("FLOXELS_SOLVER_MAX_GRID");
  const int cap = v != nullptr ? std::atoi(v) : 0;
  return cap > 0 ? cap : 0;
}

// FLOXELS_SOLVER_PDL: programmatic dependent launch of the two-kernel iteration (sm_90).
// Default on; "0" turns it off (e.g. for per-kernel GPU times, where PDL makes kernel spans
// overlap). Read on every solver_run call that takes the two-kernel iteration.
inline bool solver_pdl() { return detail::flag("FLOXELS_SOLVER_PDL", true); }

// FLOXELS_SOLVER_TRACE (profiling builds only; always false otherwise): "1" (any value but
// "0") launches the traced persistent loop kernel, which prints per-phase times per
// iteration. Default off. Read on every solver_run call that takes the persistent loop.
inline bool solver_trace() {
  if constexpr (kProfiling) return detail::flag("FLOXELS_SOLVER_TRACE", false);
  return false;
}

// FLOXELS_SOLVER_SKIP (profiling builds only; always 0 otherwise): with the trace, a bit mask
// (atoi) of parts of the iteration the traced loop leaves out, to attribute time; the results
// are then WRONG. 1 DT look-ups, 2 segment sums, 4 cluster u sums, 8 loss reduction, 16 flow
// gather, 32 vertex gradient gather, 64 next means. Default 0. Read with the trace.
inline int solver_skip() {
  if constexpr (kProfiling) {
    const char* v = std::getenv("FLOXELS_SOLVER_SKIP");
    return v != nullptr ? std::atoi(v) : 0;
  }
  return 0;
}

// --- CUDA DBSCAN (csrc/cuda/dbscan_binding.cpp) ---------------------------------------------

// FLOXELS_CPU_DBSCAN: exactly "1" routes floxels::dbscan on CUDA input to the exact CPU kernel
// (identical labels, copied back to the input's device): an escape hatch from the GPU kernel.
// Default off. Read once per process, at the first CUDA dbscan call.
inline bool cpu_dbscan() {
  static const bool on = [] {
    const char* v = std::getenv("FLOXELS_CPU_DBSCAN");
    return v != nullptr && std::strcmp(v, "1") == 0;
  }();
  return on;
}

}  // namespace floxels::env
