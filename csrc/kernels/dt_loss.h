// Kernel math of the fused multi-scan distance-transform loss, shared by the CPU and
// CUDA implementations (raw pointers and sizes only, no torch types).
//
// loss = sum_k w_k * mean_i trunc(DT_k(p_i + t_k f_i)), DT_k trilinearly interpolated with
// border clamping exactly like reference.trilinear_gather / grid_sample(border,
// align_corners=True). Each point walks over all K scans once, so the loss and its
// gradient come out of a single pass with no per-scan intermediates.
//
// NOTE: the per-axis clamping and the trilinear blend duplicate a few lines of
// csrc/kernels/trilinear.h (written in parallel); they can be merged once both land.
#pragma once
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::dt_loss {

// Largest number of scans: the CUDA launcher passes every scan's metadata by value in
// the kernel-parameter struct, which bounds its size.
constexpr int kMaxScans = 32;

#if defined(__CUDA_ARCH__)
#define FLX_DT_LDG(p) __ldg(p)  // read-only path: DTs are never written by the kernel
#else
#define FLX_DT_LDG(p) (*(p))
#endif

// One scan's distance transform and its place in the loss, in compute type T.
template <typename T, typename Index>
struct Scan {
  const float* data;  // (nz, ny, nx) float32, contiguous
  Index nx, ny, nz;
  T ox, oy, oz;  // world position of sample (0, 0, 0)
  T t;           // time offset: query = point + t * flow
  T coef;        // weight / N: folds the mean into the per-point contribution
};

// Border clamping along one axis of n samples, matching reference._corners: outside
// (0, n-1) the coordinate is clamped and its derivative is 0 (also exactly on the
// border, like the reference's strict inequalities). NaN clamps to 0 so that a bad
// coordinate can never index out of bounds.
template <typename T, typename Index>
struct Axis {
  Index i0;    // lower sample
  Index step;  // 1, or 0 for a single-sample axis (both corners are sample 0)
  T frac;      // weight of the upper sample
  T dmask;     // d(clamped coordinate) / d(coordinate): 1 inside, 0 clamped
};

template <typename T, typename Index>
FLX_HD Axis<T, Index> clamp_axis(T u, Index n) {
  const T hi = T(n - 1);
  const bool inside = (u > T(0)) && (u < hi);
  const T uc = inside ? u : (u > T(0) ? hi : T(0));
  // uc >= 0, so truncation is floor; the last cell is [n-2, n-1] so that uc == n-1 keeps frac 1.
  Index i = static_cast<Index>(uc);
  const Index imax = n >= 2 ? n - 2 : Index(0);
  i = i < imax ? i : imax;
  Axis<T, Index> a;
  a.i0 = i;
  a.step = (i + 1 < n) ? Index(1) : Index(0);
  a.frac = uc - T(i);
  a.dmask = inside ? T(1) : T(0);
  return a;
}

// Trilinear value of grid g (nz, ny, nx) at continuous sample coordinates (ux, uy, uz)
// and, if kGrad, its derivative with respect to (ux, uy, uz).
template <bool kGrad, typename T, typename Index>
FLX_HD T trilinear_value_grad(const float* __restrict__ g, Index nx, Index ny, Index nz, T ux, T uy,
                              T uz, T& gx, T& gy, T& gz) {
  const Axis<T, Index> ax = clamp_axis<T, Index>(ux, nx);
  const Axis<T, Index> ay = clamp_axis<T, Index>(uy, ny);
  const Axis<T, Index> az = clamp_axis<T, Index>(uz, nz);
  const Index base = (az.i0 * ny + ay.i0) * nx + ax.i0;
  const Index sx = ax.step, sy = ay.step * nx, sz = az.step * nx * ny;
  // c<z><y><x>
  const T c000 = T(FLX_DT_LDG(g + base)), c001 = T(FLX_DT_LDG(g + base + sx));
  const T c010 = T(FLX_DT_LDG(g + base + sy)), c011 = T(FLX_DT_LDG(g + base + sy + sx));
  const T c100 = T(FLX_DT_LDG(g + base + sz)), c101 = T(FLX_DT_LDG(g + base + sz + sx));
  const T c110 = T(FLX_DT_LDG(g + base + sz + sy)), c111 = T(FLX_DT_LDG(g + base + sz + sy + sx));
  const T fx = ax.frac, fy = ay.frac, fz = az.frac;
  const T d00 = c001 - c000, d01 = c011 - c010, d10 = c101 - c100, d11 = c111 - c110;
  const T c00 = c000 + fx * d00, c01 = c010 + fx * d01;
  const T c10 = c100 + fx * d10, c11 = c110 + fx * d11;
  const T e0 = c01 - c00, e1 = c11 - c10;
  const T c0 = c00 + fy * e0, c1 = c10 + fy * e1;
  if constexpr (kGrad) {
    const T gyz0 = d00 + fy * (d01 - d00), gyz1 = d10 + fy * (d11 - d10);
    gx = ax.dmask * (gyz0 + fz * (gyz1 - gyz0));
    gy = ay.dmask * (e0 + fz * (e1 - e0));
    gz = az.dmask * (c1 - c0);
  }
  return c0 + fz * (c1 - c0);
}

// Contribution of one point to the loss (sum_k coef_k * trunc(v_k)) and, if kGrad, to
// d loss / d flow_i (written to gf[0..2]). Values >= truncation (or NaN) count as `above`
// (0 by default; the truncation itself for FloxelsConfig.truncation_mode="clamp") with zero
// gradient.
template <bool kGrad, typename T, typename Index>
FLX_HD T point_loss(const Scan<T, Index>* scans, int k_scans, T px, T py, T pz, T fx, T fy, T fz,
                    T inv_spacing, T truncation, T* gf, T above = T(0)) {
  T loss = T(0);
  T gfx = T(0), gfy = T(0), gfz = T(0);
#if defined(__CUDA_ARCH__)
  // Unrolled, the gathers of several scans are independent and issue together, so a
  // thread waits for about one memory round trip instead of one per scan.
#pragma unroll 4
#endif
  for (int k = 0; k < k_scans; ++k) {
    const Scan<T, Index>& s = scans[k];
    const T ux = (px + s.t * fx - s.ox) * inv_spacing;
    const T uy = (py + s.t * fy - s.oy) * inv_spacing;
    const T uz = (pz + s.t * fz - s.oz) * inv_spacing;
    T gx = T(0), gy = T(0), gz = T(0);
    const T v = trilinear_value_grad<kGrad, T, Index>(s.data, s.nx, s.ny, s.nz, ux, uy, uz, gx, gy, gz);
    // Branch-free selects (the test is unpredictable on real data); unlike a multiplication
    // by 0, a select also drops the NaN/inf values and slopes of truncated samples.
    const bool keep = v < truncation;
    loss += keep ? s.coef * v : s.coef * above;
    if constexpr (kGrad) {
      // chain rule: d u / d flow = t / spacing
      const T c = s.coef * s.t * inv_spacing;
      gfx += keep ? c * gx : T(0);
      gfy += keep ? c * gy : T(0);
      gfz += keep ? c * gz : T(0);
    }
  }
  if constexpr (kGrad) {
    gf[0] = gfx;
    gf[1] = gfy;
    gf[2] = gfz;
  }
  return loss;
}

// --- data-only look-ups of the same distance transforms (dt_residual, dt_sample, dt_evidence) ---
// These use Scan::coef as the plain weight (no 1/N) and Scan::t as the query's time offset:
// query = p + t * m for a per-point motion m. Border clamping as above.

// Value of scan s at p + s.t * m and, if kGrad, its spatial gradient d DT / d query (per
// metre: the gradient trilinear_gather's backward gives, 0 along a clamped axis).
template <bool kGrad, typename T, typename Index>
FLX_HD T scan_sample(const Scan<T, Index>& s, T px, T py, T pz, T mx, T my, T mz, T inv_spacing, T* g) {
  const T ux = (px + s.t * mx - s.ox) * inv_spacing;
  const T uy = (py + s.t * my - s.oy) * inv_spacing;
  const T uz = (pz + s.t * mz - s.oz) * inv_spacing;
  T gx = T(0), gy = T(0), gz = T(0);
  const T v = trilinear_value_grad<kGrad, T, Index>(s.data, s.nx, s.ny, s.nz, ux, uy, uz, gx, gy, gz);
  if constexpr (kGrad) {
    g[0] = gx * inv_spacing;
    g[1] = gy * inv_spacing;
    g[2] = gz * inv_spacing;
  }
  return v;
}

// min(v, cap) that keeps a NaN (like torch.clamp_max), unlike the loss's select.
template <typename T>
FLX_HD T cap_value(T v, T cap) {
  return v > cap ? cap : v;
}

// A point's observed bits: bit k set = support scan k could see the point's own (unmoved)
// position (estimator/sight.py: inside the scan's range band, and its range image has a return
// at or beyond the point in that direction). The point decides, never the query: no motion can
// move a point out of a scan's sight to escape its residual. kAllScans: every scan counts.
constexpr uint32_t kAllScans = 0xffffffffu;

FLX_HD bool counts(uint32_t bits, int k) { return ((bits >> k) & 1u) != 0u; }

// Point i's bits from an optional observed array (nullptr: every scan counts).
FLX_HD uint32_t point_bits(const int32_t* observed, int64_t i) {
  return observed != nullptr ? static_cast<uint32_t>(observed[i]) : kAllScans;
}

// sum_k coef_k * c(min(DT_k(p + t_k m), cap)), c = identity or square (kSquared), over the
// scans whose bit is set in `bits`.
template <bool kSquared, typename T, typename Index>
FLX_HD T point_residual(const Scan<T, Index>* scans, int k_scans, T px, T py, T pz, T mx, T my, T mz,
                        T inv_spacing, T cap, uint32_t bits = kAllScans) {
  T r = T(0);
#if defined(__CUDA_ARCH__)
#pragma unroll 4
#endif
  for (int k = 0; k < k_scans; ++k) {
    const T v = cap_value(scan_sample<false, T, Index>(scans[k], px, py, pz, mx, my, mz, inv_spacing, nullptr), cap);
    r += counts(bits, k) ? scans[k].coef * (kSquared ? v * v : v) : T(0);
  }
  return r;
}

// The two residuals of the motion evidence in one walk over the scans: with the motion m
// (rf) and with zero motion (rz), sum_k coef_k * min(DT_k(.), cap) each, over the scans
// whose bit is set (a scan that could not see p says nothing of whether it moved).
template <typename T, typename Index>
FLX_HD void point_residual_pair(const Scan<T, Index>* scans, int k_scans, T px, T py, T pz, T mx, T my, T mz,
                                T inv_spacing, T cap, T& rf, T& rz, uint32_t bits = kAllScans) {
  T a = T(0), b = T(0);
#if defined(__CUDA_ARCH__)
#pragma unroll 4
#endif
  for (int k = 0; k < k_scans; ++k) {
    const Scan<T, Index>& s = scans[k];
    const T c = counts(bits, k) ? s.coef : T(0);
    a += c * cap_value(scan_sample<false, T, Index>(s, px, py, pz, mx, my, mz, inv_spacing, nullptr), cap);
    b += c * cap_value(scan_sample<false, T, Index>(s, px, py, pz, T(0), T(0), T(0), inv_spacing, nullptr), cap);
  }
  rf = a;
  rz = b;
}

// Motion-evidence test of one group from its residual sums (double) over `count` points:
// out = (gain, rf, rz) in T and the explained flag; a non-finite sum gives NaN and false.
template <typename T>
FLX_HD bool evidence_test(double sum_f, double sum_z, double count, T margin, T ratio, T& gain, T& rf, T& rz) {
  rf = static_cast<T>(sum_f / count);
  rz = static_cast<T>(sum_z / count);
  gain = rz - rf;
  T thr = rz * ratio;
  thr = thr < margin ? margin : thr;
  return gain > thr;  // false for NaN
}

}  // namespace floxels::dt_loss
