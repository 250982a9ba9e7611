// Torch binding of the CUDA dt_residual / dt_sample / dt_evidence kernels: checks inputs (same
// checks as the CPU implementation), allocates the outputs (and dt_evidence's workspace) and
// launches on the current stream. Nothing here synchronises with the host.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <array>
#include <cstdint>
#include <limits>
#include <optional>
#include <string_view>
#include <tuple>
#include <vector>

#include "common/dt_loss_args.h"
#include "cuda/dt_inputs.h"
#include "cuda/dt_query_launch.h"
#include "kernels/dt_loss.h"

namespace floxels {
namespace {

at::Tensor dt_residual_cuda(const at::Tensor& points, const at::Tensor& motion, at::TensorList dts,
                            c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                            c10::ArrayRef<double> weights, double cap, bool squared,
                            const std::optional<at::Tensor>& observed) {
  // checks first: a CPU tensor among the inputs must get the device message, not the guard's
  check_dt_query_args("dt_residual", points, motion, dts, origins, spacing, time_offsets, &weights, &cap);
  check_observed("dt_residual", observed, points);
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  const cuda::DtInputs in =
      cuda::prepare_dt_inputs("dt_residual", points, motion, dts, origins, time_offsets, weights);
  const c10::cuda::CUDAGuard guard(points.device());
  at::Tensor out = at::empty({points.size(0)}, points.options());
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "dt_residual_cuda", [&] {
    C10_CUDA_CHECK(cuda::launch_dt_residual(in.points.const_data_ptr<scalar_t>(), in.motion.const_data_ptr<scalar_t>(),
                                            points.size(0), in.descs.data(), in.num_scans, spacing, cap, squared,
                                            ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr,
                                            out.mutable_data_ptr<scalar_t>(), stream));
  });
  return out;
}

at::Tensor dt_sample_cuda(const at::Tensor& points, const at::Tensor& motion, at::TensorList dts,
                          c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets) {
  check_dt_query_args("dt_sample", points, motion, dts, origins, spacing, time_offsets, nullptr, nullptr);
  const cuda::DtInputs in = cuda::prepare_dt_inputs("dt_sample", points, motion, dts, origins, time_offsets, {});
  const c10::cuda::CUDAGuard guard(points.device());
  at::Tensor out = at::empty({static_cast<int64_t>(dts.size()), points.size(0), 4}, points.options());
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "dt_sample_cuda", [&] {
    C10_CUDA_CHECK(cuda::launch_dt_sample(in.points.const_data_ptr<scalar_t>(), in.motion.const_data_ptr<scalar_t>(),
                                          points.size(0), in.descs.data(), in.num_scans, spacing,
                                          out.mutable_data_ptr<scalar_t>(), stream));
  });
  return out;
}

cuda::GroupKeys keys_of(const at::Tensor& t) {
  return cuda::GroupKeys{t.const_data_ptr(), t.stride(0), t.scalar_type() == at::kLong};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> dt_evidence_cuda(
    const at::Tensor& points, const at::Tensor& flow, const std::optional<at::Tensor>& labels,
    const at::Tensor& cells, at::TensorList dts, c10::ArrayRef<double> origins, double spacing,
    c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights, double cap, double margin, double ratio,
    const std::optional<at::Tensor>& observed) {
  check_dt_query_args("dt_evidence", points, flow, dts, origins, spacing, time_offsets, &weights, &cap, "flow");
  check_observed("dt_evidence", observed, points);
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  FLX_CHECK(std::isfinite(margin), "floxels: dt_evidence: margin must be finite, got ", margin);
  FLX_CHECK(std::isfinite(ratio), "floxels: dt_evidence: ratio must be finite, got ", ratio);
  check_group_keys(cells, points, "cells");
  if (labels.has_value()) check_group_keys(*labels, points, "labels");
  const cuda::DtInputs in =
      cuda::prepare_dt_inputs("dt_evidence", points, flow, dts, origins, time_offsets, weights);
  const c10::cuda::CUDAGuard guard(points.device());
  const int64_t n = points.size(0);
  at::Tensor score = at::empty({n}, points.options());
  at::Tensor explained = at::empty({n}, points.options().dtype(at::kBool));
  at::Tensor res_f = at::empty({n}, points.options());
  at::Tensor res_z = at::empty({n}, points.options());
  if (n == 0) return {score, explained, res_f, res_z};
  at::Tensor workspace = at::empty({cuda::dt_evidence_workspace_bytes(n)}, points.options().dtype(at::kByte));
  const cuda::GroupKeys lab = labels.has_value() ? keys_of(*labels) : cuda::GroupKeys{nullptr, 0, false};
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(in.points.scalar_type(), "dt_evidence_cuda", [&] {
    C10_CUDA_CHECK(cuda::launch_dt_evidence(
        in.points.const_data_ptr<scalar_t>(), in.motion.const_data_ptr<scalar_t>(), n, lab, keys_of(cells),
        in.descs.data(), in.num_scans, spacing, cap, margin, ratio,
        ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr, score.mutable_data_ptr<scalar_t>(),
        explained.mutable_data_ptr<bool>(), res_f.mutable_data_ptr<scalar_t>(), res_z.mutable_data_ptr<scalar_t>(),
        workspace.mutable_data_ptr(), stream));
  });
  return {score, explained, res_f, res_z};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("dt_residual", &floxels::dt_residual_cuda);
  m.impl("dt_sample", &floxels::dt_sample_cuda);
  m.impl("dt_evidence", &floxels::dt_evidence_cuda);
}
