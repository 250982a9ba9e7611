// Plain launchers for the trilinear CUDA kernels (no torch types): raw device pointers,
// sizes and the stream to launch on. N == 0 launches nothing.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

struct TriGeom {
  int64_t Z, Y, X;
  double ox, oy, oz, spacing;
};

// out (N, C) = grid (C, Z, Y, X) at points (N, 3).
template <typename T>
void trilinear_gather(const T* grid, int64_t C, const T* points, int64_t N, TriGeom g, T* out, cudaStream_t s);

// The terms of the adjoint splat (the scatter; summed per voxel by the binding): per point i
// and corner k (z, y, x bits of k), keys[8i + k] = the corner's voxel (flat over Z, Y, X) and
// weights[8i + k] = its trilinear weight; a non-finite point gets voxel Z * Y * X and weight 0.
template <typename T>
void trilinear_scatter_terms(const T* points, int64_t N, TriGeom g, int64_t* keys, T* weights, cudaStream_t s);

// grad_points (N, 3) of sum(grad_out * gather(grid, points)).
template <typename T>
void trilinear_points_grad(const T* grad_out, const T* grid, int64_t C, const T* points, int64_t N, TriGeom g,
                           T* grad_points, cudaStream_t s);

}  // namespace floxels::cuda
