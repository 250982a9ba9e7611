// CPU implementation of floxels::rigid_lm (kernels/rigid_lm.h): the rigid refinement's
// Levenberg-Marquardt loop, every cluster independent (parallel over clusters), each cluster's
// sums over its rows in order in double, so the result does not depend on the number of threads.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <array>
#include <cstdint>
#include <tuple>
#include <vector>

#include "cpu/dt_scans.h"
#include "common/rigid_lm_args.h"
#include "kernels/rigid_lm.h"

namespace floxels {
namespace {

std::tuple<at::Tensor, at::Tensor> rigid_lm_cpu(const at::Tensor& points, const at::Tensor& rel,
                                                const at::Tensor& segments, const at::Tensor& theta,
                                                const at::Tensor& vz, at::TensorList dts, c10::ArrayRef<double> origins,
                                                double spacing, c10::ArrayRef<double> time_offsets,
                                                c10::ArrayRef<double> weights, double tau, int64_t iters) {
  check_rigid_lm_args(points, rel, segments, theta, vz, dts, origins, spacing, time_offsets, weights, tau, iters);
  const auto p = points.expect_contiguous();
  const auto r = rel.expect_contiguous();
  const auto sg = segments.expect_contiguous();
  const auto th0 = theta.expect_contiguous();
  const auto vzc = vz.expect_contiguous();
  const auto d = contiguous_dts(dts);
  const int64_t m = points.size(0), C = theta.size(0);
  const int K = static_cast<int>(dts.size());
  at::Tensor theta_out = at::empty({C, 3}, theta.options());
  at::Tensor cost_out = at::empty({C}, theta.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "rigid_lm_cpu", [&] {
    using T = scalar_t;
    const auto scans = make_scans<T>(d, origins, time_offsets, weights);
    const T* pp = p->const_data_ptr<T>();
    const T* rp = r->const_data_ptr<T>();
    const int64_t* seg = sg->const_data_ptr<int64_t>();
    const T* tp = th0->const_data_ptr<T>();
    const T* vp = vzc->const_data_ptr<T>();
    T* to = theta_out.mutable_data_ptr<T>();
    T* co = cost_out.mutable_data_ptr<T>();
    const T inv = T(1.0 / spacing), cap = T(tau);
    at::parallel_for(0, C, 1, [&](int64_t cb, int64_t ce) {
      for (int64_t c = cb; c < ce; ++c) {
        int64_t begin = 0, end = 0;
        rigid_lm::cluster_rows(seg, c, m, begin, end);
        const double n = end > begin ? double(end - begin) : 1.0;
        const auto sums = [&](const T* th, double* s) {
          for (int j = 0; j < rigid_lm::kSums; ++j) s[j] = 0.0;
          for (int64_t i = begin; i < end; ++i) {
            rigid_lm::add_point<T, int64_t>(scans.data(), K, inv, cap, pp[3 * i], pp[3 * i + 1], pp[3 * i + 2],
                                            rp[3 * i], rp[3 * i + 1], th, vp[c], s);
          }
          for (int j = 0; j < rigid_lm::kSums; ++j) s[j] /= n;
        };
        T th[3] = {tp[3 * c], tp[3 * c + 1], tp[3 * c + 2]}, trial[3];
        double s[rigid_lm::kSums], st[rigid_lm::kSums];
        sums(th, s);
        double lam = rigid_lm::kLamStart;
        for (int64_t it = 0; it < iters; ++it) {
          rigid_lm::trial_step<T>(s, lam, th, trial);
          sums(trial, st);
          rigid_lm::accept<T>(trial, st, th, s, lam);
        }
        for (int j = 0; j < 3; ++j) to[3 * c + j] = th[j];
        co[c] = T(s[9]);
      }
    });
  });
  return {theta_out, cost_out};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("rigid_lm", &floxels::rigid_lm_cpu); }
