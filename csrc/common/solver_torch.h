// floxels::solver_run's torch arguments -> solver::Args, with every check that needs no
// look at tensor contents (shapes, dtypes, devices, contiguity, offset tables), shared by
// the CPU and CUDA bindings. Index contents (corner_idx, seg_ptr, vtx_entry, labels) are validated
// once per frame by python/floxels_ext/ops/solver.py; the kernels still bound-check them
// so that bad indices can never touch memory outside the tables.
#pragma once
#include <ATen/core/Tensor.h>

#include <cstdint>
#include <limits>
#include <optional>
#include <vector>

#include "common/check.h"
#include "kernels/solver_args.h"

namespace floxels::solver {

inline void check_table(const at::Tensor& t, const char* name, at::ScalarType dtype, std::vector<int64_t> shape,
                        const at::Tensor& like) {
  FLX_CHECK(t.scalar_type() == dtype, "floxels: solver_run: ", name, " must be ", dtype, ", got ",
            t.scalar_type());
  FLX_CHECK(t.sizes() == c10::IntArrayRef(shape), "floxels: solver_run: ", name, " must have shape ",
            c10::IntArrayRef(shape), ", got ", t.sizes());
  FLX_CHECK(t.device() == like.device(), "floxels: solver_run: ", name, " is on ", t.device(),
            " but points are on ", like.device());
  FLX_CHECK(t.is_contiguous(), "floxels: solver_run: ", name, " must be contiguous (it is updated in place "
            "or read by raw pointer)");
}

inline void check_offsets(c10::ArrayRef<int64_t> r, int64_t B, int64_t total, const char* name) {
  FLX_CHECK(int64_t(r.size()) == B + 1, "floxels: solver_run: ", name, " needs ", B + 1, " offsets, got ",
            r.size());
  FLX_CHECK(r[0] == 0 && r[B] == total, "floxels: solver_run: ", name, " must run from 0 to ", total, ", got ",
            r);
  for (int64_t b = 0; b < B; ++b)
    FLX_CHECK(r[b] <= r[b + 1], "floxels: solver_run: ", name, " must be non-decreasing, got ", r);
}

// Number of doubles in hyper (see ops.cpp).
constexpr int kHyperValues = 21;

inline Args make_args(const at::Tensor& points, const at::Tensor& corner_idx, const at::Tensor& corner_w,
                      const at::Tensor& seg_ptr, const at::Tensor& vtx_ptr, const at::Tensor& vtx_entry,
                      const std::optional<at::Tensor>& labels, const std::optional<at::Tensor>& cluster_count,
                      at::TensorList dts, c10::ArrayRef<double> dt_origins, c10::ArrayRef<int64_t> point_ranges,
                      c10::ArrayRef<int64_t> vertex_ranges, c10::ArrayRef<int64_t> support_ranges,
                      c10::ArrayRef<int64_t> support_dt, c10::ArrayRef<double> support_t,
                      c10::ArrayRef<double> support_w, c10::ArrayRef<double> reg_scale,
                      c10::ArrayRef<double> hyper, const at::Tensor& theta, const at::Tensor& adam_m,
                      const at::Tensor& adam_v, const at::Tensor& best, const at::Tensor& state,
                      const at::Tensor& history, int64_t num_iters) {
  FLX_CHECK(points.dim() == 2 && points.size(1) == 3 && points.scalar_type() == at::kFloat,
            "floxels: solver_run: points must be (N, 3) float32, got ", points.scalar_type(), " ",
            points.sizes());
  FLX_CHECK(points.is_contiguous(), "floxels: solver_run: points must be contiguous");
  const int64_t N = points.size(0), M = theta.dim() == 2 ? theta.size(0) : -1;
  constexpr int64_t kMaxInt = std::numeric_limits<int32_t>::max();
  FLX_CHECK(8 * N <= kMaxInt && M <= kMaxInt, "floxels: solver_run: at most 2^28 points / 2^31 vertices");
  FLX_CHECK(int64_t(hyper.size()) == kHyperValues, "floxels: solver_run: hyper needs ", kHyperValues,
            " values, got ", hyper.size());
  // hyper[20] = 1: reg_scale carries B more values, each problem's cluster normaliser
  const bool cluster_n_given = hyper[20] != 0.0;
  const int64_t B = int64_t(reg_scale.size()) / (cluster_n_given ? 2 : 1);
  FLX_CHECK(B >= 1 && B <= kMaxProblems, "floxels: solver_run: 1 to ", kMaxProblems,
            " problems per call, got ", B);
  FLX_CHECK(int64_t(hyper.size()) == kHyperValues, "floxels: solver_run: hyper needs ", kHyperValues,
            " values, got ", hyper.size());
  FLX_CHECK(num_iters >= 0, "floxels: solver_run: num_iters must be >= 0, got ", num_iters);
  const int64_t max_iters = int64_t(hyper[11]);
  FLX_CHECK(max_iters >= 1, "floxels: solver_run: max_iters must be >= 1, got ", hyper[11]);

  check_table(corner_idx, "corner_idx", at::kInt, {N, 8}, points);
  check_table(corner_w, "corner_w", at::kFloat, {N, 8}, points);
  const int64_t SG = seg_ptr.dim() == 1 ? seg_ptr.size(0) - 1 : -1;
  FLX_CHECK(SG >= 0, "floxels: solver_run: seg_ptr must be 1-D with S + 1 offsets");
  check_table(seg_ptr, "seg_ptr", at::kInt, {SG + 1}, points);
  check_table(vtx_ptr, "vtx_ptr", at::kInt, {M + 1}, points);
  check_table(vtx_entry, "vtx_entry", at::kInt, {8 * SG}, points);
  for (auto* t : {&theta, &adam_m, &adam_v, &best}) check_table(*t, "theta/adam_m/adam_v/best", at::kFloat, {M, 3}, points);
  check_table(state, "state", at::kDouble, {B, kStateCols}, points);
  check_table(history, "history", at::kDouble, {B, max_iters}, points);
  FLX_CHECK(labels.has_value() == cluster_count.has_value(),
            "floxels: solver_run: labels and cluster_count must be given together");
  int64_t C = 0;
  if (labels) {
    C = cluster_count->dim() == 1 ? cluster_count->size(0) : -1;
    check_table(*labels, "labels", at::kInt, {N}, points);
    check_table(*cluster_count, "cluster_count", at::kFloat, {C}, points);
  }
  check_offsets(point_ranges, B, N, "point_ranges");
  check_offsets(vertex_ranges, B, M, "vertex_ranges");
  const int64_t S = int64_t(support_dt.size());
  check_offsets(support_ranges, B, S, "support_ranges");
  FLX_CHECK(int64_t(support_t.size()) == S && int64_t(support_w.size()) == S,
            "floxels: solver_run: support_dt, support_t and support_w must have equal lengths");
  const int64_t K = int64_t(dts.size());
  FLX_CHECK(K <= kMaxDts, "floxels: solver_run: at most ", kMaxDts, " distance transforms, got ", K);
  FLX_CHECK(int64_t(dt_origins.size()) == 3 * K, "floxels: solver_run: dt_origins needs ", 3 * K,
            " values, got ", dt_origins.size());

  Args a{};
  for (int64_t k = 0; k < K; ++k) {
    const at::Tensor& d = dts[k];
    FLX_CHECK(d.dim() == 3 && d.scalar_type() == at::kFloat && d.numel() > 0 && d.numel() <= kMaxInt &&
                  d.is_contiguous(),
              "floxels: solver_run: dts[", k, "] must be a contiguous non-empty float32 (Z, Y, X) grid below "
              "2^31 samples, got ", d.scalar_type(), " ", d.sizes());
    FLX_CHECK(d.device() == points.device(), "floxels: solver_run: dts[", k, "] is on ", d.device(),
              " but points are on ", points.device());
    a.dts[k] = DtDesc{d.data_ptr<float>(), d.size(2), d.size(1), d.size(0),
                      dt_origins[3 * k], dt_origins[3 * k + 1], dt_origins[3 * k + 2]};
  }
  a.num_dts = int(K);
  for (int64_t b = 0; b < B; ++b) {
    Problem& p = a.problems[b];
    p.point_begin = point_ranges[b];
    p.point_end = point_ranges[b + 1];
    p.vertex_begin = vertex_ranges[b];
    p.vertex_end = vertex_ranges[b + 1];
    p.reg_scale = reg_scale[b];
    p.cluster_n = cluster_n_given ? reg_scale[B + b] : -1.0;
    const int64_t s0 = support_ranges[b], s1 = support_ranges[b + 1];
    FLX_CHECK(s1 - s0 <= kMaxSupport, "floxels: solver_run: at most ", kMaxSupport,
              " support scans per problem, got ", s1 - s0);
    p.num_support = int(s1 - s0);
    for (int64_t s = s0; s < s1; ++s) {
      FLX_CHECK(support_dt[s] >= 0 && support_dt[s] < K, "floxels: solver_run: support_dt[", s, "] = ",
                support_dt[s], " is not an index into ", K, " dts");
      p.support[s - s0] = Support{int(support_dt[s]), support_t[s], support_w[s]};
    }
  }
  a.num_problems = int(B);
  a.points = points.data_ptr<float>();
  a.corner_idx = corner_idx.data_ptr<int32_t>();
  a.corner_w = corner_w.data_ptr<float>();
  a.seg_ptr = seg_ptr.data_ptr<int32_t>();
  a.num_segments = SG;
  a.vtx_ptr = vtx_ptr.data_ptr<int32_t>();
  a.vtx_entry = vtx_entry.data_ptr<int32_t>();
  a.labels = labels ? labels->data_ptr<int32_t>() : nullptr;
  a.cluster_count = cluster_count ? cluster_count->data_ptr<float>() : nullptr;
  a.num_points = N;
  a.num_vertices = M;
  a.num_clusters = C;
  FLX_CHECK(hyper[0] > 0 && hyper[1] > 0, "floxels: solver_run: dt_cell and truncation must be positive");
  a.hyper = Hyper{float(hyper[2]), float(hyper[3]), float(hyper[4]), float(hyper[5]), float(hyper[6]),
                  float(hyper[7]), float(hyper[8]), int(hyper[9]), int(hyper[10]), int(max_iters),
                  hyper[12], float(hyper[1]), float(1.0 / hyper[0])};
  // readings: hyper[13] truncation mode (1 = clamp), [14] lr_gamma, [15] number of
  // milestones, [16..19] milestones
  FLX_CHECK(hyper[15] >= 0 && hyper[15] <= kMaxMilestones, "floxels: solver_run: 0 to ", kMaxMilestones,
            " learning-rate milestones, got ", hyper[15]);
  a.hyper.trunc_above = hyper[13] != 0.0 ? float(hyper[1]) : 0.0f;
  a.hyper.lr_gamma = float(hyper[14]);
  a.hyper.num_milestones = int(hyper[15]);
  for (int k = 0; k < kMaxMilestones; ++k) a.hyper.milestones[k] = int(hyper[16 + k]);
  a.theta = theta.data_ptr<float>();
  a.adam_m = adam_m.data_ptr<float>();
  a.adam_v = adam_v.data_ptr<float>();
  a.best = best.data_ptr<float>();
  a.state = state.data_ptr<double>();
  a.history = history.data_ptr<double>();
  return a;
}

}  // namespace floxels::solver
