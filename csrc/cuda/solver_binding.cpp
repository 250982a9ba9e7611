// Torch binding of the CUDA optimiser loop: checks (common/solver_torch.h), one workspace
// allocation, and the launches on the current stream. Nothing synchronises with the host,
// so Python can capture calls into a CUDA graph and replay them.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <cstdint>
#include <optional>

#include "common/solver_torch.h"
#include "cuda/solver_launch.h"

namespace floxels {
namespace {

void solver_run_cuda(const at::Tensor& points, const at::Tensor& corner_idx, const at::Tensor& corner_w,
                     const at::Tensor& seg_ptr, const at::Tensor& vtx_ptr, const at::Tensor& vtx_entry, const std::optional<at::Tensor>& labels,
                     const std::optional<at::Tensor>& cluster_count, at::TensorList dts,
                     c10::ArrayRef<double> dt_origins, c10::ArrayRef<int64_t> point_ranges,
                     c10::ArrayRef<int64_t> vertex_ranges, c10::ArrayRef<int64_t> support_ranges,
                     c10::ArrayRef<int64_t> support_dt, c10::ArrayRef<double> support_t,
                     c10::ArrayRef<double> support_w, c10::ArrayRef<double> reg_scale, c10::ArrayRef<double> hyper,
                     const at::Tensor& theta, const at::Tensor& adam_m, const at::Tensor& adam_v,
                     const at::Tensor& best, const at::Tensor& state, const at::Tensor& history, int64_t num_iters) {
  FLX_CHECK(points.is_cuda(), "floxels: solver_run CUDA kernel called with points on ", points.device());
  const solver::Args a = solver::make_args(points, corner_idx, corner_w, seg_ptr, vtx_ptr, vtx_entry, labels, cluster_count,
                                           dts, dt_origins, point_ranges, vertex_ranges, support_ranges, support_dt,
                                           support_t, support_w, reg_scale, hyper, theta, adam_m, adam_v, best,
                                           state, history, num_iters);
  FLX_CHECK(reinterpret_cast<uintptr_t>(corner_w.data_ptr()) % 16 == 0,
            "floxels: solver_run: corner_w must be 16-byte aligned on CUDA (read as float4); pass a fresh "
            "contiguous copy");
  const c10::cuda::CUDAGuard guard(points.device());
  at::Tensor ws = at::empty({cuda::solver_workspace_bytes(a)}, points.options().dtype(at::kByte));
  C10_CUDA_CHECK(cuda::solver_launch(a, static_cast<int>(num_iters), ws.data_ptr(),
                                     at::cuda::getCurrentCUDAStream()));
}

int64_t solver_loop_blocks_cuda(const at::Tensor& points, c10::ArrayRef<int64_t> point_ranges,
                                c10::ArrayRef<int64_t> vertex_ranges, bool cluster) {
  FLX_CHECK(point_ranges.size() == vertex_ranges.size() && point_ranges.size() >= 2,
            "floxels: solver_loop_blocks needs B + 1 point and vertex offsets");
  const c10::cuda::CUDAGuard guard(points.device());
  return cuda::solver_loop_blocks(point_ranges.data(), vertex_ranges.data(), int(point_ranges.size()) - 1, cluster,
                                  at::cuda::getCurrentCUDAStream());
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("solver_run", &floxels::solver_run_cuda);
  m.impl("solver_loop_blocks", &floxels::solver_loop_blocks_cuda);
}
