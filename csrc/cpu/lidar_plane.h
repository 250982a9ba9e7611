// Step 3 of the ground surface (floxels_ext/lidar/preprocess/ground_plane.py, _plane_cap/_trimmed_plane):
// a plane z = a x + b y + c fitted by trimmed least squares to the cells of the opened map
// (cells more than 0.2 m above the fit dropped, refitted, at most 6 fits), and the map capped
// at that plane + max_rise. numpy solves each fit with lstsq (an SVD); here the centred normal
// equations (two passes: means, then centred sums), which agree to ~1e-15 m on grids of tens of metres, and, where the
// selected cells lie on one line (the rank-deficient case, detected exactly on their integer
// indices), lstsq's minimum-norm solution in closed form.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace floxels {

struct Plane {
  double a = 0, b = 0, c = 0;
};

// Least-squares plane through the selected cells (x_k, y_k, z_k); ci/cj their integer indices.
inline Plane fit_plane(const std::vector<double>& x, const std::vector<double>& y, const std::vector<double>& z,
                       const std::vector<int64_t>& ci, const std::vector<int64_t>& cj,
                       const std::vector<char>& sel) {
  const size_t n = x.size();
  // the first two distinct selected cells, and whether every selected cell lies on their line
  // (decided at the first one off it, nearly always among the first few cells)
  size_t first = n, second = n;
  bool colinear = true;
  for (size_t k = 0; k < n && colinear; ++k) {
    if (!sel[k]) continue;
    if (first == n) {
      first = k;
    } else if (second == n) {
      if (ci[k] != ci[first] || cj[k] != cj[first]) second = k;
    } else {
      const int64_t ux = ci[second] - ci[first], uy = cj[second] - cj[first];
      const int64_t vx = ci[k] - ci[first], vy = cj[k] - cj[first];
      colinear = ux * vy - uy * vx == 0;
    }
  }
  // The sums without a branch per cell: a cell not selected adds +0.0, which leaves every sum
  // as it was (each starts at +0.0 and a sum of doubles never becomes -0.0), so they are the
  // sums over the selected cells in the same order, to the bit. Why: the selection changes
  // from cell to cell, and the branch it took mispredicted on most of the grid's ~50k cells,
  // 2 passes a fit, up to 6 fits a scan (~2 ms of a 200k-point scan's preprocessing).
  double sx = 0, sy = 0, sz = 0, cnt = 0;
  for (size_t k = 0; k < n; ++k) {
    const bool on = sel[k];
    sx += on ? x[k] : 0.0, sy += on ? y[k] : 0.0, sz += on ? z[k] : 0.0, cnt += on ? 1.0 : 0.0;
  }
  const double mx = sx / cnt, my = sy / cnt, mz = sz / cnt;
  double Sxx = 0, Sxy = 0, Syy = 0, Sxz = 0, Syz = 0;
  for (size_t k = 0; k < n; ++k) {
    const bool on = sel[k];
    const double dx = on ? x[k] - mx : 0.0, dy = on ? y[k] - my : 0.0, dz = on ? z[k] - mz : 0.0;
    Sxx += dx * dx, Sxy += dx * dy, Syy += dy * dy, Sxz += dx * dz, Syz += dy * dz;
  }
  Plane p;
  if (!colinear) {
    const double det = Sxx * Syy - Sxy * Sxy;
    const double a = (Sxz * Syy - Syz * Sxy) / det, b = (Syz * Sxx - Sxz * Sxy) / det;
    p.a = double(a), p.b = double(b), p.c = double(mz - a * mx - b * my);
    return p;
  }
  // One line of cells: z depends on the position t along the line only. The solutions are
  // (a, b) = s u + lambda v (u along the line, v across it), c = mz - (a, b).m; lstsq returns
  // the one of least norm |(a, b, c)|.
  double ux = 1, uy = 0;
  if (second != n) {
    ux = double(ci[second] - ci[first]), uy = double(cj[second] - cj[first]);
    const double len = std::sqrt(ux * ux + uy * uy);
    ux /= len, uy /= len;
  }
  const double Stt = ux * ux * Sxx + 2 * ux * uy * Sxy + uy * uy * Syy;
  const double s = Stt > 0 ? (ux * Sxz + uy * Syz) / Stt : 0;
  double vx = -uy, vy = ux;
  double c0 = mz - s * (ux * mx + uy * my), q = vx * mx + vy * my;
  if (second == n) {  // one cell: any (a, b) fits; least norm over the whole plane
    const double r2 = mx * mx + my * my + 1;
    p.a = double(mz * mx / r2), p.b = double(mz * my / r2), p.c = double(mz / r2);
    return p;
  }
  const double lam = q * c0 / (1 + q * q);
  p.a = double(s * ux + lam * vx), p.b = double(s * uy + lam * vy), p.c = double(c0 - lam * q);
  return p;
}

// grid: H x W opened map (finite heights or -inf); capped in place when a plane can be fitted.
inline void cap_at_plane(std::vector<double>& grid, int64_t H, int64_t W, double cell, double max_rise,
                         int iters = 6, double keep_above = 0.2) {
  std::vector<double> x, y, z;
  std::vector<int64_t> ci, cj;
  for (auto* v : {&x, &y, &z}) v->reserve(H * W);
  ci.reserve(H * W), cj.reserve(H * W);
  for (int64_t a = 0; a < H; ++a)
    for (int64_t b = 0; b < W; ++b) {
      const double v = grid[a * W + b];
      if (!std::isfinite(v)) continue;
      x.push_back((double(a) + 0.5) * cell), y.push_back((double(b) + 0.5) * cell), z.push_back(v);
      ci.push_back(a), cj.push_back(b);
    }
  const size_t n = z.size();
  std::vector<char> sel(n, 1), next(n);
  size_t count = n;
  bool have = false;
  Plane pl;
  for (int it = 0; it < iters; ++it) {
    if (count < 10) break;
    pl = fit_plane(x, y, z, ci, cj, sel);
    have = true;
    size_t changed = 0, c2 = 0;
    for (size_t k = 0; k < n; ++k) {
      next[k] = (z[k] - (x[k] * pl.a + y[k] * pl.b + pl.c)) <= keep_above;
      changed += next[k] != sel[k];
      c2 += next[k];
    }
    if (!changed) break;
    sel.swap(next);
    count = c2;
  }
  if (!have) return;
  for (int64_t a = 0; a < H; ++a)
    for (int64_t b = 0; b < W; ++b) {
      const double plane = ((double(a) + 0.5) * cell) * pl.a + ((double(b) + 0.5) * cell) * pl.b + pl.c;
      double& v = grid[a * W + b];
      v = std::min(v, plane + max_rise);
    }
}

}  // namespace floxels
