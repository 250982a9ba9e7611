// CUDA cluster reductions. Per-cluster sums/counts and unit-residual sums use warp-aggregated
// atomics (labels of neighbouring points are often equal, and a big cluster is a hot
// address); the loss is reduced per warp before one atomicAdd. Workspace layout (zeroed by the
// caller): sums (K*C) | counts (K) | unit-residual sums (K*C).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/cluster_launch.h"
#include "cuda/warp_aggregate.cuh"
#include "kernels/cluster.h"

namespace floxels::cuda {
namespace {

constexpr int kBlock = 256;
constexpr int kMaxC = 8;  // channels kept in registers; larger C loops over global memory

int64_t blocks_for(int64_t n) { return (n + kBlock - 1) / kBlock; }

template <typename T>
__global__ void sums_kernel(const T* __restrict__ v, const int64_t* __restrict__ labels, int64_t N, int C,
                            int64_t K, T* __restrict__ sums, T* __restrict__ counts) {
  __shared__ T scratch[kBlock];
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  const int64_t l = i < N ? labels[i] : -1;
  const int64_t key = cluster::valid_label(l, K) ? l : -1;
  T* ws = scratch + (threadIdx.x & ~31);
  const T one = T(1);
  cuda_detail::warp_add(sums, key, int64_t(C), int64_t(1), v + (key >= 0 ? i : 0) * C, T(1), C, ws);
  cuda_detail::warp_add(counts, key, int64_t(1), int64_t(1), &one, T(1), 1, ws);
}

template <typename T>
__global__ void mean_kernel(const T* __restrict__ sums, const T* __restrict__ counts, int64_t K, int64_t C,
                            T* __restrict__ out) {
  const int64_t j = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (j >= K * C) return;
  const T n = counts[j / C];
  out[j] = n > T(0) ? sums[j] / n : T(0);
}

// Norms of the residuals (summed into *loss, pre-divided by N) and, when grad is given, the
// unit residuals u_i (written to grad) and their per-cluster sums.
template <typename T>
__global__ void residual_kernel(const T* __restrict__ f, const int64_t* __restrict__ labels, int64_t N, int C,
                                int64_t K, const T* __restrict__ sums, const T* __restrict__ counts,
                                T* __restrict__ usums, T* __restrict__ loss, T* __restrict__ grad) {
  __shared__ T scratch[kBlock];
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  const int64_t l = i < N ? labels[i] : -1;
  const int64_t key = cluster::valid_label(l, K) ? l : -1;
  T norm = T(0);
  T ubuf[kMaxC];
  if (key >= 0) {
    T mean[kMaxC];
    const T inv = T(1) / counts[key];
    if (C <= kMaxC) {
      for (int c = 0; c < C; ++c) mean[c] = sums[key * C + c] * inv;
      norm = cluster::residual_unit(f + i * C, mean, C, ubuf);
    } else {  // rare wide case: compute the norm channel by channel
      T sq = T(0);
      for (int c = 0; c < C; ++c) {
        const T d = f[i * C + c] - sums[key * C + c] * inv;
        sq += d * d;
      }
      norm = sq > T(0) ? sqrt(sq) : sq;  // 0, or NaN for a non-finite flow (as cluster.h)
      if (grad)
        for (int c = 0; c < C; ++c)
          grad[i * C + c] = norm > T(0) ? (f[i * C + c] - sums[key * C + c] * inv) / norm : T(0);
    }
    if (grad && C <= kMaxC)
      for (int c = 0; c < C; ++c) grad[i * C + c] = ubuf[c];
  } else if (grad && i < N) {
    for (int c = 0; c < C; ++c) grad[i * C + c] = T(0);
  }
  if (loss) {
    const T s = cuda_detail::warp_sum(norm);
    if ((threadIdx.x & 31) == 0 && s != T(0)) atomicAdd(loss, s / T(N));
  }
  if (grad) {
    const T* src = key >= 0 ? (C <= kMaxC ? ubuf : grad + i * C) : ubuf;
    cuda_detail::warp_add(usums, key, int64_t(C), int64_t(1), src, T(1), C, scratch + (threadIdx.x & ~31));
  }
}

// grad_i = scale * (u_i - mean_c u) / N for clustered points (noise rows are already 0).
template <typename T>
__global__ void grad_kernel(const int64_t* __restrict__ labels, int64_t N, int C, int64_t K,
                            const T* __restrict__ counts, const T* __restrict__ usums, const T* grad_scale,
                            T* __restrict__ grad) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i >= N) return;
  const int64_t l = labels[i];
  if (!cluster::valid_label(l, K)) return;
  const T scale = (grad_scale ? *grad_scale : T(1)) / T(N);
  const T inv = T(1) / counts[l];
  for (int c = 0; c < C; ++c) grad[i * C + c] = scale * (grad[i * C + c] - usums[l * C + c] * inv);
}

}  // namespace

template <typename T>
void cluster_mean(const T* values, const int64_t* labels, int64_t N, int64_t C, int64_t K, T* workspace, T* out,
                  cudaStream_t s) {
  if (K == 0 || C == 0) return;
  T* sums = workspace;
  T* counts = workspace + K * C;
  if (N > 0)
    sums_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(values, labels, N, static_cast<int>(C), K, sums, counts);
  mean_kernel<T><<<blocks_for(K * C), kBlock, 0, s>>>(sums, counts, K, C, out);
}

template <typename T>
void cluster_consistency(const T* flow, const int64_t* labels, int64_t N, int64_t C, int64_t K, T* workspace,
                         T* loss, T* grad, const T* grad_scale, cudaStream_t s) {
  if (N == 0) return;
  T* sums = workspace;
  T* counts = workspace + K * C;
  T* usums = counts + K;
  const int c = static_cast<int>(C);
  sums_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(flow, labels, N, c, K, sums, counts);
  residual_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(flow, labels, N, c, K, sums, counts, usums, loss, grad);
  if (grad) grad_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(labels, N, c, K, counts, usums, grad_scale, grad);
}

#define FLX_INSTANTIATE(T)                                                                                  \
  template void cluster_mean<T>(const T*, const int64_t*, int64_t, int64_t, int64_t, T*, T*, cudaStream_t); \
  template void cluster_consistency<T>(const T*, const int64_t*, int64_t, int64_t, int64_t, T*, T*, T*,     \
                                       const T*, cudaStream_t);
FLX_INSTANTIATE(float)
FLX_INSTANTIATE(double)
#undef FLX_INSTANTIATE

}  // namespace floxels::cuda
