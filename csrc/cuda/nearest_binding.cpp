// Torch binding of the CUDA nearest_neighbor: checks inputs, launches on the current stream
// and unpacks the (distance bits, index) keys of the segmented form (no host synchronisation).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/bitwise_and.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>

#include "common/op_args.h"
#include "cuda/nearest_launch.h"

namespace floxels {
namespace {

at::Tensor nearest_cuda(const at::Tensor& x_in, const at::Tensor& y_in) {
  args::nearest(x_in, y_in);
  args::require_cuda(x_in, "x");
  const c10::cuda::CUDAGuard guard(x_in.device());
  const auto x = x_in.contiguous();
  const auto y = y_in.contiguous();
  const int64_t N = x.size(0), M = y.size(0);
  const auto long_opts = x.options().dtype(at::kLong);
  if (N == 0) return at::empty({0}, long_opts);
  const int sms = at::cuda::getCurrentDeviceProperties()->multiProcessorCount;
  const int segments = cuda::nearest_segments(N, M, sms, x.scalar_type() == at::kDouble);
  at::Tensor idx, packed;
  if (segments > 1) {
    packed = at::full({N}, std::numeric_limits<int64_t>::max(), long_opts);
  } else {
    idx = at::empty({N}, long_opts);
  }
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "nearest_neighbor_cuda", [&] {
    cuda::nearest_neighbor<scalar_t>(
        x.const_data_ptr<scalar_t>(), N, y.const_data_ptr<scalar_t>(), M, segments,
        segments > 1 ? nullptr : idx.mutable_data_ptr<int64_t>(),
        segments > 1 ? reinterpret_cast<unsigned long long*>(packed.mutable_data_ptr<int64_t>()) : nullptr,
        at::cuda::getCurrentCUDAStream());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  // low 32 bits of the key: the index
  return segments > 1 ? at::bitwise_and(packed, int64_t(0xffffffff)) : idx;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("nearest_neighbor", &nearest_cuda); }

}  // namespace floxels
