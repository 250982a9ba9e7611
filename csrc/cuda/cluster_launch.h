// Plain launchers for the cluster CUDA kernels (no torch types). Labels outside [0, K) are
// treated as noise (the Python wrappers reject them; checking here would need a host sync).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// Scratch the launchers below need, in elements of T; the caller zeroes it.
inline int64_t cluster_workspace_elems(int64_t K, int64_t C) { return 2 * K * C + K; }

// out (K, C) = per-cluster mean of values (N, C); empty clusters give 0.
template <typename T>
void cluster_mean(const T* values, const int64_t* labels, int64_t N, int64_t C, int64_t K, T* workspace, T* out,
                  cudaStream_t s);

// loss (zeroed scalar, may be null) += (1/N) sum_i ||f_i - m_c(i)||;
// grad (N, C, may be null) = (*grad_scale or 1) * d loss / d flow.
template <typename T>
void cluster_consistency(const T* flow, const int64_t* labels, int64_t N, int64_t C, int64_t K, T* workspace,
                         T* loss, T* grad, const T* grad_scale, cudaStream_t s);

}  // namespace floxels::cuda
