// Torch binding of the CUDA cluster ops: checks inputs, allocates outputs plus one zeroed
// workspace, and launches on the current stream. No host synchronisation: labels outside
// [-1, num_clusters) are not detected here (the Python wrappers check them) and count as noise.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <tuple>

#include "common/op_args.h"
#include "cuda/cluster_launch.h"

namespace floxels {
namespace {

at::Tensor workspace_for(const at::Tensor& v, int64_t K) {
  return at::zeros({cuda::cluster_workspace_elems(K, v.size(1))}, v.options());
}

at::Tensor mean_cuda(const at::Tensor& values_in, const at::Tensor& labels_in, int64_t K) {
  args::cluster(values_in, labels_in, K, "values");
  args::require_cuda(values_in, "values");
  const c10::cuda::CUDAGuard guard(values_in.device());
  const auto v = values_in.contiguous();
  const auto lab = labels_in.contiguous();
  const int64_t N = v.size(0), C = v.size(1);
  auto out = at::empty({K, C}, v.options());
  if (K == 0 || C == 0) return out;
  auto ws = workspace_for(v, K);
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "cluster_mean_cuda", [&] {
    cuda::cluster_mean<scalar_t>(v.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), N, C, K,
                                 ws.mutable_data_ptr<scalar_t>(), out.mutable_data_ptr<scalar_t>(),
                                 at::cuda::getCurrentCUDAStream());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return out;
}

// Shared by the three loss ops: loss and/or grad (grad_scale: device scalar or nullptr).
void consistency(const at::Tensor& f, const at::Tensor& lab, int64_t K, at::Tensor* loss, at::Tensor* grad,
                 const at::Tensor* grad_scale) {
  const int64_t N = f.size(0), C = f.size(1);
  if (N == 0 || C == 0) {
    if (grad) grad->zero_();
    return;
  }
  auto ws = workspace_for(f, K);
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_cuda", [&] {
    cuda::cluster_consistency<scalar_t>(
        f.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), N, C, K, ws.mutable_data_ptr<scalar_t>(),
        loss ? loss->mutable_data_ptr<scalar_t>() : nullptr, grad ? grad->mutable_data_ptr<scalar_t>() : nullptr,
        grad_scale ? grad_scale->const_data_ptr<scalar_t>() : nullptr, at::cuda::getCurrentCUDAStream());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

at::Tensor loss_cuda(const at::Tensor& flow, const at::Tensor& labels, int64_t K) {
  args::cluster(flow, labels, K, "flow");
  args::require_cuda(flow, "flow");
  const c10::cuda::CUDAGuard guard(flow.device());
  const auto f = flow.contiguous();
  const auto lab = labels.contiguous();
  auto loss = at::zeros({}, f.options());
  consistency(f, lab, K, &loss, nullptr, nullptr);
  return loss;
}

at::Tensor loss_backward_cuda(const at::Tensor& grad, const at::Tensor& flow, const at::Tensor& labels,
                              int64_t K) {
  args::cluster(flow, labels, K, "flow");
  args::require_cuda(flow, "flow");
  FLX_CHECK(grad.numel() == 1, "floxels: grad must be a scalar, got shape ", grad.sizes());
  check_same_device(grad, flow, "grad", "flow");
  check_same_dtype(grad, flow, "grad", "flow");
  const c10::cuda::CUDAGuard guard(flow.device());
  const auto f = flow.contiguous();
  const auto lab = labels.contiguous();
  const auto g = grad.contiguous();
  auto out = at::empty_like(f);  // every row is written by the kernels
  consistency(f, lab, K, nullptr, &out, &g);
  return out;
}

std::tuple<at::Tensor, at::Tensor> fwd_bwd_cuda(const at::Tensor& flow, const at::Tensor& labels, int64_t K) {
  args::cluster(flow, labels, K, "flow");
  args::require_cuda(flow, "flow");
  const c10::cuda::CUDAGuard guard(flow.device());
  const auto f = flow.contiguous();
  const auto lab = labels.contiguous();
  auto loss = at::zeros({}, f.options());
  auto out = at::empty_like(f);  // every row is written by the kernels
  consistency(f, lab, K, &loss, &out, nullptr);
  return {loss, out};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("cluster_mean", &mean_cuda);
  m.impl("cluster_consistency_loss", &loss_cuda);
  m.impl("cluster_consistency_loss_backward", &loss_backward_cuda);
  m.impl("cluster_consistency_fwd_bwd", &fwd_bwd_cuda);
}

}  // namespace floxels
