// Torch binding of the CUDA rigid_lm kernel: checks inputs (the CPU implementation's checks),
// allocates the outputs and launches on the current stream. Nothing here synchronises with the host.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>
#include <tuple>

#include "common/rigid_lm_args.h"
#include "cuda/dt_inputs.h"
#include "cuda/rigid_lm_launch.h"

namespace floxels {
namespace {

std::tuple<at::Tensor, at::Tensor> rigid_lm_cuda(const at::Tensor& points, const at::Tensor& rel,
                                                 const at::Tensor& segments, const at::Tensor& theta,
                                                 const at::Tensor& vz, at::TensorList dts,
                                                 c10::ArrayRef<double> origins, double spacing,
                                                 c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights,
                                                 double tau, int64_t iters) {
  check_rigid_lm_args(points, rel, segments, theta, vz, dts, origins, spacing, time_offsets, weights, tau, iters);
  FLX_CHECK(theta.size(0) <= std::numeric_limits<int32_t>::max(),
            "floxels: rigid_lm supports at most 2^31-1 clusters on CUDA, got ", theta.size(0));
  const cuda::DtInputs in = cuda::prepare_dt_inputs("rigid_lm", points, rel, dts, origins, time_offsets, weights);
  const c10::cuda::CUDAGuard guard(points.device());
  const at::Tensor sg = segments.contiguous(), th = theta.contiguous(), v = vz.contiguous();
  at::Tensor theta_out = at::empty({theta.size(0), 3}, theta.options());
  at::Tensor cost_out = at::empty({theta.size(0)}, theta.options());
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "rigid_lm_cuda", [&] {
    C10_CUDA_CHECK(cuda::launch_rigid_lm(
        in.points.const_data_ptr<scalar_t>(), in.motion.const_data_ptr<scalar_t>(), sg.const_data_ptr<int64_t>(),
        th.const_data_ptr<scalar_t>(), v.const_data_ptr<scalar_t>(), points.size(0), theta.size(0), in.descs.data(),
        in.num_scans, spacing, tau, iters, theta_out.mutable_data_ptr<scalar_t>(),
        cost_out.mutable_data_ptr<scalar_t>(), stream));
  });
  return {theta_out, cost_out};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("rigid_lm", &floxels::rigid_lm_cuda); }
