// Launcher for the compact corner gather kernel (csrc/cuda/corners.cu); the scatter is formed
// by the binding (corners_binding.cpp).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

template <typename T>
void corner_gather(const T* params, const int32_t* idx, const T* w, int64_t n, int64_t C, T* out,
                   cudaStream_t stream);

}  // namespace floxels::cuda
