// floxels::problem_setup (and problem_setup_many, K targets with one synchronisation): the per-target preparation of the optimiser in one op with one
// host synchronisation (it used to be ~60 Python-level torch calls with three: DBSCAN's
// cluster count, torch.unique and torch.nonzero). Written with ATen calls, so the one
// implementation serves every device; python/floxels_ext/reference.py
// (reference_problem_setup) is the same computation in Python, op for op, and the tests
// compare the two exactly.
//
// Steps: points sorted by (cluster, flow-grid cell); the 8 trilinear corners and weights of
// each sorted point (clamped like trilinear_gather), renumbered densely over the touched
// vertices in lattice order; segments (runs of points with equal corner rows and labels,
// cut every `tile` points: the CUDA solver sums a segment inside one warp) and, per vertex,
// its (segment * 8 + corner) entries in segment order.
#include <ATen/core/Tensor.h>
#include <ATen/ops/_unique2.h>
#include <ATen/ops/all.h>
#include <ATen/ops/arange.h>
#include <ATen/ops/cat.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/fmax.h>
#include <ATen/ops/fmin.h>
#include <ATen/ops/full_like.h>
#include <ATen/ops/isfinite.h>
#include <ATen/ops/minimum.h>
#include <ATen/ops/ones.h>
#include <ATen/ops/ones_like.h>
#include <ATen/ops/sort.h>
#include <ATen/ops/stack.h>
#include <ATen/ops/where.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <cstdint>
#include <tuple>
#include <vector>

#include "common/check.h"

namespace floxels {
namespace {

using at::Tensor;

// A small constant on `device`: built on the host and copied without blocking. For a GPU the
// host side is page-locked: a copy from pageable memory may wait for the work already queued
// on the stream (the driver stages it), which in a pipelined batch is the optimiser's
// (python/floxels_ext/ops/_small.py says the same for the Python side).
Tensor host_values(const std::vector<double>& v, at::ScalarType dtype, const at::Device& device) {
  auto t = at::empty({int64_t(v.size())}, at::TensorOptions().dtype(at::kDouble));
  for (size_t k = 0; k < v.size(); ++k) t.data_ptr<double>()[k] = v[k];
  if (device.is_cpu()) return t.to(dtype);
  auto pinned = at::empty({int64_t(v.size())}, at::TensorOptions().dtype(dtype).pinned_memory(true));
  pinned.copy_(t);
  return pinned.to(device, /*non_blocking=*/true);
}

// (at::sort(t, true) would read `true` as the dimension)
std::tuple<Tensor, Tensor> stable_sort(const Tensor& t) { return at::sort(t, std::optional<bool>(true), 0, false); }

// The dense vertex lattice is renumbered through a mark array when it is at most this many
// times the number of corner references (cheap, no sort, no host synchronisation);
// larger (sparse, absurdly wide) lattices go through torch.unique.
constexpr int64_t kDenseFactor = 16;

using Result = std::tuple<Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, int64_t>;

// What one target's set-up has queued before the host must know its sizes (the number of
// touched vertices and of segments, of clusters, whether all points are finite): `sizes` is
// a (4,) int64 tensor on the points' device; finish() builds the rest once it is on the host.
struct Started {
  int64_t n = 0, Y = 0, X = 0;
  bool dense = true;
  Tensor P, lab_s, order, Ps, inverse, w, flat_lin, vertices, is_new, seg_incl, sizes;
  Result empty;  // n == 0: the whole result
};

Started start(const Tensor& points_in, const std::optional<Tensor>& labels_in, at::ArrayRef<double> origin,
              double spacing, at::IntArrayRef grid_shape, int64_t tile) {
  FLX_CHECK(points_in.dim() == 2 && points_in.size(1) == 3, "floxels: problem_setup: points must be (N, 3), got ",
            points_in.sizes());
  FLX_CHECK(points_in.is_floating_point(), "floxels: problem_setup: points must be float32/float64, got ",
            points_in.scalar_type());
  check_origin(origin);
  check_grid_shape(grid_shape);
  check_spacing(spacing);
  FLX_CHECK(tile >= 1, "floxels: problem_setup: tile must be >= 1, got ", tile);
  Started st;
  const int64_t Z = grid_shape[0], Y = grid_shape[1], X = grid_shape[2];
  st.Y = Y, st.X = X;
  const int64_t cells = Z * Y * X;
  FLX_CHECK(cells > 0 && cells < (int64_t(1) << 50), "floxels: problem_setup: grid of ", cells, " vertices");
  const Tensor P = points_in.contiguous();
  const int64_t n = P.size(0);
  st.n = n, st.P = P;
  const auto dev = P.device();
  const auto i64 = P.options().dtype(at::kLong), i32 = P.options().dtype(at::kInt);
  Tensor lab;
  if (labels_in.has_value() && labels_in->defined()) {
    lab = labels_in->to(at::kLong).contiguous();
    FLX_CHECK(lab.dim() == 1 && lab.size(0) == n, "floxels: problem_setup: labels must be (N,) for N = ", n);
    FLX_CHECK(lab.device() == dev, "floxels: problem_setup: labels must be on the points' device");
  }
  if (n == 0) {
    auto z1 = at::zeros({1}, i32);
    st.empty = {at::empty({0}, i64), P.clone(), lab.defined() ? lab.clone() : at::empty({0}, i64),
                at::empty({0, 8}, i32), at::empty({0, 8}, P.options()), at::empty({0}, i64), z1, z1.clone(),
                at::empty({0}, i32), 0};
    return st;
  }

  // Lattice coordinates (p - o) / spacing clamped to [0, hi] in floating point before any
  // conversion to an index: fmax/fmin send NaN to 0 and +-inf to the border, so a bad point
  // can never make an out-of-range index (on CUDA, a device-side assert); a float -> int
  // conversion of a huge value would be undefined. Non-finite points are then refused after
  // the one host synchronisation below (`finite`), at no extra synchronisation.
  const Tensor o = host_values({origin[0], origin[1], origin[2]}, P.scalar_type(), dev);
  const Tensor size = host_values({double(X), double(Y), double(Z)}, at::kLong, dev);
  const Tensor hi = size.sub(1).to(P.scalar_type());
  const Tensor zero = host_values({0.0}, P.scalar_type(), dev);
  auto clamped = [&](const Tensor& pts, bool floored) {
    Tensor u = pts.sub(o).div(spacing);
    if (floored) u = u.floor();
    return at::fmin(at::fmax(u, zero), hi);
  };
  const Tensor finite = at::isfinite(P).all();

  // 1. order: by (cluster, cell). The cell of a point, as reference.cell_key.
  const Tensor ic = clamped(P, true).to(at::kLong);
  Tensor key = ic.select(1, 2).mul(Y).add(ic.select(1, 1)).mul(X).add(ic.select(1, 0));
  Tensor order;
  if (lab.defined() && (n + 1) < (int64_t(1) << 62) / cells) {  // labels < n: (label + 1) * cells fits
    order = std::get<1>(stable_sort(lab.add(1).mul(cells).add(key)));
  } else {
    order = std::get<1>(stable_sort(key));
    if (lab.defined()) order = order.index_select(0, std::get<1>(stable_sort(lab.index_select(0, order))));
  }
  st.order = order;
  const Tensor Ps = P.index_select(0, order);
  st.Ps = Ps;
  const Tensor lab_s = lab.defined() ? lab.index_select(0, order) : Tensor();
  st.lab_s = lab_s;

  // 2. corners and weights, as ops/corners.py compact_corners (same arithmetic, same dtype)
  const Tensor u = clamped(Ps, false);
  const Tensor i0 = at::minimum(u.floor().to(at::kLong), size.sub(2).clamp_min(0));
  const Tensor t = u.sub(i0.to(P.scalar_type()));
  std::vector<double> off;
  for (int cz = 0; cz < 2; ++cz)
    for (int cy = 0; cy < 2; ++cy)
      for (int cx = 0; cx < 2; ++cx) off.insert(off.end(), {double(cx), double(cy), double(cz)});
  const Tensor offs = host_values(off, at::kLong, dev).view({8, 3});
  const Tensor idx = at::minimum(i0.unsqueeze(1).add(offs), size.sub(1));  // (n, 8, 3)
  const Tensor lin = idx.select(2, 2).mul(Y).add(idx.select(2, 1)).mul(X).add(idx.select(2, 0));  // (n, 8)
  const Tensor tt = t.unsqueeze(1);
  const Tensor wf = at::where(offs.to(at::kBool), tt, tt.neg().add(1));
  st.w = wf.select(2, 0).mul(wf.select(2, 1)).mul(wf.select(2, 2)).contiguous();

  // 3. compact vertex rows, in lattice order (= torch.unique(lin, sorted=True))
  st.flat_lin = lin.reshape({-1});
  Tensor num_vertices;
  st.dense = cells <= kDenseFactor * 8 * n;
  if (st.dense) {
    auto mark = at::zeros({cells}, i32);
    mark.index_fill_(0, st.flat_lin, 1);
    const Tensor pos = mark.cumsum(0, at::kInt);  // inclusive: row + 1 at marked vertices
    st.inverse = pos.index_select(0, st.flat_lin).sub(1).view({n, 8});
    num_vertices = pos.select(0, cells - 1).to(at::kLong);
  } else {
    auto u2 = at::_unique2(st.flat_lin, /*sorted=*/true, /*return_inverse=*/true, /*return_counts=*/false);
    st.vertices = std::get<0>(u2);
    st.inverse = std::get<1>(u2).to(at::kInt).view({n, 8});
    num_vertices = at::full_like(st.vertices.select(0, 0), st.vertices.size(0));
  }

  // 4. segment starts, as ops/solver.py _segments
  st.is_new = at::ones({n}, P.options().dtype(at::kBool));
  if (n > 1) {
    Tensor diff = st.inverse.slice(0, 1).ne(st.inverse.slice(0, 0, n - 1)).any(1);
    if (lab_s.defined()) diff = diff.logical_or(lab_s.slice(0, 1).ne(lab_s.slice(0, 0, n - 1)));
    st.is_new.slice(0, 1).copy_(diff);
  }
  st.is_new.slice(0, 0, n, tile).fill_(true);
  st.seg_incl = st.is_new.cumsum(0, at::kLong);  // segment of each point + 1
  const Tensor num_clusters = lab_s.defined() ? lab_s.max().add(1).clamp_min(0) : at::zeros({}, i64);
  st.sizes = at::stack({num_vertices.reshape({}), st.seg_incl.select(0, n - 1), num_clusters.reshape({}),
                        finite.to(at::kLong)});
  return st;
}

// The rest of a target's set-up, `sizes` (its 4 values) on the host.
Result finish(const Started& st, const int64_t* sizes) {
  if (st.n == 0) return st.empty;
  const int64_t n = st.n, M = sizes[0], S = sizes[1], ncl = sizes[2];
  const auto i64 = st.P.options().dtype(at::kLong);
  FLX_CHECK(sizes[3] == 1,
            "floxels: problem_setup: points must be finite (found NaN/inf coordinates); drop those rows first");
  FLX_CHECK(M < (int64_t(1) << 31), "floxels: problem_setup: too many touched voxel corners for int32 indexing");
  Tensor vertices = st.vertices;
  if (st.dense) {
    vertices = at::empty({M}, i64);  // each row's lattice index (duplicates write the same value)
    vertices.index_put_({st.inverse.reshape({-1}).to(at::kLong)}, st.flat_lin);
  }
  // first point of each segment (slot S collects the other points and is then overwritten)
  const Tensor slot = at::where(st.is_new, st.seg_incl.sub(1), at::full_like(st.seg_incl, S));
  auto first = at::empty({S + 1}, i64);
  first.index_put_({slot}, at::arange(n, i64));
  first.select(0, S).fill_(n);
  const Tensor seg_ptr = first.to(at::kInt);
  const Tensor flat = st.inverse.index_select(0, first.slice(0, 0, S)).reshape({-1}).to(at::kLong);  // (8S)
  const Tensor ent_order = std::get<1>(stable_sort(flat));
  const Tensor counts = at::zeros({M}, i64).index_add_(0, flat, at::ones_like(flat));
  const Tensor vtx_ptr = at::cat({at::zeros({1}, i64), counts.cumsum(0)}).to(at::kInt);
  return {st.order, st.Ps, st.lab_s.defined() ? st.lab_s : at::empty({0}, i64), st.inverse.contiguous(), st.w,
          vertices, seg_ptr, vtx_ptr, ent_order.to(at::kInt), ncl};
}

Result problem_setup(const Tensor& points, const std::optional<Tensor>& labels, at::ArrayRef<double> origin,
                     double spacing, at::IntArrayRef grid_shape, int64_t tile) {
  const Started st = start(points, labels, origin, spacing, grid_shape, tile);
  if (st.n == 0) return st.empty;
  const Tensor sizes = st.sizes.cpu();  // the one host synchronisation: sizes of what follows
  return finish(st, sizes.data_ptr<int64_t>());
}

// problem_setup of K targets with ONE host synchronisation: every target's work up to its
// sizes is queued first, then the K sizes come back together. In a pipelined sequence the
// preparing stream's kernels run between the optimiser's, each behind the GPU's current
// work; a synchronisation per target made the host wait that out K times a batch.
// Returns the K results' tensors flattened (9 per target, as problem_setup's) and the K
// numbers of clusters. grid_shapes: 3 per target; origins: 3 per target.
std::tuple<std::vector<Tensor>, std::vector<int64_t>> problem_setup_many(
    at::TensorList points, const c10::List<std::optional<Tensor>>& labels, at::ArrayRef<double> origins,
    double spacing, at::IntArrayRef grid_shapes, int64_t tile) {
  const int64_t K = int64_t(points.size());
  FLX_CHECK(int64_t(labels.size()) == K && int64_t(origins.size()) == 3 * K && int64_t(grid_shapes.size()) == 3 * K,
            "floxels: problem_setup_many: ", K, " targets need as many labels, and 3 origin values and 3 grid "
            "sizes per target; got ", int64_t(labels.size()), ", ", int64_t(origins.size()), ", ",
            int64_t(grid_shapes.size()));
  std::vector<Started> started;
  std::vector<Tensor> live_sizes;
  started.reserve(size_t(K));
  for (int64_t k = 0; k < K; ++k) {
    started.push_back(start(points[size_t(k)], labels.get(size_t(k)), origins.slice(size_t(3 * k), 3), spacing,
                            grid_shapes.slice(size_t(3 * k), 3), tile));
    if (started.back().n > 0) live_sizes.push_back(started.back().sizes);
  }
  Tensor host;
  if (!live_sizes.empty()) host = at::stack(live_sizes).cpu();  // the one host synchronisation
  std::vector<Tensor> out;
  std::vector<int64_t> ncl;
  out.reserve(size_t(9 * K));
  int64_t live = 0;
  for (const Started& st : started) {
    const Result r = st.n == 0 ? st.empty : finish(st, host.data_ptr<int64_t>() + 4 * live++);
    out.insert(out.end(), {std::get<0>(r), std::get<1>(r), std::get<2>(r), std::get<3>(r), std::get<4>(r),
                           std::get<5>(r), std::get<6>(r), std::get<7>(r), std::get<8>(r)});
    ncl.push_back(std::get<9>(r));
  }
  return {out, ncl};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CompositeExplicitAutograd, m) {
  m.impl("problem_setup", &problem_setup);
  m.impl("problem_setup_many", &problem_setup_many);
}

}  // namespace floxels
