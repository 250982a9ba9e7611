// The inputs of a dt_loss-family CUDA kernel (dt_loss, dt_residual, dt_sample, dt_evidence) as
// the launchers want them: contiguous points, per-point motion and DTs (kept alive here; no copy
// when the inputs already are contiguous, the normal case) and one DtLossScanDesc per DT. For the
// torch bindings only (csrc/cuda/*_binding.cpp); the arguments are checked before this is called.
#pragma once

#include <ATen/core/Tensor.h>

#include <array>
#include <cstdint>
#include <limits>
#include <string_view>
#include <vector>

#include "common/check.h"
#include "cuda/dt_loss_launch.h"
#include "kernels/dt_loss.h"

namespace floxels::cuda {

struct DtInputs {
  at::Tensor points, motion;
  std::vector<at::Tensor> dts;
  std::array<DtLossScanDesc, dt_loss::kMaxScans> descs;
  int num_scans = 0;
};

// ``weights`` may be empty (ops without weights: each scan's weight is then 0).
inline DtInputs prepare_dt_inputs(std::string_view op, const at::Tensor& points, const at::Tensor& motion,
                                  at::TensorList dts, c10::ArrayRef<double> origins,
                                  c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights) {
  constexpr int64_t kMaxInt32 = std::numeric_limits<int32_t>::max();
  FLX_CHECK(points.is_cuda(), "floxels: ", op, " CUDA kernel called with points on ", points.device());
  FLX_CHECK(points.size(0) <= kMaxInt32, "floxels: ", op, " supports at most 2^31-1 points on CUDA, got ",
            points.size(0));
  DtInputs in;
  in.points = points.contiguous();
  in.motion = motion.contiguous();
  in.num_scans = static_cast<int>(dts.size());
  in.dts.reserve(dts.size());
  for (int k = 0; k < in.num_scans; ++k) {
    // 32-bit indexing inside the kernels
    FLX_CHECK(dts[k].numel() <= kMaxInt32, "floxels: ", op, ": dts[", k, "] has ", dts[k].numel(),
              " samples; the CUDA kernel supports at most 2^31-1 per grid");
    in.dts.push_back(dts[k].contiguous());
    const at::Tensor& d = in.dts.back();
    in.descs[k] = DtLossScanDesc{d.data_ptr<float>(), d.size(2), d.size(1), d.size(0),
                                 origins[3 * k], origins[3 * k + 1], origins[3 * k + 2],
                                 time_offsets[k], weights.empty() ? 0.0 : weights[k]};
  }
  return in;
}

}  // namespace floxels::cuda
