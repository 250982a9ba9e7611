// Torch binding of the CUDA exact DBSCAN (csrc/cuda/dbscan.cu).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>
#include <ATen/core/dispatch/Dispatcher.h>
#include <torch/library.h>

#include <cmath>
#include <cstdint>
#include <limits>

#include "common/env_switches.h"
#include "common/op_args.h"
#include "cuda/dbscan_launch.h"

namespace floxels {
namespace {

at::Tensor dbscan_cuda(const at::Tensor& points, double eps, int64_t min_samples) {
  args::dbscan(points, eps, min_samples);
  const int64_t n = points.size(0);
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
  FLX_CHECK(status == cuda::kDbscanOk, "floxels: dbscan CUDA failure (status ", status,
            "; 2 = CUDA error, 3 = bad arguments or workspace)");
  return labels;
}

// CUDA input runs the GPU kernel. Escape hatch: FLOXELS_CPU_DBSCAN=1 (env::cpu_dbscan, read
// once per process) routes CUDA input to the exact CPU kernel instead (identical labels,
// copied back to the input's device). The GPU kernel used to fail intermittently with
// cudaErrorInvalidAddressSpace; the cause (roots stored into the union-find's parent array
// while other threads were still path-halving through it, leaving non-roots that indexed
// min_orig/cid with INT_MAX) is fixed in dbscan.cu (commit d81449d, which also added a
// torch-free stress harness, since removed: see tools/README.md).
at::Tensor dbscan_cuda_input(const at::Tensor& points, double eps, int64_t min_samples) {
  if (!env::cpu_dbscan()) return dbscan_cuda(points, eps, min_samples);
  args::dbscan(points, eps, min_samples);
  static const auto cpu_op = c10::Dispatcher::singleton()
                                 .findSchemaOrThrow("floxels::dbscan", "")
                                 .typed<at::Tensor(const at::Tensor&, double, int64_t)>();
  return cpu_op.call(points.cpu(), eps, min_samples).to(points.device());
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) { m.impl("dbscan", &dbscan_cuda_input); }

}  // namespace floxels
