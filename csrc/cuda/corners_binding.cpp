// Torch binding of the CUDA compact corner gather/scatter. The scatter is deterministic
// (issue 31): each (point, corner) term w_ik * values_i is formed elementwise and the terms
// are summed per row by index_put_ with accumulate, which sorts the rows stably and adds each
// row's terms in index order (no float atomics), so the same input gives the same bytes.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/index_put.h>
#include <ATen/ops/mul.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "common/op_args.h"
#include "cuda/corners_launch.h"

namespace floxels {
namespace {

at::Tensor corner_gather_cuda(const at::Tensor& params, const at::Tensor& idx_in, const at::Tensor& w_in) {
  FLX_CHECK(params.dim() == 2, "floxels: params must be (M, C), got ", params.sizes());
  const int64_t n = idx_in.dim() == 2 ? idx_in.size(0) : -1;
  args::corners(idx_in, w_in, n, params, "params");
  c10::cuda::CUDAGuard guard(params.device());
  auto p = params.contiguous();
  auto idx = idx_in.contiguous();
  auto w = w_in.contiguous();
  auto out = at::empty({n, p.size(1)}, p.options());
  auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "corner_gather_cuda", [&] {
    cuda::corner_gather<scalar_t>(p.data_ptr<scalar_t>(), idx.data_ptr<int32_t>(), w.data_ptr<scalar_t>(), n,
                                  p.size(1), out.data_ptr<scalar_t>(), stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

at::Tensor corner_scatter_cuda(const at::Tensor& values, const at::Tensor& idx_in, const at::Tensor& w_in,
                               int64_t num_params) {
  FLX_CHECK(values.dim() == 2, "floxels: values must be (N, C), got ", values.sizes());
  FLX_CHECK(num_params >= 0, "floxels: num_params must be >= 0, got ", num_params);
  const int64_t n = values.size(0);
  args::corners(idx_in, w_in, n, values, "values");
  c10::cuda::CUDAGuard guard(values.device());
  auto v = values.contiguous();
  auto idx = idx_in.contiguous();
  auto w = w_in.contiguous();
  const int64_t C = v.size(1);
  auto out = at::zeros({num_params, C}, v.options());
  if (n == 0 || C == 0) return out;
  const auto terms = w.reshape({n, 8, 1}).mul(v.reshape({n, 1, C})).reshape({n * 8, C});
  out.index_put_({idx.reshape({n * 8}).to(at::kLong)}, terms, /*accumulate=*/true);
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("corner_gather", &corner_gather_cuda);
  m.impl("corner_scatter", &corner_scatter_cuda);
}

}  // namespace floxels
