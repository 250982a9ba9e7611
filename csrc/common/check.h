// Input checks shared by the CPU and CUDA bindings: every op validates dtype, shape and
// device up front so that bad input raises a RuntimeError naming the argument instead
// of reading out of bounds.
#pragma once
#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <string_view>
#include <vector>

namespace floxels {

inline void check_points(const at::Tensor& p, std::string_view name = "points") {
  TORCH_CHECK(p.dim() == 2 && p.size(1) == 3, "floxels: ", name, " must have shape (N, 3), got ",
              p.sizes());
  TORCH_CHECK(p.scalar_type() == at::kFloat || p.scalar_type() == at::kDouble, "floxels: ", name,
              " must be float32 or float64, got ", p.scalar_type());
}

inline void check_same_device(const at::Tensor& a, const at::Tensor& b, std::string_view na,
                              std::string_view nb) {
  TORCH_CHECK(a.device() == b.device(), "floxels: ", na, " is on ", a.device(), " but ", nb,
              " is on ", b.device());
}

inline void check_same_dtype(const at::Tensor& a, const at::Tensor& b, std::string_view na,
                             std::string_view nb) {
  TORCH_CHECK(a.scalar_type() == b.scalar_type(), "floxels: ", na, " is ", a.scalar_type(),
              " but ", nb, " is ", b.scalar_type());
}

inline void check_origin(c10::ArrayRef<double> origin, std::string_view name = "origin") {
  TORCH_CHECK(origin.size() == 3, "floxels: ", name, " must have 3 values [x0, y0, z0], got ",
              origin.size());
}

inline void check_spacing(double spacing) {
  TORCH_CHECK(spacing > 0.0 && spacing < 1e30, "floxels: spacing must be positive and finite, got ",
              spacing);
}

inline void check_grid_shape(c10::ArrayRef<int64_t> shape) {
  TORCH_CHECK(shape.size() == 3, "floxels: grid_shape must be (Z, Y, X), got ", shape.size(),
              " values");
  for (auto s : shape) TORCH_CHECK(s >= 1, "floxels: grid_shape entries must be >= 1, got ", shape);
}

}  // namespace floxels
