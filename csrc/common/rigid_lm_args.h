// Argument checks of floxels::rigid_lm, shared by the CPU implementation and the CUDA binding
// so both reject bad input with the same messages (before touching memory).
#pragma once
#include <ATen/core/Tensor.h>

#include <string_view>

#include "common/check.h"
#include "common/dt_loss_args.h"

namespace floxels {

constexpr int64_t kRigidLmMaxIters = 1000;

inline void check_rigid_lm_args(const at::Tensor& points, const at::Tensor& rel, const at::Tensor& segments,
                                const at::Tensor& theta, const at::Tensor& vz, at::TensorList dts,
                                c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                                c10::ArrayRef<double> weights, double tau, int64_t iters) {
  check_dt_query_args("rigid_lm", points, rel, dts, origins, spacing, time_offsets, &weights, &tau, "rel");
  FLX_CHECK(theta.dim() == 2 && theta.size(1) == 3, "floxels: rigid_lm: theta must have shape (C, 3), got ",
            theta.sizes());
  check_same_dtype(points, theta, "points", "theta");
  check_same_device(points, theta, "points", "theta");
  const int64_t C = theta.size(0);
  FLX_CHECK(vz.dim() == 1 && vz.size(0) == C, "floxels: rigid_lm: vz must have shape (", C, ",), got ", vz.sizes());
  check_same_dtype(points, vz, "points", "vz");
  check_same_device(points, vz, "points", "vz");
  check_segments("rigid_lm", segments, points, C);
  FLX_CHECK(iters >= 0 && iters <= kRigidLmMaxIters, "floxels: rigid_lm: iters must be in [0, ",
            kRigidLmMaxIters, "], got ", iters);
}

}  // namespace floxels
