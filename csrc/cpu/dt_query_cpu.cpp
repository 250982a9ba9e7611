// CPU implementation of the data-only distance-transform look-ups of the dt_loss family
// (kernels/dt_loss.h): dt_residual (capped, weighted residual per point), dt_sample (value and
// spatial gradient per scan and point) and dt_evidence (the motion-evidence test per group of
// points, estimator/evidence.py). One pass over the points; every output row is written by the
// point that owns it, and dt_evidence sums each group in order in double, so the results do not
// depend on the number of threads. A point or motion row with a NaN/inf coordinate gives NaN
// (dt_sample: NaN value, zero gradient, like trilinear_gather).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/core/TensorOptions.h>
#include <torch/library.h>

#include <array>
#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

#include "common/dt_loss_args.h"
#include "cpu/dt_scans.h"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels {
namespace {

constexpr int64_t kGrain = 1024;

at::Tensor dt_residual_cpu(const at::Tensor& points, const at::Tensor& motion, at::TensorList dts,
                           c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                           c10::ArrayRef<double> weights, double cap, bool squared,
                           const std::optional<at::Tensor>& observed) {
  check_dt_query_args("dt_residual", points, motion, dts, origins, spacing, time_offsets, &weights, &cap);
  check_observed("dt_residual", observed, points);
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  const auto p = points.expect_contiguous();
  const auto m = motion.expect_contiguous();
  const auto d = contiguous_dts(dts);
  const int64_t n = points.size(0);
  const int K = static_cast<int>(dts.size());
  at::Tensor out = at::empty({n}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_residual_cpu", [&] {
    using T = scalar_t;
    const auto scans = make_scans<T>(d, origins, time_offsets, weights);
    const T* pp = p->const_data_ptr<T>();
    const T* mp = m->const_data_ptr<T>();
    T* o = out.mutable_data_ptr<T>();
    const int32_t* obs = ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr;
    const T inv = T(1.0 / spacing), c = T(cap);
    at::parallel_for(0, n, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        const T* pi = pp + 3 * i;
        const T* mi = mp + 3 * i;
        T r = squared ? dt_loss::point_residual<true, T, int64_t>(scans.data(), K, pi[0], pi[1], pi[2], mi[0],
                                                                  mi[1], mi[2], inv, c, dt_loss::point_bits(obs, i))
                      : dt_loss::point_residual<false, T, int64_t>(scans.data(), K, pi[0], pi[1], pi[2], mi[0],
                                                                   mi[1], mi[2], inv, c, dt_loss::point_bits(obs, i));
        if (!finite3(pi[0], pi[1], pi[2]) || !finite3(mi[0], mi[1], mi[2])) [[unlikely]] r = quiet_nan<T>();
        o[i] = r;
      }
    });
  });
  return out;
}

at::Tensor dt_sample_cpu(const at::Tensor& points, const at::Tensor& motion, at::TensorList dts,
                         c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets) {
  check_dt_query_args("dt_sample", points, motion, dts, origins, spacing, time_offsets, nullptr, nullptr);
  const auto p = points.expect_contiguous();
  const auto m = motion.expect_contiguous();
  const auto d = contiguous_dts(dts);
  const int64_t n = points.size(0);
  const int K = static_cast<int>(dts.size());
  at::Tensor out = at::empty({K, n, 4}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_sample_cpu", [&] {
    using T = scalar_t;
    const auto scans = make_scans<T>(d, origins, time_offsets, {});
    const T* pp = p->const_data_ptr<T>();
    const T* mp = m->const_data_ptr<T>();
    T* o = out.mutable_data_ptr<T>();
    const T inv = T(1.0 / spacing);
    at::parallel_for(0, n, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        const T* pi = pp + 3 * i;
        const T* mi = mp + 3 * i;
        const bool ok = finite3(pi[0], pi[1], pi[2]) && finite3(mi[0], mi[1], mi[2]);
        for (int k = 0; k < K; ++k) {
          T* oi = o + 4 * (k * n + i);
          T g[3];
          const T v = dt_loss::scan_sample<true, T, int64_t>(scans[k], pi[0], pi[1], pi[2], mi[0], mi[1], mi[2],
                                                             inv, g);
          oi[0] = ok ? v : quiet_nan<T>();
          oi[1] = ok ? g[0] : T(0);
          oi[2] = ok ? g[1] : T(0);
          oi[3] = ok ? g[2] : T(0);
        }
      }
    });
  });
  return out;
}

// Group key reader: int32 or int64, any stride.
struct Keys {
  const void* data = nullptr;
  int64_t stride = 0;
  bool is64 = false;
  int64_t operator[](int64_t i) const {
    return is64 ? static_cast<const int64_t*>(data)[i * stride] : static_cast<const int32_t*>(data)[i * stride];
  }
};

Keys keys_of(const at::Tensor& t) {
  return Keys{t.const_data_ptr(), t.stride(0), t.scalar_type() == at::kLong};
}

void check_evidence_scalars(double margin, double ratio) {
  FLX_CHECK(std::isfinite(margin), "floxels: dt_evidence: margin must be finite, got ", margin);
  FLX_CHECK(std::isfinite(ratio), "floxels: dt_evidence: ratio must be finite, got ", ratio);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> dt_evidence_cpu(
    const at::Tensor& points, const at::Tensor& flow, const std::optional<at::Tensor>& labels,
    const at::Tensor& cells, at::TensorList dts, c10::ArrayRef<double> origins, double spacing,
    c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights, double cap, double margin, double ratio,
    const std::optional<at::Tensor>& observed) {
  check_dt_query_args("dt_evidence", points, flow, dts, origins, spacing, time_offsets, &weights, &cap, "flow");
  check_evidence_scalars(margin, ratio);
  check_observed("dt_evidence", observed, points);
  const at::Tensor ob = observed.has_value() ? observed->contiguous() : at::Tensor();
  check_group_keys(cells, points, "cells");
  if (labels.has_value()) check_group_keys(*labels, points, "labels");
  const auto p = points.expect_contiguous();
  const auto f = flow.expect_contiguous();
  const auto d = contiguous_dts(dts);
  const int64_t n = points.size(0);
  const int K = static_cast<int>(dts.size());
  at::Tensor score = at::empty({n}, points.options());
  at::Tensor explained = at::empty({n}, points.options().dtype(at::kBool));
  at::Tensor res_f = at::empty({n}, points.options());
  at::Tensor res_z = at::empty({n}, points.options());
  if (n == 0) return {score, explained, res_f, res_z};
  const Keys cell = keys_of(cells);
  const Keys lab = labels.has_value() ? keys_of(*labels) : Keys{};
  const bool has_lab = labels.has_value();
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_evidence_cpu", [&] {
    using T = scalar_t;
    const auto scans = make_scans<T>(d, origins, time_offsets, weights);
    const T* pp = p->const_data_ptr<T>();
    const T* fp = f->const_data_ptr<T>();
    T* rf = res_f.mutable_data_ptr<T>();
    T* rz = res_z.mutable_data_ptr<T>();
    const int32_t* obs = ob.defined() ? ob.const_data_ptr<int32_t>() : nullptr;
    const T inv = T(1.0 / spacing), c = T(cap);
    // per point residuals (staged in the residual outputs, overwritten by the group means)
    at::parallel_for(0, n, kGrain, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        const T* pi = pp + 3 * i;
        const T* fi = fp + 3 * i;
        dt_loss::point_residual_pair<T, int64_t>(scans.data(), K, pi[0], pi[1], pi[2], fi[0], fi[1], fi[2], inv, c,
                                                 rf[i], rz[i], dt_loss::point_bits(obs, i));
        if (!finite3(pi[0], pi[1], pi[2]) || !finite3(fi[0], fi[1], fi[2])) [[unlikely]] rf[i] = rz[i] = quiet_nan<T>();
      }
    });
    // groups: runs of equal (label, and for label < 0 the cell); sums in order, in double
    T* sc = score.mutable_data_ptr<T>();
    bool* ex = explained.mutable_data_ptr<bool>();
    const T mg = T(margin), ra = T(ratio);
    int64_t first = 0;
    while (first < n) {
      int64_t last = first;
      const int64_t l0 = has_lab ? lab[first] : -1, c0 = cell[first];
      while (last + 1 < n) {
        const int64_t l1 = has_lab ? lab[last + 1] : -1;
        if (l1 != l0 || (l0 < 0 && cell[last + 1] != c0)) break;
        ++last;
      }
      double sf = 0.0, sz = 0.0;
      for (int64_t i = first; i <= last; ++i) {
        sf += static_cast<double>(rf[i]);
        sz += static_cast<double>(rz[i]);
      }
      T gain, mf, mz;
      const bool e = dt_loss::evidence_test<T>(sf, sz, static_cast<double>(last - first + 1), mg, ra, gain, mf, mz);
      for (int64_t i = first; i <= last; ++i) {
        sc[i] = gain;
        ex[i] = e;
        rf[i] = mf;
        rz[i] = mz;
      }
      first = last + 1;
    }
  });
  return {score, explained, res_f, res_z};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("dt_residual", &floxels::dt_residual_cpu);
  m.impl("dt_sample", &floxels::dt_sample_cpu);
  m.impl("dt_evidence", &floxels::dt_evidence_cpu);
}
