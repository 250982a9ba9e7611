// CUDA fixed_segment_sum: one thread per term and column adds its fixed-point integer to its
// row with a 64-bit integer atomic (exact, so the order the atomics land in does not matter);
// a second kernel decodes the rows. The rule per term: kernels/segment_sum.h.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/segment_sum_launch.h"
#include "kernels/segment_sum.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;

using Acc = unsigned long long;  // two's complement int64 bits; atomicAdd wraps like int64

template <typename T, typename I>
__global__ void accumulate_kernel(const T* __restrict__ values, const I* __restrict__ index, int64_t M, int64_t C,
                                  int64_t rows, double limit, Acc* __restrict__ sums, Acc* __restrict__ flags,
                                  Acc* __restrict__ counts) {
  const int64_t cols = C > 0 ? C : 1;  // C == 0: a thread a term, for its count alone
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= M * cols) return;
  const int64_t i = k / cols, c = k - i * cols;
  const int64_t r = static_cast<int64_t>(index[i]);
  if (r < 0 || r >= rows) return;
  if (c == 0) atomicAdd(counts + r, Acc(1));
  if (C == 0) return;
  const double x = static_cast<double>(values[k]);
  if (segment_sum::finite(x)) {
    atomicAdd(sums + r * C + c, static_cast<Acc>(segment_sum::encode(x, limit)));
  } else {
    atomicAdd(flags + r * C + c, Acc(1));
  }
}

__global__ void finish_kernel(const long long* __restrict__ ws, int64_t C, int64_t rows, bool void_row, bool count,
                              double* __restrict__ out) {
  const int64_t r = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (r >= rows) return;
  const long long* sums = ws + r * C;
  const long long* flags = ws + rows * C + r * C;
  const int64_t W = C + (count ? 1 : 0);
  bool any = false;
  for (int64_t c = 0; c < C; ++c) any |= flags[c] != 0;
  for (int64_t c = 0; c < C; ++c) {
    const bool bad = void_row ? any : flags[c] != 0;
    out[r * W + c] = bad ? __longlong_as_double(0x7ff8000000000000LL) : segment_sum::decode(sums[c]);
  }
  if (count) out[r * W + C] = static_cast<double>(ws[2 * rows * C + r]);
}

}  // namespace

template <typename T, typename I>
void segment_sum_accumulate(const T* values, const I* index, int64_t M, int64_t C, int64_t rows, double limit,
                            long long* ws, cudaStream_t s) {
  if (M == 0 || rows == 0) return;
  const int64_t n = M * (C > 0 ? C : 1);
  Acc* base = reinterpret_cast<Acc*>(ws);
  accumulate_kernel<T, I><<<unsigned((n + kThreads - 1) / kThreads), kThreads, 0, s>>>(
      values, index, M, C, rows, limit, base, base + rows * C, base + 2 * rows * C);
}

void segment_sum_finish(const long long* ws, int64_t C, int64_t rows, bool void_row, bool count, double* out,
                        cudaStream_t s) {
  if (rows == 0) return;
  finish_kernel<<<unsigned((rows + kThreads - 1) / kThreads), kThreads, 0, s>>>(ws, C, rows, void_row, count, out);
}

template void segment_sum_accumulate<float, int64_t>(const float*, const int64_t*, int64_t, int64_t, int64_t, double,
                                                     long long*, cudaStream_t);
template void segment_sum_accumulate<double, int64_t>(const double*, const int64_t*, int64_t, int64_t, int64_t,
                                                      double, long long*, cudaStream_t);
template void segment_sum_accumulate<float, int32_t>(const float*, const int32_t*, int64_t, int64_t, int64_t, double,
                                                     long long*, cudaStream_t);
template void segment_sum_accumulate<double, int32_t>(const double*, const int32_t*, int64_t, int64_t, int64_t,
                                                      double, long long*, cudaStream_t);

}  // namespace floxels::cuda
