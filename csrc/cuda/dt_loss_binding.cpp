// Torch binding of the CUDA dt_loss kernels: checks inputs (same checks as the CPU
// implementation), allocates the outputs and the per-block workspace, and launches on
// the current stream. Nothing here synchronises with the host: the loss stays on the
// device as a 0-dim tensor of the points' dtype.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <tuple>
#include <vector>

#include "common/dt_loss_args.h"
#include "cuda/dt_inputs.h"
#include "cuda/dt_loss_launch.h"
#include "kernels/dt_loss.h"

namespace floxels {
namespace {

// The checks the CPU implementation makes, then the inputs as the launcher wants them.
cuda::DtInputs prepare(const at::Tensor& points, const at::Tensor& flow, at::TensorList dts,
                       c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                       c10::ArrayRef<double> weights, double truncation) {
  check_dt_loss_args(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  return cuda::prepare_dt_inputs("dt_loss", points, flow, dts, origins, time_offsets, weights);
}

// Runs one fused pass; loss / grad_flow / grad_scale are undefined tensors when unused.
void run(const cuda::DtInputs& in, double spacing, double truncation, const at::Tensor& grad_scale,
         const at::Tensor& loss, const at::Tensor& grad_flow) {
  const int64_t n = in.points.size(0);
  const bool need_loss = loss.defined();
  at::Tensor workspace;
  if (need_loss && n > 0) {
    workspace = at::empty({cuda::dt_loss_workspace_size(n)}, in.points.options().dtype(at::kDouble));
  }
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "dt_loss_cuda", [&] {
    const cudaError_t err = cuda::launch_dt_loss(
        in.points.const_data_ptr<scalar_t>(), in.motion.const_data_ptr<scalar_t>(), n, in.descs.data(),
        in.num_scans, spacing, truncation,
        grad_scale.defined() ? grad_scale.const_data_ptr<scalar_t>() : nullptr,
        need_loss ? loss.mutable_data_ptr<scalar_t>() : nullptr,
        grad_flow.defined() ? grad_flow.mutable_data_ptr<scalar_t>() : nullptr,
        workspace.defined() ? workspace.mutable_data_ptr<double>() : nullptr, stream);
    C10_CUDA_CHECK(err);
  });
}

at::Tensor dt_loss_cuda(const at::Tensor& points, const at::Tensor& flow, at::TensorList dts,
                        c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                        c10::ArrayRef<double> weights, double truncation) {
  // checks first: a CPU tensor among the inputs must get the device message, not the guard's
  const cuda::DtInputs in = prepare(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  const c10::cuda::CUDAGuard guard(points.device());
  at::Tensor loss = at::empty({}, points.options());
  run(in, spacing, truncation, at::Tensor(), loss, at::Tensor());
  return loss;
}

at::Tensor dt_loss_backward_cuda(const at::Tensor& grad, const at::Tensor& points, const at::Tensor& flow,
                                 at::TensorList dts, c10::ArrayRef<double> origins, double spacing,
                                 c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights,
                                 double truncation) {
  // checks first: a CPU tensor among the inputs must get the device message, not the guard's
  const cuda::DtInputs in = prepare(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  const c10::cuda::CUDAGuard guard(points.device());
  check_dt_loss_grad(grad, points);
  // The kernel reads the upstream gradient on the device: no host sync.
  const at::Tensor scale = grad.to(points.scalar_type()).contiguous();
  at::Tensor grad_flow = at::empty({points.size(0), 3}, points.options());
  run(in, spacing, truncation, scale, at::Tensor(), grad_flow);
  return grad_flow;
}

std::tuple<at::Tensor, at::Tensor> dt_loss_fwd_bwd_cuda(const at::Tensor& points, const at::Tensor& flow,
                                                        at::TensorList dts, c10::ArrayRef<double> origins,
                                                        double spacing, c10::ArrayRef<double> time_offsets,
                                                        c10::ArrayRef<double> weights, double truncation) {
  // checks first: a CPU tensor among the inputs must get the device message, not the guard's
  const cuda::DtInputs in = prepare(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  const c10::cuda::CUDAGuard guard(points.device());
  at::Tensor loss = at::empty({}, points.options());
  at::Tensor grad_flow = at::empty({points.size(0), 3}, points.options());
  run(in, spacing, truncation, at::Tensor(), loss, grad_flow);
  return {loss, grad_flow};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("dt_loss", &floxels::dt_loss_cuda);
  m.impl("dt_loss_backward", &floxels::dt_loss_backward_cuda);
  m.impl("dt_loss_fwd_bwd", &floxels::dt_loss_fwd_bwd_cuda);
}
