// Torch binding of the CUDA problem_setup: the ATen implementation's steps (cpu/problem_setup.cpp)
// in six kernels, two stable sorts and two prefix sums, with the one host read of the sizes,
// all on the current stream: a dozen launches instead of ~90 small ATen calls, whose host
// time was the single frame's critical path (bench/RESULTS.md: the set-up ~2 ms of a ~14.5 ms
// frame). Sparse lattices (renumbered through torch.unique) and sort keys that do not fit one
// int64 take the ATen implementation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/cumsum.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/sort.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>

#include "common/problem_setup.h"
#include "cuda/problem_setup_launch.h"

namespace floxels {
namespace {

using at::Tensor;
using setup::Result;
using setup::stable_order;

template <typename T>
cuda::SetupGrid<T> grid_of(at::ArrayRef<double> origin, double spacing, at::IntArrayRef grid_shape) {
  cuda::SetupGrid<T> g{};
  for (int a = 0; a < 3; ++a) g.o[a] = static_cast<T>(origin[a]);  // as the ATen path's origin tensor
  g.spacing = static_cast<T>(spacing);
  g.size[0] = grid_shape[2], g.size[1] = grid_shape[1], g.size[2] = grid_shape[0];  // {X, Y, Z}
  g.cells = grid_shape[0] * grid_shape[1] * grid_shape[2];
  return g;
}

Result problem_setup_cuda(const Tensor& points_in, const std::optional<Tensor>& labels_in,
                          at::ArrayRef<double> origin, double spacing, at::IntArrayRef grid_shape, int64_t tile) {
  const int64_t cells = setup::check_args(points_in, labels_in, origin, spacing, grid_shape, tile);
  const int64_t n = points_in.size(0);
  const bool labelled = labels_in.has_value() && labels_in->defined();
  if (n == 0 || !setup::dense(cells, n) || (labelled && !setup::one_key(cells, n)))
    return setup::problem_setup_aten(points_in, labels_in, origin, spacing, grid_shape, tile);
  const c10::cuda::CUDAGuard guard(points_in.device());
  const auto stream = at::cuda::getCurrentCUDAStream();
  const Tensor P = points_in.contiguous();
  const Tensor lab = labelled ? labels_in->to(at::kLong).contiguous() : Tensor();
  const auto i64 = P.options().dtype(at::kLong), i32 = P.options().dtype(at::kInt);
  const int64_t* lab_p = labelled ? lab.const_data_ptr<int64_t>() : nullptr;

  // one int64 scratch row: bad flag, largest label; then the four sizes
  auto scratch = at::zeros({6}, i64);
  int* bad = reinterpret_cast<int*>(scratch.mutable_data_ptr<int64_t>());
  long long* max_label = reinterpret_cast<long long*>(scratch.mutable_data_ptr<int64_t>() + 1);
  scratch.select(0, 1).fill_(-1);
  auto key = at::empty({n}, i64);
  auto Ps = at::empty_like(P);
  auto lab_s = labelled ? at::empty({n}, i64) : at::empty({0}, i64);
  auto lin = at::empty({n, 8}, i64);
  auto w = at::empty({n, 8}, P.options());
  auto mark = at::zeros({cells}, i32);
  Tensor order;
  AT_DISPATCH_FLOATING_TYPES(P.scalar_type(), "problem_setup_cuda", [&] {
    const auto g = grid_of<scalar_t>(origin, spacing, grid_shape);
    cuda::setup_keys<scalar_t>(P.const_data_ptr<scalar_t>(), lab_p, n, g, key.mutable_data_ptr<int64_t>(), bad, stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    order = stable_order(key);
    cuda::setup_corners<scalar_t>(P.const_data_ptr<scalar_t>(), lab_p, order.const_data_ptr<int64_t>(), n, g,
                                  Ps.mutable_data_ptr<scalar_t>(),
                                  labelled ? lab_s.mutable_data_ptr<int64_t>() : nullptr,
                                  lin.mutable_data_ptr<int64_t>(), w.mutable_data_ptr<scalar_t>(),
                                  mark.mutable_data_ptr<int>(), max_label, stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  const Tensor pos = at::cumsum(mark, 0, at::kInt);  // inclusive: row + 1 at marked vertices
  auto inverse = at::empty({n, 8}, i32);
  auto is_new = at::empty({n}, i32);
  cuda::setup_segments(lin.const_data_ptr<int64_t>(), pos.const_data_ptr<int>(),
                       labelled ? lab_s.const_data_ptr<int64_t>() : nullptr, n, tile,
                       inverse.mutable_data_ptr<int>(), is_new.mutable_data_ptr<int>(), stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  const Tensor seg_incl = at::cumsum(is_new, 0, at::kLong);  // segment of each point + 1
  int64_t* sizes_d = scratch.mutable_data_ptr<int64_t>() + 2;
  cuda::setup_sizes(pos.const_data_ptr<int>(), cells, seg_incl.const_data_ptr<int64_t>(), n, max_label, bad, sizes_d,
                    stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();

  // the one host synchronisation: sizes of what follows
  const Tensor sizes = scratch.slice(0, 2).cpu();
  const int64_t M = sizes.data_ptr<int64_t>()[0], S = sizes.data_ptr<int64_t>()[1];
  const int64_t ncl = sizes.data_ptr<int64_t>()[2];
  FLX_CHECK(sizes.data_ptr<int64_t>()[3] == 1,
            "floxels: problem_setup: points must be finite (found NaN/inf coordinates); drop those rows first");
  FLX_CHECK(M < (int64_t(1) << 31), "floxels: problem_setup: too many touched voxel corners for int32 indexing");
  auto vertices = at::empty({M}, i64);
  auto seg_ptr = at::empty({S + 1}, i32);
  auto flat = at::empty({8 * S}, i32);  // each segment's 8 vertex rows
  cuda::setup_tables(lin.const_data_ptr<int64_t>(), inverse.const_data_ptr<int>(), is_new.const_data_ptr<int>(),
                     seg_incl.const_data_ptr<int64_t>(), n, S, vertices.mutable_data_ptr<int64_t>(),
                     seg_ptr.mutable_data_ptr<int>(), flat.mutable_data_ptr<int>(), stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  const Tensor ent_order = stable_order(flat);
  auto counts = at::zeros({M}, i32);
  cuda::setup_counts(flat.const_data_ptr<int>(), 8 * S, counts.mutable_data_ptr<int>(), stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  auto vtx_ptr = at::zeros({M + 1}, i32);
  auto vtx_tail = vtx_ptr.slice(0, 1);  // vtx_ptr[0] = 0, then the running counts
  at::cumsum_out(vtx_tail, counts, 0, at::kInt);
  return {order, Ps, lab_s, inverse, w, vertices, seg_ptr, vtx_ptr, ent_order.to(at::kInt), ncl};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("problem_setup", &problem_setup_cuda); }

}  // namespace floxels
