// CPU implementation of the fused multi-scan distance-transform loss.
//
// Called hundreds of times per frame by the optimiser, so one pass over the points does
// everything: each point loops over the K scans and writes its own gradient row (no
// atomics); the loss is reduced deterministically (fixed chunking that depends on N
// only, per-chunk partial sums in double, chunks summed in order), so the result does
// not depend on the number of threads. Nothing is allocated besides the outputs.
// A row whose point or flow has a NaN/inf coordinate makes the loss NaN and gets a zero
// gradient row (docs/ops.md); the solver, which calls dt_loss::point_loss on
// rows that are finite by construction, does not pay for that test.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/core/TensorOptions.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <tuple>
#include <vector>

#include "common/dt_loss_args.h"
#include "cpu/dt_scans.h"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels {
namespace {


// Fixed chunking: at most kMaxChunks chunks of >= kMinChunk points, derived from N only.
constexpr int64_t kMaxChunks = 256;
constexpr int64_t kMinChunk = 1024;

// Runs the fused pass. `scale` multiplies every contribution (the upstream gradient for
// dt_loss_backward, 1 otherwise); loss_out / grad_out may be null when not wanted.
template <typename T, bool kLoss, bool kGrad>
void run(const at::Tensor& points, const at::Tensor& flow, const std::vector<at::Tensor>& dts,
         c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
         c10::ArrayRef<double> weights, double truncation, double scale, T* loss_out, T* grad_out) {
  const int64_t n = points.size(0);
  const int K = static_cast<int>(dts.size());
  if (n == 0) {
    if (kLoss) *loss_out = T(0);
    return;
  }
  const auto scans = make_scans<T>(dts, origins, time_offsets, weights, scale, static_cast<double>(n));
  const T* p = points.const_data_ptr<T>();
  const T* f = flow.const_data_ptr<T>();
  const T inv_spacing = T(1.0 / spacing);
  const T trunc = T(truncation);

  const int64_t n_chunks = std::min(kMaxChunks, (n + kMinChunk - 1) / kMinChunk);
  const int64_t chunk = (n + n_chunks - 1) / n_chunks;
  std::array<double, kMaxChunks> partial{};
  at::parallel_for(0, n_chunks, 1, [&](int64_t c_begin, int64_t c_end) {
    for (int64_t c = c_begin; c < c_end; ++c) {
      const int64_t i_end = std::min(n, (c + 1) * chunk);
      double acc = 0.0;
      for (int64_t i = c * chunk; i < i_end; ++i) {
        const T* pi = p + 3 * i;
        const T* fi = f + 3 * i;
        T* gi = kGrad ? grad_out + 3 * i : nullptr;
        T l = dt_loss::point_loss<kGrad, T, int64_t>(scans.data(), K, pi[0], pi[1], pi[2], fi[0], fi[1], fi[2],
                                                     inv_spacing, trunc, gi);
        // Non-finite point or flow row: the loss shows it (NaN), its gradient row is 0.
        if (!finite3(pi[0], pi[1], pi[2]) || !finite3(fi[0], fi[1], fi[2])) [[unlikely]] {
          l = quiet_nan<T>();
          if constexpr (kGrad) gi[0] = gi[1] = gi[2] = T(0);
        }
        if (kLoss) acc += static_cast<double>(l);
      }
      partial[c] = acc;
    }
  });
  if (kLoss) {
    double total = 0.0;
    for (int64_t c = 0; c < n_chunks; ++c) total += partial[c];
    *loss_out = T(total);
  }
}

at::Tensor dt_loss_cpu(const at::Tensor& points, const at::Tensor& flow, at::TensorList dts,
                       c10::ArrayRef<double> origins, double spacing, c10::ArrayRef<double> time_offsets,
                       c10::ArrayRef<double> weights, double truncation) {
  check_dt_loss_args(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  const auto p = points.expect_contiguous();
  const auto f = flow.expect_contiguous();
  const auto d = contiguous_dts(dts);
  at::Tensor loss = at::empty({}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_loss_cpu", [&] {
    run<scalar_t, true, false>(*p, *f, d, origins, spacing, time_offsets, weights, truncation, 1.0,
                               loss.mutable_data_ptr<scalar_t>(), nullptr);
  });
  return loss;
}

at::Tensor dt_loss_backward_cpu(const at::Tensor& grad, const at::Tensor& points, const at::Tensor& flow,
                                at::TensorList dts, c10::ArrayRef<double> origins, double spacing,
                                c10::ArrayRef<double> time_offsets, c10::ArrayRef<double> weights,
                                double truncation) {
  check_dt_loss_args(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  check_dt_loss_grad(grad, points);
  const auto p = points.expect_contiguous();
  const auto f = flow.expect_contiguous();
  const auto d = contiguous_dts(dts);
  const double scale = grad.item<double>();  // CPU: reading the scalar is free
  at::Tensor grad_flow = at::empty({points.size(0), 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_loss_backward_cpu", [&] {
    run<scalar_t, false, true>(*p, *f, d, origins, spacing, time_offsets, weights, truncation, scale,
                               nullptr, grad_flow.mutable_data_ptr<scalar_t>());
  });
  return grad_flow;
}

std::tuple<at::Tensor, at::Tensor> dt_loss_fwd_bwd_cpu(const at::Tensor& points, const at::Tensor& flow,
                                                       at::TensorList dts, c10::ArrayRef<double> origins,
                                                       double spacing, c10::ArrayRef<double> time_offsets,
                                                       c10::ArrayRef<double> weights, double truncation) {
  check_dt_loss_args(points, flow, dts, origins, spacing, time_offsets, weights, truncation);
  const auto p = points.expect_contiguous();
  const auto f = flow.expect_contiguous();
  const auto d = contiguous_dts(dts);
  at::Tensor loss = at::empty({}, points.options());
  at::Tensor grad_flow = at::empty({points.size(0), 3}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "dt_loss_fwd_bwd_cpu", [&] {
    run<scalar_t, true, true>(*p, *f, d, origins, spacing, time_offsets, weights, truncation, 1.0,
                              loss.mutable_data_ptr<scalar_t>(), grad_flow.mutable_data_ptr<scalar_t>());
  });
  return {loss, grad_flow};
}

}  // namespace
}  // namespace floxels

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("dt_loss", &floxels::dt_loss_cpu);
  m.impl("dt_loss_backward", &floxels::dt_loss_backward_cpu);
  m.impl("dt_loss_fwd_bwd", &floxels::dt_loss_fwd_bwd_cpu);
}
