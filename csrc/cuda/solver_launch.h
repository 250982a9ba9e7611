// Launcher of the device-resident Floxels optimiser (no torch types; see kernels/solver.h).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "kernels/solver_args.h"

namespace floxels::cuda {

// Bytes of device workspace solver_launch needs for `args` (256-byte aligned pieces).
int64_t solver_workspace_bytes(const solver::Args& args);

// Enqueues a few per-call setup kernels, then `num_iters` iterations (two kernels each) on
// `stream`; no host synchronisation
// and no allocation, so the call can be captured into a CUDA graph. Problems whose state
// row is inactive are skipped by every kernel, so extra iterations are cheap no-ops.
cudaError_t solver_launch(const solver::Args& args, int num_iters, void* workspace, cudaStream_t stream);

}  // namespace floxels::cuda
