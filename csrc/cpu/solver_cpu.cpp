// CPU implementation of the Floxels optimiser loop (stages in kernels/solver.h).
//
// Same stages as the CUDA version, each a parallel loop; the loop stops as soon as every
// problem has stopped. Everything is deterministic and independent of the thread count:
// losses are summed per fixed chunk of points, and cluster sums run per cluster over a
// member list (built once per call) instead of with atomics.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <vector>

#include "common/solver_torch.h"
#include "kernels/cluster.h"
#include "kernels/corners.h"
#include "kernels/dt_loss.h"
#include "kernels/solver.h"

namespace floxels {
namespace {

using namespace solver;
using CpuScan = dt_loss::Scan<float, int64_t>;

constexpr int64_t kChunk = 2048;  // points per loss partial (fixed: results do not depend on threads)

struct Chunk {
  int problem;
  int64_t begin, end;
};

// Contents checks the CUDA kernels cannot afford per call (they bound-check instead).
void check_indices(const Args& a) {
  const int64_t N = a.num_points, M = a.num_vertices, C = a.num_clusters;
  for (int64_t j = 0; j < 8 * N; ++j) {
    FLX_CHECK(a.corner_idx[j] >= 0 && a.corner_idx[j] < M, "floxels: solver_run: corner_idx[", j / 8, ", ",
              j % 8, "] = ", a.corner_idx[j], " is not a row of theta (", M, " rows)");
    FLX_CHECK(a.vtx_entry[j] >= 0 && a.vtx_entry[j] < 8 * N, "floxels: solver_run: vtx_entry[", j, "] = ",
              a.vtx_entry[j], " is out of range");
  }
  FLX_CHECK(a.vtx_ptr[0] == 0 && a.vtx_ptr[M] == 8 * N, "floxels: solver_run: vtx_ptr must run from 0 to 8N");
  for (int64_t v = 0; v < M; ++v)
    FLX_CHECK(a.vtx_ptr[v] <= a.vtx_ptr[v + 1], "floxels: solver_run: vtx_ptr must be non-decreasing");
  if (a.labels)
    for (int64_t i = 0; i < N; ++i)
      FLX_CHECK(a.labels[i] >= -1 && a.labels[i] < C, "floxels: solver_run: labels[", i, "] = ", a.labels[i],
                " is outside [-1, ", C, ")");
}

class CpuSolver {
 public:
  explicit CpuSolver(const Args& a) : a_(a) {
    const int64_t N = a.num_points, C = a.num_clusters;
    for (int p = 0; p < a.num_problems; ++p) {
      const Problem& pr = a.problems[p];
      const int64_t n = pr.point_end - pr.point_begin;
      const double inv_n = n > 0 ? 1.0 / double(n) : 0.0;
      flow_coef_[p] = float(pr.reg_scale * inv_n);
      cluster_coef_[p] = float(pr.reg_scale * a.hyper.lambda_c * inv_n);
      for (int k = 0; k < pr.num_support; ++k) {
        const Support& s = pr.support[k];
        const DtDesc& d = a.dts[s.dt];
        scans_[p][k] = CpuScan{d.data, d.nx, d.ny, d.nz, float(d.ox), float(d.oy), float(d.oz), float(s.t),
                               float(s.weight * inv_n)};
      }
      for (int64_t b = pr.point_begin; b < pr.point_end; b += kChunk)
        chunks_.push_back({p, b, std::min(b + kChunk, pr.point_end)});
    }
    f_.resize(3 * N);
    g_.resize(3 * N);
    part_.resize(chunks_.size());
    cluster_ = a.labels != nullptr && C > 0;
    if (cluster_) {
      u_.resize(3 * N);
      mean_.resize(3 * C);
      umean_.resize(3 * C);
      // members of each cluster in point order (counting sort)
      member_ptr_.assign(C + 1, 0);
      for (int64_t i = 0; i < N; ++i)
        if (a.labels[i] >= 0) ++member_ptr_[a.labels[i] + 1];
      for (int64_t c = 0; c < C; ++c) member_ptr_[c + 1] += member_ptr_[c];
      members_.resize(member_ptr_[C]);
      std::vector<int64_t> fill(member_ptr_.begin(), member_ptr_.end() - 1);
      for (int64_t i = 0; i < N; ++i)
        if (a.labels[i] >= 0) members_[fill[a.labels[i]]++] = i;
    }
  }

  void run(int64_t num_iters) {
    for (int64_t it = 0; it < num_iters; ++it) {
      if (!any_active()) break;
      points_stage();
      if (cluster_) cluster_stage();
      control_stage();
      vertex_stage();
    }
  }

 private:
  bool active(int p) const { return a_.state[p * kStateCols + kActive] != 0.0; }
  bool any_active() const {
    for (int p = 0; p < a_.num_problems; ++p)
      if (active(p)) return true;
    return false;
  }

  void points_stage() {
    at::parallel_for(0, int64_t(chunks_.size()), 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        const Chunk ch = chunks_[c];
        if (!active(ch.problem)) continue;
        const double* st = a_.state + ch.problem * kStateCols;
        const float lam = float(lambda_g(a_.hyper, st[kIter])) * flow_coef_[ch.problem];
        double acc = 0.0;
        for (int64_t i = ch.begin; i < ch.end; ++i) {
          float* f = &f_[3 * i];
          corners::gather_point<float>(a_.theta, a_.corner_idx + 8 * i, a_.corner_w + 8 * i, 3, f);
          const float* p = a_.points + 3 * i;
          float g[3];
          float l = dt_loss::point_loss<true, float, int64_t>(scans_[ch.problem], a_.problems[ch.problem].num_support,
                                                              p[0], p[1], p[2], f[0], f[1], f[2],
                                                              a_.hyper.inv_dt_cell, a_.hyper.truncation, g);
          float unit[3];
          l += lam * norm_and_unit(f, unit);
          for (int k = 0; k < 3; ++k) g_[3 * i + k] = g[k] + lam * unit[k];
          acc += double(l);
        }
        part_[c] = acc;
      }
    });
  }

  // sums[c] = mean over cluster c's members of v (3 values per point)
  void cluster_means(const std::vector<float>& v, std::vector<float>& out) {
    at::parallel_for(0, a_.num_clusters, 64, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        double s[3] = {0.0, 0.0, 0.0};
        for (int64_t m = member_ptr_[c]; m < member_ptr_[c + 1]; ++m)
          for (int k = 0; k < 3; ++k) s[k] += v[3 * members_[m] + k];
        const double inv = 1.0 / double(a_.cluster_count[c]);
        for (int k = 0; k < 3; ++k) out[3 * c + k] = float(s[k] * inv);
      }
    });
  }

  void cluster_stage() {
    cluster_means(f_, mean_);
    at::parallel_for(0, int64_t(chunks_.size()), 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) {
        const Chunk ch = chunks_[c];
        if (!active(ch.problem)) continue;
        const float coef = cluster_coef_[ch.problem];
        double acc = 0.0;
        for (int64_t i = ch.begin; i < ch.end; ++i) {
          float* u = &u_[3 * i];
          const int32_t l = a_.labels[i];
          if (l < 0) {
            u[0] = u[1] = u[2] = 0.0f;
            continue;
          }
          const float r = cluster::residual_unit<float>(&f_[3 * i], &mean_[3 * int64_t(l)], 3, u);
          for (int k = 0; k < 3; ++k) g_[3 * i + k] += coef * u[k];
          acc += double(coef * r);
        }
        part_[c] += acc;
      }
    });
    cluster_means(u_, umean_);
  }

  void control_stage() {
    size_t c = 0;
    for (int p = 0; p < a_.num_problems; ++p) {
      double loss = 0.0;
      for (; c < chunks_.size() && chunks_[c].problem == p; ++c) loss += part_[c];
      control_update(a_.state + p * kStateCols, loss, a_.history + int64_t(p) * a_.hyper.max_iters, a_.hyper);
    }
  }

  void vertex_stage() {
    for (int p = 0; p < a_.num_problems; ++p) {
      const double* st = a_.state + p * kStateCols;
      const bool step = st[kStep] != 0.0, copy = st[kCopyBest] != 0.0;
      if (!step && !copy) continue;
      const float step_size = float(st[kStepSize]), bc2 = float(st[kBc2Sqrt]);
      const float ccoef = cluster_coef_[p];
      const Problem& pr = a_.problems[p];
      at::parallel_for(pr.vertex_begin, pr.vertex_end, 2048, [&](int64_t v0, int64_t v1) {
        for (int64_t v = v0; v < v1; ++v) {
          float* th = a_.theta + 3 * v;
          if (copy)
            for (int k = 0; k < 3; ++k) a_.best[3 * v + k] = th[k];
          if (!step) continue;
          float G[3] = {0.0f, 0.0f, 0.0f};
          for (int32_t e = a_.vtx_ptr[v]; e < a_.vtx_ptr[v + 1]; ++e) {
            const int32_t ent = a_.vtx_entry[e];
            const int64_t i = ent >> 3;
            const float w = a_.corner_w[ent];
            float gi[3] = {g_[3 * i], g_[3 * i + 1], g_[3 * i + 2]};
            if (cluster_ && a_.labels[i] >= 0) {
              const float* um = &umean_[3 * int64_t(a_.labels[i])];
              for (int k = 0; k < 3; ++k) gi[k] -= ccoef * um[k];
            }
            for (int k = 0; k < 3; ++k) G[k] += w * gi[k];
          }
          for (int k = 0; k < 3; ++k) adam_update(th[k], a_.adam_m[3 * v + k], a_.adam_v[3 * v + k], G[k], a_.hyper,
                                                  step_size, bc2);
        }
      });
    }
  }

  const Args& a_;
  CpuScan scans_[kMaxProblems][kMaxSupport];
  float flow_coef_[kMaxProblems] = {};
  float cluster_coef_[kMaxProblems] = {};
  std::vector<Chunk> chunks_;
  std::vector<float> f_, g_, u_, mean_, umean_;
  std::vector<double> part_;
  bool cluster_ = false;
  std::vector<int64_t> member_ptr_, members_;
};

void solver_run_cpu(const at::Tensor& points, const at::Tensor& corner_idx, const at::Tensor& corner_w,
                    const at::Tensor& vtx_ptr, const at::Tensor& vtx_entry, const std::optional<at::Tensor>& labels,
                    const std::optional<at::Tensor>& cluster_count, at::TensorList dts,
                    c10::ArrayRef<double> dt_origins, c10::ArrayRef<int64_t> point_ranges,
                    c10::ArrayRef<int64_t> vertex_ranges, c10::ArrayRef<int64_t> support_ranges,
                    c10::ArrayRef<int64_t> support_dt, c10::ArrayRef<double> support_t, c10::ArrayRef<double> support_w,
                    c10::ArrayRef<double> reg_scale, c10::ArrayRef<double> hyper, const at::Tensor& theta,
                    const at::Tensor& adam_m, const at::Tensor& adam_v, const at::Tensor& best,
                    const at::Tensor& state, const at::Tensor& history, int64_t num_iters) {
  FLX_CHECK(points.is_cpu(), "floxels: solver_run CPU kernel called with points on ", points.device());
  const Args a = make_args(points, corner_idx, corner_w, vtx_ptr, vtx_entry, labels, cluster_count, dts, dt_origins,
                           point_ranges, vertex_ranges, support_ranges, support_dt, support_t, support_w, reg_scale,
                           hyper, theta, adam_m, adam_v, best, state, history, num_iters);
  check_indices(a);
  CpuSolver(a).run(num_iters);
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("solver_run", &floxels::solver_run_cpu); }
