// CUDA compact corner gather (math in csrc/kernels/corners.h). The scatter (its adjoint) is
// formed deterministically by the binding with ATen (corners_binding.cpp).
#include <cuda_runtime.h>

#include "cuda/corners_launch.h"
#include "kernels/corners.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;

template <typename T>
__global__ void corner_gather_kernel(const T* __restrict__ params, const int32_t* __restrict__ idx,
                                     const T* __restrict__ w, int64_t n, int64_t C, T* __restrict__ out) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  if (C == 3) {  // the flow case: keep the row in registers
    T acc[3];
    corners::gather_point<T>(params, idx + i * 8, w + i * 8, 3, acc);
    out[i * 3] = acc[0];
    out[i * 3 + 1] = acc[1];
    out[i * 3 + 2] = acc[2];
    return;
  }
  for (int64_t c = 0; c < C; ++c) {
    T s = T(0);
    for (int j = 0; j < 8; ++j) s += w[i * 8 + j] * params[int64_t(idx[i * 8 + j]) * C + c];
    out[i * C + c] = s;
  }
}

inline unsigned blocks_for(int64_t work) { return unsigned((work + kThreads - 1) / kThreads); }

}  // namespace

template <typename T>
void corner_gather(const T* params, const int32_t* idx, const T* w, int64_t n, int64_t C, T* out,
                   cudaStream_t stream) {
  if (n == 0) return;
  corner_gather_kernel<T><<<blocks_for(n), kThreads, 0, stream>>>(params, idx, w, n, C, out);
}

template void corner_gather<float>(const float*, const int32_t*, const float*, int64_t, int64_t, float*, cudaStream_t);
template void corner_gather<double>(const double*, const int32_t*, const double*, int64_t, int64_t, double*,
                                    cudaStream_t);

}  // namespace floxels::cuda
