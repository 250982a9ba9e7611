// floxels::stage_points: one pass over a host scan that copies it (as float32) into a
// caller's buffer, typically page-locked so that the upload to the GPU is asynchronous, and
// returns its bounds. The estimator then knows each scan's grid without waiting for the
// GPU, and starts the distance transforms while later scans are still being copied.
// (numpy's axis-0 min/max of an (N, 3) array costs ~5 ms per 100k points; this pass costs
// about as much as the copy alone.)
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <exception>
#include <limits>
#include <thread>
#include <vector>

#include "common/check.h"

namespace floxels {
namespace {

struct Bounds {
  double lo[3], hi[3];
  bool finite = true;
};

// One thread: a scan is ~1 MB, which one core copies in ~0.1 ms; waking the intra-op
// thread pool for it cost more than that, and far more on a busy host (measured: 6-9 ms
// for single scans on a device machine whose frames also varied 20-55 ms). The loop runs
// over blocks of kW values with kW accumulators each (value j of a block is axis j % 3), so
// the compiler vectorises it; NaN/inf anywhere turns a `v * 0` accumulator into NaN.
template <typename T>
Bounds stage(const T* src, float* dst, int64_t n) {
  constexpr int kW = 24;  // 8 points: a multiple of 3 and of the vector widths
  const int64_t total = 3 * n, main = total / kW * kW;
  float lo[kW], hi[kW], bad[kW];
  for (int j = 0; j < kW; ++j) lo[j] = std::numeric_limits<float>::infinity(), hi[j] = -lo[j], bad[j] = 0.0f;
  for (int64_t i = 0; i < main; i += kW) {
    for (int j = 0; j < kW; ++j) {
      const float v = static_cast<float>(src[i + j]);  // the float32 the GPU will see
      dst[i + j] = v;
      bad[j] += v * 0.0f;
      lo[j] = v < lo[j] ? v : lo[j];
      hi[j] = v > hi[j] ? v : hi[j];
    }
  }
  for (int64_t i = main; i < total; ++i) {
    const float v = static_cast<float>(src[i]);
    const int j = int(i - main);  // main is a multiple of 3: same axis as j
    dst[i] = v;
    bad[j] += v * 0.0f;
    lo[j] = v < lo[j] ? v : lo[j];
    hi[j] = v > hi[j] ? v : hi[j];
  }
  Bounds out{};
  for (int a = 0; a < 3; ++a) out.lo[a] = lo[a], out.hi[a] = hi[a];
  for (int j = 0; j < kW; ++j) {
    out.finite &= bad[j] == 0.0f;
    out.lo[j % 3] = std::min(out.lo[j % 3], double(lo[j]));
    out.hi[j % 3] = std::max(out.hi[j % 3], double(hi[j]));
  }
  return out;
}

// Checks one (points, out) pair.
void check_pair(const at::Tensor& points, const at::Tensor& out) {
  FLX_CHECK(points.dim() == 2 && points.size(1) == 3, "floxels: stage_points: points must be (N, 3), got ",
            points.sizes());
  FLX_CHECK(points.device().is_cpu(), "floxels: stage_points: points must be on the CPU");
  FLX_CHECK(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
            "floxels: stage_points: points must be float32 or float64, got ", points.scalar_type());
  FLX_CHECK(out.device().is_cpu() && out.scalar_type() == at::kFloat && out.is_contiguous() &&
                out.numel() == points.numel(),
            "floxels: stage_points: out must be a contiguous float32 CPU tensor of ", points.numel(),
            " values");
}

void stage_one(const at::Tensor& points, const at::Tensor& out, double* r) {
  const int64_t n = points.size(0);
  if (n == 0) {
    for (int a = 0; a < 6; ++a) r[a] = 0.0;
    r[6] = 1.0;
    return;
  }
  const at::Tensor src = points.contiguous();
  Bounds b{};
  AT_DISPATCH_FLOATING_TYPES(src.scalar_type(), "stage_points_cpu", [&] {
    b = stage<scalar_t>(src.const_data_ptr<scalar_t>(), out.data_ptr<float>(), n);
  });
  for (int a = 0; a < 3; ++a) r[a] = b.lo[a], r[3 + a] = b.hi[a];
  r[6] = b.finite ? 1.0 : 0.0;
}

// Row k of the (K, 7) float64 result: min xyz, max xyz (of the float32 values) of
// points[k], and 1 if all its values are finite (0: the bounds are meaningless and the
// caller drops the bad rows another way). Several scans are staged by one thread each
// (the copies are memory bound: ~1.5 ms for a 5-scan frame on one thread of a device
// host, ~0.4 ms on five).
at::Tensor stage_points_cpu(at::TensorList points, at::TensorList out) {
  FLX_CHECK(points.size() == out.size(), "floxels: stage_points: ", int64_t(points.size()), " scans but ",
            int64_t(out.size()), " outputs");
  for (size_t k = 0; k < points.size(); ++k) check_pair(points[k], out[k]);
  const int64_t K = int64_t(points.size());
  auto res = at::empty({K, 7}, at::TensorOptions().dtype(at::kDouble));
  double* r = res.data_ptr<double>();
  if (K == 1) {
    stage_one(points[0], out[0], r);
    return res;
  }
  std::vector<std::thread> workers;
  std::vector<std::exception_ptr> errors(static_cast<size_t>(K));
  for (int64_t k = 1; k < K; ++k)
    workers.emplace_back([&, k] {
      try {
        stage_one(points[size_t(k)], out[size_t(k)], r + 7 * k);
      } catch (...) {
        errors[size_t(k)] = std::current_exception();
      }
    });
  try {
    stage_one(points[0], out[0], r);
  } catch (...) {
    errors[0] = std::current_exception();
  }
  for (auto& w : workers) w.join();
  for (auto& e : errors)
    if (e) std::rethrow_exception(e);
  return res;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) { m.impl("stage_points", &stage_points_cpu); }

}  // namespace floxels
