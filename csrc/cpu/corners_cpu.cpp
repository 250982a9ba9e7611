// CPU compact corner gather/scatter (see csrc/kernels/corners.h).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <vector>

#include "common/op_args.h"
#include "kernels/corners.h"

namespace floxels {
namespace {

at::Tensor corner_gather_cpu(const at::Tensor& params, const at::Tensor& idx_in, const at::Tensor& w_in) {
  FLX_CHECK(params.dim() == 2, "floxels: params must be (M, C), got ", params.sizes());
  const int64_t n = idx_in.dim() == 2 ? idx_in.size(0) : -1;
  args::corners(idx_in, w_in, n, params, "params");
  auto p = params.contiguous();
  auto idx = idx_in.contiguous();
  auto w = w_in.contiguous();
  const int64_t C = p.size(1), M = p.size(0);
  auto out = at::empty({n, C}, p.options());
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "corner_gather_cpu", [&] {
    const scalar_t* pp = p.data_ptr<scalar_t>();
    const int32_t* ip = idx.data_ptr<int32_t>();
    const scalar_t* wp = w.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    at::parallel_for(0, n, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        for (int j = 0; j < 8; ++j)
          FLX_CHECK(ip[i * 8 + j] >= 0 && ip[i * 8 + j] < M, "floxels: corner_idx[", i, ", ", j, "] = ",
                      ip[i * 8 + j], " is outside [0, ", M, ")");
        corners::gather_point(pp, ip + i * 8, wp + i * 8, C, op + i * C);
      }
    });
  });
  return out;
}

at::Tensor corner_scatter_cpu(const at::Tensor& values, const at::Tensor& idx_in, const at::Tensor& w_in,
                              int64_t num_params) {
  FLX_CHECK(values.dim() == 2, "floxels: values must be (N, C), got ", values.sizes());
  FLX_CHECK(num_params >= 0, "floxels: num_params must be >= 0, got ", num_params);
  const int64_t n = values.size(0), C = values.size(1);
  args::corners(idx_in, w_in, n, values, "values");
  auto v = values.contiguous();
  auto idx = idx_in.contiguous();
  auto w = w_in.contiguous();
  auto out = at::zeros({num_params, C}, v.options());
  if (n == 0 || num_params == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "corner_scatter_cpu", [&] {
    const scalar_t* vp = v.data_ptr<scalar_t>();
    const int32_t* ip = idx.data_ptr<int32_t>();
    const scalar_t* wp = w.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    const int64_t row = num_params * C;
    // Each thread accumulates a contiguous block of points into a private table; the
    // tables are then summed in thread order, so the result is deterministic for a given
    // thread count and there are no atomics. Fall back to one table when they would be large.
    const int64_t nt = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), (n + 4095) / 4096));
    const bool privatise = nt > 1 && row * nt <= (int64_t(1) << 26);
    auto accumulate = [&](scalar_t* dst, int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        for (int j = 0; j < 8; ++j) {
          const int32_t m = ip[i * 8 + j];
          FLX_CHECK(m >= 0 && m < num_params, "floxels: corner_idx[", i, ", ", j, "] = ", m,
                      " is outside [0, ", num_params, ")");
          const scalar_t wj = wp[i * 8 + j];
          for (int64_t c = 0; c < C; ++c) dst[int64_t(m) * C + c] += wj * vp[i * C + c];
        }
      }
    };
    if (!privatise) {
      accumulate(op, 0, n);
      return;
    }
    std::vector<scalar_t> priv(size_t(row * (nt - 1)), scalar_t(0));
    const int64_t chunk = (n + nt - 1) / nt;
    at::parallel_for(0, nt, 1, [&](int64_t tb, int64_t te) {
      for (int64_t t = tb; t < te; ++t) {
        scalar_t* dst = t == 0 ? op : priv.data() + (t - 1) * row;
        accumulate(dst, t * chunk, std::min(n, (t + 1) * chunk));
      }
    });
    at::parallel_for(0, row, 16384, [&](int64_t b, int64_t e) {
      for (int64_t t = 1; t < nt; ++t) {
        const scalar_t* src = priv.data() + (t - 1) * row;
        for (int64_t k = b; k < e; ++k) op[k] += src[k];
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("corner_gather", &corner_gather_cpu);
  m.impl("corner_scatter", &corner_scatter_cpu);
}

}  // namespace floxels
