// Compact trilinear gather/scatter: each point reads/writes 8 rows of a (M, C) parameter
// table through precomputed corner indices and weights. Shared by CPU and CUDA.
#pragma once
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::corners {

constexpr int kCorners = 8;

// out[c] = sum_j w[j] * params[idx[j] * C + c] for one point.
template <typename T>
FLX_HD void gather_point(const T* params, const int32_t* idx, const T* w, int64_t C, T* out) {
  for (int64_t c = 0; c < C; ++c) out[c] = T(0);
  for (int j = 0; j < kCorners; ++j) {
    const T* row = params + int64_t(idx[j]) * C;
    for (int64_t c = 0; c < C; ++c) out[c] += w[j] * row[c];
  }
}

}  // namespace floxels::corners
