// Kernel math of the rigid refinement's Levenberg-Marquardt loop (floxels::rigid_lm,
// estimator/refine.py), shared by the CPU and CUDA implementations; raw pointers and sizes only.
//
// Every cluster c is a planar rigid motion theta_c = (vx, vy, w) plus a fixed vertical
// velocity vz_c: a point with offset r = q - centroid moves u = (vx - w r_y, vy + w r_x, vz) per
// frame. Its normal equations at theta (divided by the cluster's number of points n):
//   H = sum_i sum_k w_k [DT_k(q_i + t_k u_i) < tau] J J^T,   b = sum_i sum_k w_k [..] J d,
//   cost = sum_i sum_k w_k min(DT_k(q_i + t_k u_i), tau)^2,   J = t_k (g_x, g_y, g_y r_x - g_x r_y)
// with d, g the DT's trilinear value and gradient (dt_loss.h's scan_sample, the look-up of
// floxels::dt_sample) and w_k the scans' weights (Scan::coef). One step:
//   A = H + lam (diag(H) + kDamp I),  trial = theta - A^-1 b  (adjugate, double)
// taken when its cost is lower (lam *= kLamDown), else not (lam *= kLamUp); lam clamped to
// [kLamMin, kLamMax]. The reference is floxels_ext.reference.rigid_lm.
#pragma once
#include <cstdint>

#include "common/cuda_compat.h"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels::rigid_lm {

constexpr int kSums = 10;  // H's upper triangle (6), b (3), cost (1)
constexpr double kLamStart = 1e-2;
constexpr double kLamDown = 0.3;
constexpr double kLamUp = 10.0;
constexpr double kLamMin = 1e-6;
constexpr double kLamMax = 1e6;
constexpr double kDamp = 1e-3;

// Add point (q, r) at motion th (vx, vy, w) and vertical velocity vz to s[kSums].
template <typename T, typename Index>
FLX_HD void add_point(const dt_loss::Scan<T, Index>* scans, int num_scans, T inv_spacing, T tau, T qx, T qy, T qz,
                      T rx, T ry, const T* th, T vz, double* s) {
  const T ux = th[0] - th[2] * ry;
  const T uy = th[1] + th[2] * rx;
  if (!finite3(qx, qy, qz) || !finite3(rx, ry, vz)) [[unlikely]] {
    s[9] += double(quiet_nan<T>());  // a non-finite row: the cluster's cost is NaN, no step is taken
    return;
  }
  for (int k = 0; k < num_scans; ++k) {
    T g[3];
    const T d = dt_loss::scan_sample<true, T, Index>(scans[k], qx, qy, qz, ux, uy, vz, inv_spacing, g);
    const T t = scans[k].t, w = scans[k].coef;
    const T j0 = t * g[0], j1 = t * g[1], j2 = t * (g[1] * rx - g[0] * ry);
    const T wi = d < tau ? w : T(0);  // inliers only (a NaN value is none)
    s[0] += double(wi * j0 * j0);
    s[1] += double(wi * j0 * j1);
    s[2] += double(wi * j0 * j2);
    s[3] += double(wi * j1 * j1);
    s[4] += double(wi * j1 * j2);
    s[5] += double(wi * j2 * j2);
    s[6] += double(wi * j0 * d);
    s[7] += double(wi * j1 * d);
    s[8] += double(wi * j2 * d);
    const T dc = d > tau ? tau : d;  // min(d, tau), a NaN kept (the cost is then NaN: no step taken)
    s[9] += double(w * dc * dc);
  }
}

// The damped step from th with the normal equations s (already divided by n), rounded to T.
template <typename T>
FLX_HD void trial_step(const double* s, double lam, const T* th, T* out) {
  const double a00 = s[0] + lam * (s[0] + kDamp), a01 = s[1], a02 = s[2];
  const double a11 = s[3] + lam * (s[3] + kDamp), a12 = s[4];
  const double a22 = s[5] + lam * (s[5] + kDamp);
  // adjugate of the symmetric A (its cofactors), then A^-1 b = adj b / det
  const double c00 = a11 * a22 - a12 * a12, c01 = a02 * a12 - a01 * a22, c02 = a01 * a12 - a02 * a11;
  const double c11 = a00 * a22 - a02 * a02, c12 = a01 * a02 - a00 * a12, c22 = a00 * a11 - a01 * a01;
  const double det = a00 * c00 + a01 * c01 + a02 * c02;
  const double b0 = s[6], b1 = s[7], b2 = s[8];
  out[0] = T(double(th[0]) - (c00 * b0 + c01 * b1 + c02 * b2) / det);
  out[1] = T(double(th[1]) - (c01 * b0 + c11 * b1 + c12 * b2) / det);
  out[2] = T(double(th[2]) - (c02 * b0 + c12 * b1 + c22 * b2) / det);
}

// After a trial with sums st: keep it if its cost is lower (NaN never is); returns whether taken
// and updates th, s and lam.
template <typename T>
FLX_HD bool accept(const T* trial, const double* st, T* th, double* s, double& lam) {
  const bool better = st[9] < s[9];
  if (better) {
    for (int j = 0; j < 3; ++j) th[j] = trial[j];
    for (int j = 0; j < kSums; ++j) s[j] = st[j];
  }
  lam = better ? lam * kLamDown : lam * kLamUp;
  lam = lam < kLamMin ? kLamMin : (lam > kLamMax ? kLamMax : lam);
  return better;
}

// Rows [begin, end) of cluster c from the segment offsets, clamped to [0, m] (offsets that are
// not non-decreasing give an empty or shorter cluster, never an out-of-range row).
FLX_HD void cluster_rows(const int64_t* segments, int64_t c, int64_t m, int64_t& begin, int64_t& end) {
  int64_t b = segments[c], e = segments[c + 1];
  b = b < 0 ? 0 : (b > m ? m : b);
  e = e < b ? b : (e > m ? m : e);
  begin = b;
  end = e;
}

}  // namespace floxels::rigid_lm
