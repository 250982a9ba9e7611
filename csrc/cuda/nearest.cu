// CUDA nearest_neighbor (NSFP's Chamfer loss): one thread per query point, the reference
// cloud streamed through shared memory in tiles. The reference cloud is cut into `segments`
// ranges (grid.y) so that a few thousand queries still fill the device; the segments' partial
// minima meet in one 64-bit atomicMin per query on (distance bits, index), which is exact and
// deterministic (non-negative float bits order like the floats; equal distances keep the
// lowest index, like argmin).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "cuda/nearest_launch.h"
#include "kernels/nearest.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kTile = 512;

template <typename T>
__global__ void nearest_kernel(const T* __restrict__ x, int64_t N, const T* __restrict__ y, int64_t M,
                               int64_t seg_len, int64_t* __restrict__ idx, unsigned long long* __restrict__ packed) {
  __shared__ T sy[3 * kTile];
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t j0 = int64_t(blockIdx.y) * seg_len;
  const int64_t j1 = j0 + seg_len < M ? j0 + seg_len : M;
  const bool valid = i < N;
  T qx = T(0), qy = T(0), qz = T(0);
  if (valid) {
    qx = x[3 * i];
    qy = x[3 * i + 1];
    qz = x[3 * i + 2];
  }
  T best = T(INFINITY);
  int64_t bi = j0;  // all distances NaN/inf: the segment's first index at distance +inf
  for (int64_t t = j0; t < j1; t += kTile) {
    const int cnt = int(j1 - t < kTile ? j1 - t : kTile);
    __syncthreads();
    for (int k = threadIdx.x; k < 3 * cnt; k += blockDim.x) sy[k] = y[3 * t + k];
    __syncthreads();
    if (valid) {
      for (int k = 0; k < cnt; ++k) {
        const T d = nearest::sq_dist(qx, qy, qz, sy[3 * k], sy[3 * k + 1], sy[3 * k + 2]);
        if (d < best) {
          best = d;
          bi = t + k;
        }
      }
    }
  }
  if (!valid) return;
  if (packed == nullptr) {
    idx[i] = bi;
  } else {
    const unsigned int bits = __float_as_uint(float(best));
    atomicMin(packed + i, (static_cast<unsigned long long>(bits) << 32) | static_cast<unsigned long long>(bi));
  }
}

}  // namespace

int nearest_segments(int64_t N, int64_t M, int num_sms, bool is_double) {
  if (is_double) return 1;
  const int64_t qblocks = (N + kThreads - 1) / kThreads;
  const int64_t want = (4 * int64_t(std::max(num_sms, 1)) + qblocks - 1) / std::max<int64_t>(qblocks, 1);
  const int64_t tiles = (M + kTile - 1) / kTile;
  return int(std::max<int64_t>(1, std::min<int64_t>({want, tiles, 65535})));
}

template <typename T>
void nearest_neighbor(const T* x, int64_t N, const T* y, int64_t M, int segments, int64_t* idx,
                      unsigned long long* packed, cudaStream_t s) {
  if (N == 0) return;
  const int64_t tiles = (M + kTile - 1) / kTile;
  const int64_t tiles_per_seg = (tiles + segments - 1) / segments;
  const int64_t seg_len = tiles_per_seg * kTile;
  const int64_t nseg = (M + seg_len - 1) / seg_len;
  const dim3 grid(unsigned((N + kThreads - 1) / kThreads), unsigned(nseg));
  nearest_kernel<T><<<grid, kThreads, 0, s>>>(x, N, y, M, seg_len, nseg > 1 ? nullptr : idx,
                                               nseg > 1 ? packed : nullptr);
}

template void nearest_neighbor<float>(const float*, int64_t, const float*, int64_t, int, int64_t*,
                                      unsigned long long*, cudaStream_t);
template void nearest_neighbor<double>(const double*, int64_t, const double*, int64_t, int, int64_t*,
                                       unsigned long long*, cudaStream_t);

}  // namespace floxels::cuda
