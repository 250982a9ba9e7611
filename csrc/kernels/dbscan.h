// Exact DBSCAN (scikit-learn semantics) on a sparse uniform grid: math shared by CPU and CUDA.
//
// Points are binned into cells of size >= eps, sorted by a packed 64-bit cell key
// (x bits | y bits | z bits, z lowest). Any pair within eps lies in cells differing by at
// most 1 per axis, and the cells (cx+dx, cy+dy, cz-1..cz+1) are CONSECUTIVE in key order,
// so the 27-cell neighbourhood is 9 contiguous ranges of the sorted points. No array
// spans the bounding box: cells are looked up by binary search over the sorted cell keys.
//
// The distance predicate reproduces scikit-learn's KDTree (used by DBSCAN for 3D input):
// coordinates as float64, rdist = ((dx*dx + dy*dy) + dz*dz) in that order, compared
// `<=` against eps*eps, with no fused multiply-add (sklearn wheels are built without FMA).
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::dbscan {

// Per-axis cells: cell c on axis a covers [lo[a] + c * cs, lo[a] + (c+1) * cs).
struct Grid {
  double lo[3];
  double inv_cs[3];
  int64_t dims[3];  // number of cells per axis (>= 1)
  int bits[3];      // key bits per axis; dims[a] <= 2^bits[a], bits sum <= 60
};

// 20 bits per axis: 60 cell bits plus the 3 sub-cell bits of the CUDA sort key fit in 64.
constexpr int kMaxAxisBits = 20;

// Host only. Cell size slightly above eps so that two points within eps land in cells at
// most one apart despite the rounding of (v - lo) * inv_cs (relative margin 2^-16, far above
// the ~1e-9 rounding error for coordinates up to 2^20 cells). An axis whose extent would need
// more than 2^21 cells (degenerate, very sparse input) gets larger cells: still exact, since
// only cell size >= eps matters for correctness.
inline Grid make_grid(const double lo[3], const double hi[3], double eps) {
  Grid g;
  const double base = eps * (1.0 + 1.0 / 65536.0);
  for (int a = 0; a < 3; ++a) {
    const double extent = hi[a] - lo[a];
    double cs = base;
    const double max_cells = double((int64_t(1) << kMaxAxisBits) - 2);
    if (extent / cs > max_cells) cs = extent / max_cells * (1.0 + 1.0 / 65536.0);
    g.lo[a] = lo[a];
    g.inv_cs[a] = 1.0 / cs;
    int64_t d = int64_t(std::floor(extent * g.inv_cs[a])) + 1;
    if (d < 1) d = 1;
    if (d > (int64_t(1) << kMaxAxisBits)) d = int64_t(1) << kMaxAxisBits;
    g.dims[a] = d;
    int b = 0;
    while ((int64_t(1) << b) < d) ++b;
    g.bits[a] = b;
  }
  return g;
}

FLX_HD int64_t cell_coord(const Grid& g, int a, double v) {
  double u = std::floor((v - g.lo[a]) * g.inv_cs[a]);
  // Clamping is monotone, so neighbours stay at most one cell apart.
  if (!(u >= 0.0)) u = 0.0;
  const double top = double(g.dims[a] - 1);
  if (u > top) u = top;
  return int64_t(u);
}

FLX_HD uint64_t pack(const Grid& g, int64_t cx, int64_t cy, int64_t cz) {
  return (uint64_t(cx) << (g.bits[1] + g.bits[2])) | (uint64_t(cy) << g.bits[2]) | uint64_t(cz);
}

FLX_HD uint64_t point_key(const Grid& g, double x, double y, double z) {
  return pack(g, cell_coord(g, 0, x), cell_coord(g, 1, y), cell_coord(g, 2, z));
}

FLX_HD void unpack(const Grid& g, uint64_t key, int64_t& cx, int64_t& cy, int64_t& cz) {
  cz = int64_t(key & ((uint64_t(1) << g.bits[2]) - 1));
  cy = int64_t((key >> g.bits[2]) & ((uint64_t(1) << g.bits[1]) - 1));
  cx = int64_t(key >> (g.bits[1] + g.bits[2]));
}

// sklearn's euclidean rdist, operation by operation (no contraction into FMA on the GPU).
FLX_HD double rdist(double ax, double ay, double az, double bx, double by, double bz) {
  const double dx = ax - bx, dy = ay - by, dz = az - bz;
#if defined(__CUDA_ARCH__)
  return __dadd_rn(__dadd_rn(__dmul_rn(dx, dx), __dmul_rn(dy, dy)), __dmul_rn(dz, dz));
#else
  return (dx * dx + dy * dy) + dz * dz;
#endif
}

// Sub-cells (CUDA kernel): each cell split in 2 x 2 x 2 halves. Coordinate in half-cell units;
// scaling by 2 is exact, so sub_coord >> 1 == cell_coord for every point.
FLX_HD int64_t sub_coord(const Grid& g, int a, double v) {
  double u = std::floor((v - g.lo[a]) * (2.0 * g.inv_cs[a]));
  if (!(u >= 0.0)) u = 0.0;
  const double top = double(2 * g.dims[a] - 1);
  if (u > top) u = top;
  return int64_t(u);
}

constexpr int kSubBits = 3;

// Cell key << 3 | (x, y, z) half bits: sorting by it keeps every cell contiguous (and in cell
// key order) and every sub-cell contiguous inside its cell.
FLX_HD uint64_t point_sub_key(const Grid& g, double x, double y, double z) {
  const int64_t sx = sub_coord(g, 0, x), sy = sub_coord(g, 1, y), sz = sub_coord(g, 2, z);
  return (pack(g, sx >> 1, sy >> 1, sz >> 1) << kSubBits) | uint64_t(((sx & 1) << 2) | ((sy & 1) << 1) | (sz & 1));
}

FLX_HD void unpack_sub(const Grid& g, uint64_t sub_key, int64_t& sx, int64_t& sy, int64_t& sz) {
  unpack(g, sub_key >> kSubBits, sx, sy, sz);
  sx = 2 * sx + int64_t((sub_key >> 2) & 1);
  sy = 2 * sy + int64_t((sub_key >> 1) & 1);
  sz = 2 * sz + int64_t(sub_key & 1);
}

// Host only. True when every cell side is <= 1.1 eps (the grid was not enlarged), so a
// sub-cell's diagonal is <= sqrt(3)/2 * 1.1 eps < 0.96 eps: any two points of one sub-cell
// are within eps of each other with a margin far above any rounding (the misplacement of a
// point by the rounding of its cell coordinate is < 2^-28 cell).
inline bool subcells_within_eps(const Grid& g, double eps) {
  for (int a = 0; a < 3; ++a)
    if (!(eps * g.inv_cs[a] * 1.1 >= 1.0)) return false;
  return true;
}

// First index in sorted keys[0, n) with keys[k] >= v (upper = false) or > v (upper = true).
FLX_HD int32_t search(const uint64_t* keys, int32_t n, uint64_t v, bool upper) {
  int32_t lo = 0, hi = n;
  while (lo < hi) {
    const int32_t mid = lo + (hi - lo) / 2;
    const bool go_right = upper ? keys[mid] <= v : keys[mid] < v;
    if (go_right) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

constexpr int kRanges = 9;

// The 9 contiguous ranges [out[2r], out[2r+1]) of sorted points that cover the 27 cells around
// the cell `key`. cell_keys (num_cells) are the sorted distinct keys, cell_start
// (num_cells + 1) their first point (cell_start[num_cells] = N). Empty ranges have begin == end.
FLX_HD void neighbour_ranges(const Grid& g, const uint64_t* cell_keys, const int32_t* cell_start,
                             int32_t num_cells, uint64_t key, int32_t* out) {
  int64_t cx, cy, cz;
  unpack(g, key, cx, cy, cz);
  const int64_t z0 = cz > 0 ? cz - 1 : 0;
  const int64_t z1 = cz + 1 < g.dims[2] ? cz + 1 : cz;
  int r = 0;
  for (int64_t dx = -1; dx <= 1; ++dx) {
    for (int64_t dy = -1; dy <= 1; ++dy, ++r) {
      const int64_t x = cx + dx, y = cy + dy;
      if (x < 0 || y < 0 || x >= g.dims[0] || y >= g.dims[1]) {
        out[2 * r] = out[2 * r + 1] = 0;
        continue;
      }
      const int32_t a = search(cell_keys, num_cells, pack(g, x, y, z0), false);
      const int32_t b = search(cell_keys, num_cells, pack(g, x, y, z1), true);
      out[2 * r] = cell_start[a];
      out[2 * r + 1] = cell_start[b];
    }
  }
}

// Number of points within eps of point i (itself included), stopping once `limit` is reached:
// only core-ness (count >= min_samples) is needed.
FLX_HD int32_t count_neighbours(const double* xs, const double* ys, const double* zs, int32_t i,
                                const int32_t* ranges, double eps2, int32_t limit) {
  const double px = xs[i], py = ys[i], pz = zs[i];
  int32_t count = 0;
  for (int r = 0; r < kRanges; ++r) {
    const int32_t e = ranges[2 * r + 1];
    for (int32_t j = ranges[2 * r]; j < e; ++j) count += rdist(px, py, pz, xs[j], ys[j], zs[j]) <= eps2;
    if (count >= limit) return count;
  }
  return count;
}

}  // namespace floxels::dbscan
