// Exact Euclidean distance transform: math shared by the CPU and CUDA implementations.
//
// The transform is separable: squared distances are computed exactly in integers, one axis
// at a time (X by two linear sweeps, then Y and Z as a lower envelope of parabolas
// f[v] + (x - v)^2, Felzenszwalb & Huttenlocher). All intermediate squared distances fit
// int32 because the op rejects grids whose largest possible squared distance does not;
// kInf marks "no occupied sample on this line yet" and is never added to.
#pragma once
#include <cmath>
#include <cstdint>
#include <limits>

#include "common/cuda_compat.h"

namespace floxels::edt {

constexpr int32_t kInf = std::numeric_limits<int32_t>::max();

// Largest squared distance a (Z, Y, X) grid can produce; must stay below kInf.
FLX_HD int64_t max_squared_distance(int64_t Z, int64_t Y, int64_t X) {
  return (Z - 1) * (Z - 1) + (Y - 1) * (Y - 1) + (X - 1) * (X - 1);
}

// Parabola with apex at v of height f, evaluated at x (exact: bounded by kInf, see above).
FLX_HD int32_t parabola(int32_t v, int32_t f, int32_t x) { return f + (x - v) * (x - v); }

// Envelope stack [.., p, t] receiving q (p < t < q): true when t is nowhere strictly below
// both neighbours, i.e. the real intersection s(t, q) <= s(p, t), where
// s(a, b) = (f_b - f_a + b^2 - a^2) / (2 (b - a)). Cross-multiplied so no division is
// needed (denominators are positive); int64 keeps products exact.
FLX_HD bool middle_hidden(int32_t p, int32_t fp, int32_t t, int32_t ft, int32_t q, int32_t fq) {
  const int64_t num_tq = int64_t(fq) - ft + int64_t(q) * q - int64_t(t) * t;
  const int64_t num_pt = int64_t(ft) - fp + int64_t(t) * t - int64_t(p) * p;
  return num_tq * int64_t(t - p) <= num_pt * int64_t(q - t);
}

// First integer x >= 0 at which the parabola at t (height ft) is <= the one at p < t:
// ceil(s(p, t)) clamped below at 0. Only called once per surviving envelope member.
FLX_HD int32_t segment_start(int32_t p, int32_t fp, int32_t t, int32_t ft) {
  const int64_t num = int64_t(ft) - fp + int64_t(t) * t - int64_t(p) * p;
  const int64_t den = 2 * int64_t(t - p);
  if (num <= 0) return 0;
  return static_cast<int32_t>((num + den - 1) / den);
}

// Final distance: sqrt in double then * spacing, like reference.edt (and scipy with
// isotropic sampling, to float32 rounding).
FLX_HD float to_distance(int32_t d2, double spacing) {
  return d2 == kInf ? std::numeric_limits<float>::infinity()
                    : static_cast<float>(sqrt(static_cast<double>(d2)) * spacing);
}

// Nearest-sample index of coordinate p along one axis: floor((p - o) / s + 0.5), always in
// double (like reference.points_to_occupancy): float32 arithmetic would snap points lying
// within rounding of a half-sample boundary, and the origin itself, differently from a
// float64 implementation. Returns -1 when outside [0, n) (or NaN).
FLX_HD int64_t snap_index(double p, double o, double s, int64_t n) {
  const double u = floor((p - o) / s + 0.5);
  return (u >= 0.0 && u < static_cast<double>(n)) ? static_cast<int64_t>(u) : -1;
}

}  // namespace floxels::edt
