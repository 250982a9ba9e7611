// CUDA kernels of the fused multi-scan distance-transform loss: one thread per point,
// each looping over the K scans (math in kernels/dt_loss.h). Every scan's metadata is
// passed by value in the kernel parameters (__grid_constant__: read through the constant
// bank, never copied to local memory), so a launch needs no host-to-device copy.
//
// The loss is reduced deterministically without a host sync: each block writes one
// double partial, then a one-block kernel sums the partials in a fixed order and writes
// the loss in the points' dtype. Gradients are written per point (no atomics). A row whose
// point or flow has a NaN/inf coordinate makes the loss NaN and gets a zero gradient row.
//
// The 8 corner loads per scan are gathers: sorting the points spatially (done by the
// caller, once per frame) makes neighbouring threads hit the same cache lines.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/block_reduce.cuh"
#include "cuda/dt_loss_launch.h"
#include "cuda/dt_scan.cuh"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels::cuda {
namespace {

using cuda_detail::block_sum;
constexpr int kThreads = 256;
constexpr int kFinalThreads = 256;

template <typename T>
struct Params {
  dt_loss::Scan<T, int> scans[dt_loss::kMaxScans];
  const T* points;
  const T* flow;
  const T* grad_scale;  // null: 1
  T* grad_out;
  double* partials;  // one per block
  int n;
  int num_scans;
  T inv_spacing;
  T truncation;
};

template <typename T, bool kLoss, bool kGrad>
__global__ void __launch_bounds__(kThreads) dt_loss_kernel(const __grid_constant__ Params<T> p) {
  const int i = blockIdx.x * kThreads + threadIdx.x;
  T l = T(0);
  if (i < p.n) {
    const T* pi = p.points + 3 * static_cast<int64_t>(i);
    const T* fi = p.flow + 3 * static_cast<int64_t>(i);
    T g[3];
    l = dt_loss::point_loss<kGrad, T, int>(p.scans, p.num_scans, pi[0], pi[1], pi[2], fi[0], fi[1], fi[2],
                                           p.inv_spacing, p.truncation, g);
    // Non-finite point or flow row: the loss shows it (NaN), its gradient row is 0.
    const bool bad = !finite3(pi[0], pi[1], pi[2]) || !finite3(fi[0], fi[1], fi[2]);
    if (bad) l = quiet_nan<T>();
    if constexpr (kGrad) {
      const T s = bad ? T(0) : (p.grad_scale ? *p.grad_scale : T(1));
      if (bad) g[0] = g[1] = g[2] = T(0);
      T* go = p.grad_out + 3 * static_cast<int64_t>(i);
      go[0] = s * g[0];
      go[1] = s * g[1];
      go[2] = s * g[2];
    }
  }
  if constexpr (kLoss) {
    // every thread of the block takes part (out-of-range threads add 0)
    const double total = block_sum<kThreads>(static_cast<double>(l));
    if (threadIdx.x == 0) p.partials[blockIdx.x] = total;
  }
}

template <typename T>
__global__ void __launch_bounds__(kFinalThreads)
    sum_partials_kernel(const double* __restrict__ partials, int num_partials, T* __restrict__ loss_out) {
  double v = 0.0;
  for (int j = threadIdx.x; j < num_partials; j += kFinalThreads) v += partials[j];
  const double total = block_sum<kFinalThreads>(v);
  if (threadIdx.x == 0) *loss_out = static_cast<T>(total);
}

int num_blocks(int64_t n) { return static_cast<int>((n + kThreads - 1) / kThreads); }

template <typename T, bool kLoss, bool kGrad>
cudaError_t launch_pass(const Params<T>& params, int blocks, T* loss_out, cudaStream_t stream) {
  dt_loss_kernel<T, kLoss, kGrad><<<blocks, kThreads, 0, stream>>>(params);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess || !kLoss) return err;
  sum_partials_kernel<T><<<1, kFinalThreads, 0, stream>>>(params.partials, blocks, loss_out);
  return cudaGetLastError();
}

template <typename T>
cudaError_t launch_impl(const T* points, const T* flow, int64_t n, const DtLossScanDesc* scans, int num_scans,
                        double spacing, double truncation, const T* grad_scale, T* loss_out, T* grad_out,
                        double* workspace, cudaStream_t stream) {
  if (num_scans < 1 || num_scans > dt_loss::kMaxScans || n < 0 || n > INT32_MAX) return cudaErrorInvalidValue;
  if (n == 0) return loss_out ? cudaMemsetAsync(loss_out, 0, sizeof(T), stream) : cudaSuccess;  // 0.0 is all-zero bits
  if (!loss_out && !grad_out) return cudaSuccess;
  Params<T> params{};
  for (int k = 0; k < num_scans; ++k) {
    params.scans[k] = device_scan<T>(scans[k], scans[k].weight / static_cast<double>(n));
  }
  params.points = points;
  params.flow = flow;
  params.grad_scale = grad_scale;
  params.grad_out = grad_out;
  params.partials = workspace;
  params.n = static_cast<int>(n);
  params.num_scans = num_scans;
  params.inv_spacing = T(1.0 / spacing);
  params.truncation = T(truncation);
  const int blocks = num_blocks(n);
  if (loss_out && grad_out) return launch_pass<T, true, true>(params, blocks, loss_out, stream);
  if (loss_out) return launch_pass<T, true, false>(params, blocks, loss_out, stream);
  return launch_pass<T, false, true>(params, blocks, loss_out, stream);
}

}  // namespace

int64_t dt_loss_workspace_size(int64_t n) { return n > 0 ? num_blocks(n) : 0; }

cudaError_t launch_dt_loss(const float* points, const float* flow, int64_t n, const DtLossScanDesc* scans,
                           int num_scans, double spacing, double truncation, const float* grad_scale,
                           float* loss_out, float* grad_out, double* workspace, cudaStream_t stream) {
  return launch_impl<float>(points, flow, n, scans, num_scans, spacing, truncation, grad_scale, loss_out,
                            grad_out, workspace, stream);
}

cudaError_t launch_dt_loss(const double* points, const double* flow, int64_t n, const DtLossScanDesc* scans,
                           int num_scans, double spacing, double truncation, const double* grad_scale,
                           double* loss_out, double* grad_out, double* workspace, cudaStream_t stream) {
  return launch_impl<double>(points, flow, n, scans, num_scans, spacing, truncation, grad_scale, loss_out,
                             grad_out, workspace, stream);
}

}  // namespace floxels::cuda
