// Argument checks for the dt_loss ops, shared by the CPU implementation and the CUDA
// binding so both reject bad input with the same messages (before touching memory).
#pragma once
#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <cmath>
#include <optional>
#include <string>
#include <string_view>

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

// dt_residual / dt_sample / dt_evidence: points and motion (N, 3) of one dtype and device, 1 to
// kMaxScans float32 (Z, Y, X) DTs there, finite origins / time offsets / weights (weights may be
// empty: dt_sample takes none) and, where given, a positive finite cap.
inline void check_dt_query_args(std::string_view op, const at::Tensor& points, const at::Tensor& motion,
                                at::TensorList dts, c10::ArrayRef<double> origins, double spacing,
                                c10::ArrayRef<double> time_offsets, const c10::ArrayRef<double>* weights,
                                const double* cap, std::string_view motion_name = "motion") {
  check_points(points, "points");
  check_points(motion, motion_name);
  FLX_CHECK(motion.size(0) == points.size(0), "floxels: ", op, ": ", motion_name, " must have the shape of points ",
            points.sizes(), ", got ", motion.sizes());
  check_same_dtype(points, motion, "points", motion_name);
  check_same_device(points, motion, "points", motion_name);
  const int64_t K = static_cast<int64_t>(dts.size());
  FLX_CHECK(K >= 1, "floxels: ", op, " needs at least one distance transform");
  FLX_CHECK(K <= dt_loss::kMaxScans, "floxels: ", op, " supports at most ", dt_loss::kMaxScans,
            " distance transforms, got ", K);
  for (int64_t k = 0; k < K; ++k) {
    const at::Tensor& d = dts[k];
    FLX_CHECK(d.dim() == 3, "floxels: ", op, ": dts[", k, "] must be a (Z, Y, X) grid, got shape ", d.sizes());
    FLX_CHECK(d.scalar_type() == at::kFloat, "floxels: ", op, ": dts[", k, "] must be float32, got ",
              d.scalar_type());
    FLX_CHECK(d.numel() > 0, "floxels: ", op, ": dts[", k, "] must not be empty, got shape ", d.sizes());
    FLX_CHECK(d.device() == points.device(), "floxels: ", op, ": dts[", k, "] is on ", d.device(),
              " but points are on ", points.device());
  }
  FLX_CHECK(static_cast<int64_t>(origins.size()) == 3 * K, "floxels: ", op, ": origins needs 3 values per "
            "distance transform (", 3 * K, " for ", K, "), got ", origins.size());
  FLX_CHECK(static_cast<int64_t>(time_offsets.size()) == K, "floxels: ", op, ": time_offsets needs ", K,
            " values (one per distance transform), got ", time_offsets.size());
  for (double v : origins) FLX_CHECK(std::isfinite(v), "floxels: ", op, ": origins must be finite, got ", origins);
  for (double v : time_offsets)
    FLX_CHECK(std::isfinite(v), "floxels: ", op, ": time_offsets must be finite, got ", time_offsets);
  if (weights != nullptr) {
    FLX_CHECK(static_cast<int64_t>(weights->size()) == K, "floxels: ", op, ": weights needs ", K,
              " values (one per distance transform), got ", weights->size());
    for (double v : *weights) FLX_CHECK(std::isfinite(v), "floxels: ", op, ": weights must be finite, got ", *weights);
  }
  check_spacing(spacing);
  if (cap != nullptr) {
    FLX_CHECK(std::isfinite(*cap) && *cap > 0.0, "floxels: ", op, ": cap must be positive and finite, got ", *cap);
  }
}

// dt_residual / dt_evidence's optional observed bits: (N,) int32 on the points' device, bit k
// of row i set where scan k counts for point i (the kernels read it contiguous).
inline void check_observed(std::string_view op, const std::optional<at::Tensor>& observed, const at::Tensor& points) {
  if (!observed.has_value()) return;
  const at::Tensor& b = *observed;
  FLX_CHECK(b.dim() == 1 && b.size(0) == points.size(0), "floxels: ", op, ": observed must have shape (",
            points.size(0), ",) (one bit mask per point), got ", b.sizes());
  FLX_CHECK(b.scalar_type() == at::kInt, "floxels: ", op, ": observed must be int32, got ", b.scalar_type());
  check_same_device(points, b, "points", "observed");
}

// Row offsets of C clusters (rigid_lm, velocity_search): int64 (C + 1,) on the points' device;
// num_clusters < 0: any C >= 0. Their values are not read (that would synchronise a CUDA caller):
// the kernels clamp them to the rows (kernels/rigid_lm.h cluster_rows).
inline void check_segments(std::string_view op, const at::Tensor& segments, const at::Tensor& points,
                           int64_t num_clusters = -1) {
  const bool any = num_clusters < 0;
  FLX_CHECK(segments.dim() == 1 && (any ? segments.size(0) >= 1 : segments.size(0) == num_clusters + 1),
            "floxels: ", op, ": segments must have shape (", any ? std::string("C + 1") : std::to_string(num_clusters + 1),
            ",) (row offsets of the C clusters), got ", segments.sizes());
  FLX_CHECK(segments.scalar_type() == at::kLong, "floxels: ", op, ": segments must be int64, got ",
            segments.scalar_type());
  check_same_device(points, segments, "points", "segments");
}

// dt_evidence's group keys: (N,) int32/int64 on the points' device (any stride).
inline void check_group_keys(const at::Tensor& keys, const at::Tensor& points, std::string_view name) {
  FLX_CHECK(keys.dim() == 1 && keys.size(0) == points.size(0), "floxels: dt_evidence: ", name,
            " must have shape (", points.size(0), ",), got ", keys.sizes());
  FLX_CHECK(keys.scalar_type() == at::kInt || keys.scalar_type() == at::kLong, "floxels: dt_evidence: ", name,
            " must be int32 or int64, got ", keys.scalar_type());
  check_same_device(keys, points, name, "points");
}

}  // namespace floxels
