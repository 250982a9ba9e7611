// floxels::problem_setup: the per-target preparation of the optimiser in one op with one
// host synchronisation (it used to be ~60 Python-level torch calls with three: DBSCAN's
// cluster count, torch.unique and torch.nonzero). Written with ATen calls, so this
// implementation serves every device (on a GPU the CUDA op, csrc/cuda/problem_setup_binding.cpp,
// does the same in a dozen launches instead of ~90, and falls back to this one for sparse
// lattices); python/floxels_ext/reference/ops.py
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

#include "common/problem_setup.h"

namespace floxels::setup {
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

}  // namespace

Result problem_setup_aten(const Tensor& points_in, const std::optional<Tensor>& labels_in,
                          at::ArrayRef<double> origin, double spacing, at::IntArrayRef grid_shape, int64_t tile) {
  check_args(points_in, labels_in, origin, spacing, grid_shape, tile);
  const int64_t Z = grid_shape[0], Y = grid_shape[1], X = grid_shape[2];
  const int64_t cells = Z * Y * X;
  const Tensor P = points_in.contiguous();
  const int64_t n = P.size(0);
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
    return {at::empty({0}, i64), P.clone(), lab.defined() ? lab.clone() : at::empty({0}, i64),
            at::empty({0, 8}, i32), at::empty({0, 8}, P.options()), at::empty({0}, i64), z1, z1.clone(),
            at::empty({0}, i32), 0};
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
  if (lab.defined() && one_key(cells, n)) {  // labels < n: (label + 1) * cells fits
    order = stable_order(lab.add(1).mul(cells).add(key));
  } else {
    order = stable_order(key);
    if (lab.defined()) order = order.index_select(0, stable_order(lab.index_select(0, order)));
  }
  const Tensor Ps = P.index_select(0, order);
  const Tensor lab_s = lab.defined() ? lab.index_select(0, order) : Tensor();

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
  const Tensor w = wf.select(2, 0).mul(wf.select(2, 1)).mul(wf.select(2, 2)).contiguous();

  // 3. compact vertex rows, in lattice order (= torch.unique(lin, sorted=True))
  const Tensor flat_lin = lin.reshape({-1});
  Tensor inverse, vertices, num_vertices;
  const bool is_dense = dense(cells, n);
  if (is_dense) {
    auto mark = at::zeros({cells}, i32);
    mark.index_fill_(0, flat_lin, 1);
    const Tensor pos = mark.cumsum(0, at::kInt);  // inclusive: row + 1 at marked vertices
    inverse = pos.index_select(0, flat_lin).sub(1).view({n, 8});
    num_vertices = pos.select(0, cells - 1).to(at::kLong);
  } else {
    auto u2 = at::_unique2(flat_lin, /*sorted=*/true, /*return_inverse=*/true, /*return_counts=*/false);
    vertices = std::get<0>(u2);
    inverse = std::get<1>(u2).to(at::kInt).view({n, 8});
    num_vertices = at::full_like(vertices.select(0, 0), vertices.size(0));
  }

  // 4. segment starts, as ops/solver.py _segments
  auto is_new = at::ones({n}, P.options().dtype(at::kBool));
  if (n > 1) {
    Tensor diff = inverse.slice(0, 1).ne(inverse.slice(0, 0, n - 1)).any(1);
    if (lab_s.defined()) diff = diff.logical_or(lab_s.slice(0, 1).ne(lab_s.slice(0, 0, n - 1)));
    is_new.slice(0, 1).copy_(diff);
  }
  is_new.slice(0, 0, n, tile).fill_(true);
  const Tensor seg_incl = is_new.cumsum(0, at::kLong);  // segment of each point + 1
  const Tensor num_clusters = lab_s.defined() ? lab_s.max().add(1).clamp_min(0) : at::zeros({}, i64);

  // the one host synchronisation: sizes of what follows
  const Tensor sizes = at::stack({num_vertices.reshape({}), seg_incl.select(0, n - 1), num_clusters.reshape({}),
                                  finite.to(at::kLong)})
                            .cpu();
  const int64_t M = sizes.data_ptr<int64_t>()[0], S = sizes.data_ptr<int64_t>()[1];
  const int64_t ncl = sizes.data_ptr<int64_t>()[2];
  FLX_CHECK(sizes.data_ptr<int64_t>()[3] == 1,
            "floxels: problem_setup: points must be finite (found NaN/inf coordinates); drop those rows first");
  FLX_CHECK(M < (int64_t(1) << 31), "floxels: problem_setup: too many touched voxel corners for int32 indexing");
  if (is_dense) {
    vertices = at::empty({M}, i64);  // each row's lattice index (duplicates write the same value)
    vertices.index_put_({inverse.reshape({-1}).to(at::kLong)}, flat_lin);
  }
  // first point of each segment (slot S collects the other points and is then overwritten)
  const Tensor slot = at::where(is_new, seg_incl.sub(1), at::full_like(seg_incl, S));
  auto first = at::empty({S + 1}, i64);
  first.index_put_({slot}, at::arange(n, i64));
  first.select(0, S).fill_(n);
  const Tensor seg_ptr = first.to(at::kInt);
  // (8S) vertex rows, int32 (M < 2^31 above): a radix sort of 32-bit keys takes half the
  // passes of 64-bit ones, and a stable sort gives the same order either way
  const Tensor flat = inverse.index_select(0, first.slice(0, 0, S)).reshape({-1});
  const Tensor ent_order = stable_order(flat);
  const Tensor counts = at::zeros({M}, i64).index_add_(0, flat, at::ones_like(flat, i64));
  const Tensor vtx_ptr = at::cat({at::zeros({1}, i64), counts.cumsum(0)}).to(at::kInt);
  return {order, Ps, lab_s.defined() ? lab_s : at::empty({0}, i64), inverse.contiguous(), w, vertices, seg_ptr,
          vtx_ptr, ent_order.to(at::kInt), ncl};
}

}  // namespace floxels::setup

namespace floxels {
TORCH_LIBRARY_IMPL(floxels, CompositeExplicitAutograd, m) { m.impl("problem_setup", &setup::problem_setup_aten); }
}  // namespace floxels
