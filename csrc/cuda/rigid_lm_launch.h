// Plain launcher of floxels::rigid_lm's CUDA kernel (no torch types), so that rigid_lm.cu
// compiles with nvcc alone; the torch binding (rigid_lm_binding.cpp) checks inputs, allocates
// the outputs and calls it. Scans as for dt_loss (DtLossScanDesc; `weight` is scan k's w_k).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_loss_launch.h"

namespace floxels::cuda {

// One block per cluster (C blocks; nothing runs for C == 0): the whole Levenberg-Marquardt loop
// of `iters` steps in one launch, the sums over a cluster's rows reduced in a fixed order
// (the same bits on every run), no host synchronisation.
cudaError_t launch_rigid_lm(const float* points, const float* rel, const int64_t* segments, const float* theta,
                            const float* vz, int64_t m, int64_t num_clusters, const DtLossScanDesc* scans,
                            int num_scans, double spacing, double tau, int64_t iters, float* theta_out,
                            float* cost_out, cudaStream_t stream);
cudaError_t launch_rigid_lm(const double* points, const double* rel, const int64_t* segments, const double* theta,
                            const double* vz, int64_t m, int64_t num_clusters, const DtLossScanDesc* scans,
                            int num_scans, double spacing, double tau, int64_t iters, double* theta_out,
                            double* cost_out, cudaStream_t stream);

}  // namespace floxels::cuda
