// Launchers for the compact corner gather/scatter kernels (csrc/cuda/corners.cu).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

template <typename T>
void corner_gather(const T* params, const int32_t* idx, const T* w, int64_t n, int64_t C, T* out,
                   cudaStream_t stream);

// out must be zeroed by the caller.
template <typename T>
void corner_scatter(const T* values, const int32_t* idx, const T* w, int64_t n, int64_t C, T* out,
                    cudaStream_t stream);

}  // namespace floxels::cuda
