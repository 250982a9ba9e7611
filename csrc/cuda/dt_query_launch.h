// Plain launchers of the data-only distance-transform look-ups (dt_residual, dt_sample,
// dt_evidence; no torch types), so that dt_query.cu compiles with nvcc alone; the torch binding
// (dt_query_binding.cpp) checks inputs, allocates outputs and the workspace, and calls these.
// Scans are described as for dt_loss (DtLossScanDesc, `weight` used as given: no 1/N).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_loss_launch.h"

namespace floxels::cuda {

// out (n) = sum_k weight_k * c(min(DT_k(p + t_k m), cap)), c = x or x^2; NaN for a non-finite row.
cudaError_t launch_dt_residual(const float* points, const float* motion, int64_t n, const DtLossScanDesc* scans,
                               int num_scans, double spacing, double cap, bool squared, const int32_t* observed, float* out,
                               cudaStream_t stream);
cudaError_t launch_dt_residual(const double* points, const double* motion, int64_t n, const DtLossScanDesc* scans,
                               int num_scans, double spacing, double cap, bool squared, const int32_t* observed, double* out,
                               cudaStream_t stream);

// out (num_scans, n, 4) = [DT_k(p + t_k m), d DT_k / d q]; NaN value and zero gradient for a
// non-finite row.
cudaError_t launch_dt_sample(const float* points, const float* motion, int64_t n, const DtLossScanDesc* scans,
                             int num_scans, double spacing, float* out, cudaStream_t stream);
cudaError_t launch_dt_sample(const double* points, const double* motion, int64_t n, const DtLossScanDesc* scans,
                             int num_scans, double spacing, double* out, cudaStream_t stream);

// Group keys of dt_evidence: int32 or int64 values `stride` elements apart (data null: none).
struct GroupKeys {
  const void* data;
  int64_t stride;
  bool is64;
};

// Bytes of device workspace dt_evidence needs for n points.
int64_t dt_evidence_workspace_bytes(int64_t n);

// The motion evidence of n points (n < 2^31; nothing runs for n == 0) in 4 kernels whatever
// the number of scans: residuals and per-block totals, a one-block scan of the block totals,
// per point prefix sums (double) and its group's first/last point, then per point the group
// sums as prefix-sum differences and the test. Fixed reduction orders, no atomics, no host
// synchronisation: the same bits on every run.
cudaError_t launch_dt_evidence(const float* points, const float* flow, int64_t n, GroupKeys labels,
                               GroupKeys cells, const DtLossScanDesc* scans, int num_scans, double spacing,
                               double cap, double margin, double ratio, const int32_t* observed, float* score, bool* explained,
                               float* res_flow, float* res_zero, void* workspace, cudaStream_t stream);
cudaError_t launch_dt_evidence(const double* points, const double* flow, int64_t n, GroupKeys labels,
                               GroupKeys cells, const DtLossScanDesc* scans, int num_scans, double spacing,
                               double cap, double margin, double ratio, const int32_t* observed, double* score, bool* explained,
                               double* res_flow, double* res_zero, void* workspace, cudaStream_t stream);

}  // namespace floxels::cuda
