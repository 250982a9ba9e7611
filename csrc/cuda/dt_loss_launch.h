// Plain launchers of the fused multi-scan distance-transform loss (no torch types), so
// that dt_loss.cu compiles with nvcc alone; the torch binding (dt_loss_binding.cpp)
// checks inputs, allocates outputs and the workspace, and calls these.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// One scan as described by the host (converted to the compute type by the launcher).
struct DtLossScanDesc {
  const float* data;  // (nz, ny, nx) float32, contiguous, on the device; nx*ny*nz < 2^31
  int64_t nx, ny, nz;
  double ox, oy, oz;  // origin [x0, y0, z0]
  double time_offset;
  double weight;
};

// Doubles of device workspace the launcher needs for n points (per-block loss partials).
int64_t dt_loss_workspace_size(int64_t n);

// One fused pass over n points (n < 2^31; for n == 0 no kernel runs and loss_out, if
// non-null, is zeroed with cudaMemsetAsync).
//  * loss_out (device, 1 value) receives the loss if non-null, written by a second
//    one-block kernel that sums the per-block partials in a fixed order (deterministic,
//    no host sync);
//  * grad_out (device, n x 3) receives d loss / d flow if non-null, multiplied by
//    *grad_scale when grad_scale (device, 1 value) is non-null.
// Returns the first launch error, cudaSuccess otherwise.
cudaError_t launch_dt_loss(const float* points, const float* flow, int64_t n, const DtLossScanDesc* scans,
                           int num_scans, double spacing, double truncation, const float* grad_scale,
                           float* loss_out, float* grad_out, double* workspace, cudaStream_t stream);
cudaError_t launch_dt_loss(const double* points, const double* flow, int64_t n, const DtLossScanDesc* scans,
                           int num_scans, double spacing, double truncation, const double* grad_scale,
                           double* loss_out, double* grad_out, double* workspace, cudaStream_t stream);

}  // namespace floxels::cuda
