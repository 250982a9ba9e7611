// CUDA trilinear gather / points gradient / scatter: one thread per point. The scatter uses
// warp-aggregated atomics (warp_aggregate.cuh) because LiDAR points pile up in the voxels
// near the sensor. Non-finite points: NaN gather rows, zero points-gradient rows, ignored by
// the scatter (kernels/trilinear.h).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/trilinear_launch.h"
#include "cuda/warp_aggregate.cuh"
#include "kernels/trilinear.h"

namespace floxels::cuda {
namespace {

constexpr int kBlock = 256;

int64_t blocks_for(int64_t n) { return (n + kBlock - 1) / kBlock; }

template <typename T>
__device__ __forceinline__ tri::Cell<T> cell_at(const T* points, int64_t i, const TriGeom& g) {
  return tri::cell_setup<T>(points + 3 * i, T(g.ox), T(g.oy), T(g.oz), T(g.spacing), g.Z, g.Y, g.X);
}

template <typename T>
__global__ void gather_kernel(const T* __restrict__ grid, int64_t C, const T* __restrict__ points, int64_t N,
                              TriGeom g, T* __restrict__ out) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i >= N) return;
  tri::gather_point(grid, C, g.Z * g.Y * g.X, cell_at(points, i, g), out + i * C, int64_t(1));
}

template <typename T>
__global__ void points_grad_kernel(const T* __restrict__ grad_out, const T* __restrict__ grid, int64_t C,
                                   const T* __restrict__ points, int64_t N, TriGeom g, T* __restrict__ gp) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i >= N) return;
  tri::gather_point_grad(grid, C, g.Z * g.Y * g.X, cell_at(points, i, g), grad_out + i * C, T(g.spacing),
                         gp + 3 * i);
}

// No early return: every lane takes part in the warp-aggregated adds (out-of-range lanes
// pass key -1).
template <typename T>
__global__ void scatter_kernel(const T* __restrict__ values, int C, const T* __restrict__ points, int64_t N,
                               TriGeom g, T* __restrict__ out) {
  __shared__ T scratch[kBlock];
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  bool valid = i < N;
  tri::Cell<T> c{};
  if (valid) {
    c = cell_at(points, i, g);
    valid = c.ok;  // a non-finite point is ignored (key -1 like an out-of-range lane)
  }
  const T* v = values + (valid ? i : 0) * C;
  T* ws = scratch + (threadIdx.x & ~31);
  const int64_t vol = g.Z * g.Y * g.X;
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx) {
        const T w = (dz ? c.tz : T(1) - c.tz) * (dy ? c.ty : T(1) - c.ty) * (dx ? c.tx : T(1) - c.tx);
        const int64_t key = valid ? c.base + dz * c.sz + dy * c.sy + dx * c.sx : int64_t(-1);
        cuda_detail::warp_add(out, key, int64_t(1), vol, v, w, C, ws);
      }
}

}  // namespace

template <typename T>
void trilinear_gather(const T* grid, int64_t C, const T* points, int64_t N, TriGeom g, T* out, cudaStream_t s) {
  if (N == 0 || C == 0) return;
  gather_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(grid, C, points, N, g, out);
}

template <typename T>
void trilinear_scatter(const T* values, int64_t C, const T* points, int64_t N, TriGeom g, T* out,
                       cudaStream_t s) {
  if (N == 0 || C == 0) return;
  scatter_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(values, static_cast<int>(C), points, N, g, out);
}

template <typename T>
void trilinear_points_grad(const T* grad_out, const T* grid, int64_t C, const T* points, int64_t N, TriGeom g,
                           T* grad_points, cudaStream_t s) {
  if (N == 0) return;
  points_grad_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(grad_out, grid, C, points, N, g, grad_points);
}

#define FLX_INSTANTIATE(T)                                                                               \
  template void trilinear_gather<T>(const T*, int64_t, const T*, int64_t, TriGeom, T*, cudaStream_t);     \
  template void trilinear_scatter<T>(const T*, int64_t, const T*, int64_t, TriGeom, T*, cudaStream_t);    \
  template void trilinear_points_grad<T>(const T*, const T*, int64_t, const T*, int64_t, TriGeom, T*,     \
                                         cudaStream_t);
FLX_INSTANTIATE(float)
FLX_INSTANTIATE(double)
#undef FLX_INSTANTIATE

}  // namespace floxels::cuda
