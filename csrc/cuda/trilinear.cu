// CUDA trilinear gather / points gradient / scatter terms: one thread per point. The scatter
// is deterministic (issue 31): this file writes each point's 8 (voxel, weight) terms and the
// binding sums them per voxel in index order (trilinear_binding.cpp), instead of float
// atomics. Non-finite points: NaN gather rows, zero points-gradient rows, ignored by the
// scatter (kernels/trilinear.h).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/trilinear_launch.h"
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

// Per point and corner: the voxel (vol for a non-finite point: a row the binding drops) and
// the trilinear weight (0 there).
template <typename T>
__global__ void scatter_terms_kernel(const T* __restrict__ points, int64_t N, TriGeom g, int64_t* __restrict__ keys,
                                     T* __restrict__ weights) {
  const int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (i >= N) return;
  const tri::Cell<T> c = cell_at(points, i, g);
  const int64_t vol = g.Z * g.Y * g.X;
  int k = 0;
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx, ++k) {
        const T w = (dz ? c.tz : T(1) - c.tz) * (dy ? c.ty : T(1) - c.ty) * (dx ? c.tx : T(1) - c.tx);
        keys[8 * i + k] = c.ok ? c.base + dz * c.sz + dy * c.sy + dx * c.sx : vol;
        weights[8 * i + k] = c.ok ? w : T(0);
      }
}

}  // namespace

template <typename T>
void trilinear_gather(const T* grid, int64_t C, const T* points, int64_t N, TriGeom g, T* out, cudaStream_t s) {
  if (N == 0 || C == 0) return;
  gather_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(grid, C, points, N, g, out);
}

template <typename T>
void trilinear_scatter_terms(const T* points, int64_t N, TriGeom g, int64_t* keys, T* weights, cudaStream_t s) {
  if (N == 0) return;
  scatter_terms_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(points, N, g, keys, weights);
}

template <typename T>
void trilinear_points_grad(const T* grad_out, const T* grid, int64_t C, const T* points, int64_t N, TriGeom g,
                           T* grad_points, cudaStream_t s) {
  if (N == 0) return;
  points_grad_kernel<T><<<blocks_for(N), kBlock, 0, s>>>(grad_out, grid, C, points, N, g, grad_points);
}

#define FLX_INSTANTIATE(T)                                                                               \
  template void trilinear_gather<T>(const T*, int64_t, const T*, int64_t, TriGeom, T*, cudaStream_t);     \
  template void trilinear_scatter_terms<T>(const T*, int64_t, TriGeom, int64_t*, T*, cudaStream_t);        \
  template void trilinear_points_grad<T>(const T*, const T*, int64_t, const T*, int64_t, TriGeom, T*,     \
                                         cudaStream_t);
FLX_INSTANTIATE(float)
FLX_INSTANTIATE(double)
#undef FLX_INSTANTIATE

}  // namespace floxels::cuda
