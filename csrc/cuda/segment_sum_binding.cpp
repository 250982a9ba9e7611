// Torch binding of the CUDA fixed_segment_sum: checks inputs, one zeroed int64 workspace, two
// launches on the current stream, no host synchronisation.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>

#include "common/op_args.h"
#include "cuda/segment_sum_launch.h"

namespace floxels {
namespace {

at::Tensor fixed_segment_sum_cuda(const at::Tensor& values_in, const at::Tensor& index_in, int64_t rows,
                                  double limit, bool void_row, bool count) {
  args::segment_sum(values_in, index_in, rows, limit);
  args::require_cuda(values_in, "values");
  const c10::cuda::CUDAGuard guard(values_in.device());
  const auto values = values_in.contiguous();
  const auto index = index_in.contiguous();
  const int64_t M = values.size(0), C = values.size(1);
  auto out = at::empty({rows, C + (count ? 1 : 0)}, values.options().dtype(at::kDouble));
  if (rows == 0) return out;
  auto ws = at::zeros({rows * (2 * C + 1)}, values.options().dtype(at::kLong));
  const auto stream = at::cuda::getCurrentCUDAStream();
  long long* w = reinterpret_cast<long long*>(ws.mutable_data_ptr<int64_t>());
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "fixed_segment_sum_cuda", [&] {
    if (index.scalar_type() == at::kLong) {
      cuda::segment_sum_accumulate<scalar_t, int64_t>(values.const_data_ptr<scalar_t>(),
                                                      index.const_data_ptr<int64_t>(), M, C, rows, limit, w, stream);
    } else {
      cuda::segment_sum_accumulate<scalar_t, int32_t>(values.const_data_ptr<scalar_t>(),
                                                      index.const_data_ptr<int32_t>(), M, C, rows, limit, w, stream);
    }
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  cuda::segment_sum_finish(w, C, rows, void_row, count, out.mutable_data_ptr<double>(), stream);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("fixed_segment_sum", &fixed_segment_sum_cuda); }

}  // namespace floxels
