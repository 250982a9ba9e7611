// Torch binding of the CUDA exact DBSCAN (csrc/cuda/dbscan.cu).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cmath>
#include <cstdint>
#include <limits>

#include "common/check.h"
#include "cuda/dbscan_launch.h"

namespace floxels {
namespace {

at::Tensor dbscan_cuda(const at::Tensor& points, double eps, int64_t min_samples) {
  check_points(points);
  FLX_CHECK(std::isfinite(eps) && eps > 0.0, "floxels: dbscan eps must be positive and finite, got ", eps);
  FLX_CHECK(min_samples >= 1, "floxels: dbscan min_samples must be >= 1, got ", min_samples);
  const int64_t n = points.size(0);
  FLX_CHECK(n < std::numeric_limits<int32_t>::max(), "floxels: dbscan supports < 2^31 points, got ", n);
  c10::cuda::CUDAGuard guard(points.device());
  auto labels = at::empty({n}, points.options().dtype(at::kLong));
  if (n == 0) return labels;
  auto p = points.contiguous();
  const int32_t ms = int32_t(std::min<int64_t>(min_samples, n + 1));  // > n: nothing is core
  const size_t ws_bytes = cuda::dbscan_workspace_bytes(n);
  auto workspace = at::empty({int64_t(ws_bytes)}, p.options().dtype(at::kByte));
  auto stream = at::cuda::getCurrentCUDAStream();
  int status = cuda::kDbscanOk;
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "dbscan_cuda", [&] {
    status = cuda::dbscan<scalar_t>(p.data_ptr<scalar_t>(), n, eps, ms, labels.data_ptr<int64_t>(),
                                    workspace.data_ptr(), ws_bytes, stream);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  FLX_CHECK(status != cuda::kDbscanNonFinite,
              "floxels: dbscan points must be finite (found NaN/inf or an overflowing extent)");
  FLX_CHECK(status == cuda::kDbscanOk, "floxels: dbscan CUDA failure (status ", status, ")");
  return labels;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("dbscan", &dbscan_cuda); }

}  // namespace floxels
