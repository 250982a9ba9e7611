// Trilinear interpolation math shared by the CPU and CUDA kernels.
//
// Sample (iz, iy, ix) of a (C, Z, Y, X) grid sits at origin + (ix, iy, iz) * spacing. A query
// is clamped to the lattice exactly like grid_sample(padding_mode="border",
// align_corners=True): the value is that of the nearest border point, and a coordinate gets
// a gradient only when it lies strictly inside (0, size - 1).
//
// Non-finite points (a NaN or +-inf coordinate; docs/ops.md): the gather gives a
// NaN row and a zero points-gradient row, the scatter (and the gather's grid gradient)
// skips the point. Huge finite coordinates clamp like any outside point: the clamp is done
// in floating point before the conversion to an index, so no float -> int cast ever sees a
// value out of range (that would be undefined behaviour).
#pragma once
#include <cstdint>

#include "common/cuda_compat.h"
#include "kernels/finite.h"

namespace floxels::tri {

// The 8 interpolation corners of one query: corner (dz, dy, dx) is base + dz*sz + dy*sy + dx*sx
// with weight (dz ? tz : 1-tz) * (dy ? ty : 1-ty) * (dx ? tx : 1-tx). On a size-1 axis the step
// is 0 and t is 0, so both corners alias the single sample with weights 1 and 0.
template <typename T>
struct Cell {
  int64_t base;        // linear index of the lower corner in one (Z, Y, X) channel
  int64_t row;         // z0 * Y + y0: the (z, y) row of the lower corner (sort key)
  int64_t sx, sy, sz;  // linear steps to the upper corner per axis (0 on size-1 axes)
  T tx, ty, tz;        // fractional offsets in [0, 1]
  bool gx, gy, gz;     // coordinate strictly inside the lattice: has a gradient
  bool ok;             // all three coordinates finite (otherwise the clamped indices are in
                       // bounds but meaningless)
};

// One axis: clamp u = (p - o) / spacing to [0, size-1] in floating point (+-inf and huge
// values clamp to the border, NaN to 0) so that bad input can never index out of bounds.
template <typename T>
FLX_HD void axis_setup(T p, T o, T spacing, int64_t size, int64_t& i0, T& t, bool& grad) {
  const T u = (p - o) / spacing;
  const T hi = T(size - 1);
  grad = (u > T(0)) && (u < hi);
  const T uc = u > T(0) ? (u < hi ? u : hi) : T(0);
  const int64_t lo_max = size >= 2 ? size - 2 : 0;
  int64_t i = static_cast<int64_t>(uc);  // uc >= 0: truncation == floor
  i0 = i < lo_max ? i : lo_max;
  t = uc - T(i0);
}

template <typename T>
FLX_HD Cell<T> cell_setup(const T* p, T ox, T oy, T oz, T spacing, int64_t Z, int64_t Y, int64_t X) {
  Cell<T> c;
  int64_t x0, y0, z0;
  axis_setup(p[0], ox, spacing, X, x0, c.tx, c.gx);
  axis_setup(p[1], oy, spacing, Y, y0, c.ty, c.gy);
  axis_setup(p[2], oz, spacing, Z, z0, c.tz, c.gz);
  c.row = z0 * Y + y0;
  c.base = c.row * X + x0;
  c.sx = X >= 2 ? 1 : 0;
  c.sy = Y >= 2 ? X : 0;
  c.sz = Z >= 2 ? X * Y : 0;
  c.ok = finite3(p[0], p[1], p[2]);
  return c;
}

// out[ch] = interpolated value of channel ch (channels are `vol` apart in `grid`); NaN for a
// non-finite point.
template <typename T>
FLX_HD void gather_point(const T* grid, int64_t C, int64_t vol, const Cell<T>& c, T* out, int64_t out_stride) {
  if (!c.ok) {
    for (int64_t ch = 0; ch < C; ++ch) out[ch * out_stride] = quiet_nan<T>();
    return;
  }
  const T wx0 = T(1) - c.tx, wx1 = c.tx;
  const T wy0 = T(1) - c.ty, wy1 = c.ty;
  const T wz0 = T(1) - c.tz, wz1 = c.tz;
  const int64_t o00 = c.base, o01 = c.base + c.sy, o10 = c.base + c.sz, o11 = c.base + c.sz + c.sy;
  for (int64_t ch = 0; ch < C; ++ch) {
    const T* g = grid + ch * vol;
    const T r00 = wx0 * g[o00] + wx1 * g[o00 + c.sx];
    const T r01 = wx0 * g[o01] + wx1 * g[o01 + c.sx];
    const T r10 = wx0 * g[o10] + wx1 * g[o10 + c.sx];
    const T r11 = wx0 * g[o11] + wx1 * g[o11 + c.sx];
    out[ch * out_stride] = wz0 * (wy0 * r00 + wy1 * r01) + wz1 * (wy0 * r10 + wy1 * r11);
  }
}

// d/dp of sum_ch gout[ch] * gather(grid, p)[ch]; zero for a clamped coordinate and for a
// non-finite point (its NaN output row is a constant).
template <typename T>
FLX_HD void gather_point_grad(const T* grid, int64_t C, int64_t vol, const Cell<T>& c, const T* gout,
                              T spacing, T* gp) {
  if (!c.ok) {
    gp[0] = gp[1] = gp[2] = T(0);
    return;
  }
  const T wx0 = T(1) - c.tx, wx1 = c.tx;
  const T wy0 = T(1) - c.ty, wy1 = c.ty;
  const T wz0 = T(1) - c.tz, wz1 = c.tz;
  const int64_t o00 = c.base, o01 = c.base + c.sy, o10 = c.base + c.sz, o11 = c.base + c.sz + c.sy;
  T dx = T(0), dy = T(0), dz = T(0);
  for (int64_t ch = 0; ch < C; ++ch) {
    const T* g = grid + ch * vol;
    const T go = gout[ch];
    const T v000 = g[o00], v001 = g[o00 + c.sx], v010 = g[o01], v011 = g[o01 + c.sx];
    const T v100 = g[o10], v101 = g[o10 + c.sx], v110 = g[o11], v111 = g[o11 + c.sx];
    // derivative along x of each (z, y) row, then interpolate in y and z
    dx += go * (wz0 * (wy0 * (v001 - v000) + wy1 * (v011 - v010)) +
                wz1 * (wy0 * (v101 - v100) + wy1 * (v111 - v110)));
    const T r00 = wx0 * v000 + wx1 * v001, r01 = wx0 * v010 + wx1 * v011;
    const T r10 = wx0 * v100 + wx1 * v101, r11 = wx0 * v110 + wx1 * v111;
    dy += go * (wz0 * (r01 - r00) + wz1 * (r11 - r10));
    dz += go * ((wy0 * r10 + wy1 * r11) - (wy0 * r00 + wy1 * r01));
  }
  gp[0] = c.gx ? dx / spacing : T(0);
  gp[1] = c.gy ? dy / spacing : T(0);
  gp[2] = c.gz ? dz / spacing : T(0);
}

}  // namespace floxels::tri
