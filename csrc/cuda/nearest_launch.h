// Plain launcher of the CUDA nearest-neighbour kernel (no torch types).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// Number of y segments nearest_neighbor splits the work into (grid.y): enough blocks to fill
// the device when x is small; 1 for float64 (the packed atomic form below needs float keys).
int nearest_segments(int64_t N, int64_t M, int num_sms, bool is_double);

// For each of the N rows of x: the index of its nearest row of y (M >= 1 rows).
// segments == 1: written to idx directly. segments > 1 (float only): `packed` (N entries, set
// to INT64_MAX beforehand) receives atomicMin of (float bits of the squared distance << 32 | j),
// i.e. the smallest distance and, among equal ones, the lowest index.
template <typename T>
void nearest_neighbor(const T* x, int64_t N, const T* y, int64_t M, int segments, int64_t* idx,
                      unsigned long long* packed, cudaStream_t s);

}  // namespace floxels::cuda
