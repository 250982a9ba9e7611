// Plain launcher of floxels::velocity_search's CUDA kernel (no torch types), so that
// velocity_search.cu compiles with nvcc alone; velocity_search_binding.cpp checks inputs,
// allocates the outputs and the scratch (``axes`` (C, 2) in T, ``global`` (C, 1 + directions *
// speeds) doubles) and calls it. Scans as for dt_loss (`weight`: scan k's w_k / sum w).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_loss_launch.h"

namespace floxels::cuda {

// Three launches (nothing runs for C == 0): the clusters' axes, the global candidates' scores
// over a grid of (cluster, candidate chunk) blocks, and the pattern search, a block per
// cluster; each score summed in a fixed order (the same bits on every run).
cudaError_t launch_velocity_search(const float* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, float* axes, double* global, float* best,
                                   float* best_score, float* zero_score, cudaStream_t stream);
cudaError_t launch_velocity_search(const double* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, double* axes, double* global, double* best,
                                   double* best_score, double* zero_score, cudaStream_t stream);

}  // namespace floxels::cuda
