// CPU fixed_segment_sum: one serial pass over the terms (integer sums: any order gives the same
// bits, so the CUDA kernel's atomics agree with it), then each row decoded.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>
#include <vector>

#include "common/op_args.h"
#include "kernels/segment_sum.h"

namespace floxels {
namespace {

template <typename I, typename T>
void sum_rows(const T* v, const I* index, int64_t M, int64_t C, int64_t rows, double limit, bool void_row,
              bool count, double* out) {
  const int64_t W = C + (count ? 1 : 0);
  std::vector<int64_t> acc(rows * C, 0), n(count ? rows : 0, 0);
  std::vector<uint8_t> bad(rows * (void_row ? 1 : C), 0);
  for (int64_t i = 0; i < M; ++i) {
    const int64_t r = static_cast<int64_t>(index[i]);
    if (r < 0 || r >= rows) continue;  // a term of no row (e.g. an unclustered point): ignored
    if (count) ++n[r];
    for (int64_t c = 0; c < C; ++c) {
      const double x = static_cast<double>(v[i * C + c]);
      if (!segment_sum::finite(x)) {
        bad[void_row ? r : r * C + c] = 1;
      } else {
        // two's complement wrap-around, as the CUDA atomics (callers' limits keep sums in range)
        acc[r * C + c] = static_cast<int64_t>(static_cast<uint64_t>(acc[r * C + c]) +
                                              static_cast<uint64_t>(segment_sum::encode(x, limit)));
      }
    }
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (int64_t r = 0; r < rows; ++r) {
    for (int64_t c = 0; c < C; ++c) {
      out[r * W + c] = bad[void_row ? r : r * C + c] ? nan : segment_sum::decode(acc[r * C + c]);
    }
    if (count) out[r * W + C] = static_cast<double>(n[r]);
  }
}

at::Tensor fixed_segment_sum_cpu(const at::Tensor& values_in, const at::Tensor& index_in, int64_t rows,
                                 double limit, bool void_row, bool count) {
  args::segment_sum(values_in, index_in, rows, limit);
  const auto values = values_in.contiguous();
  const auto index = index_in.contiguous();
  const int64_t M = values.size(0), C = values.size(1);
  auto out = at::empty({rows, C + (count ? 1 : 0)}, values.options().dtype(at::kDouble));
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "fixed_segment_sum_cpu", [&] {
    if (index.scalar_type() == at::kLong) {
      sum_rows(values.const_data_ptr<scalar_t>(), index.const_data_ptr<int64_t>(), M, C, rows, limit, void_row,
               count, out.mutable_data_ptr<double>());
    } else {
      sum_rows(values.const_data_ptr<scalar_t>(), index.const_data_ptr<int32_t>(), M, C, rows, limit, void_row,
               count, out.mutable_data_ptr<double>());
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("fixed_segment_sum", &fixed_segment_sum_cpu); }

}  // namespace floxels
