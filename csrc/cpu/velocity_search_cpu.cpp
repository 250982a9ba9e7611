// CPU implementation of floxels::velocity_search (kernels/velocity_search.h): every cluster
// independent (parallel over clusters), each score a sum over the cluster's rows in order in
// double, so the result does not depend on the number of threads.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <array>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

#include "cpu/dt_scans.h"
#include "common/velocity_search_args.h"
#include "kernels/rigid_lm.h"
#include "kernels/velocity_search.h"

namespace floxels {
namespace {

std::tuple<at::Tensor, at::Tensor, at::Tensor> velocity_search_cpu(
    const at::Tensor& points, const at::Tensor& segments, const std::optional<at::Tensor>& observed,
    at::TensorList dts, c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
    c10::ArrayRef<double> weights, double tau, int64_t num_directions, double speed_step, int64_t num_speeds,
    int64_t local_steps, int64_t local_rounds) {
  check_velocity_search_args(points, segments, observed, dts, origins, spacing, time_offsets, weights, tau,
                             num_directions, speed_step, num_speeds, local_steps, local_rounds);
  const auto p = points.expect_contiguous();
  const auto sg = segments.expect_contiguous();
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  const auto d = contiguous_dts(dts);
  const int64_t m = points.size(0), C = segments.size(0) - 1;
  const int K = static_cast<int>(dts.size());
  const int nc = static_cast<int>(1 + num_directions * num_speeds);
  at::Tensor best_out = at::empty({C, 3}, points.options());
  at::Tensor best_score = at::empty({C}, points.options());
  at::Tensor zero_score = at::empty({C}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "velocity_search_cpu", [&] {
    using T = scalar_t;
    namespace vs = velocity_search;
    const auto scans = make_scans<T>(d, origins, time_offsets, weights);
    const T* q = p->const_data_ptr<T>();
    const int64_t* seg = sg->const_data_ptr<int64_t>();
    const int32_t* obs = ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr;
    T* bo = best_out.mutable_data_ptr<T>();
    T* bs = best_score.mutable_data_ptr<T>();
    T* zs = zero_score.mutable_data_ptr<T>();
    const T inv = T(1.0 / spacing), cap = T(tau), st0 = T(speed_step);
    at::parallel_for(0, C, 1, [&](int64_t cb, int64_t ce) {
      std::vector<double> scores(nc);
      for (int64_t c = cb; c < ce; ++c) {
        int64_t begin = 0, end = 0;
        rigid_lm::cluster_rows(seg, c, m, begin, end);
        const double n = end > begin ? double(end - begin) : 1.0;
        const auto score = [&](const T* v) {
          return vs::row_sum<T, int64_t>(scans.data(), K, inv, cap, q, obs, begin, end, 0, 1, v) / n;
        };
        T ax, ay, v[3];
        vs::principal_axis<T>(q, begin, end, ax, ay);
        for (int j = 0; j < nc; ++j) {
          vs::global_candidate<T>(j, static_cast<int>(num_directions), static_cast<int>(num_speeds), st0, ax, ay, v);
          scores[j] = score(v);
        }
        const int k = vs::first_min(scores.data(), nc);
        T best[3];
        vs::global_candidate<T>(k, static_cast<int>(num_directions), static_cast<int>(num_speeds), st0, ax, ay, best);
        double best_s = scores[k];
        const double zero = scores[0];
        double step = speed_step;
        double local[vs::kLocal];
        T cand[vs::kLocal][3];
        for (int64_t ls = 0; ls < local_steps; ++ls, step /= 2) {
          for (int64_t r = 0; r < local_rounds; ++r) {
            for (int j = 0; j < vs::kLocal; ++j) {
              vs::local_candidate<T>(j, best, T(step), cand[j]);
              local[j] = score(cand[j]);
            }
            const int kk = vs::first_min(local, vs::kLocal);
            if (!(local[kk] < best_s)) break;  // no better candidate: the next round would be the same
            for (int x = 0; x < 3; ++x) best[x] = cand[kk][x];
            best_s = local[kk];
          }
        }
        for (int x = 0; x < 3; ++x) bo[3 * c + x] = best[x];
        bs[c] = T(best_s);
        zs[c] = T(zero);
      }
    });
  });
  return {best_out, best_score, zero_score};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("velocity_search", &floxels::velocity_search_cpu); }
