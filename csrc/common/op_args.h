// Argument checks of the trilinear, cluster, corner and dbscan ops, shared by their CPU
// implementations and CUDA bindings so both devices accept the same inputs and give the
// same messages. (dt_loss has its own: csrc/common/dt_loss_args.h.)
#pragma once
#include "common/check.h"

#include <cmath>
#include <cstdint>
#include <limits>

namespace floxels::args {

inline void require_cuda(const at::Tensor& t, const char* name) {
  FLX_CHECK(t.is_cuda(), "floxels: ", name, " must be a CUDA tensor, got ", t.device());
}

inline void grid(const at::Tensor& grid, const at::Tensor& points) {
  FLX_CHECK(grid.dim() == 4, "floxels: grid must be (C, Z, Y, X), got shape ", grid.sizes());
  FLX_CHECK(grid.size(1) >= 1 && grid.size(2) >= 1 && grid.size(3) >= 1,
            "floxels: grid spatial sizes must be >= 1, got ", grid.sizes());
  check_same_dtype(grid, points, "grid", "points");
  check_same_device(grid, points, "grid", "points");
}

inline void gather(const at::Tensor& grid_in, const at::Tensor& points, c10::ArrayRef<double> origin,
                   double spacing) {
  check_points(points);
  grid(grid_in, points);
  check_origin(origin);
  check_spacing(spacing);
}

inline void gather_backward(const at::Tensor& grad, const at::Tensor& grid_in, const at::Tensor& points,
                            c10::ArrayRef<double> origin, double spacing) {
  gather(grid_in, points, origin, spacing);
  FLX_CHECK(grad.dim() == 2 && grad.size(0) == points.size(0) && grad.size(1) == grid_in.size(0),
            "floxels: grad_out must be (N, C) = (", points.size(0), ", ", grid_in.size(0), "), got ",
            grad.sizes());
  check_same_dtype(grad, grid_in, "grad_out", "grid");
  check_same_device(grad, grid_in, "grad_out", "grid");
}

inline void scatter(const at::Tensor& values, const at::Tensor& points, c10::ArrayRef<double> origin,
                    double spacing, c10::ArrayRef<int64_t> grid_shape) {
  check_points(points);
  check_origin(origin);
  check_spacing(spacing);
  check_grid_shape(grid_shape);
  FLX_CHECK(values.dim() == 2 && values.size(0) == points.size(0),
            "floxels: values must be (N, C) with N = points.size(0) = ", points.size(0), ", got ",
            values.sizes());
  check_same_dtype(values, points, "values", "points");
  check_same_device(values, points, "values", "points");
}

inline void cluster(const at::Tensor& v, const at::Tensor& labels, int64_t K, const char* name) {
  FLX_CHECK(v.dim() == 2, "floxels: ", name, " must be (N, C), got shape ", v.sizes());
  FLX_CHECK(v.scalar_type() == at::kFloat || v.scalar_type() == at::kDouble, "floxels: ", name,
            " must be float32 or float64, got ", v.scalar_type());
  FLX_CHECK(labels.dim() == 1 && labels.size(0) == v.size(0), "floxels: labels must be (N,) with N = ",
            v.size(0), ", got shape ", labels.sizes());
  FLX_CHECK(labels.scalar_type() == at::kLong, "floxels: labels must be int64, got ", labels.scalar_type());
  check_same_device(v, labels, name, "labels");
  FLX_CHECK(K >= 0, "floxels: num_clusters must be >= 0, got ", K);
}

// corner_idx (N, 8) int32 and corner_w (N, 8) of data's dtype and device.
inline void corners(const at::Tensor& idx, const at::Tensor& w, int64_t n, const at::Tensor& data,
                    const char* data_name) {
  FLX_CHECK(idx.dim() == 2 && idx.size(0) == n && idx.size(1) == 8,
            "floxels: corner_idx must be (N, 8) with N=", n, ", got ", idx.sizes());
  FLX_CHECK(idx.scalar_type() == at::kInt, "floxels: corner_idx must be int32, got ", idx.scalar_type());
  FLX_CHECK(w.sizes() == idx.sizes(), "floxels: corner_w must have the shape of corner_idx ", idx.sizes(),
            ", got ", w.sizes());
  check_same_dtype(w, data, "corner_w", data_name);
  check_same_device(idx, data, "corner_idx", data_name);
  check_same_device(w, data, "corner_w", data_name);
  FLX_CHECK(data.scalar_type() == at::kFloat || data.scalar_type() == at::kDouble, "floxels: ", data_name,
            " must be float32 or float64, got ", data.scalar_type());
}

inline void dbscan(const at::Tensor& points, double eps, int64_t min_samples) {
  check_points(points);
  FLX_CHECK(std::isfinite(eps) && eps > 0.0, "floxels: dbscan eps must be positive and finite, got ", eps);
  FLX_CHECK(min_samples >= 1, "floxels: dbscan min_samples must be >= 1, got ", min_samples);
  FLX_CHECK(points.size(0) < std::numeric_limits<int32_t>::max(), "floxels: dbscan supports < 2^31 points, got ",
            points.size(0));
}

inline void nearest(const at::Tensor& x, const at::Tensor& y) {
  check_points(x, "x");
  check_points(y, "y");
  check_same_dtype(x, y, "x", "y");
  check_same_device(x, y, "x", "y");
  FLX_CHECK(y.size(0) >= 1, "floxels: nearest_neighbor: the reference cloud y is empty");
  FLX_CHECK(y.size(0) < (int64_t(1) << 31), "floxels: nearest_neighbor supports < 2^31 reference points, got ",
            y.size(0));
}

inline void segment_sum(const at::Tensor& values, const at::Tensor& index, int64_t rows, double limit) {
  FLX_CHECK(values.dim() == 2, "floxels: fixed_segment_sum: values must be (M, C), got shape ", values.sizes());
  FLX_CHECK(values.scalar_type() == at::kFloat || values.scalar_type() == at::kDouble,
            "floxels: fixed_segment_sum: values must be float32 or float64, got ", values.scalar_type());
  FLX_CHECK(index.dim() == 1 && index.size(0) == values.size(0), "floxels: fixed_segment_sum: index must be (",
            values.size(0), ",), got shape ", index.sizes());
  FLX_CHECK(index.scalar_type() == at::kLong || index.scalar_type() == at::kInt,
            "floxels: fixed_segment_sum: index must be int64 or int32, got ", index.scalar_type());
  check_same_device(values, index, "values", "index");
  FLX_CHECK(rows >= 0 && rows < (int64_t(1) << 31), "floxels: fixed_segment_sum: rows must be in [0, 2^31), got ",
            rows);
  // limit * 2^24 below 2^52: every clamped term is an exact integer in a double, and 2^11 terms
  // of that size still fit an int64 row (the callers' terms are far smaller)
  FLX_CHECK(std::isfinite(limit) && limit > 0 && limit <= 268435456.0,
            "floxels: fixed_segment_sum: limit must be in (0, 2^28], got ", limit);
}

}  // namespace floxels::args
