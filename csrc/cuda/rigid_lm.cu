// CUDA kernel of floxels::rigid_lm (math in kernels/rigid_lm.h): one block per cluster runs
// the whole Levenberg-Marquardt loop. Per evaluation each thread sums its rows' terms in
// double, the warps reduce by shuffles and thread 0 adds the warps' sums in order (a fixed
// order: the same bits on every run); thread 0 takes the step decision and the block reads the
// next motion from shared memory. The scans' metadata travels by value in the kernel
// parameters (__grid_constant__, as in dt_query.cu).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_scan.cuh"
#include "cuda/rigid_lm_launch.h"
#include "kernels/dt_loss.h"
#include "kernels/rigid_lm.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;  // the refinement samples at most 256 rows per cluster
constexpr int kWarps = kThreads / 32;
constexpr int kS = rigid_lm::kSums;

template <typename T>
struct Params {
  dt_loss::Scan<T, int> scans[dt_loss::kMaxScans];
  const T* points;
  const T* rel;
  const int64_t* segments;
  const T* theta;
  const T* vz;
  T* theta_out;
  T* cost_out;
  int64_t m;
  int num_scans;
  int iters;
  T inv_spacing;
  T tau;
};

// The cluster's sums at motion th (shared), divided by n, into out (shared); every thread calls it.
template <typename T>
__device__ void cluster_sums(const Params<T>& p, int64_t begin, int64_t end, double n, T vz, const T* th,
                             double (*warp_sums)[kWarps], double* out) {
  double s[kS];
#pragma unroll
  for (int j = 0; j < kS; ++j) s[j] = 0.0;
  for (int64_t i = begin + threadIdx.x; i < end; i += kThreads) {
    const T* q = p.points + 3 * i;
    const T* r = p.rel + 3 * i;
    rigid_lm::add_point<T, int>(p.scans, p.num_scans, p.inv_spacing, p.tau, q[0], q[1], q[2], r[0], r[1], th, vz, s);
  }
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
  for (int j = 0; j < kS; ++j) {
    double v = s[j];
    for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
    if (lane == 0) warp_sums[j][warp] = v;
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    for (int j = 0; j < kS; ++j) {
      double total = 0.0;
      for (int w = 0; w < kWarps; ++w) total += warp_sums[j][w];
      out[j] = total / n;
    }
  }
  __syncthreads();
}

template <typename T>
__global__ void __launch_bounds__(kThreads) lm_kernel(const __grid_constant__ Params<T> p) {
  __shared__ double warp_sums[kS][kWarps];
  __shared__ double s[kS], st[kS];
  __shared__ T th[3], trial[3];
  __shared__ double lam;
  const int64_t c = blockIdx.x;
  int64_t begin = 0, end = 0;
  rigid_lm::cluster_rows(p.segments, c, p.m, begin, end);
  const double n = end > begin ? double(end - begin) : 1.0;
  const T vz = p.vz[c];
  if (threadIdx.x == 0) {
    for (int j = 0; j < 3; ++j) th[j] = p.theta[3 * c + j];
    lam = rigid_lm::kLamStart;
  }
  __syncthreads();
  cluster_sums(p, begin, end, n, vz, th, warp_sums, s);
  for (int it = 0; it < p.iters; ++it) {
    if (threadIdx.x == 0) rigid_lm::trial_step<T>(s, lam, th, trial);
    __syncthreads();
    cluster_sums(p, begin, end, n, vz, trial, warp_sums, st);
    if (threadIdx.x == 0) {
      double l = lam;
      rigid_lm::accept<T>(trial, st, th, s, l);
      lam = l;
    }
    __syncthreads();
  }
  if (threadIdx.x == 0) {
    for (int j = 0; j < 3; ++j) p.theta_out[3 * c + j] = th[j];
    p.cost_out[c] = T(s[9]);
  }
}

template <typename T>
cudaError_t lm_impl(const T* points, const T* rel, const int64_t* segments, const T* theta, const T* vz, int64_t m,
                    int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing, double tau,
                    int64_t iters, T* theta_out, T* cost_out, cudaStream_t stream) {
  if (num_clusters == 0) return cudaSuccess;
  Params<T> p{};
  for (int k = 0; k < num_scans; ++k) p.scans[k] = device_scan<T>(scans[k], scans[k].weight);
  p.points = points;
  p.rel = rel;
  p.segments = segments;
  p.theta = theta;
  p.vz = vz;
  p.theta_out = theta_out;
  p.cost_out = cost_out;
  p.m = m;
  p.num_scans = num_scans;
  p.iters = static_cast<int>(iters);
  p.inv_spacing = T(1.0 / spacing);
  p.tau = T(tau);
  lm_kernel<T><<<static_cast<unsigned>(num_clusters), kThreads, 0, stream>>>(p);
  return cudaGetLastError();
}

}  // namespace

cudaError_t launch_rigid_lm(const float* points, const float* rel, const int64_t* segments, const float* theta,
                            const float* vz, int64_t m, int64_t num_clusters, const DtLossScanDesc* scans,
                            int num_scans, double spacing, double tau, int64_t iters, float* theta_out,
                            float* cost_out, cudaStream_t stream) {
  return lm_impl<float>(points, rel, segments, theta, vz, m, num_clusters, scans, num_scans, spacing, tau, iters,
                        theta_out, cost_out, stream);
}

cudaError_t launch_rigid_lm(const double* points, const double* rel, const int64_t* segments, const double* theta,
                            const double* vz, int64_t m, int64_t num_clusters, const DtLossScanDesc* scans,
                            int num_scans, double spacing, double tau, int64_t iters, double* theta_out,
                            double* cost_out, cudaStream_t stream) {
  return lm_impl<double>(points, rel, segments, theta, vz, m, num_clusters, scans, num_scans, spacing, tau, iters,
                         theta_out, cost_out, stream);
}

}  // namespace floxels::cuda
