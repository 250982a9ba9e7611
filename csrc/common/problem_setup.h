// floxels::problem_setup, shared by its two implementations: the argument checks, the result
// type, when the vertex lattice is renumbered densely, and the ATen implementation
// (csrc/cpu/problem_setup.cpp: every device; the CUDA op, csrc/cuda/problem_setup_binding.cpp,
// falls back to it for sparse lattices and keys that do not fit one int64).
#pragma once
#include <ATen/core/Tensor.h>
#include <ATen/ops/sort.h>

#include <cstdint>
#include <optional>
#include <tuple>

#include "common/check.h"

namespace floxels::setup {

// (order, sorted points, sorted labels, corner_idx, corner_w, vertices, seg_ptr, vtx_ptr,
// vtx_entry, number of clusters): see csrc/ops.cpp
using Result = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
                          at::Tensor, at::Tensor, int64_t>;

// The dense vertex lattice is renumbered through a mark array when it is at most this many
// times the number of corner references (cheap, no sort, no host synchronisation);
// larger (sparse, absurdly wide) lattices go through torch.unique.
constexpr int64_t kDenseFactor = 16;

inline bool dense(int64_t cells, int64_t n) { return cells <= kDenseFactor * 8 * n; }

// One sort key per point, (label + 1) * cells + cell, when it fits an int64 (labels < n).
inline bool one_key(int64_t cells, int64_t n) { return (n + 1) < (int64_t(1) << 62) / cells; }

// Indices of a stable ascending sort of `t` (both implementations sort this way, so equal keys
// keep their input order and the CPU and CUDA outputs agree). (at::sort(t, true) would read
// `true` as the dimension.)
inline at::Tensor stable_order(const at::Tensor& t) {
  return std::get<1>(at::sort(t, std::optional<bool>(true), 0, false));
}

// The checks of every implementation; returns the number of lattice vertices.
inline int64_t check_args(const at::Tensor& points, const std::optional<at::Tensor>& labels,
                          at::ArrayRef<double> origin, double spacing, at::IntArrayRef grid_shape, int64_t tile) {
  FLX_CHECK(points.dim() == 2 && points.size(1) == 3, "floxels: problem_setup: points must be (N, 3), got ",
            points.sizes());
  FLX_CHECK(points.is_floating_point(), "floxels: problem_setup: points must be float32/float64, got ",
            points.scalar_type());
  check_origin(origin);
  check_grid_shape(grid_shape);
  check_spacing(spacing);
  FLX_CHECK(tile >= 1, "floxels: problem_setup: tile must be >= 1, got ", tile);
  const int64_t cells = grid_shape[0] * grid_shape[1] * grid_shape[2];
  FLX_CHECK(cells > 0 && cells < (int64_t(1) << 50), "floxels: problem_setup: grid of ", cells, " vertices");
  if (labels.has_value() && labels->defined()) {
    FLX_CHECK(labels->dim() == 1 && labels->size(0) == points.size(0),
              "floxels: problem_setup: labels must be (N,) for N = ", points.size(0));
    FLX_CHECK(labels->device() == points.device(), "floxels: problem_setup: labels must be on the points' device");
  }
  return cells;
}

// The ATen implementation (any device).
Result problem_setup_aten(const at::Tensor& points, const std::optional<at::Tensor>& labels,
                          at::ArrayRef<double> origin, double spacing, at::IntArrayRef grid_shape, int64_t tile);

}  // namespace floxels::setup
