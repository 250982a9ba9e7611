// Launcher of the device-resident Floxels optimiser (no torch types; see kernels/solver.h).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "kernels/solver_args.h"

namespace floxels::cuda {

// Bytes of device workspace solver_launch needs for `args` (256-byte aligned pieces).
int64_t solver_workspace_bytes(const solver::Args& args);

// Enqueues a few per-call setup kernels, then `num_iters` iterations (two kernels each, or
// all in one persistent loop launch: see solver_loop_blocks) on `stream`; no host
// synchronisation and no allocation, so the call can be captured into a CUDA graph (where
// the two-kernel iteration is used). Problems whose state row is inactive are skipped by
// every kernel, so extra iterations are cheap no-ops. Implemented in solver.cu (launcher) and
// solver_{setup,iteration,loop}.cu (kernels).
cudaError_t solver_launch(const solver::Args& args, int num_iters, void* workspace, cudaStream_t stream);

// Blocks of the persistent loop kernel solver_launch would use for problems with these
// B + 1 point / vertex offsets (all iterations of a call in one cooperative launch), or 0
// for two kernels per iteration. Default: the loop when every point block fits on the GPU
// at once (single frames, small batches), where launches and kernel fill/drain dominate;
// FLOXELS_SOLVER_PERSISTENT=0/1 forces either (common/env_switches.h lists the switches).
int solver_loop_blocks(const int64_t* point_ranges, const int64_t* vertex_ranges, int num_problems, bool cluster,
                       cudaStream_t stream);

}  // namespace floxels::cuda
