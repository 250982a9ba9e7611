// Per-item stages of the CUDA exact DBSCAN (csrc/cuda/dbscan.cu), as host+device functions:
// the kernels are one call each, so the very same code can also run sequentially on the CPU
// (checks the logic, not the concurrency, without a GPU; the torch-free stress harness that
// did so, scripts/dbscan_stress.cu --emulate, was removed after the race fix: tools/README.md).
//
// Sorted order: points sorted by dbscan::point_sub_key. Sub-cell s covers sorted points
// [sub_start[s], sub_start[s+1]); point i lies in sub-cell sub_incl[i] - 1 and cell
// cell_incl[i] - 1; ranges[c * kR2 + 2r, +1] are the 9 neighbour ranges of cell c as
// sub-cell index ranges; rep[s] is the first core of sub-cell s (or -1).
#pragma once
#include <climits>
#include <cstdint>

#include "common/cuda_compat.h"
#include "kernels/dbscan.h"

namespace floxels::cuda::stages {

constexpr int kR2 = 2 * dbscan::kRanges;  // ints per cell in `ranges`

// Everything the per-point stages need besides the arrays.
struct Params {
  dbscan::Grid g;
  double inv2[3];      // 2 * inv_cs: half-cell units
  double h2[3];        // 1 / inv2: half-cell side
  int64_t sub_top[3];  // last half-cell coordinate per axis
  double eps2;         // eps * eps, the sklearn comparison
  double far2;         // eps2 * (1 + 2^-20): box pruning threshold (margin over rounding)
  int32_t min_samples;
  int dense;  // dbscan::subcells_within_eps: any two points of a sub-cell are within eps
};

// Host only.
inline Params make_params(const double lo[3], const double hi[3], double eps, int32_t min_samples) {
  Params P{};
  P.g = dbscan::make_grid(lo, hi, eps);
  for (int a = 0; a < 3; ++a) {
    P.inv2[a] = 2.0 * P.g.inv_cs[a];
    P.h2[a] = 1.0 / P.inv2[a];
    P.sub_top[a] = 2 * P.g.dims[a] - 1;
  }
  P.eps2 = eps * eps;
  P.far2 = P.eps2 * (1.0 + 0x1p-20);
  P.min_samples = min_samples;
  P.dense = dbscan::subcells_within_eps(P.g, eps) ? 1 : 0;
  return P;
}

FLX_HD double mul_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dmul_rn(a, b);
#else
  return a * b;
#endif
}
FLX_HD double add_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dadd_rn(a, b);
#else
  return a + b;
#endif
}

// Point position in half-cell units, computed exactly as sub_coord does (before the floor).
FLX_HD void half_units(const Params& P, double x, double y, double z, double* u) {
  u[0] = mul_rn(x - P.g.lo[0], P.inv2[0]);
  u[1] = mul_rn(y - P.g.lo[1], P.inv2[1]);
  u[2] = mul_rn(z - P.g.lo[2], P.inv2[2]);
}

// True when every point of the sub-cell `key` is provably farther than eps from the point at
// half-cell position u (so sklearn's rounded rdist > eps2 too). A point of half-cell s has
// computed u in [s, s + 1) and its true position differs by < 2^-30 half cell (at most 2^21
// half cells per axis, relative error 2^-52), far below the 2^-20 taken off each gap; the
// far2 threshold keeps a 2^-20 relative margin over the rounding of the sums. Boundary
// half-cells may hold clamped points: they are unbounded outwards.
FLX_HD bool far(const Params& P, const double* u, uint64_t key) {
  int64_t s[3];
  dbscan::unpack_sub(P.g, key, s[0], s[1], s[2]);
  double d2 = 0.0;
  for (int a = 0; a < 3; ++a) {
    double gap = 0.0;
    if (s[a] > 0 && u[a] < double(s[a])) gap = double(s[a]) - u[a];
    else if (s[a] < P.sub_top[a] && u[a] > double(s[a] + 1)) gap = u[a] - double(s[a] + 1);
    gap = gap > 0x1p-20 ? gap - 0x1p-20 : 0.0;
    const double d = mul_rn(gap, P.h2[a]);
    d2 = add_rn(d2, mul_rn(d, d));
  }
  return d2 > P.far2;
}

FLX_HD bool within(const double* xs, const double* ys, const double* zs, double px, double py, double pz, int32_t j,
                   double eps2) {
  return dbscan::rdist(px, py, pz, xs[j], ys[j], zs[j]) <= eps2;
}

// Per cell c: point ranges of the 27 cells -> sub-cell index ranges (cells are unions of
// whole sub-cells, so [p0, p1) maps to sub-cells sub(p0) .. sub(p1 - 1)).
FLX_HD void cell_ranges(const dbscan::Grid& g, const uint64_t* cell_keys, const int32_t* cell_start,
                        int32_t num_cells, const int32_t* sub_incl, int64_t c, int32_t* out) {
  int32_t pr[kR2];
  dbscan::neighbour_ranges(g, cell_keys, cell_start, num_cells, cell_keys[c], pr);
  for (int r = 0; r < dbscan::kRanges; ++r) {
    const int32_t p0 = pr[2 * r], p1 = pr[2 * r + 1];
    out[2 * r] = p0 < p1 ? sub_incl[p0] - 1 : 0;
    out[2 * r + 1] = p0 < p1 ? sub_incl[p1 - 1] : 0;
  }
}

// At least min_samples points within eps of i (itself included); counting stops there.
FLX_HD uint8_t is_core(const Params& P, const double* xs, const double* ys, const double* zs, const int32_t* sub_incl,
                       const int32_t* cell_incl, const int32_t* sub_start, const uint64_t* sub_key,
                       const int32_t* ranges, int32_t i) {
  const int32_t own = sub_incl[i] - 1;
  int32_t count = P.dense ? sub_start[own + 1] - sub_start[own] : 0;  // dense: whole sub-cell within eps
  if (count >= P.min_samples) return 1;
  const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * kR2;
  const double px = xs[i], py = ys[i], pz = zs[i];
  double u[3];
  half_units(P, px, py, pz, u);
  for (int r = 0; r < dbscan::kRanges; ++r)
    for (int32_t t = rg[2 * r]; t < rg[2 * r + 1]; ++t) {
      if ((P.dense && t == own) || far(P, u, sub_key[t])) continue;
      const int32_t e = sub_start[t + 1];
      for (int32_t j = sub_start[t]; j < e; ++j)
        if (within(xs, ys, zs, px, py, pz, j, P.eps2) && ++count >= P.min_samples) return 1;
    }
  return 0;
}

FLX_HD int32_t first_core(const uint8_t* core, const int32_t* sub_start, int64_t s) {
  for (int32_t j = sub_start[s]; j < sub_start[s + 1]; ++j)
    if (core[j]) return j;
  return -1;
}

// Union-find invariant: every value ever stored in parent[x] is an index <= x (roots are
// hooked under SMALLER roots only, path halving stores ancestors only), so there is no
// cycle and, whatever the interleaving, every load yields a valid index and find_root ends
// on a root. Loads are volatile: other threads hook and halve concurrently.
FLX_HD int32_t find_root(int32_t* parent, int32_t x) {
  volatile int32_t* vp = parent;
  int32_t p = vp[x];
  while (p != x) {
    const int32_t gp = vp[p];
    if (gp != p) vp[x] = gp;  // path halving: only ever an ancestor
    x = p;
    p = gp;
  }
  return x;
}

FLX_HD bool hook(int32_t* parent, int32_t root, int32_t new_parent) {
#if defined(__CUDA_ARCH__)
  return atomicCAS(parent + root, root, new_parent) == root;
#else
  if (parent[root] != root) return false;
  parent[root] = new_parent;
  return true;
#endif
}

FLX_HD void unite(int32_t* parent, int32_t a, int32_t b) {
  while (true) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a == b) return;
    if (a < b) {
      const int32_t t = a;
      a = b;
      b = t;
    }
    if (hook(parent, a, b)) return;  // the larger root, if still a root, under the smaller
  }
}

// Dense mode: cores start under their sub-cell's first core (same cluster, smaller index,
// itself a root). Otherwise every point is its own root.
FLX_HD int32_t initial_parent(const Params& P, const uint8_t* core, const int32_t* sub_incl, const int32_t* rep,
                              int32_t i) {
  return (P.dense && core[i]) ? rep[sub_incl[i] - 1] : i;
}

// Core point i of sub-cell S. Dense mode: for each neighbouring sub-cell T < S (each
// unordered pair of sub-cells is handled from the larger one) that has cores, is not
// provably farther than eps and is not yet in i's component (one root lookup for the whole
// sub-cell), unite with the FIRST core of T within eps. Otherwise: every core j < i in the
// neighbourhood (each pair once).
FLX_HD void hook_point(const Params& P, const double* xs, const double* ys, const double* zs, const int32_t* sub_incl,
                       const int32_t* cell_incl, const int32_t* sub_start, const uint64_t* sub_key, const int32_t* rep,
                       const int32_t* ranges, const uint8_t* core, int32_t* parent, int32_t i) {
  const int32_t own = sub_incl[i] - 1;
  const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * kR2;
  const double px = xs[i], py = ys[i], pz = zs[i];
  double u[3];
  half_units(P, px, py, pz, u);
  int32_t ri = find_root(parent, i);
  volatile const int32_t* vp = parent;
  for (int r = 0; r < dbscan::kRanges; ++r) {
    for (int32_t t = rg[2 * r]; t < rg[2 * r + 1]; ++t) {
      if (P.dense ? t >= own : t > own) break;  // sub-cell indices ascend along the ranges
      const int32_t first = rep[t];
      if (first < 0 || far(P, u, sub_key[t])) continue;
      if (P.dense) {
        if (find_root(parent, first) == ri) continue;
        const int32_t e = sub_start[t + 1];
        for (int32_t j = first; j < e; ++j) {
          if (!core[j] || !within(xs, ys, zs, px, py, pz, j, P.eps2)) continue;
          unite(parent, i, j);
          ri = find_root(parent, i);
          break;
        }
      } else {
        const int32_t e = sub_start[t + 1] < i ? sub_start[t + 1] : i;
        for (int32_t j = first; j < e; ++j) {
          // parent[j] == an ancestor of i proves j is already connected: no distance test.
          if (!core[j] || vp[j] == ri || !within(xs, ys, zs, px, py, pz, j, P.eps2)) continue;
          unite(parent, i, j);
          ri = find_root(parent, i);
        }
      }
    }
  }
}

// After all hooking (parent no longer written): read-only walk.
FLX_HD int32_t final_root(const int32_t* parent, int32_t x) {
  for (int32_t p = parent[x]; p != x; p = parent[x]) x = p;
  return x;
}

// Non-core point i: smallest cluster id among its core neighbours, -1 for noise. Dense mode:
// all cores of a sub-cell share one id, so a sub-cell that cannot improve `best` is skipped
// and its first core within eps settles it.
FLX_HD int32_t border_label(const Params& P, const double* xs, const double* ys, const double* zs,
                            const int32_t* cell_incl, const int32_t* sub_start, const uint64_t* sub_key,
                            const int32_t* rep, const int32_t* ranges, const uint8_t* core, const int32_t* lab,
                            int32_t i) {
  const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * kR2;
  const double px = xs[i], py = ys[i], pz = zs[i];
  double u[3];
  half_units(P, px, py, pz, u);
  int32_t best = INT_MAX;
  for (int r = 0; r < dbscan::kRanges; ++r) {
    for (int32_t t = rg[2 * r]; t < rg[2 * r + 1]; ++t) {
      const int32_t first = rep[t];
      if (first < 0) continue;
      const int32_t e = sub_start[t + 1];
      if (P.dense) {
        const int32_t lt = lab[first];
        if (lt >= best || far(P, u, sub_key[t])) continue;
        for (int32_t j = first; j < e; ++j)
          if (core[j] && within(xs, ys, zs, px, py, pz, j, P.eps2)) {
            best = lt;
            break;
          }
      } else {
        if (far(P, u, sub_key[t])) continue;
        for (int32_t j = first; j < e; ++j)
          if (core[j] && lab[j] < best && within(xs, ys, zs, px, py, pz, j, P.eps2)) best = lab[j];
      }
    }
  }
  return best == INT_MAX ? -1 : best;
}

}  // namespace floxels::cuda::stages
