// Finite-ness tests for the ops' non-finite input contract (docs/ops.md), shared by
// the CPU and CUDA kernels. Plain comparisons on values the kernel has already loaded: no
// function call, no extra pass. (NaN compares false; the build never uses -ffast-math /
// finite-math-only, which would fold these tests away.)
#pragma once
#include <limits>

#include "common/cuda_compat.h"

namespace floxels {

template <typename T>
FLX_HD bool is_finite(T v) {
  return v >= -std::numeric_limits<T>::max() && v <= std::numeric_limits<T>::max();
}

// All three coordinates of an (x, y, z) row are finite.
template <typename T>
FLX_HD bool finite3(T x, T y, T z) {
  return is_finite(x) && is_finite(y) && is_finite(z);
}

template <typename T>
FLX_HD T quiet_nan() {
  return std::numeric_limits<T>::quiet_NaN();
}

}  // namespace floxels
