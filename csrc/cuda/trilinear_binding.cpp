// Torch binding of the CUDA trilinear ops: checks inputs, allocates outputs and launches on
// the current stream (no host synchronisation). The scatter (and the grid gradient, its
// other use) is deterministic (issue 31): the kernel writes each point's 8 (voxel, weight)
// terms and index_put_ with accumulate sums them per voxel in index order (it sorts the voxel
// keys stably), instead of float atomics; scratch of 8 terms per point.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/index_put.h>
#include <ATen/ops/mul.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <tuple>

#include "common/op_args.h"
#include "cuda/trilinear_launch.h"

namespace floxels {
namespace {

cuda::TriGeom geom(c10::ArrayRef<double> origin, double spacing, int64_t Z, int64_t Y, int64_t X) {
  return cuda::TriGeom{Z, Y, X, origin[0], origin[1], origin[2], spacing};
}

// out (C, Z, Y, X), zeroed: the adjoint splat of values (N, C), N > 0 and C > 0.
void scatter_into(const at::Tensor& values, const at::Tensor& points, const cuda::TriGeom& g, at::Tensor& out) {
  const int64_t N = points.size(0), C = values.size(1), vol = g.Z * g.Y * g.X;
  auto keys = at::empty({N * 8}, points.options().dtype(at::kLong));
  auto weights = at::empty({N, 8, 1}, values.options());
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "trilinear_scatter_cuda", [&] {
    cuda::trilinear_scatter_terms<scalar_t>(points.const_data_ptr<scalar_t>(), N, g, keys.mutable_data_ptr<int64_t>(),
                                            weights.mutable_data_ptr<scalar_t>(), at::cuda::getCurrentCUDAStream());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  // row vol collects the terms of non-finite points (weight 0) and is dropped
  auto sums = at::zeros({vol + 1, C}, values.options());
  sums.index_put_({keys}, weights.mul(values.reshape({N, 1, C})).reshape({N * 8, C}), /*accumulate=*/true);
  out.copy_(sums.narrow(0, 0, vol).t().reshape({C, g.Z, g.Y, g.X}));
}

at::Tensor gather_cuda(const at::Tensor& grid_in, const at::Tensor& points_in, c10::ArrayRef<double> origin,
                       double spacing) {
  args::gather(grid_in, points_in, origin, spacing);
  args::require_cuda(points_in, "points");
  const c10::cuda::CUDAGuard guard(points_in.device());
  const auto grid = grid_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = grid.size(0);
  auto out = at::empty({N, C}, grid.options());
  if (N == 0 || C == 0) return out;
  const auto g = geom(origin, spacing, grid.size(1), grid.size(2), grid.size(3));
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "trilinear_gather_cuda", [&] {
    cuda::trilinear_gather<scalar_t>(grid.const_data_ptr<scalar_t>(), C, points.const_data_ptr<scalar_t>(), N, g,
                                     out.mutable_data_ptr<scalar_t>(), at::cuda::getCurrentCUDAStream());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

at::Tensor scatter_cuda(const at::Tensor& values_in, const at::Tensor& points_in, c10::ArrayRef<double> origin,
                        double spacing, c10::ArrayRef<int64_t> grid_shape) {
  args::scatter(values_in, points_in, origin, spacing, grid_shape);
  args::require_cuda(points_in, "points");
  const c10::cuda::CUDAGuard guard(points_in.device());
  const auto values = values_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = values.size(1);
  const auto g = geom(origin, spacing, grid_shape[0], grid_shape[1], grid_shape[2]);
  auto out = at::zeros({C, g.Z, g.Y, g.X}, values.options());
  if (N == 0 || C == 0) return out;
  scatter_into(values, points, g, out);
  return out;
}

std::tuple<at::Tensor, at::Tensor> gather_backward_cuda(const at::Tensor& grad_in, const at::Tensor& grid_in,
                                                        const at::Tensor& points_in, c10::ArrayRef<double> origin,
                                                        double spacing, bool need_grid_grad,
                                                        bool need_points_grad) {
  args::gather_backward(grad_in, grid_in, points_in, origin, spacing);
  args::require_cuda(points_in, "points");
  const c10::cuda::CUDAGuard guard(points_in.device());
  const auto grad = grad_in.contiguous();
  const auto grid = grid_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = grid.size(0);
  const auto g = geom(origin, spacing, grid.size(1), grid.size(2), grid.size(3));
  at::Tensor gg = need_grid_grad ? at::zeros_like(grid) : at::empty({0}, grid.options());
  at::Tensor gp = need_points_grad ? at::empty_like(points) : at::empty({0}, points.options());
  if (N == 0) return {gg, gp};
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  if (need_grid_grad && C > 0) scatter_into(grad, points, g, gg);
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "trilinear_gather_backward_cuda", [&] {
    if (need_points_grad) {
      cuda::trilinear_points_grad<scalar_t>(grad.const_data_ptr<scalar_t>(), grid.const_data_ptr<scalar_t>(), C,
                                            points.const_data_ptr<scalar_t>(), N, g,
                                            gp.mutable_data_ptr<scalar_t>(), stream);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  return {gg, gp};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("trilinear_gather", &gather_cuda);
  m.impl("trilinear_gather_backward", &gather_backward_cuda);
  m.impl("trilinear_scatter", &scatter_cuda);
}

}  // namespace floxels
