// Per-point math of floxels::problem_setup (the CUDA op's kernels, csrc/cuda/problem_setup.cu):
// a point's flow-grid cell and its 8 trilinear corners and weights, with the arithmetic of the
// ATen implementation (csrc/cpu/problem_setup.cpp) step for step, so both give the same bits:
// (p - o) / spacing in T (a true division, as the CPU's), clamped to [0, size - 1] with
// fmax/fmin semantics (NaN -> 0, +-inf -> the border) before any conversion to an index.
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"
#include "kernels/trilinear.h"

namespace floxels::setup {

constexpr int kCorners = 8;

// fmax(u, 0) then fmin(., hi): a NaN operand gives the other one (at::fmax / at::fmin)
template <typename T>
FLX_HD T clamp_lattice(T u, T hi) {
  u = (u != u) ? T(0) : (u > T(0) ? u : T(0));
  return u < hi ? u : hi;
}

// The lattice coordinate of one axis, clamped, optionally floored first (the cell key floors
// before clamping, the corners clamp the unfloored value).
template <typename T>
FLX_HD T lattice(T p, T o, T spacing, T hi, bool floored) {
  T u = (p - o) / spacing;
  if (floored) u = floor(u);
  return clamp_lattice(u, hi);
}

// The cell of a point, numbered (z * Y + y) * X + x. o, spacing in T; size = {X, Y, Z}.
template <typename T>
FLX_HD int64_t cell_key(const T* p, const T* o, T spacing, const int64_t* size) {
  int64_t ic[3];
  for (int a = 0; a < 3; ++a) ic[a] = static_cast<int64_t>(lattice(p[a], o[a], spacing, T(size[a] - 1), true));
  return (ic[2] * size[1] + ic[1]) * size[0] + ic[0];
}

// The 8 corners (x fastest, then y, then z: corner j = cz * 4 + cy * 2 + cx) of a point as
// lattice indices `lin` and their weights `w`: u clamped as in `lattice`, i0 = min(floor(u),
// max(size - 2, 0)), t = u - i0 (tri::axis_setup, shared with the trilinear ops), corner index
// min(i0 + offset, size - 1), weight prod over the axes of (offset ? t : 1 - t), multiplied x,
// then y, then z.
template <typename T>
FLX_HD void corners(const T* p, const T* o, T spacing, const int64_t* size, int64_t* lin, T* w) {
  int64_t i0[3];
  T t[3];
  for (int a = 0; a < 3; ++a) {  // the trilinear ops' clamp and cell, the same bits
    bool inside;                 // (their gradient flag: not needed here)
    tri::axis_setup(p[a], o[a], spacing, size[a], i0[a], t[a], inside);
  }
  for (int j = 0; j < kCorners; ++j) {
    const int off[3] = {j & 1, (j >> 1) & 1, (j >> 2) & 1};
    int64_t idx[3];
    T wf[3];
    for (int a = 0; a < 3; ++a) {
      const int64_t k = i0[a] + off[a];
      idx[a] = k < size[a] - 1 ? k : size[a] - 1;
      wf[a] = off[a] ? t[a] : -t[a] + T(1);
    }
    lin[j] = (idx[2] * size[1] + idx[1]) * size[0] + idx[0];
    w[j] = wf[0] * wf[1] * wf[2];
  }
}

}  // namespace floxels::setup
