// Step 0 of the ground surface (floxels_ext/lidar/preprocess/ground_outliers.py, the reference): the robust
// reference height of every block of the lowest-point map, against which points far below the
// ground (multipath) are outliers. Exact order statistics (nth_element picks the value the
// reference's sort puts at the same index) and the reference's arithmetic, so both flag the
// same points.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace floxels {

// preprocess/ground_outliers.py's constants (tests/lidar/test_ground_outliers.py reads them there)
constexpr int64_t kRefRadiusBlocks = 3;
constexpr double kRefMaxSlope = 0.2;
constexpr double kRefConeMargin = 1.0;
constexpr double kNearGroundM = 15.0;

inline int64_t ref_block_cells(int64_t window_cells) { return std::max<int64_t>(1, window_cells / 4); }

// The value at index (n - 1) / den of the n values in v (reordered), NaN if empty: the lower
// median (den 2) or quartile (den 4).
inline double order_stat(std::vector<double>& v, size_t den) {
  if (v.empty()) return std::numeric_limits<double>::quiet_NaN();
  const auto k = static_cast<std::ptrdiff_t>((v.size() - 1) / den);
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// grid: H x W lowest z per cell (+inf: empty); lo_c: the grid's first cell (floor(min / cell)).
// Returns the (Hb x Wb) block references (NaN: no non-empty block around), row-major.
inline std::vector<double> ground_reference(const std::vector<double>& grid, int64_t H, int64_t W, const double lo_c[2],
                                            double cell, int64_t window_cells, int64_t& Hb, int64_t& Wb) {
  const int64_t b = ref_block_cells(window_cells);
  Hb = (H + b - 1) / b, Wb = (W + b - 1) / b;
  std::vector<double> q(Hb * Wb), vals;
  vals.reserve(b * b);
  for (int64_t I = 0; I < Hb; ++I)
    for (int64_t J = 0; J < Wb; ++J) {
      vals.clear();
      for (int64_t a = I * b; a < std::min(H, (I + 1) * b); ++a)
        for (int64_t c = J * b; c < std::min(W, (J + 1) * b); ++c)
          if (std::isfinite(grid[a * W + c])) vals.push_back(grid[a * W + c]);
      q[I * Wb + J] = order_stat(vals, 2);
    }
  const int64_t R = kRefRadiusBlocks;
  std::vector<double> ref(Hb * Wb);
  vals.reserve((2 * R + 1) * (2 * R + 1));
  for (int64_t I = 0; I < Hb; ++I)
    for (int64_t J = 0; J < Wb; ++J) {
      vals.clear();
      for (int64_t a = std::max<int64_t>(0, I - R); a <= std::min(Hb - 1, I + R); ++a)
        for (int64_t c = std::max<int64_t>(0, J - R); c <= std::min(Wb - 1, J + R); ++c)
          if (!std::isnan(q[a * Wb + c])) vals.push_back(q[a * Wb + c]);
      ref[I * Wb + J] = order_stat(vals, 4);
    }
  // the cone around the ground near the sensor (block centres as the reference computes them)
  std::vector<double> rb(Hb * Wb), near;
  for (int64_t I = 0; I < Hb; ++I)
    for (int64_t J = 0; J < Wb; ++J) {
      const double cx = (double(I * b) + double(b) / 2.0 + lo_c[0]) * cell;
      const double cy = (double(J * b) + double(b) / 2.0 + lo_c[1]) * cell;
      rb[I * Wb + J] = std::hypot(cx, cy);
      if (rb[I * Wb + J] <= kNearGroundM && !std::isnan(ref[I * Wb + J])) near.push_back(ref[I * Wb + J]);
    }
  if (near.empty()) return ref;
  const double g0 = order_stat(near, 2);
  for (int64_t i = 0; i < Hb * Wb; ++i) {
    const double spread = kRefMaxSlope * rb[i] + kRefConeMargin;
    const double lo = g0 - spread, hi = g0 + spread;
    double& v = ref[i];
    if (v < lo) v = lo;
    else if (v > hi) v = hi;  // NaN fails both: stays NaN
  }
  return ref;
}

}  // namespace floxels
