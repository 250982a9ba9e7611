// CPU exact DBSCAN with scikit-learn's labels (see csrc/kernels/dbscan.h).
//
// Stages: cell keys -> sort -> distinct cells and their 9 neighbour ranges -> core test
// (early-exit counting) -> concurrent union-find over core-core pairs within eps ->
// cluster ids in order of each component's smallest original core index (the order in
// which sklearn's dbscan_inner discovers clusters) -> border points take the smallest
// cluster id among their core neighbours (the cluster sklearn reaches them from first).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <utility>
#include <vector>

#include "common/op_args.h"
#include "kernels/dbscan.h"

namespace floxels {
namespace {

using dbscan::Grid;

// Lock-free union-find: roots only ever get hooked onto SMALLER roots, so there are no
// cycles, and path halving writes only ancestors, which stays valid under concurrency.
struct UnionFind {
  std::vector<int32_t> parent;
  explicit UnionFind(int32_t n) : parent(static_cast<size_t>(n)) { std::iota(parent.begin(), parent.end(), 0); }

  int32_t find(int32_t x) {
    std::atomic_ref<int32_t> px(parent[size_t(x)]);
    int32_t p = px.load(std::memory_order_relaxed);
    while (p != x) {
      std::atomic_ref<int32_t> pp(parent[size_t(p)]);
      const int32_t gp = pp.load(std::memory_order_relaxed);
      if (gp != p) std::atomic_ref<int32_t>(parent[size_t(x)]).store(gp, std::memory_order_relaxed);
      x = p;
      p = gp;
    }
    return x;
  }

  void unite(int32_t a, int32_t b) {
    while (true) {
      a = find(a);
      b = find(b);
      if (a == b) return;
      if (a < b) std::swap(a, b);  // hook the larger root under the smaller one
      int32_t expected = a;
      if (std::atomic_ref<int32_t>(parent[size_t(a)])
              .compare_exchange_strong(expected, b, std::memory_order_acq_rel))
        return;
    }
  }
};

template <typename scalar_t>
void dbscan_impl(const scalar_t* p, int32_t n, double eps, int32_t min_samples, int64_t* labels) {
  const double eps2 = eps * eps;
  const size_t N = static_cast<size_t>(n);
  // Bounding box (float64, like sklearn's converted input).
  double lo[3] = {p[0], p[1], p[2]}, hi[3] = {p[0], p[1], p[2]};
  for (int32_t i = 1; i < n; ++i)
    for (int a = 0; a < 3; ++a) {
      const double v = double(p[int64_t(i) * 3 + a]);
      if (v != v) lo[a] = v;  // std::min would skip NaN; make the check below see it
      lo[a] = std::min(lo[a], v);
      hi[a] = std::max(hi[a], v);
    }
  for (int a = 0; a < 3; ++a)
    FLX_CHECK(std::isfinite(lo[a]) && std::isfinite(hi[a]) && std::isfinite(hi[a] - lo[a]),
                "floxels: dbscan points must be finite (found NaN/inf or an overflowing extent)");
  const Grid g = dbscan::make_grid(lo, hi, eps);

  // Sort (key, original index): ties by index keep the order deterministic.
  std::vector<std::pair<uint64_t, int32_t>> order(N);
  at::parallel_for(0, n, 8192, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i)
      order[size_t(i)] = {dbscan::point_key(g, double(p[i * 3]), double(p[i * 3 + 1]), double(p[i * 3 + 2])),
                          int32_t(i)};
  });
  std::sort(order.begin(), order.end());

  std::vector<double> xs(N), ys(N), zs(N);
  std::vector<int32_t> orig(N);
  std::vector<uint64_t> cell_keys;
  std::vector<int32_t> cell_start, cell_of(N);
  for (int32_t i = 0; i < n; ++i) {
    const int64_t o = order[size_t(i)].second;
    orig[size_t(i)] = int32_t(o);
    xs[size_t(i)] = double(p[o * 3]);
    ys[size_t(i)] = double(p[o * 3 + 1]);
    zs[size_t(i)] = double(p[o * 3 + 2]);
    if (i == 0 || order[size_t(i)].first != order[size_t(i - 1)].first) {
      cell_keys.push_back(order[size_t(i)].first);
      cell_start.push_back(i);
    }
    cell_of[size_t(i)] = int32_t(cell_keys.size()) - 1;
  }
  const int32_t num_cells = int32_t(cell_keys.size());
  cell_start.push_back(n);
  order.clear();
  order.shrink_to_fit();

  std::vector<int32_t> ranges(size_t(num_cells) * 2 * dbscan::kRanges);
  at::parallel_for(0, num_cells, 256, [&](int64_t b, int64_t e) {
    for (int64_t c = b; c < e; ++c)
      dbscan::neighbour_ranges(g, cell_keys.data(), cell_start.data(), num_cells, cell_keys[size_t(c)],
                               ranges.data() + c * 2 * dbscan::kRanges);
  });
  auto ranges_of = [&](int32_t i) { return ranges.data() + size_t(cell_of[size_t(i)]) * 2 * dbscan::kRanges; };

  std::vector<uint8_t> core(N);
  at::parallel_for(0, n, 1024, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i)
      core[size_t(i)] = dbscan::count_neighbours(xs.data(), ys.data(), zs.data(), int32_t(i), ranges_of(int32_t(i)),
                                                 eps2, min_samples) >= min_samples;
  });

  // Core-core edges: each unordered pair once (j < i). In dense clusters almost every
  // neighbour soon hangs directly under i's root: parent[j] == (an ancestor of i) proves
  // they are already connected, with one sequential load and no distance test.
  UnionFind uf(n);
  at::parallel_for(0, n, 1024, [&](int64_t b, int64_t e) {
    for (int64_t ii = b; ii < e; ++ii) {
      const int32_t i = int32_t(ii);
      if (!core[size_t(i)]) continue;
      const int32_t* rg = ranges_of(i);
      const double px = xs[size_t(i)], py = ys[size_t(i)], pz = zs[size_t(i)];
      int32_t ri = uf.find(i);
      for (int r = 0; r < dbscan::kRanges; ++r) {
        const int32_t end = std::min(rg[2 * r + 1], i);
        for (int32_t j = rg[2 * r]; j < end; ++j) {
          if (!core[size_t(j)]) continue;
          if (std::atomic_ref<int32_t>(uf.parent[size_t(j)]).load(std::memory_order_relaxed) == ri) continue;
          if (dbscan::rdist(px, py, pz, xs[size_t(j)], ys[size_t(j)], zs[size_t(j)]) > eps2) continue;
          uf.unite(i, j);
          ri = uf.find(i);
        }
      }
    }
  });

  // Cluster ids: component roots ordered by their smallest original core index.
  constexpr int32_t kNone = std::numeric_limits<int32_t>::max();
  std::vector<int32_t> root(N, -1), min_orig(N, kNone);
  for (int32_t i = 0; i < n; ++i) {
    if (!core[size_t(i)]) continue;
    const int32_t r = uf.find(i);
    root[size_t(i)] = r;
    min_orig[size_t(r)] = std::min(min_orig[size_t(r)], orig[size_t(i)]);
  }
  std::vector<int32_t> id_at_orig(N, -1);  // cluster id keyed by its first core's original index
  for (int32_t i = 0; i < n; ++i)
    if (core[size_t(i)] && min_orig[size_t(root[size_t(i)])] == orig[size_t(i)]) id_at_orig[size_t(orig[size_t(i)])] = 0;
  int32_t next = 0;
  for (int32_t o = 0; o < n; ++o)
    if (id_at_orig[size_t(o)] == 0) id_at_orig[size_t(o)] = next++;
  std::vector<int32_t> lab(N, -1);  // sorted order; cores only for now
  for (int32_t i = 0; i < n; ++i)
    if (core[size_t(i)]) lab[size_t(i)] = id_at_orig[size_t(min_orig[size_t(root[size_t(i)])])];

  at::parallel_for(0, n, 1024, [&](int64_t b, int64_t e) {
    for (int64_t ii = b; ii < e; ++ii) {
      const int32_t i = int32_t(ii);
      int32_t best = lab[size_t(i)];
      if (!core[size_t(i)]) {
        const int32_t* rg = ranges_of(i);
        const double px = xs[size_t(i)], py = ys[size_t(i)], pz = zs[size_t(i)];
        best = kNone;
        for (int r = 0; r < dbscan::kRanges; ++r)
          for (int32_t j = rg[2 * r]; j < rg[2 * r + 1]; ++j)
            if (core[size_t(j)] && lab[size_t(j)] < best &&
                dbscan::rdist(px, py, pz, xs[size_t(j)], ys[size_t(j)], zs[size_t(j)]) <= eps2)
              best = lab[size_t(j)];
        if (best == kNone) best = -1;
      }
      labels[orig[size_t(i)]] = best;
    }
  });
}

at::Tensor dbscan_cpu(const at::Tensor& points, double eps, int64_t min_samples) {
  args::dbscan(points, eps, min_samples);
  const int64_t n = points.size(0);
  auto labels = at::empty({n}, points.options().dtype(at::kLong));
  if (n == 0) return labels;
  auto p = points.contiguous();
  const int32_t ms = int32_t(std::min<int64_t>(min_samples, int64_t(n) + 1));  // > n: nothing is core
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "dbscan_cpu", [&] {
    dbscan_impl<scalar_t>(p.data_ptr<scalar_t>(), int32_t(n), eps, ms, labels.data_ptr<int64_t>());
  });
  return labels;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("dbscan", &dbscan_cpu); }

}  // namespace floxels
