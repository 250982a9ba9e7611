// CPU cluster reductions: per-cluster mean and the cluster-consistency loss (+ gradient).
//
// Everything is linear in N: one pass for per-cluster sums/counts, one pass for residual
// norms (and unit residuals u_i plus their per-cluster sums when a gradient is wanted), one
// pass for the gradient. Passes run over fixed point chunks in parallel, each chunk with its
// own partial per-cluster buffer (reduced afterwards in chunk order, so results do not
// depend on scheduling); when clusters outnumber points the partials would cost more than
// the pass, so that case runs serially. Sums accumulate in double.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <vector>

#include "common/op_args.h"
#include "kernels/cluster.h"

namespace floxels {
namespace {

constexpr int64_t kParallelMin = 16384;

int64_t num_chunks(int64_t N, int64_t KC) {
  const int64_t nt = std::max<int64_t>(1, at::get_num_threads());
  if (nt == 1 || N < kParallelMin || KC > N) return 1;
  return nt;
}

// Calls f(chunk, begin, end) for P contiguous chunks of [0, N), in parallel.
template <class F>
void for_chunks(int64_t N, int64_t P, const F& f) {
  if (P == 1) {
    f(int64_t(0), int64_t(0), N);
    return;
  }
  at::parallel_for(0, P, 1, [&](int64_t b, int64_t e) {
    for (int64_t p = b; p < e; ++p) f(p, N * p / P, N * (p + 1) / P);
  });
}

// Adds the P partial buffers (P, len) into out (len).
void reduce_partials(const std::vector<double>& part, int64_t P, int64_t len, double* out) {
  for (int64_t j = 0; j < len; ++j) {
    double s = 0;
    for (int64_t p = 0; p < P; ++p) s += part[p * len + j];
    out[j] = s;
  }
}

// Per-cluster sums (K*C) and counts (K); throws on a label outside [-1, K).
template <typename T>
void cluster_sums(const T* v, const int64_t* lab, int64_t N, int64_t C, int64_t K, std::vector<double>& sums,
                  std::vector<double>& cnt) {
  const int64_t P = num_chunks(N, K * C);
  std::vector<double> ps(P * K * C, 0.0), pc(P * K, 0.0);
  std::atomic<bool> bad{false};
  for_chunks(N, P, [&](int64_t p, int64_t b, int64_t e) {
    double* s = ps.data() + p * K * C;
    double* c = pc.data() + p * K;
    bool my_bad = false;
    for (int64_t i = b; i < e; ++i) {
      const int64_t l = lab[i];
      if (!cluster::valid_label(l, K)) {
        my_bad |= l != -1;
        continue;
      }
      c[l] += 1;
      for (int64_t ch = 0; ch < C; ++ch) s[l * C + ch] += v[i * C + ch];
    }
    if (my_bad) bad = true;
  });
  FLX_CHECK(!bad.load(), "floxels: labels must lie in [-1, num_clusters = ", K, ")");
  sums.resize(K * C);
  cnt.resize(K);
  reduce_partials(ps, P, K * C, sums.data());
  reduce_partials(pc, P, K, cnt.data());
}

template <typename T>
std::vector<T> means_of(const std::vector<double>& sums, const std::vector<double>& cnt, int64_t K, int64_t C) {
  std::vector<T> m(K * C);
  for (int64_t k = 0; k < K; ++k)
    for (int64_t c = 0; c < C; ++c) m[k * C + c] = cnt[k] > 0 ? T(sums[k * C + c] / cnt[k]) : T(0);
  return m;
}

// Loss and/or gradient of the cluster-consistency loss; grad = grad_scale * dloss/dflow.
template <typename T>
void consistency(const T* f, const int64_t* lab, int64_t N, int64_t C, int64_t K, T* loss, T* grad,
                 double grad_scale) {
  if (N == 0) {
    if (loss) *loss = T(0);
    return;
  }
  std::vector<double> sums, cnt;
  cluster_sums(f, lab, N, C, K, sums, cnt);
  const std::vector<T> mean = means_of<T>(sums, cnt, K, C);
  const int64_t P = num_chunks(N, K * C);
  std::vector<double> norm_part(P, 0.0);
  std::vector<double> upart(grad ? P * K * C : 0, 0.0);
  // pass 2: norms; u_i written into grad (noise: 0) and summed per cluster
  for_chunks(N, P, [&](int64_t p, int64_t b, int64_t e) {
    double acc = 0;
    double* us = grad ? upart.data() + p * K * C : nullptr;
    for (int64_t i = b; i < e; ++i) {
      const int64_t l = lab[i];
      if (!cluster::valid_label(l, K)) {
        if (grad)
          for (int64_t ch = 0; ch < C; ++ch) grad[i * C + ch] = T(0);
        continue;
      }
      if (grad) {
        T* u = grad + i * C;
        acc += cluster::residual_unit(f + i * C, mean.data() + l * C, C, u);
        for (int64_t ch = 0; ch < C; ++ch) us[l * C + ch] += u[ch];
      } else {
        acc += cluster::residual_norm(f + i * C, mean.data() + l * C, C);
      }
    }
    norm_part[p] = acc;
  });
  if (loss) {
    double s = 0;
    for (double x : norm_part) s += x;
    *loss = T(s / double(N));
  }
  if (!grad) return;
  // pass 3: grad_i = scale * (u_i - mean_c u) / N
  std::vector<double> usum(K * C);
  reduce_partials(upart, P, K * C, usum.data());
  std::vector<T> ubar(K * C);
  for (int64_t k = 0; k < K; ++k)
    for (int64_t c = 0; c < C; ++c) ubar[k * C + c] = cnt[k] > 0 ? T(usum[k * C + c] / cnt[k]) : T(0);
  const T scale = T(grad_scale / double(N));
  for_chunks(N, P, [&](int64_t, int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      const int64_t l = lab[i];
      if (!cluster::valid_label(l, K)) continue;
      for (int64_t ch = 0; ch < C; ++ch) grad[i * C + ch] = scale * (grad[i * C + ch] - ubar[l * C + ch]);
    }
  });
}

at::Tensor mean_cpu(const at::Tensor& values_in, const at::Tensor& labels_in, int64_t K) {
  args::cluster(values_in, labels_in, K, "values");
  const auto v = values_in.contiguous();
  const auto lab = labels_in.contiguous();
  const int64_t N = v.size(0), C = v.size(1);
  auto out = at::empty({K, C}, v.options());
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "cluster_mean_cpu", [&] {
    std::vector<double> sums, cnt;
    cluster_sums(v.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), N, C, K, sums, cnt);
    const auto m = means_of<scalar_t>(sums, cnt, K, C);
    std::copy(m.begin(), m.end(), out.mutable_data_ptr<scalar_t>());
  });
  return out;
}

at::Tensor loss_cpu(const at::Tensor& flow_in, const at::Tensor& labels_in, int64_t K) {
  args::cluster(flow_in, labels_in, K, "flow");
  const auto f = flow_in.contiguous();
  const auto lab = labels_in.contiguous();
  auto loss = at::empty({}, f.options());
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_loss_cpu", [&] {
    consistency(f.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), f.size(0), f.size(1), K,
                loss.mutable_data_ptr<scalar_t>(), static_cast<scalar_t*>(nullptr), 0.0);
  });
  return loss;
}

at::Tensor loss_backward_cpu(const at::Tensor& grad, const at::Tensor& flow_in, const at::Tensor& labels_in,
                             int64_t K) {
  args::cluster(flow_in, labels_in, K, "flow");
  FLX_CHECK(grad.numel() == 1, "floxels: grad must be a scalar, got shape ", grad.sizes());
  check_same_device(grad, flow_in, "grad", "flow");
  const auto f = flow_in.contiguous();
  const auto lab = labels_in.contiguous();
  auto out = at::zeros_like(f);
  const double g = grad.item<double>();
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_loss_backward_cpu", [&] {
    consistency(f.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), f.size(0), f.size(1), K,
                static_cast<scalar_t*>(nullptr), out.mutable_data_ptr<scalar_t>(), g);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> fwd_bwd_cpu(const at::Tensor& flow_in, const at::Tensor& labels_in, int64_t K) {
  args::cluster(flow_in, labels_in, K, "flow");
  const auto f = flow_in.contiguous();
  const auto lab = labels_in.contiguous();
  auto loss = at::empty({}, f.options());
  auto out = at::zeros_like(f);
  AT_DISPATCH_FLOATING_TYPES(f.scalar_type(), "cluster_consistency_fwd_bwd_cpu", [&] {
    consistency(f.const_data_ptr<scalar_t>(), lab.const_data_ptr<int64_t>(), f.size(0), f.size(1), K,
                loss.mutable_data_ptr<scalar_t>(), out.mutable_data_ptr<scalar_t>(), 1.0);
  });
  return {loss, out};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("cluster_mean", &mean_cpu);
  m.impl("cluster_consistency_loss", &loss_cpu);
  m.impl("cluster_consistency_loss_backward", &loss_backward_cpu);
  m.impl("cluster_consistency_fwd_bwd", &fwd_bwd_cpu);
}

}  // namespace floxels
