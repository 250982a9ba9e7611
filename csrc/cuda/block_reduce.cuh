// Deterministic block-wide sum shared by the CUDA kernels that reduce a loss per block.
#pragma once
#include <cuda_runtime.h>

namespace floxels::cuda_detail {

// Sum of one double per thread over a block of kBlock threads, in a fixed order (so the
// result does not depend on scheduling); valid in thread 0. Every thread must call it.
template <int kBlock>
__device__ double block_sum(double v) {
  static_assert(kBlock % 32 == 0 && kBlock <= 1024, "block size must be whole warps");
  __shared__ double warp_sums[kBlock / 32];
  for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if (lane == 0) warp_sums[warp] = v;
  __syncthreads();
  double total = 0.0;
  if (threadIdx.x == 0) {
    for (int w = 0; w < kBlock / 32; ++w) total += warp_sums[w];
  }
  return total;
}

}  // namespace floxels::cuda_detail
