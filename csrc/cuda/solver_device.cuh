// Device helpers of the CUDA solver shared by its kernel files: programmatic dependent launch,
// block -> problem lookups, warp run sums over sorted points, the blocks' shared-memory
// layouts, and each point's / vertex's fixed per-call data. nvcc only.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/solver_params.cuh"

namespace floxels::cuda::solver_detail {

// Programmatic dependent launch (sm_90; on unless FLOXELS_SOLVER_PDL=0: with the fixed
// per-point loads ahead of the wait, 24.1 vs 28.1 us per iteration at one frame on an H100,
// 212 vs 217 at 16 frames): a kernel lets the next one in the stream start early, and the next one reads
// nothing the previous kernel writes before wait. Without the launch attribute both are no-ops.
// (sm_90 instructions: no-ops when built for older architectures, which launch without PDL
// effect anyway.)
__device__ __forceinline__ void pdl_allow_next() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  asm volatile("griddepcontrol.launch_dependents;" ::: "memory");
#endif
}
__device__ __forceinline__ void pdl_wait_previous() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  asm volatile("griddepcontrol.wait;" ::: "memory");
#endif
}

__device__ __forceinline__ int problem_of(int block, const int* begins, int num_problems) {
  int p = 0;
  while (p + 1 < num_problems && block >= begins[p + 1]) ++p;
  return p;
}

__device__ __forceinline__ int warp_max(int x) {
  for (int off = 16; off > 0; off >>= 1) x = max(x, __shfl_xor_sync(0xffffffffu, x, off));
  return x;
}

// First point of point block `block` of problem p.
__device__ __forceinline__ int block_first_point(const KParams& P, int p, int block) {
  return P.point_begin[p] + (block - P.block_begin[p]) * kThreads;
}

// Runs of equal keys over the lanes of a warp (a key's lanes must be consecutive, as sorted
// points make them), for warp_run_sums. Every lane of the warp must call it.
struct WarpRuns {
  int start;         // first lane of this lane's run
  unsigned longest;  // longest run in the warp
  bool tail;         // this lane ends its run
};

__device__ __forceinline__ WarpRuns warp_runs(int key) {
  constexpr unsigned kFull = 0xffffffffu;
  const int lane = threadIdx.x & 31;
  const int prev = __shfl_up_sync(kFull, key, 1), next = __shfl_down_sync(kFull, key, 1);
  WarpRuns r;
  r.tail = lane == 31 || next != key;
  const unsigned heads = __ballot_sync(kFull, lane == 0 || prev != key);
  r.start = 31 - __clz(heads & (kFull >> (31 - lane)));
  unsigned len = r.tail ? unsigned(lane - r.start + 1) : 0u;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 800
  r.longest = __reduce_max_sync(kFull, len);
#else
  for (int off = 16; off > 0; off >>= 1) len = max(len, __shfl_xor_sync(kFull, len, off));
  r.longest = len;
#endif
  return r;
}

// Sums K values per run: afterwards the run's last lane holds the run's sum in v. A
// segmented Hillis-Steele scan: fixed order (deterministic), no shared memory and no block
// barrier, and only as many steps as the warp's longest run needs (log2 of it). Every lane
// of the warp must call it.
template <int K>
__device__ __forceinline__ void warp_run_sums(const WarpRuns& r, float (&v)[K]) {
  const int lane = threadIdx.x & 31;
  for (unsigned off = 1; off < r.longest; off <<= 1) {
    const bool take = lane - int(off) >= r.start;
    for (int j = 0; j < K; ++j) {
      const float o = __shfl_up_sync(0xffffffffu, v[j], off);
      if (take) v[j] += o;
    }
  }
}

// Shared memory of one block of the iteration kernels (the persistent loop uses both parts).
// The per-slot sums are fixed-point integers (cuda/fixed_point.cuh).
struct PointSmem {
  int ukey[kThreads];                 // cluster summed in u-sum slot (cluster % kThreads), -1 empty
  unsigned long long usum[kThreads][3];  // the block's u sums per slot
  double wloss[kWarps];               // loss per warp
};
struct VertexSmem {
  unsigned long long scratch[kThreads];  // warp_add's per-warp scratch
  double st[kStateCols];
  int mkey[kThreads];                    // cluster summed in mean slot (cluster % kThreads), -1 empty
  unsigned long long msum[kThreads * 3];  // the block's shares of the next means per slot
};

__device__ __forceinline__ void zero_strided_u64(unsigned long long* a, int64_t n) {
  for (int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; j < n; j += int64_t(gridDim.x) * blockDim.x)
    a[j] = 0ull;
}

// Per iteration, by the whole grid: clear the other parity's means, u sums and losses (the
// vertex stage of this iteration fills them for the next one).
template <bool kCluster>
__device__ __forceinline__ void clear_other_parity(const KParams& P, int parity) {
  const int C3 = 3 * P.num_clusters;
  if constexpr (kCluster) {
    zero_strided_u64(P.ufx + (parity ? 0 : C3), C3);
    zero_strided_u64(P.mfx + (parity ? 0 : C3), C3);
  }
  if (blockIdx.x == 0 && threadIdx.x < kMaxProblems) {
    P.loss_fx[(parity ? 0 : kMaxProblems) + threadIdx.x] = 0ull;
    P.loss_flag[(parity ? 0 : kMaxProblems) + threadIdx.x] = 0;
  }
}

// The sum over a spanning segment's point tiles of its partial rows
// (span_part, written by the point stage) for corner k, in tile order. `ent` = segment * 8 +
// corner. Only tables built outside the package have such segments (the Python tables split
// segments at tiles), so this slow path costs nothing there.
__device__ __forceinline__ void span_sum(const KParams& P, int ent, float (&out)[3]) {
  out[0] = out[1] = out[2] = 0.0f;
  const int s = ent >> 3, k = ent & 7;
  int b = max(P.seg_ptr[s], 0), e = min(P.seg_ptr[s + 1], P.num_points);
  int p = 0;
  while (p + 1 < P.num_problems && b >= P.point_end[p]) ++p;
  b = max(b, P.point_begin[p]);
  e = min(e, P.point_end[p]);
  if (b >= e) return;
  const int base = P.point_begin[p];
  const int t0 = (b - base) / kTile, t1 = (e - 1 - base) / kTile;
  const int64_t tile0 = int64_t(P.block_begin[p]) * kWarps;
  for (int t = t0; t <= t1; ++t) {
    // the segment's run holds the tile's first point, except in its first tile when the
    // segment starts inside it (then the run holds the tile's last point)
    const int slot = (t == t0 && (b - base) % kTile != 0) ? 1 : 0;
    const float* sp = P.span_part + ((tile0 + t) * 2 + slot) * kSegVals + 3 * k;
    for (int c = 0; c < 3; ++c) out[c] += sp[c];
  }
}

// The fixed per-call data of one point (the same in every iteration): its record (x, y, z,
// segment tag), corner weights, its segment's corner rows and cluster.
struct PointFixed {
  float4 pt;
  float4 w0, w1;
  int4 c0, c1;  // vertex rows of the 8 corners, -1 where none
  int label;    // -1: noise, or no cluster term
};

// The persistent loop keeps each block's PointFixed in shared memory (structure of arrays:
// conflict-free 16-byte accesses), so iterations start without the two dependent global
// loads (record, then the segment's corners).
struct PointCache {
  float4 pt[kThreads], w0[kThreads], w1[kThreads];
  int4 c0[kThreads], c1[kThreads];
  int label[kThreads];
  __device__ void put(const PointFixed& f) {
    const int t = threadIdx.x;
    pt[t] = f.pt, w0[t] = f.w0, w1[t] = f.w1, c0[t] = f.c0, c1[t] = f.c1, label[t] = f.label;
  }
  __device__ PointFixed get() const {
    const int t = threadIdx.x;
    return PointFixed{pt[t], w0[t], w1[t], c0[t], c1[t], label[t]};
  }
};

// Segment of a point record's tag, or -1 (no segment: invalid tables or past the end).
__device__ __forceinline__ int tag_segment(const KParams& P, float tagf) {
  const int tag = __float_as_int(tagf);
  return (tag >= 0 && (tag & kSegMask) < P.num_segments) ? (tag & kSegMask) : -1;
}

template <bool kCluster>
__device__ __forceinline__ PointFixed load_fixed(const KParams& P, int vb) {
  const int p = problem_of(vb, P.block_begin, P.num_problems);
  const int i = block_first_point(P, p, vb) + int(threadIdx.x);
  PointFixed f{make_float4(0.0f, 0.0f, 0.0f, __int_as_float(-1)), make_float4(0.0f, 0.0f, 0.0f, 0.0f),
               make_float4(0.0f, 0.0f, 0.0f, 0.0f), make_int4(-1, -1, -1, -1), make_int4(-1, -1, -1, -1), -1};
  if (i < P.point_end[p]) {
    f.pt = P.rec[i];
    const float4* wp = reinterpret_cast<const float4*>(P.corner_w + 8 * int64_t(i));
    f.w0 = wp[0];
    f.w1 = wp[1];
  }
  const int seg = tag_segment(P, f.pt.w);
  if (seg >= 0) {
    const int4* cp = reinterpret_cast<const int4*>(P.seg_corner + 8 * int64_t(seg));
    f.c0 = cp[0];
    f.c1 = cp[1];
    if constexpr (kCluster) f.label = P.seg_label[seg];
  }
  return f;
}

// Vertex of this thread's lane group in vertex block vb of problem p (>= vertex_end[p]: none).
__device__ __forceinline__ int vertex_of(const KParams& P, int p, int vb) {
  return P.vertex_begin[p] + (vb - P.vblock_begin[p]) * kVerticesPerBlock + int(threadIdx.x / kLanesPerVertex);
}

// Fixed per-call data of vertex_body: the range of this lane group's vertex entries.
__device__ __forceinline__ int2 vertex_entries(const KParams& P, int vb) {
  const int p = problem_of(vb, P.vblock_begin, P.num_problems);
  const int v = vertex_of(P, p, vb);
  if (v >= P.vertex_end[p]) return make_int2(0, 0);
  return make_int2(max(P.vtx_ptr[v], 0), min(P.vtx_ptr[v + 1], 8 * P.num_segments));
}

}  // namespace floxels::cuda::solver_detail
