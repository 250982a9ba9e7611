// Argument checks of floxels::velocity_search, shared by the CPU implementation and the CUDA
// binding (the same messages).
#pragma once
#include <ATen/core/Tensor.h>

#include <optional>

#include "common/check.h"
#include "common/dt_loss_args.h"
#include "kernels/velocity_search.h"

namespace floxels {

inline void check_velocity_search_args(const at::Tensor& points, const at::Tensor& segments,
                                       const std::optional<at::Tensor>& observed, at::TensorList dts,
                                       c10::ArrayRef<double> origins, double spacing,
                                       c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights, double tau,
                                       int64_t num_directions, double speed_step, int64_t num_speeds,
                                       int64_t local_steps, int64_t local_rounds) {
  check_dt_query_args("velocity_search", points, points, dts, origins, spacing, time_offsets, &weights, &tau);
  check_observed("velocity_search", observed, points);
  check_segments("velocity_search", segments, points);
  FLX_CHECK(num_directions >= 1 && num_speeds >= 1 &&
                1 + num_directions * num_speeds <= velocity_search::kMaxCandidates,
            "floxels: velocity_search: 1 + num_directions * num_speeds must be in [2, ",
            velocity_search::kMaxCandidates, "], got num_directions ", num_directions, ", num_speeds ", num_speeds);
  FLX_CHECK(std::isfinite(speed_step) && speed_step > 0.0,
            "floxels: velocity_search: speed_step must be positive and finite, got ", speed_step);
  FLX_CHECK(local_steps >= 0 && local_steps <= 30 && local_rounds >= 0 && local_rounds <= 1000,
            "floxels: velocity_search: local_steps must be in [0, 30] and local_rounds in [0, 1000], got ",
            local_steps, " and ", local_rounds);
}

}  // namespace floxels
