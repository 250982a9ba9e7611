// CPU op scan_disorder: the .bin reader's scan-order score of one reading of a file's rows
// (floxels_ext/lidar/io/readers.py, _disorder; its numpy formula is the reference,
// tests/lidar/test_bin_disorder_reference.py): per column of x y z (float64, finite rows only),
// the median |step| between consecutive rows over the interquartile range, np.percentile's
// 'linear' quartiles; the median of the three. Exact: the order statistics are selected
// (nth_element picks the value a sort puts at that index) and combined with numpy's arithmetic
// (its lerp, the mean of the two middle steps), so the score is numpy's to the bit.
// Why an op: the reader scores every column count a file's size allows on every frame of a
// run (8,192 rows each); in numpy that was ~0.5 ms a count (fresh arrays, selections with the
// GIL taken back between calls), ~12 % of the engine's CPU a frame (bench/RESULTS.md).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "common/check.h"
#include "kernels/finite.h"

namespace floxels {
namespace {

// np.percentile(c, 100 * q) ('linear') for q75 > q25: numpy's virtual index (n - 1) q, then
// its _lerp, from the order statistics at i and i + 1 of each index. One selection of the whole
// column (at i75), the one below it within its lower part, and the i + 1 neighbours as the
// smallest value of the part above each (nth_element leaves no smaller value there).
void quartiles(std::vector<double>& c, double& q75, double& q25) {
  const size_t n = c.size();
  auto lerp = [](double a, double b, double t) {
    const double d = b - a;
    return t >= 0.5 ? b - d * (1 - t) : a + d * t;
  };
  const double v75 = double(n - 1) * 0.75, v25 = double(n - 1) * 0.25;
  const size_t i75 = size_t(std::floor(v75)), i25 = size_t(std::floor(v25));
  const auto at = [&](size_t k) { return c.begin() + static_cast<std::ptrdiff_t>(k); };
  std::nth_element(c.begin(), at(i75), c.end());
  const double a75 = c[i75], b75 = i75 + 1 < n ? *std::min_element(at(i75 + 1), c.end()) : a75;
  double a25 = a75, b25 = a75;  // i25 == i75 (n < 4): the same statistics
  if (i25 < i75) {
    std::nth_element(c.begin(), at(i25), at(i75));
    a25 = c[i25];
    b25 = i25 + 1 < i75 ? *std::min_element(at(i25 + 1), at(i75)) : a75;
  } else {
    b25 = b75;
  }
  q75 = lerp(a75, b75, v75 - std::floor(v75));
  q25 = lerp(a25, b25, v25 - std::floor(v25));
}

// median |c[i + 1] - c[i]| / max(q75 - q25, 1e-6) of one column (c reordered).
double column_disorder(std::vector<double>& c, std::vector<double>& step) {
  const size_t n = c.size(), m = n - 1, half = m / 2;
  step.resize(m);
  for (size_t i = 0; i < m; ++i) step[i] = std::fabs(c[i + 1] - c[i]);
  std::nth_element(step.begin(), step.begin() + static_cast<std::ptrdiff_t>(half), step.end());
  const double hi = step[half];
  // the (half - 1)-th order statistic: the largest of the values nth_element left before half
  const double med = m % 2 ? hi : (*std::max_element(step.begin(), step.begin() + half) + hi) / 2.0;
  double q75, q25;
  quartiles(c, q75, q25);
  return med / std::max(q75 - q25, 1e-6);
}

double scan_disorder_cpu(const at::Tensor& points) {
  check_points(points);
  FLX_CHECK(points.device().is_cpu(), "floxels: scan_disorder runs on the CPU, got points on ", points.device());
  const int64_t N = points.size(0);
  std::vector<double> cols[3];
  for (auto& c : cols) c.reserve(N);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "scan_disorder", [&] {
    const scalar_t* p = points.const_data_ptr<scalar_t>();
    const int64_t r = points.stride(0), s = points.stride(1);
    for (int64_t i = 0; i < N; ++i) {
      const double x = double(p[i * r]), y = double(p[i * r + s]), z = double(p[i * r + 2 * s]);
      if (!finite3(x, y, z)) continue;
      cols[0].push_back(x), cols[1].push_back(y), cols[2].push_back(z);
    }
  });
  if (cols[0].size() < 16) return std::numeric_limits<double>::quiet_NaN();
  std::vector<double> step;
  double score[3];
  for (int k = 0; k < 3; ++k) score[k] = column_disorder(cols[k], step);
  std::sort(score, score + 3);
  return score[1];
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("scan_disorder", &scan_disorder_cpu); }

}  // namespace floxels
