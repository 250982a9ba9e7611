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
  const int64_t N = a.num_points, M = a.num_vertices, C = a.num_clusters, S = a.num_segments;
  for (int64_t j = 0; j < 8 * N; ++j)
    FLX_CHECK(a.corner_idx[j] >= 0 && a.corner_idx[j] < M, "floxels: solver_run: corner_idx[", j / 8, ", ",
              j % 8, "] = ", a.corner_idx[j], " is not a row of theta (", M, " rows)");
  if (a.labels)
    for (int64_t i = 0; i < N; ++i)
      FLX_CHECK(a.labels[i] >= -1 && a.labels[i] < C, "floxels: solver_run: labels[", i, "] = ", a.labels[i],
                " is outside [-1, ", C, ")");
  // Segments: cover the points in order, never span two problems, and their points share
  // corner rows and labels (the vertex gradient is computed per segment).
  FLX_CHECK(a.seg_ptr[0] == 0 && a.seg_ptr[S] == N, "floxels: solver_run: seg_ptr must run from 0 to N");
  int p = 0;
  for (int64_t s = 0; s < S; ++s) {
    const int64_t b = a.seg_ptr[s], e = a.seg_ptr[s + 1];
    FLX_CHECK(b < e, "floxels: solver_run: seg_ptr must be increasing (segment ", s, " is empty)");
    while (p + 1 < a.num_problems && b >= a.problems[p].point_end) ++p;
    FLX_CHECK(e <= a.problems[p].point_end, "floxels: solver_run: segment ", s, " spans two problems");
    for (int64_t i = b + 1; i < e; ++i) {
      for (int k = 0; k < 8; ++k)
        FLX_CHECK(a.corner_idx[8 * i + k] == a.corner_idx[8 * b + k], "floxels: solver_run: point ", i,
                  " has other corners than the first point of its segment ", s);
      FLX_CHECK(!a.labels || a.labels[i] == a.labels[b], "floxels: solver_run: point ", i,
                " has another label than the first point of its segment ", s);
    }
  }
  FLX_CHECK(a.vtx_ptr[0] == 0 && a.vtx_ptr[M] == 8 * S, "floxels: solver_run: vtx_ptr must run from 0 to 8S");
  for (int64_t v = 0; v < M; ++v) {
    FLX_CHECK(a.vtx_ptr[v] <= a.vtx_ptr[v + 1], "floxels: solver_run: vtx_ptr must be non-decreasing");
    for (int32_t e = a.vtx_ptr[v]; e < a.vtx_ptr[v + 1]; ++e) {
      const int32_t ent = a.vtx_entry[e];
      FLX_CHECK(ent >= 0 && ent < 8 * S && a.corner_idx[8 * int64_t(a.seg_ptr[ent >> 3]) + (ent & 7)] == v,
                "floxels: solver_run: vtx_entry[", e, "] = ", ent, " is not a (segment, corner) of vertex ", v);
    }
  }
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
      // the cluster term averages over all points, or over pr.cluster_n (clustered points)
      const double inv_c = pr.cluster_n < 0 ? inv_n : (pr.cluster_n > 0 ? 1.0 / pr.cluster_n : 0.0);
      cluster_coef_[p] = float(pr.reg_scale * a.hyper.lambda_c * inv_c);
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
    const int64_t S = a.num_segments;
    seg_grad_.resize(24 * S);
    seg_wsum_.assign(8 * S, 0.0f);
    for (int64_t s = 0; s < S; ++s)
      for (int64_t i = a.seg_ptr[s]; i < a.seg_ptr[s + 1]; ++i)
        for (int k = 0; k < 8; ++k) seg_wsum_[8 * s + k] += a.corner_w[8 * i + k];
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
                                                              a_.hyper.inv_dt_cell, a_.hyper.truncation, g,
                                                              a_.hyper.trunc_above);
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

  // Per segment: sum over its points of w_k * g_i (8 corners x 3), in point order.
  void segment_stage() {
    at::parallel_for(0, a_.num_segments, 256, [&](int64_t s0, int64_t s1) {
      for (int64_t s = s0; s < s1; ++s) {
        float acc[24] = {};
        for (int64_t i = a_.seg_ptr[s]; i < a_.seg_ptr[s + 1]; ++i)
          for (int k = 0; k < 8; ++k)
            for (int c = 0; c < 3; ++c) acc[3 * k + c] += a_.corner_w[8 * i + k] * g_[3 * i + c];
        std::copy(acc, acc + 24, &seg_grad_[24 * s]);
      }
    });
  }

  void vertex_stage() {
    bool any = false;
    for (int p = 0; p < a_.num_problems; ++p) any |= a_.state[p * kStateCols + kStep] != 0.0;
    if (any) segment_stage();
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
            const int64_t s = ent >> 3, k = ent & 7;
            const float* sg = &seg_grad_[24 * s + 3 * k];
            float gs[3] = {sg[0], sg[1], sg[2]};
            const int32_t l = cluster_ ? a_.labels[a_.seg_ptr[s]] : -1;
            if (l >= 0) {  // minus ccoef * mean_c(u) for each of the segment's points, weighted
              const float* um = &umean_[3 * int64_t(l)];
              const float w = seg_wsum_[8 * s + k];
              for (int c = 0; c < 3; ++c) gs[c] -= ccoef * um[c] * w;
            }
            for (int c = 0; c < 3; ++c) G[c] += gs[c];
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
  std::vector<float> f_, g_, u_, mean_, umean_, seg_grad_, seg_wsum_;
  std::vector<double> part_;
  bool cluster_ = false;
  std::vector<int64_t> member_ptr_, members_;
};

void solver_run_cpu(const at::Tensor& points, const at::Tensor& corner_idx, const at::Tensor& corner_w,
                    const at::Tensor& seg_ptr, const at::Tensor& vtx_ptr, const at::Tensor& vtx_entry, const std::optional<at::Tensor>& labels,
                    const std::optional<at::Tensor>& cluster_count, at::TensorList dts,
                    c10::ArrayRef<double> dt_origins, c10::ArrayRef<int64_t> point_ranges,
                    c10::ArrayRef<int64_t> vertex_ranges, c10::ArrayRef<int64_t> support_ranges,
                    c10::ArrayRef<int64_t> support_dt, c10::ArrayRef<double> support_t, c10::ArrayRef<double> support_w,
                    c10::ArrayRef<double> reg_scale, c10::ArrayRef<double> hyper, const at::Tensor& theta,
                    const at::Tensor& adam_m, const at::Tensor& adam_v, const at::Tensor& best,
                    const at::Tensor& state, const at::Tensor& history, int64_t num_iters) {
  FLX_CHECK(points.is_cpu(), "floxels: solver_run CPU kernel called with points on ", points.device());
  const Args a = make_args(points, corner_idx, corner_w, seg_ptr, vtx_ptr, vtx_entry, labels, cluster_count, dts, dt_origins,
                           point_ranges, vertex_ranges, support_ranges, support_dt, support_t, support_w, reg_scale,
                           hyper, theta, adam_m, adam_v, best, state, history, num_iters);
  check_indices(a);
  CpuSolver(a).run(num_iters);
}

}  // namespace
}  // namespace floxels

namespace floxels {
namespace {
// The CPU loop has no persistent kernel.
int64_t solver_loop_blocks_cpu(const at::Tensor&, c10::ArrayRef<int64_t>, c10::ArrayRef<int64_t>, bool) { return 0; }
}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("solver_run", &floxels::solver_run_cpu);
  m.impl("solver_loop_blocks", &floxels::solver_loop_blocks_cpu);
}
