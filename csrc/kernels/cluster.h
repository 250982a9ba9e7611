// Cluster-consistency math shared by the CPU and CUDA kernels.
//
// loss = (1/N) sum_i ||f_i - m_{c(i)}||, m_c the mean flow of cluster c, noise (label -1) adds 0.
// With u_i = (f_i - m_c) / ||f_i - m_c|| (0 where the norm is 0) the gradient of a clustered
// point is (u_i - mean_{j in c} u_j) / N: the mean's own dependence on f_i contributes the
// second term; noise points get 0.
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::cluster {

// Labels outside [0, K) (noise, or invalid input that the checks missed) are skipped so a
// kernel can never index out of bounds.
FLX_HD bool valid_label(int64_t label, int64_t K) { return label >= 0 && label < K; }

// d = f - mean (C values); writes u = d / ||d|| (or 0) and returns ||d||. A non-finite flow
// (or mean) gives a NaN (or inf) norm, so the loss shows it, and u = 0: returning `sq`
// instead of 0 costs nothing (docs/ops.md, non-finite input).
template <typename T>
FLX_HD T residual_unit(const T* f, const T* mean, int64_t C, T* u) {
  T sq = T(0);
  for (int64_t c = 0; c < C; ++c) {
    const T d = f[c] - mean[c];
    u[c] = d;
    sq += d * d;
  }
  if (!(sq > T(0))) {  // 0, or NaN
    for (int64_t c = 0; c < C; ++c) u[c] = T(0);
    return sq;
  }
  using std::sqrt;
  const T n = sqrt(sq);
  for (int64_t c = 0; c < C; ++c) u[c] /= n;
  return n;
}

template <typename T>
FLX_HD T residual_norm(const T* f, const T* mean, int64_t C) {
  T sq = T(0);
  for (int64_t c = 0; c < C; ++c) {
    const T d = f[c] - mean[c];
    sq += d * d;
  }
  using std::sqrt;
  return sq > T(0) ? T(sqrt(sq)) : sq;  // 0, or NaN for a non-finite flow
}

}  // namespace floxels::cluster
