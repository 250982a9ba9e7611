// Argument checks for the dt_loss ops, shared by the CPU implementation and the CUDA
// binding so both reject bad input with the same messages (before touching memory).
#pragma once
#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <cmath>

#include "common/check.h"
#include "kernels/dt_loss.h"

namespace floxels {

inline void check_dt_loss_args(const at::Tensor& points, const at::Tensor& flow, at::TensorList dts,
                               c10::ArrayRef<double> origins, double spacing,
                               c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights,
                               double truncation) {
  check_points(points, "points");
  check_points(flow, "flow");
  FLX_CHECK(flow.size(0) == points.size(0), "floxels: flow must have the shape of points ",
              points.sizes(), ", got ", flow.sizes());
  check_same_dtype(points, flow, "points", "flow");
  check_same_device(points, flow, "points", "flow");
  const int64_t K = static_cast<int64_t>(dts.size());
  FLX_CHECK(K >= 1, "floxels: dt_loss needs at least one distance transform");
  FLX_CHECK(K <= dt_loss::kMaxScans, "floxels: dt_loss supports at most ", dt_loss::kMaxScans,
              " distance transforms, got ", K);
  for (int64_t k = 0; k < K; ++k) {
    const at::Tensor& d = dts[k];
    FLX_CHECK(d.dim() == 3, "floxels: dts[", k, "] must be a (Z, Y, X) grid, got shape ", d.sizes());
    FLX_CHECK(d.scalar_type() == at::kFloat, "floxels: dts[", k, "] must be float32, got ",
                d.scalar_type());
    FLX_CHECK(d.numel() > 0, "floxels: dts[", k, "] must not be empty, got shape ", d.sizes());
    FLX_CHECK(d.device() == points.device(), "floxels: dts[", k, "] is on ", d.device(),
                " but points are on ", points.device());
  }
  FLX_CHECK(static_cast<int64_t>(origins.size()) == 3 * K, "floxels: origins needs 3 values per "
              "distance transform (", 3 * K, " for ", K, "), got ", origins.size());
  FLX_CHECK(static_cast<int64_t>(time_offsets.size()) == K, "floxels: time_offsets needs ", K,
              " values (one per distance transform), got ", time_offsets.size());
  FLX_CHECK(static_cast<int64_t>(weights.size()) == K, "floxels: weights needs ", K,
              " values (one per distance transform), got ", weights.size());
  for (double v : origins) FLX_CHECK(std::isfinite(v), "floxels: origins must be finite, got ", origins);
  for (double v : time_offsets)
    FLX_CHECK(std::isfinite(v), "floxels: time_offsets must be finite, got ", time_offsets);
  for (double v : weights) FLX_CHECK(std::isfinite(v), "floxels: weights must be finite, got ", weights);
  check_spacing(spacing);
  FLX_CHECK(truncation > 0.0, "floxels: truncation must be positive, got ", truncation);
}

inline void check_dt_loss_grad(const at::Tensor& grad, const at::Tensor& points) {
  FLX_CHECK(grad.numel() == 1, "floxels: dt_loss_backward grad must be a scalar, got shape ",
              grad.sizes());
  check_same_device(grad, points, "grad", "points");
}

}  // namespace floxels
