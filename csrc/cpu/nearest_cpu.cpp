// CPU nearest_neighbor: brute force over y for each row of x, parallel over x. NSFP on the
// CPU uses the chunked torch.cdist path (floxels_ext/baselines/chamfer.py); this op is the
// CPU twin of the CUDA kernel (same rule: kernels/nearest.h) for tests and small inputs.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>

#include "common/op_args.h"
#include "kernels/nearest.h"

namespace floxels {
namespace {

at::Tensor nearest_cpu(const at::Tensor& x_in, const at::Tensor& y_in) {
  args::nearest(x_in, y_in);
  const auto x = x_in.contiguous();
  const auto y = y_in.contiguous();
  const int64_t N = x.size(0), M = y.size(0);
  auto out = at::empty({N}, x.options().dtype(at::kLong));
  int64_t* o = out.mutable_data_ptr<int64_t>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "nearest_neighbor_cpu", [&] {
    const scalar_t* px = x.const_data_ptr<scalar_t>();
    const scalar_t* py = y.const_data_ptr<scalar_t>();
    at::parallel_for(0, N, 64, [&](int64_t a, int64_t b) {
      for (int64_t i = a; i < b; ++i) {
        const scalar_t qx = px[3 * i], qy = px[3 * i + 1], qz = px[3 * i + 2];
        scalar_t best = scalar_t(INFINITY);
        int64_t bi = 0;
        for (int64_t j = 0; j < M; ++j) {
          const scalar_t d = nearest::sq_dist(qx, qy, qz, py[3 * j], py[3 * j + 1], py[3 * j + 2]);
          if (d < best) {
            best = d;
            bi = j;
          }
        }
        o[i] = bi;
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("nearest_neighbor", &nearest_cpu); }

}  // namespace floxels
