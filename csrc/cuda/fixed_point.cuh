// Deterministic sums by fixed-point integer atomics (the CUDA solver's cluster sums and loss).
//
// Float atomics add in whatever order the blocks arrive, and float addition is not
// associative, so the last bits of a sum change from run to run; the optimiser then takes a
// different path (issue 31). Where many blocks add into one slot (a big cluster's mean and
// u sum, a problem's loss), each contribution is converted to a 64-bit integer with a fixed
// power-of-two scale and added with an integer atomic: integer addition is associative, so
// the sum is the same whatever the order, and whatever else is batched with a problem.
// Contributions are clamped to a documented range so that no sum can overflow; the range is
// far beyond what a sensible solve produces (see each constant). Everything before the
// conversion (per-lane values, fixed-order warp run sums) is deterministic already.
// nvcc only.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda_detail::fixed {

using Acc = unsigned long long;  // two's complement int64 bits; atomicAdd on it wraps like int64

// Sums of unit residuals u_i (|component| <= 1 after clamping) over a cluster's points:
// scale 2^32, so |sum| <= N * 2^32 < 2^63 for every N < 2^31 (point indices are int32);
// resolution 2^-32 = 2.3e-10 per contribution.
constexpr float kUnitScale = 4294967296.0f;  // 2^32
// Cluster means m_c = sum_v A_cv theta_v with A_cv >= 0 and sum_v A_cv = 1: scale 2^32
// (resolution 2.3e-10 m), each parameter clamped to +-2^24 m (16,777 km: a solve that
// reaches it has diverged), so |m_c| * 2^32 <= 2^56: no overflow unless the cluster counts
// passed in are wrong by a factor 128.
constexpr float kMeanScale = 4294967296.0f;  // 2^32
constexpr float kParamLimit = 16777216.0f;   // 2^24
// A problem's loss: per point block a double partial, scale 2^40 (resolution 9.1e-13),
// each partial at most 2^22 / (the problem's point blocks) in magnitude, so the total stays
// within +-2^22 (4.2 million; a typical loss is below 10) and 2^62 < 2^63. A partial outside
// that (or NaN) sets the problem's flag instead: the loss then reads +inf (or NaN).
constexpr double kLossScale = 1099511627776.0;  // 2^40
constexpr double kLossRange = 4194304.0;       // 2^22
constexpr int kLossNaN = 1, kLossOver = 2;

// x clamped to [-limit, limit]; NaN to 0.
__device__ __forceinline__ float clamp_finite(float x, float limit) {
  return x == x ? fminf(fmaxf(x, -limit), limit) : 0.0f;
}

// x * scale rounded to an integer; |x| * scale must fit (callers clamp first).
__device__ __forceinline__ Acc encode(float x, float scale) {
  return static_cast<Acc>(__float2ll_rn(x * scale));
}

// The sum back to float: one rounding, then an exact power-of-two scaling.
__device__ __forceinline__ float decode(Acc s, float scale) {
  return __ll2float_rn(static_cast<long long>(s)) * (1.0f / scale);
}

// Adds a point block's loss partial to the problem's sum (or flags it); `blocks`: the
// problem's point blocks.
__device__ __forceinline__ void add_loss(Acc* sum, int* flag, double partial, int blocks) {
  const double cap = kLossRange / double(blocks > 0 ? blocks : 1);
  if (partial != partial) {
    atomicOr(flag, kLossNaN);
  } else if (partial > cap || partial < -cap) {
    atomicOr(flag, kLossOver);
  } else if (partial != 0.0) {
    atomicAdd(sum, static_cast<Acc>(__double2ll_rn(partial * kLossScale)));
  }
}

__device__ __forceinline__ double decode_loss(Acc sum, int flag) {
  if (flag & kLossNaN) return __longlong_as_double(0x7ff8000000000000LL);  // NaN
  if (flag & kLossOver) return __longlong_as_double(0x7ff0000000000000LL);  // +inf
  return double(static_cast<long long>(sum)) * (1.0 / kLossScale);
}

}  // namespace floxels::cuda_detail::fixed
