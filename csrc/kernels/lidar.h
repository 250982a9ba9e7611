// Per-point rules of the lidar pipeline ops (cpu/lidar_cpu.cpp): the cropping and ground tests
// of floxels_ext/lidar/preprocess/masks.py, the rigid transform, and the min/max running filters of
// the ground surface's morphological opening. Every comparison is written as the numpy
// reference writes it, in float64, so the op's masks equal the reference's (NaN heights fail
// every test, as there).
#pragma once
#include <cmath>
#include <cstdint>
#include <limits>

#include "common/cuda_compat.h"

namespace floxels::lidar {

// (N, 3) points with any strides (a view of a file's rows, e.g. x y z of x y z intensity rows,
// read without a copy).
template <typename T>
struct Rows {
  const T* p;
  int64_t row, col;  // strides in elements
  FLX_HD double x(int64_t i) const { return double(p[i * row]); }
  FLX_HD double y(int64_t i) const { return double(p[i * row + col]); }
  FLX_HD double z(int64_t i) const { return double(p[i * row + 2 * col]); }
  FLX_HD T at(int64_t i, int k) const { return p[i * row + k * col]; }
};

// Optional limits arrive as NaN when unset (None in Python).
struct CropRule {
  double min_range, max_range, max_height;  // NaN: no limit
  bool remove_ground;
  double ground_threshold;
};

FLX_HD bool has(double v) { return v == v; }

// floor(q) for |q| < 2^62, exactly std::floor, without the libm call the baseline x86-64 build
// makes for std::floor (a third of the grid pass: two per point).
FLX_HD double floor_exact(double q) {
  const double t = double(int64_t(q));  // truncation toward zero: exact for such q
  return t > q ? t - 1.0 : t;
}

// Sign of hypot(x, y) - limit, as hypot decides it (the reference compares np.hypot's value):
// from the squared range where that is unambiguous (x*x + y*y is within a few ulp of the true
// value, and the band below is 1e-9 wide), hypot only for points within the band (hypot
// costs ~20 ns, a third of the op's time when called for every point).
FLX_HD int compare_range(double x, double y, double limit) {
  const double r2 = x * x + y * y, l2 = limit * limit;
  if (r2 < l2 * (1 - 1e-9)) return -1;
  if (r2 > l2 * (1 + 1e-9)) return 1;
  const double r = hypot(x, y);
  return r < limit ? -1 : (r > limit ? 1 : 0);
}

// Class of one finite point at (x, y, z) (preprocess/settings.py's CROPPED 0, KEPT 1, GROUND 2, OUTLIER 3,
// in its precedence): height above the ground surface h (NaN where the point has no surface), or
// z itself when no surface is built (need_surface false); outlier: step 0 flagged it.
FLX_HD int point_class(const CropRule& c, double x, double y, double z, double h, bool need_surface, bool outlier) {
  if (has(c.min_range) && compare_range(x, y, c.min_range) < 0) return 0;
  if (has(c.max_range) && compare_range(x, y, c.max_range) > 0) return 0;
  if (outlier) return 3;
  if (need_surface) {
    if (has(c.max_height) && !(h <= c.max_height)) return 0;
    if (c.remove_ground && (h < c.ground_threshold)) return 2;
  } else if (has(c.max_height) && !(z <= c.max_height)) {
    return 0;
  }
  return 1;
}

// out = R p + t for a row-major 4x4 rigid transform, accumulated in float64 in the order of
// numpy's (p @ R.T + t) (no fused multiply-add: the build does not contract across statements).
template <typename T>
FLX_HD void transform(const double* M, T x, T y, T z, T* out) {
  const double px = double(x), py = double(y), pz = double(z);
  for (int j = 0; j < 3; ++j) {
    const double acc = px * M[4 * j] + py * M[4 * j + 1] + pz * M[4 * j + 2];
    out[j] = T(acc + M[4 * j + 3]);
  }
}

// Running extremum of width w = 2h + 1 over n values read with stride s, the outside of the
// array being `pad` (scipy.ndimage's mode="constant"): the van Herk / Gil-Werman scheme, three
// comparisons per value whatever the width. Exact: min/max pick values, they round nothing.
// buf needs running_buffer(n, h) doubles. Less = std::less for a min filter, std::greater for max.
inline int64_t running_padded(int64_t n, int64_t h) {
  const int64_t w = 2 * h + 1;
  return ((n + 2 * h + w - 1) / w) * w;  // whole blocks covering every window
}
inline int64_t running_buffer(int64_t n, int64_t h) { return 2 * running_padded(n, h); }

template <typename Less>
void running_extremum(const double* in, double* out, int64_t n, int64_t s, int64_t h, double pad,
                      double* buf, Less less) {
  const int64_t w = 2 * h + 1;
  const int64_t m = running_padded(n, h);
  double* g = buf;       // extremum from each block's start up to i
  double* r = buf + m;   // extremum from i up to its block's end
  auto at = [&](int64_t i) { return (i >= h && i < n + h) ? in[(i - h) * s] : pad; };
  for (int64_t b = 0; b < m; b += w) {
    g[b] = at(b);
    for (int64_t i = b + 1; i < b + w; ++i) {
      const double v = at(i);
      g[i] = less(v, g[i - 1]) ? v : g[i - 1];
    }
    r[b + w - 1] = at(b + w - 1);
    for (int64_t i = b + w - 2; i >= b; --i) {
      const double v = at(i);
      r[i] = less(v, r[i + 1]) ? v : r[i + 1];
    }
  }
  // window of output k spans padded positions [k, k + w - 1]
  for (int64_t k = 0; k < n; ++k) {
    const double a = r[k], b = g[k + w - 1];
    out[k * s] = less(b, a) ? b : a;
  }
}

}  // namespace floxels::lidar
