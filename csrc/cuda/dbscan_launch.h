// Launcher of the CUDA exact DBSCAN (csrc/cuda/dbscan.cu).
#pragma once
#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>

namespace floxels::cuda {

// Bytes of device scratch memory dbscan() needs for n points (caller allocates it).
size_t dbscan_workspace_bytes(int64_t n);

// kDbscanBadArgs: n >= 2^31, eps/min_samples invalid, or a workspace smaller than
// dbscan_workspace_bytes(n) (checked before any launch).
enum DbscanStatus : int { kDbscanOk = 0, kDbscanNonFinite = 1, kDbscanCudaError = 2, kDbscanBadArgs = 3 };

// labels (n,) int64 in the points' original order, exactly sklearn's DBSCAN labels. All work
// is queued on `stream`; the stream is synchronised once (to read the bounding box, which
// sizes the grid and the sort), the labels are ready when the stream's later work runs.
// points (n, 3) contiguous on the device, 0 < n < 2^31, eps > 0 finite, min_samples >= 1.
template <typename T>
int dbscan(const T* points, int64_t n, double eps, int32_t min_samples, int64_t* labels, void* workspace,
           size_t workspace_bytes, cudaStream_t stream);

}  // namespace floxels::cuda
