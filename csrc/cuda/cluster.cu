// CUDA cluster reductions, deterministic (issue 31): the per-cluster sums (values, counts,
// unit residuals) are formed by the binding with index_put_(accumulate=True), which sorts
// the keys stably and adds each cluster's rows in index order (no float atomics), and the
// loss is the sum of per-point norms by one ATen reduction (fixed tree). These kernels do the
// per-point work: residual norms and unit residuals from the sums, and the gradient.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/cluster_launch.h"
#include "kernels/cluster.h"

namespace floxels::cuda {
namespace {

constexpr int kBlock = 256;
constexpr int kMaxC = 8;  // channels kept in registers; larger C loops over global memory

int64_t blocks_for(int64_t n) { return (n + kBlock - 1) / kBlock; }

// Per point: the norm of its residual to its cluster's mean (0 for noise) into norms (may be
// null) and, when u is given, the unit residual u_i (0 rows for noise).
template <typename T>
__global__ void residual_kernel(const T* __restrict__ f, const int64_t* __restrict__ labels, int64_t N, int C,
                                int64_t K, const T* __restrict__ sums, const T* __restrict__ counts,
                                T* __restrict__ norms, T* __restrict__ u) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i >= N) return;
  const int64_t l = labels[i];
  const int64_t key = cluster::valid_label(l, K) ? l : -1;
  T norm = T(0);
  if (key >= 0) {
    const T inv = T(1) / counts[key];
    if (C <= kMaxC) {
      T mean[kMaxC], ubuf[kMaxC];
      for (int c = 0; c < C; ++c) mean[c] = sums[key * C + c] * inv;
      norm = cluster::residual_unit(f + i * C, mean, C, ubuf);
      if (u)
        for (int c = 0; c < C; ++c) u[i * C + c] = ubuf[c];
    } else {  // rare wide case: compute the norm channel by channel
      T sq = T(0);
      for (int c = 0; c < C; ++c) {
        const T d = f[i * C + c] - sums[key * C + c] * inv;
        sq += d * d;
      }
      norm = sq > T(0) ? sqrt(sq) : sq;  // 0, or NaN for a non-finite flow (as cluster.h)
      if (u)
        for (int c = 0; c < C; ++c) u[i * C + c] = norm > T(0) ? (f[i * C + c] - sums[key * C + c] * inv) / norm : T(0);
    }
  } else if (u) {
    for (int c = 0; c < C; ++c) u[i * C + c] = T(0);
  }
  if (norms) norms[i] = norm;
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
void cluster_residuals(const T* flow, const int64_t* labels, int64_t N, int64_t C, int64_t K, const T* sums,
                       const T* counts, T* norms, T* u, cudaStream_t s) {
  if (N == 0) return;
  residual_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(flow, labels, N, static_cast<int>(C), K, sums, counts, norms,
                                                      u);
}

template <typename T>
void cluster_grad(const int64_t* labels, int64_t N, int64_t C, int64_t K, const T* counts, const T* usums,
                  const T* grad_scale, T* grad, cudaStream_t s) {
  if (N == 0) return;
  grad_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(labels, N, static_cast<int>(C), K, counts, usums, grad_scale,
                                                  grad);
}

#define FLX_INSTANTIATE(T)                                                                                    \
  template void cluster_residuals<T>(const T*, const int64_t*, int64_t, int64_t, int64_t, const T*, const T*, \
                                     T*, T*, cudaStream_t);                                                   \
  template void cluster_grad<T>(const int64_t*, int64_t, int64_t, int64_t, const T*, const T*, const T*, T*,  \
                                cudaStream_t);
FLX_INSTANTIATE(float)
FLX_INSTANTIATE(double)
#undef FLX_INSTANTIATE

}  // namespace floxels::cuda
