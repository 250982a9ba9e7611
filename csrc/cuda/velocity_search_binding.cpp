// Torch binding of the CUDA velocity_search kernel: checks inputs (the CPU implementation's
// checks), allocates the outputs and the kernels' scratch and launches on the current stream; no
// host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>
#include <optional>
#include <tuple>

#include "common/velocity_search_args.h"
#include "cuda/dt_inputs.h"
#include "cuda/velocity_search_launch.h"

namespace floxels {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> velocity_search_cuda(
    const at::Tensor& points, const at::Tensor& segments, const std::optional<at::Tensor>& observed,
    at::TensorList dts, c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
    c10::ArrayRef<double> weights, double tau, int64_t num_directions, double speed_step, int64_t num_speeds,
    int64_t local_steps, int64_t local_rounds) {
  check_velocity_search_args(points, segments, observed, dts, origins, spacing, time_offsets, weights, tau,
                             num_directions, speed_step, num_speeds, local_steps, local_rounds);
  const int64_t C = segments.size(0) - 1;
  FLX_CHECK(C <= std::numeric_limits<int32_t>::max(),
            "floxels: velocity_search supports at most 2^31-1 clusters on CUDA, got ", C);
  const cuda::DtInputs in =
      cuda::prepare_dt_inputs("velocity_search", points, points, dts, origins, time_offsets, weights);
  const c10::cuda::CUDAGuard guard(points.device());
  const at::Tensor sg = segments.contiguous();
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  at::Tensor best = at::empty({C, 3}, points.options());
  at::Tensor best_score = at::empty({C}, points.options());
  at::Tensor zero_score = at::empty({C}, points.options());
  at::Tensor axes = at::empty({C, 2}, in.points.options());  // scratch of the three launches
  at::Tensor global = at::empty({C, 1 + num_directions * num_speeds}, in.points.options().dtype(at::kDouble));
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "velocity_search_cuda", [&] {
    C10_CUDA_CHECK(cuda::launch_velocity_search(
        in.points.const_data_ptr<scalar_t>(), sg.const_data_ptr<int64_t>(),
        ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr, points.size(0), C, in.descs.data(), in.num_scans,
        spacing, tau, static_cast<int>(num_directions), speed_step, static_cast<int>(num_speeds),
        static_cast<int>(local_steps), static_cast<int>(local_rounds), axes.mutable_data_ptr<scalar_t>(),
        global.mutable_data_ptr<double>(), best.mutable_data_ptr<scalar_t>(),
        best_score.mutable_data_ptr<scalar_t>(), zero_score.mutable_data_ptr<scalar_t>(), stream));
  });
  return {best, best_score, zero_score};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("velocity_search", &floxels::velocity_search_cuda); }
