// Per-call setup kernels of the CUDA solver: the support scans to device memory, each
// segment's corner rows / label / weight sums and its points' records, one record per vertex
// entry, each vertex's cluster pairs, and Adam's bias-correction table. They run once per
// solver_run call, before the first cluster means and the iterations (launcher: solver.cu).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/solver_params.cuh"

namespace floxels::cuda {
namespace {

using namespace solver_detail;

// Whether segment s spans two point tiles of its problem (then its row is summed by atomics).
__device__ bool segment_spans_tiles(const KParams& P, int s) {
  const int b = P.seg_ptr[s], e = P.seg_ptr[s + 1];
  int p = 0;
  while (p + 1 < P.num_problems && b >= P.point_end[p]) ++p;
  const int first = P.point_begin[p] + (b - P.point_begin[p]) / kTile * kTile;
  return b < P.point_begin[p] || e > first + kTile;
}

// Per call, a warp per segment: corner rows, label, weight sums (fixed lane order, so
// deterministic) and the point records of its points.
__global__ void __launch_bounds__(kThreads) segment_setup_kernel(const __grid_constant__ KParams P) {
  const int s = int((int64_t(blockIdx.x) * kThreads + threadIdx.x) >> 5), lane = threadIdx.x & 31;
  if (s >= P.num_segments) return;
  const int b = max(P.seg_ptr[s], 0), e = min(P.seg_ptr[s + 1], P.num_points);
  float w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  const int tag = s | (b < e && segment_spans_tiles(P, s) ? kSpansBit : 0);
  for (int i = b + lane; i < e; i += 32) {
    P.rec[i] = make_float4(P.points[3 * int64_t(i)], P.points[3 * int64_t(i) + 1], P.points[3 * int64_t(i) + 2],
                           __int_as_float(tag));
    for (int k = 0; k < 8; ++k) w[k] += P.corner_w[8 * int64_t(i) + k];
  }
  for (int k = 0; k < 8; ++k)
    for (int off = 16; off > 0; off >>= 1) w[k] += __shfl_xor_sync(0xffffffffu, w[k], off);
  if (lane < 8) {
    P.seg_wsum[8 * int64_t(s) + lane] = w[lane];
    const int v = b < e ? P.corner_idx[8 * int64_t(b) + lane] : -1;
    P.seg_corner[8 * int64_t(s) + lane] = unsigned(v) < unsigned(P.num_vertices) ? v : -1;
  }
  if (lane == 0) {
    const int l = (P.labels != nullptr && b < e) ? P.labels[b] : -1;
    P.seg_label[s] = unsigned(l) < unsigned(P.num_clusters) ? l : -1;
  }
}

// Per call, a thread per vertex entry: one record instead of a chain of dependent loads in
// every iteration.
__global__ void __launch_bounds__(kThreads) entry_setup_kernel(const __grid_constant__ KParams P) {
  const int64_t e = int64_t(blockIdx.x) * kThreads + threadIdx.x;
  if (e >= 8 * int64_t(P.num_segments)) return;
  const int ent = P.vtx_entry[e];
  const int s = ent >> 3, k = ent & 7;
  int4 r = make_int4(-1, 0, -1, 0);
  if (ent >= 0 && s < P.num_segments) {
    const int l = P.seg_label[s];
    r = make_int4(ent, __float_as_int(l >= 0 ? P.seg_wsum[8 * int64_t(s) + k] / P.cluster_count[l] : 0.0f), l,
                  segment_spans_tiles(P, s) ? 1 : 0);
  }
  P.ent[e] = r;
}

// Per call, a thread per vertex: its entries' mean coefficients summed per cluster (the
// entries of a vertex are in segment order, so a cluster's entries are consecutive).
__global__ void __launch_bounds__(kThreads) pair_setup_kernel(const __grid_constant__ KParams P) {
  const int v = blockIdx.x * kThreads + threadIdx.x;
  if (v >= P.num_vertices) return;
  const int b = max(P.vtx_ptr[v], 0), e = min(P.vtx_ptr[v + 1], 8 * P.num_segments);
  int n = 0, cur = -1;
  float acc = 0.0f;
  for (int x = b; x < e; ++x) {
    const int4 r = P.ent[x];
    if (r.z < 0) continue;
    if (r.z != cur) {
      if (cur >= 0) P.pair[b + n++] = make_int2(cur, __float_as_int(acc));
      cur = r.z;
      acc = 0.0f;
    }
    acc += __int_as_float(r.y);
  }
  if (cur >= 0) P.pair[b + n++] = make_int2(cur, __float_as_int(acc));
  P.num_pairs[v] = n;
}

// Per call: the support scans to device memory.
__global__ void scans_setup_kernel(const __grid_constant__ ScanTable T, Scan* dst) {
  for (int j = threadIdx.x; j < kMaxProblems * kMaxSupport; j += blockDim.x) dst[j] = (&T.scans[0][0])[j];
}

// Per call: Adam's bias corrections of every step (stage 3 looks them up).
__global__ void bias_kernel(const __grid_constant__ KParams P) {
  const int it = blockIdx.x * blockDim.x + threadIdx.x;
  if (it < P.hyper.max_iters) bias_corrections(P.hyper, it + 1, &P.bias[2 * it], &P.bias[2 * it + 1]);
}

}  // namespace

namespace solver_detail {

void launch_setup(const KParams& P, const ScanTable& T, Scan* scans, int64_t S, int64_t M, bool cluster,
                  cudaStream_t stream) {
  scans_setup_kernel<<<1, kThreads, 0, stream>>>(T, scans);
  if (S > 0) {
    segment_setup_kernel<<<unsigned((S * 32 + kThreads - 1) / kThreads), kThreads, 0, stream>>>(P);
    entry_setup_kernel<<<unsigned(blocks_for(8 * S)), kThreads, 0, stream>>>(P);
    if (cluster && M > 0) pair_setup_kernel<<<unsigned(blocks_for(M)), kThreads, 0, stream>>>(P);
  }
  bias_kernel<<<unsigned((P.hyper.max_iters + 127) / 128), 128, 0, stream>>>(P);
}

}  // namespace solver_detail
}  // namespace floxels::cuda
