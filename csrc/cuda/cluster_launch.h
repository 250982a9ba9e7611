// Plain launchers for the cluster CUDA kernels (no torch types). Labels outside [0, K) are
// treated as noise (the Python wrappers reject them; checking here would need a host sync).
// The per-cluster sums they read are formed by the binding (cluster_binding.cpp) in a fixed
// order, so every result is deterministic.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// Per point i of flow (N, C) with cluster c = labels[i]: norms[i] (may be null) =
// ||f_i - m_c|| (0 for noise) and, when u is given, u (N, C) = (f_i - m_c) / ||f_i - m_c||
// (0 rows for noise and zero residuals), where m_c = sums[c] / counts[c].
template <typename T>
void cluster_residuals(const T* flow, const int64_t* labels, int64_t N, int64_t C, int64_t K, const T* sums,
                       const T* counts, T* norms, T* u, cudaStream_t s);

// In place on grad (N, C) holding the unit residuals: grad_i = (*grad_scale or 1) / N *
// (u_i - usums[c] / counts[c]) for clustered points (noise rows stay 0).
template <typename T>
void cluster_grad(const int64_t* labels, int64_t N, int64_t C, int64_t K, const T* counts, const T* usums,
                  const T* grad_scale, T* grad, cudaStream_t s);

}  // namespace floxels::cuda
