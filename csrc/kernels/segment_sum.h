// Fixed-point sums by row (floxels::fixed_segment_sum): the per-term rule shared by the CPU
// (cpu/segment_sum_cpu.cpp) and CUDA (cuda/segment_sum.cu) implementations. Each finite term
// is clamped to +-limit and rounded (to nearest, ties to even) to a multiple of 1/kScale, and
// the integers are summed: integer addition is associative, so a row's sum is the same bits in
// any order and on any device (float atomics are not: issue 31). The same arithmetic as the
// PyTorch reference (reference/ops.py fixed_segment_sum: round(clamp(x) * 2^24) as int64, the
// sum as float64 / 2^24), so the op and the reference agree bit for bit.
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::segment_sum {

constexpr double kScale = 16777216.0;  // 2^24: estimator/group_sums.FIXED_POINT

// A finite term as its fixed-point integer; `limit` * kScale must stay below 2^62.
FLX_HD int64_t encode(double x, double limit) {
  const double c = x < -limit ? -limit : (x > limit ? limit : x);
#ifdef __CUDA_ARCH__
  return __double2ll_rn(c * kScale);
#else
  return static_cast<int64_t>(std::nearbyint(c * kScale));
#endif
}

// A row's integer sum back to float64: one rounding to double, then an exact power-of-two scaling.
FLX_HD double decode(int64_t s) { return static_cast<double>(s) / kScale; }

FLX_HD bool finite(double x) { return x - x == 0.0; }  // false for NaN and +-inf

}  // namespace floxels::segment_sum
