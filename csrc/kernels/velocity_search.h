// Kernel math of the per-cluster velocity search (floxels::velocity_search, estimator/refine.py
// cluster_velocity_search), shared by the CPU and CUDA implementations; raw pointers and sizes.
//
// A cluster's score of a constant velocity v is the mean over its rows of
//   sum_k w_k min(DT_k(q + t_k v), tau)       (w_k already divided by their sum; observed bits as dt_residual)
// The search scores candidate 0 (zero flow) and v = s * dir_d for s = (1..S) * speed_step along
// D directions (the cluster's horizontal principal axis turned by d * 2 pi / D), takes the best,
// then a pattern search: the 3 x 3 horizontal offsets step * (i, j), i, j in {-1, 0, 1}, around
// the best, repeated while the cluster improves (at most `rounds` times per step), for `steps`
// steps halving from speed_step. Ties go to the lowest candidate index. The reference is
// floxels_ext.reference.velocity_search.
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels::velocity_search {

constexpr int kLocal = 9;              // the pattern search's candidates
constexpr int kMaxCandidates = 1025;   // 1 + directions * speeds, bounded by the kernels' shared memory
constexpr double kTwoPi = 6.283185307179586;

// Horizontal principal axis (ax, ay) of rows [begin, end) of q (n, 3): the major axis of the
// covariance of x, y (means and products in double), as cos/sin of 0.5 atan2(2 cxy, cxx - cyy).
template <typename T>
FLX_HD void principal_axis(const T* q, int64_t begin, int64_t end, T& ax, T& ay) {
  const double n = end > begin ? double(end - begin) : 1.0;
  double mx = 0.0, my = 0.0;
  for (int64_t i = begin; i < end; ++i) {
    mx += double(q[3 * i]);
    my += double(q[3 * i + 1]);
  }
  mx /= n;
  my /= n;
  double a = 0.0, b = 0.0, c = 0.0;
  for (int64_t i = begin; i < end; ++i) {
    const double dx = double(q[3 * i]) - mx, dy = double(q[3 * i + 1]) - my;
    a += dx * dx;
    b += dx * dy;
    c += dy * dy;
  }
  const double ang = 0.5 * atan2(2.0 * (b / n), a / n - c / n);
  ax = T(cos(ang));
  ay = T(sin(ang));
}

// Candidate j of the global search (0: zero flow).
template <typename T>
FLX_HD void global_candidate(int j, int num_directions, int num_speeds, T speed_step, T ax, T ay, T* v) {
  v[0] = v[1] = v[2] = T(0);
  if (j == 0) return;
  const int d = (j - 1) / num_speeds, s = (j - 1) % num_speeds;
  const T ang = T(d) * T(kTwoPi / num_directions);
  const T ca = cos(ang), sa = sin(ang);
  const T speed = T(s + 1) * speed_step;
  v[0] = (ax * ca - ay * sa) * speed;
  v[1] = (ax * sa + ay * ca) * speed;
}

// Candidate j of the pattern search around `best` at `step`.
template <typename T>
FLX_HD void local_candidate(int j, const T* best, T step, T* v) {
  v[0] = best[0] + step * T(j / 3 - 1);
  v[1] = best[1] + step * T(j % 3 - 1);
  v[2] = best[2];
}

// Sum over rows i = begin + first, begin + first + stride, ... < end of row i's robust residual
// at velocity v (in T, as dt_residual), in double.
template <typename T, typename Index>
FLX_HD double row_sum(const dt_loss::Scan<T, Index>* scans, int num_scans, T inv_spacing, T tau, const T* q,
                      const int32_t* observed, int64_t begin, int64_t end, int64_t first, int64_t stride,
                      const T* v) {
  double s = 0.0;
  const bool v_ok = finite3(v[0], v[1], v[2]);
  for (int64_t i = begin + first; i < end; i += stride) {
    if (!v_ok || !finite3(q[3 * i], q[3 * i + 1], q[3 * i + 2])) [[unlikely]] {
      s += double(quiet_nan<T>());  // a non-finite row: its cluster's scores are NaN (zero flow stays best)
      continue;
    }
    s += double(dt_loss::point_residual<false, T, Index>(scans, num_scans, q[3 * i], q[3 * i + 1], q[3 * i + 2],
                                                          v[0], v[1], v[2], inv_spacing, tau,
                                                          dt_loss::point_bits(observed, i)));
  }
  return s;
}

// Index of the first smallest of scores[0, count) (a NaN is never smallest).
FLX_HD int first_min(const double* scores, int count) {
  int k = 0;
  for (int j = 1; j < count; ++j) {
    if (scores[j] < scores[k] || (scores[k] != scores[k] && scores[j] == scores[j])) k = j;
  }
  return k;
}

}  // namespace floxels::velocity_search
