// Torch binding of the CUDA cluster ops: checks inputs, forms the per-cluster sums in a fixed
// order (cluster_sums) and launches the per-point kernels on the current stream. No host
// synchronisation: labels outside [-1, num_clusters) are not detected here (the Python
// wrappers check them) and count as noise. Deterministic: the same input gives the same bytes
// (tests/ops/test_determinism_solver_ops.py).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/div.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/index_put.h>
#include <ATen/ops/ones.h>
#include <ATen/ops/sum.h>
#include <ATen/ops/where.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <tuple>
#include <vector>

#include "common/op_args.h"
#include "cuda/cluster_launch.h"

namespace floxels {
namespace {

// Row of each point's sums: its label, or K (an extra row that is never read) for noise and
// labels outside [0, K).
at::Tensor keys_of(const at::Tensor& lab, int64_t K) { return at::where(lab.ge(0).logical_and(lab.lt(K)), lab, K); }

// (K + 1, C) or (K + 1): rows (N, C) or (N) summed by key. index_put_ with accumulate on CUDA
// sorts the keys stably and adds each key's rows in index order: a fixed order, unlike float
// atomics, so the sums are the same bytes run after run.
at::Tensor cluster_sums(const at::Tensor& rows, const at::Tensor& keys, int64_t K) {
  std::vector<int64_t> shape = rows.sizes().vec();
  shape[0] = K + 1;
  auto out = at::zeros(shape, rows.options());
  out.index_put_({keys}, rows, /*accumulate=*/true);
  return out;
}

at::Tensor counts_of(const at::Tensor& keys, int64_t K, const at::TensorOptions& opts) {
  return cluster_sums(at::ones({keys.size(0)}, opts), keys, K);
}

at::Tensor mean_cuda(const at::Tensor& values_in, const at::Tensor& labels_in, int64_t K) {
  args::cluster(values_in, labels_in, K, "values");
  args::require_cuda(values_in, "values");
  const c10::cuda::CUDAGuard guard(values_in.device());
  const auto v = values_in.contiguous();
  const auto lab = labels_in.contiguous();
  const int64_t C = v.size(1);
  if (K == 0 || C == 0) return at::empty({K, C}, v.options());
  const auto keys = keys_of(lab, K);
  const auto sums = cluster_sums(v, keys, K).narrow(0, 0, K);
  const auto counts = counts_of(keys, K, v.options()).narrow(0, 0, K).unsqueeze(1);
  return at::where(counts.gt(0), sums.div(counts), 0).contiguous();  // empty clusters give 0
}

// Shared by the three loss ops: loss (a zeroed scalar) and/or grad (grad_scale: device
// scalar or nullptr).
void consistency(const at::Tensor& f, const at::Tensor& lab, int64_t K, at::Tensor* loss, at::Tensor* grad,
                 const at::Tensor* grad_scale) {
  const int64_t N = f.size(0), C = f.size(1);
  if (N == 0 || C == 0) {
    if (grad) grad->zero_();
    return;
  }
  const auto keys = keys_of(lab, K);
  const auto sums = cluster_sums(f, keys, K);
  const auto counts = counts_of(keys, K, f.options());
  auto norms = loss ? at::empty({N}, f.options()) : at::Tensor();
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_cuda", [&] {
    cuda::cluster_residuals<scalar_t>(f.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), N, C, K,
                                      sums.const_data_ptr<scalar_t>(), counts.const_data_ptr<scalar_t>(),
                                      loss ? norms.mutable_data_ptr<scalar_t>() : nullptr,
                                      grad ? grad->mutable_data_ptr<scalar_t>() : nullptr, stream);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  if (loss) loss->copy_(at::sum(norms).div(double(N)));  // one reduction: a fixed order
  if (!grad) return;
  const auto usums = cluster_sums(*grad, keys, K);  // grad holds the unit residuals here
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_grad_cuda", [&] {
    cuda::cluster_grad<scalar_t>(lab.const_data_ptr<int64_t>(), N, C, K, counts.const_data_ptr<scalar_t>(),
                                 usums.const_data_ptr<scalar_t>(),
                                 grad_scale ? grad_scale->const_data_ptr<scalar_t>() : nullptr,
                                 grad->mutable_data_ptr<scalar_t>(), stream);
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
