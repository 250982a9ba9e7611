// Plain launchers of the CUDA fixed_segment_sum kernels (no torch types).
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// ws: int64 workspace of rows * (2 C + 1) entries, zeroed beforehand (integer sums rows x C,
// then non-finite flags rows x C, then counts rows). Adds every term of values (M, C) to its
// row (index outside [0, rows): ignored).
template <typename T, typename I>
void segment_sum_accumulate(const T* values, const I* index, int64_t M, int64_t C, int64_t rows, double limit,
                            long long* ws, cudaStream_t s);

// out (rows, C [+1]) float64 from the workspace: NaN where a term was non-finite (void_row:
// the row's every value column), else the decoded sum; the count last when `count`.
void segment_sum_finish(const long long* ws, int64_t C, int64_t rows, bool void_row, bool count, double* out,
                        cudaStream_t s);

}  // namespace floxels::cuda
