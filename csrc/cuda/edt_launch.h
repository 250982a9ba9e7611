// Plain launchers of the CUDA exact distance transform (csrc/cuda/edt.cu); torch-free so
// the .cu file compiles without torch headers. Each returns the first launch error.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// Scratch int32 elements edt_launch needs for a (Z, Y, X) grid.
inline int64_t edt_scratch_elems(int64_t Z, int64_t Y, int64_t X) { return 2 * Z * Y * X; }

// occ: (Z, Y, X) contiguous bytes (0/1); out: (Z, Y, X) float32; scratch: edt_scratch_elems
// int32. Requires Z*Y*X > 0 and the squared-distance bound of kernels/edt.h.
cudaError_t edt_launch(const uint8_t* occ, float* out, int32_t* scratch, int64_t Z, int64_t Y, int64_t X,
                       double spacing, cudaStream_t stream);

// Sets out[(iz*Y + iy)*X + ix] = 1 for every point's nearest sample inside the grid; out must
// be zeroed by the caller. origin = [x0, y0, z0].
cudaError_t points_to_occupancy_launch(const float* points, int64_t n, const double* origin, double spacing,
                                       int64_t Z, int64_t Y, int64_t X, uint8_t* out, cudaStream_t stream);
cudaError_t points_to_occupancy_launch(const double* points, int64_t n, const double* origin, double spacing,
                                       int64_t Z, int64_t Y, int64_t X, uint8_t* out, cudaStream_t stream);

}  // namespace floxels::cuda
