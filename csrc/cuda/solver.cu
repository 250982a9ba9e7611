// CUDA implementation of the device-resident Floxels optimiser (stages in kernels/solver.h).
//
// One iteration = two kernels:
//   points   per point: flow f_i from its 8 vertices, multi-scan DT loss + gradient, flow
//            norm, residual to the cluster mean and its unit vector u_i (stages 1-2); per
//            warp, the sums of w_k * g_i per segment; per block, the sums of u_i per
//            cluster and the loss (one atomic each into the totals);
//   vertices stage 3 (loss, early stopping: every block takes the same decision from the
//            problem's loss and a state snapshot, so no block waits for another), best
//            copy, gradient = sum over the vertex's (segment, corner) entries minus the
//            cluster-mean term, Adam (stage 4); then the vertex's share of the next
//            iteration's cluster means.
// Cluster means need no pass over the points: m_c = (1/|c|) sum_{i in c} sum_k w_ik theta_{v_ik}
// is a fixed linear combination of vertex parameters (sum over the vertices v of c's points
// of A_cv theta_v, A_cv = weight of c's points at v / |c|). So the vertex kernel, right after
// its Adam step, adds A_cv theta_v into the next iteration's means, and the point kernel
// reads finished means instead of waiting for every point's flow: that is what makes one
// point kernel per iteration possible.
// Sums over points use sorted order: points are sorted by (cluster, voxel), so a warp's
// points form runs of equal segment and label, which warp_run_sums adds up with shuffles
// (no block barrier); the segment tables are split at 32-point tiles, so a segment's row
// gets one plain write per iteration (atomics only for tables that cross tiles). The
// means and the u sums alternate between two buffers by iteration parity (a kernel
// parameter): a point kernel reads one and clears the other, which the next kernel fills.
// Nothing synchronises with the host, so any number of iterations can be captured into a
// CUDA graph.
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>

#include "cuda/solver_launch.h"
#include "cuda/warp_aggregate.cuh"
#include "kernels/cluster.h"
#include "kernels/dt_loss.h"
#include "kernels/solver.h"

namespace floxels::cuda {
namespace {

using namespace floxels::solver;
using cuda_detail::warp_add;
using Scan = dt_loss::Scan<float, int>;
namespace cg = cooperative_groups;

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kLanesPerVertex = 8;  // stage 4: a group of 8 lanes per vertex
constexpr int kVerticesPerBlock = kThreads / kLanesPerVertex;
constexpr int kSegVals = 24;  // 8 corners x 3 components per segment

// Support scans of every problem: kMaxProblems x kMaxSupport descriptors (8 KB). They live in
// device memory (copied there once per call) so that the per-iteration kernels take ~1 KB of
// parameters: a large parameter block makes every launch slower.
struct ScanTable {
  Scan scans[kMaxProblems][kMaxSupport];
};

struct KParams {
  const Scan* scans;  // (kMaxProblems, kMaxSupport) in device memory
  int num_support[kMaxProblems];
  int block_begin[kMaxProblems + 1];   // point blocks of each problem (at least one each)
  int vblock_begin[kMaxProblems + 1];  // vertex blocks of each problem (at least one each)
  int point_begin[kMaxProblems], point_end[kMaxProblems];
  int vertex_begin[kMaxProblems], vertex_end[kMaxProblems];
  float flow_coef[kMaxProblems];     // reg_scale / n: multiplies lambda_g(it) * ||f_i||
  float cluster_coef[kMaxProblems];  // reg_scale * lambda_c / n
  int num_problems;
  int num_clusters;
  int num_vertices;
  int num_points;
  int num_segments;
  int parity;  // iteration parity of this launch: selects the mean / u-sum buffers
  int debug_skip;  // measurement only (FLOXELS_SOLVER_SKIP, traced loop): parts left out
  Hyper hyper;
  const float* points;
  const int32_t* corner_idx;
  const float* corner_w;
  const int32_t* seg_ptr;
  const int32_t* vtx_ptr;
  const int32_t* vtx_entry;
  const int32_t* labels;
  const float* cluster_count;
  float* theta;
  float* adam_m;
  float* adam_v;
  float* best;
  double* state;
  double* history;
  // workspace, fixed per call
  float4* rec;          // (N) x, y, z, segment id (int bits); segment -1 for uncovered points
  int32_t* seg_corner;  // (S, 8) vertex rows of the segment's corners (-1: invalid)
  int32_t* seg_label;   // (S) cluster of the segment's points, -1 noise
  float* seg_wsum;      // (S, 8) sum over the segment's points of w_k
  int4* ent;            // (8S) per vertex entry: segment * 8 + corner, bits of seg_wsum / |cluster|,
                        //      cluster, 1 if the segment spans two point tiles (its row is summed
                        //      by atomics and cleared by its readers)
  int2* pair;           // (8S) per vertex, its clusters and summed coefficients A_cv (bits)
  int32_t* num_pairs;   // (M)
  double* bias;         // (max_iters, 2) Adam bias corrections (bias_corrections)
  // workspace, per iteration
  float* seg_grad;  // (S, 24) sum over the segment's points of w_k * g_i
  float* mbuf;      // (2, C, 3) cluster means, by parity
  float* ubuf;      // (2, C, 3) sums of the unit residuals per cluster, by parity
  double* loss;     // (2, kMaxProblems) each problem's loss (sum of its point blocks' atomics), by parity
  double* snap;     // (B, kStateCols) state rows as the point kernel saw them
};

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

__device__ __forceinline__ void zero_strided(float* a, int64_t n) {
  for (int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; j < n; j += int64_t(gridDim.x) * blockDim.x)
    a[j] = 0.0f;
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

// Points are summed per warp: a segment's sums are complete in one warp when its points lie
// in one tile of 32 points (tiles start at the problem's first point), which the segment
// tables built in Python guarantee (they split segments at tile boundaries). A segment that
// crosses a tile anyway (tables built elsewhere) is summed by atomics and flagged in its
// point records (kSpansBit of the segment id) and vertex entries (cleared by its readers).
constexpr int kTile = 32;
constexpr int kSpansBit = 1 << 30;
constexpr int kSegMask = kSpansBit - 1;

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

// Shared memory of one block of the iteration kernels (the persistent loop uses both parts).
struct PointSmem {
  int ukey[kThreads];       // cluster summed in u-sum slot (cluster % kThreads), -1 empty
  float usum[kThreads][3];  // the block's u sums per slot
  double wloss[kWarps];     // loss per warp
};
struct VertexSmem {
  float scratch[kThreads];
  double st[kStateCols];
  int mkey[kThreads];        // cluster summed in mean slot (cluster % kThreads), -1 empty
  float msum[kThreads * 3];  // the block's shares of the next means per slot
};

// Per iteration, by the whole grid: clear the other parity's means, u sums and losses (the
// vertex stage of this iteration fills them for the next one).
template <bool kCluster>
__device__ __forceinline__ void clear_other_parity(const KParams& P, int parity) {
  const int C3 = 3 * P.num_clusters;
  if constexpr (kCluster) {
    zero_strided(P.ubuf + (parity ? 0 : C3), C3);
    zero_strided(P.mbuf + (parity ? 0 : C3), C3);
  }
  if (blockIdx.x == 0 && threadIdx.x < kMaxProblems) P.loss[(parity ? 0 : kMaxProblems) + threadIdx.x] = 0.0;
}

// Stages 1-2 of point block `vb`, a thread per point.
// `clear`: also run clear_other_parity (the per-iteration kernel; the persistent loop clears
// once per iteration instead).
// kDebug (measurement only, the traced loop): P.debug_skip leaves parts out (see
// FLOXELS_SOLVER_SKIP in solver_launch); the results are then wrong.
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

// Stages 1-2 of point block `vb`, a thread per point, from its fixed data `fx` (load_fixed).
// `clear`: also run clear_other_parity (the per-iteration kernel; the persistent loop clears
// once per iteration instead).
// kDebug (measurement only, the traced loop): P.debug_skip leaves parts out (see
// FLOXELS_SOLVER_SKIP in solver_launch); the results are then wrong.
template <bool kCluster, bool kDebug = false>
__device__ __forceinline__ void points_body(const KParams& P, int parity, int vb, bool clear, PointSmem& sm,
                                            const PointFixed& fx) {
  const int skip = kDebug ? P.debug_skip : 0;
  const int p = problem_of(vb, P.block_begin, P.num_problems);
  const float4 pt = fx.pt;
  const int seg = tag_segment(P, pt.w);
  const bool spans = (__float_as_int(pt.w) & kSpansBit) != 0;
  const float w[8] = {fx.w0.x, fx.w0.y, fx.w0.z, fx.w0.w, fx.w1.x, fx.w1.y, fx.w1.z, fx.w1.w};
  const int idx[8] = {fx.c0.x, fx.c0.y, fx.c0.z, fx.c0.w, fx.c1.x, fx.c1.y, fx.c1.z, fx.c1.w};
  const bool valid = seg >= 0;
  const int label = kCluster ? fx.label : -1;
  if constexpr (kCluster) {  // empty u-sum slots (the barrier below publishes them)
    sm.ukey[threadIdx.x] = -1;
    sm.usum[threadIdx.x][0] = sm.usum[threadIdx.x][1] = sm.usum[threadIdx.x][2] = 0.0f;
  }
  pdl_wait_previous();
  if (clear) clear_other_parity<kCluster>(P, parity);
  const int C3 = 3 * P.num_clusters;
  const double* st = P.state + p * kStateCols;
  if (vb == P.block_begin[p] && threadIdx.x < kStateCols)  // for stage 3 (vertex kernel)
    P.snap[p * kStateCols + threadIdx.x] = st[threadIdx.x];
  __syncthreads();
  const bool active = st[kActive] != 0.0;  // uniform per block
  float loss = 0.0f;
  if (active) {
    float f[3] = {0.0f, 0.0f, 0.0f};
    float mean[3] = {0.0f, 0.0f, 0.0f};
    if (valid && !(skip & 16)) {
      for (int j = 0; j < 8; ++j) {
        if (idx[j] < 0) continue;  // invalid tables (validated in Python): never read outside
        const float* row = P.theta + 3 * int64_t(idx[j]);
        for (int c = 0; c < 3; ++c) f[c] += w[j] * row[c];
      }
      if (kCluster && label >= 0) {
        const float* m = P.mbuf + (parity ? C3 : 0) + 3 * label;
        for (int c = 0; c < 3; ++c) mean[c] = m[c];
      }
    }
    float g[3] = {0.0f, 0.0f, 0.0f};
    float u[3] = {0.0f, 0.0f, 0.0f};
    if (valid && !(skip & 1))
      loss = dt_loss::point_loss<true, float, int>(P.scans + p * kMaxSupport, P.num_support[p], pt.x, pt.y, pt.z, f[0], f[1], f[2],
                                                   P.hyper.inv_dt_cell, P.hyper.truncation, g,
                                                   P.hyper.trunc_above);
    if (valid) {
      const float lam = float(lambda_g(P.hyper, st[kIter])) * P.flow_coef[p];
      float unit[3];
      loss += lam * norm_and_unit(f, unit);
      for (int c = 0; c < 3; ++c) g[c] += lam * unit[c];
      if (kCluster && label >= 0) {
        const float coef = P.cluster_coef[p];
        loss += coef * cluster::residual_unit<float>(f, mean, 3, u);
        for (int c = 0; c < 3; ++c) g[c] += coef * u[c];
      }
    }
    // Segment sums of w_k * g_i, per warp: the run's last lane writes the row (plain stores:
    // one writer per segment), or adds it where the segment crosses tiles.
    if (!(skip & 2)) {
      const WarpRuns runs = warp_runs(seg);
      float* dst = P.seg_grad + int64_t(kSegVals) * seg;
      // two halves of 4 corners: fewer values live at once (the loop kernel has 64 registers)
      for (int h = 0; h < 2; ++h) {
        float wg[kSegVals / 2];
        for (int k = 0; k < 4; ++k)
          for (int c = 0; c < 3; ++c) wg[3 * k + c] = w[4 * h + k] * g[c];
        warp_run_sums(runs, wg);
        if (runs.tail && valid) {
          if (!spans) {
            float4* d4 = reinterpret_cast<float4*>(dst + 12 * h);  // rows of 96 bytes: 16-byte aligned
            for (int j = 0; j < 3; ++j) d4[j] = make_float4(wg[4 * j], wg[4 * j + 1], wg[4 * j + 2], wg[4 * j + 3]);
          } else {
            for (int j = 0; j < 12; ++j) atomicAdd(dst + 12 * h + j, wg[j]);  // cleared by its readers
          }
        }
      }
    }
    // Cluster u sums: per warp run, into the block's slot of the cluster (one atomic per
    // cluster and block below); a slot taken by another cluster (labels of one block more
    // than kThreads apart: not with sorted tables) adds to global memory directly.
    if (kCluster && !(skip & 4)) {
      const int key = valid ? label : -1;
      const WarpRuns runs = warp_runs(key);
      warp_run_sums(runs, u);
      if (runs.tail && key >= 0) {
        const int slot = key % kThreads;
        const int had = atomicCAS(&sm.ukey[slot], -1, key);
        if (had == -1 || had == key) {
          for (int c = 0; c < 3; ++c) atomicAdd(&sm.usum[slot][c], u[c]);
        } else {
          float* ub = P.ubuf + (parity ? C3 : 0) + 3 * key;
          for (int c = 0; c < 3; ++c) atomicAdd(ub + c, u[c]);
        }
      }
    }
  }
  // Loss: per warp, then one double atomic per block. The sum order across blocks varies
  // between runs (last bits of the loss), like the float atomics of the other sums; a
  // per-block table re-read by every vertex block cost more than the whole vertex gradient
  // with 16 problems.
  if (!(skip & 8)) {
    double dl = double(loss);
    for (int off = 16; off > 0; off >>= 1) dl += __shfl_xor_sync(0xffffffffu, dl, off);
    if ((threadIdx.x & 31) == 0) sm.wloss[threadIdx.x >> 5] = dl;
  }
  __syncthreads();
  if (!active) return;  // uniform per block
  if constexpr (kCluster) {
    const int key = sm.ukey[threadIdx.x];
    if (key >= 0) {
      float* ub = P.ubuf + (parity ? C3 : 0) + 3 * key;
      for (int c = 0; c < 3; ++c) atomicAdd(ub + c, sm.usum[threadIdx.x][c]);
    }
  }
  if (threadIdx.x == 0 && !(skip & 8)) {
    double total = 0.0;
    for (int k = 0; k < kWarps; ++k) total += sm.wloss[k];
    if (total != 0.0) atomicAdd(P.loss + (parity ? kMaxProblems : 0) + p, total);
  }
}

template <bool kCluster>
__global__ void __launch_bounds__(kThreads) points_kernel(const __grid_constant__ KParams P) {
  __shared__ PointSmem sm;
  pdl_allow_next();
  // fixed per-call data first (overlaps the previous kernel's tail under PDL)
  const PointFixed fx = load_fixed<kCluster>(P, int(blockIdx.x));
  points_body<kCluster>(P, P.parity, int(blockIdx.x), true, sm, fx);
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

// Stage 3 then 4, a group of 8 lanes per vertex, then the vertex's terms of the next
// iteration's cluster means. kInitMeans: only the means, of the current parameters (once
// per call, before the first iteration).
template <bool kCluster, bool kInitMeans, bool kDebug = false>
__device__ __forceinline__ void vertex_body(const KParams& P, int parity, int vb, VertexSmem& sm, int2 entries) {
  const int skip = kDebug ? P.debug_skip : 0;
  float* scratch = sm.scratch;
  double* st = sm.st;
  const int p = problem_of(vb, P.vblock_begin, P.num_problems);
  const int sub = threadIdx.x & (kLanesPerVertex - 1), lane = threadIdx.x & 31;
  const int v = vertex_of(P, p, vb);
  const bool has_v = v < P.vertex_end[p];
  const int e_begin = entries.x, e_end = entries.y;
  pdl_wait_previous();
  const int C3 = 3 * P.num_clusters;
  if constexpr (!kInitMeans) {
    if (P.snap[p * kStateCols + kActive] == 0.0) return;  // stopped earlier: nothing changes (uniform)
    if (threadIdx.x == 0) {
      // Stage 3, by every block from the same loss and state snapshot (so all take the same
      // decision; the others gather gradients meanwhile); the problem's first block keeps
      // the record.
      for (int c = 0; c < kStateCols; ++c) st[c] = P.snap[p * kStateCols + c];
      const double loss = P.loss[(parity ? kMaxProblems : 0) + p];
      const bool keeper = vb == P.vblock_begin[p];
      control_update(st, loss, keeper ? P.history + int64_t(p) * P.hyper.max_iters : nullptr, P.hyper, P.bias);
      if (keeper)
        for (int c = 0; c < kStateCols; ++c) P.state[p * kStateCols + c] = st[c];
    }
    const float* ub = P.ubuf + (parity ? C3 : 0);
    const float ccoef = P.cluster_coef[p];
    float G[3] = {0.0f, 0.0f, 0.0f};
    // kUnroll entries per lane at once: their loads are in flight together (a vertex near
    // the sensor has hundreds of entries; one at a time, each waits for two dependent loads)
    constexpr int kUnroll = 4;
    const int e_stop = (skip & 32) ? e_begin : e_end;
    for (int e0 = e_begin + sub; e0 < e_stop; e0 += kUnroll * kLanesPerVertex) {
      int4 r[kUnroll];
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        const int e = e0 + u * kLanesPerVertex;
        r[u] = e < e_stop ? P.ent[e] : make_int4(-1, 0, -1, 0);
      }
      float gv[kUnroll][3];
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        // r.x < 0: invalid tables (validated in Python) or past the end: never read outside
        const float* sg = P.seg_grad + 3 * int64_t(max(r[u].x, 0));
        for (int c = 0; c < 3; ++c) gv[u][c] = r[u].x >= 0 ? sg[c] : 0.0f;
      }
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        if (r[u].x < 0) continue;
        if (r[u].w) {  // summed by atomics: clear for the next iteration
          float* sg = P.seg_grad + 3 * int64_t(r[u].x);
          sg[0] = sg[1] = sg[2] = 0.0f;
        }
        if (kCluster && r[u].z >= 0) {
          const float c = ccoef * __int_as_float(r[u].y);
          for (int k = 0; k < 3; ++k) gv[u][k] -= c * ub[3 * r[u].z + k];
        }
        for (int k = 0; k < 3; ++k) G[k] += gv[u][k];
      }
    }
    for (int c = 0; c < 3; ++c)
      for (int off = kLanesPerVertex / 2; off > 0; off >>= 1) G[c] += __shfl_xor_sync(0xffffffffu, G[c], off);
    __syncthreads();  // stage 3 done
    const bool step = st[kStep] != 0.0, copy = st[kCopyBest] != 0.0;
    if (!step && !copy) return;  // uniform per block
    float* th = P.theta + 3 * int64_t(v);
    if (has_v && copy && sub < 3) P.best[3 * int64_t(v) + sub] = th[sub];
    if (!step) return;  // uniform per block
    if (has_v && sub < 3)
      adam_update(th[sub], P.adam_m[3 * int64_t(v) + sub], P.adam_v[3 * int64_t(v) + sub], G[sub], P.hyper,
                  float(st[kStepSize]), float(st[kBc2Sqrt]));
  }
  if constexpr (kCluster) {
    // this vertex's (updated) parameters to every lane of its group
    const float mine = (has_v && sub < 3) ? P.theta[3 * int64_t(v) + sub] : 0.0f;
    const int g0 = lane & ~(kLanesPerVertex - 1);
    const float t[3] = {__shfl_sync(0xffffffffu, mine, g0), __shfl_sync(0xffffffffu, mine, g0 + 1),
                        __shfl_sync(0xffffffffu, mine, g0 + 2)};
    float* mdst = P.mbuf + ((kInitMeans || parity) ? 0 : C3);  // the means of the next iteration
    const int np = has_v ? min(P.num_pairs[v], e_end - e_begin) : 0;
    const int mine_n = np > sub ? (np - sub + kLanesPerVertex - 1) / kLanesPerVertex : 0;
    const int rounds = (skip & 64) ? 0 : warp_max(mine_n);
    // Summed per block first: a vertex block (32 neighbouring vertices) meets few clusters,
    // while a big cluster's mean receives shares from hundreds of blocks, so one global
    // atomic per (block, cluster) instead of one per (warp, round, cluster) (those cost
    // 2.8 of 24.7 us per iteration at one frame on an H100). A slot taken by another
    // cluster adds to global memory directly.
    sm.mkey[threadIdx.x] = -1;
    for (int c = 0; c < 3; ++c) sm.msum[3 * threadIdx.x + c] = 0.0f;
    __syncthreads();
    float* wscratch = scratch + (threadIdx.x & ~31u);
    for (int r = 0; r < rounds; ++r) {  // warp-uniform trip count: warp_add is collective
      int slot = -1, spill = -1;
      float val[3] = {0.0f, 0.0f, 0.0f};
      if (r < mine_n) {
        const int2 pr = P.pair[e_begin + sub + r * kLanesPerVertex];
        if (unsigned(pr.x) < unsigned(P.num_clusters)) {
          const float a = __int_as_float(pr.y);
          for (int c = 0; c < 3; ++c) val[c] = a * t[c];
          const int s = pr.x % kThreads;
          const int had = atomicCAS(&sm.mkey[s], -1, pr.x);
          if (had == -1 || had == pr.x) slot = s; else spill = pr.x;
        }
      }
      warp_add<float>(sm.msum, slot, 3, 1, val, 1.0f, 3, wscratch);
      warp_add<float>(mdst, spill, 3, 1, val, 1.0f, 3, wscratch);
    }
    __syncthreads();
    if (const int key = sm.mkey[threadIdx.x]; key >= 0)
      for (int c = 0; c < 3; ++c) atomicAdd(mdst + 3 * key + c, sm.msum[3 * threadIdx.x + c]);
  }
}

template <bool kCluster, bool kInitMeans>
__global__ void __launch_bounds__(kThreads) vertex_kernel(const __grid_constant__ KParams P) {
  __shared__ VertexSmem sm;
  pdl_allow_next();
  vertex_body<kCluster, kInitMeans>(P, P.parity, int(blockIdx.x), sm, vertex_entries(P, int(blockIdx.x)));
}

// All iterations in one cooperative launch: every block of a grid that fits on the GPU at
// once walks over the point blocks, the grid waits at a barrier, walks over the vertex
// blocks, and waits again; the barriers take the place of the kernel boundaries of the
// two-kernel iteration (same bodies, same buffers, same order of every write and read).
// This saves the launch and the fill/drain of two kernels per iteration, which dominate at
// one frame (~100k points fill the GPU less than once). The loop ends early once every
// problem has stopped: the state rows are only written before a barrier, so all blocks
// read the same rows after it and leave together.
// Measurement only (FLOXELS_SOLVER_TRACE=1): per block, the time spent in each phase and at
// each barrier, summed over the iterations; block 0 prints the slowest block's phase times
// and its own barrier waits per iteration.
__device__ unsigned long long g_trace[8];

__device__ __forceinline__ unsigned long long now_ns() {
  unsigned long long t;
  asm volatile("mov.u64 %0, %globaltimer;" : "=l"(t));
  return t;
}

template <bool kCluster, bool trace = false>
__global__ void __launch_bounds__(kThreads, 4) loop_kernel(const __grid_constant__ KParams P, int num_iters,
                                                        int point_blocks, int vertex_blocks) {
  __shared__ PointSmem psm;
  __shared__ VertexSmem vsm;
  __shared__ PointCache pcache;
  __shared__ int any_active;
  cg::grid_group grid = cg::this_grid();
  // a block that owns one point block keeps its points' fixed data in shared memory (each
  // thread reads only its own slot: no barrier needed)
  const bool cached = point_blocks <= int(gridDim.x) && int(blockIdx.x) < point_blocks;
  if (cached) pcache.put(load_fixed<kCluster>(P, int(blockIdx.x)));
  __shared__ int2 ventries[kThreads];  // the same for the vertex block it owns, if one
  const bool vcached = vertex_blocks <= int(gridDim.x) && int(blockIdx.x) < vertex_blocks;
  if (vcached) ventries[threadIdx.x] = vertex_entries(P, int(blockIdx.x));
  unsigned long long acc[4] = {0, 0, 0, 0}, t_begin = 0;
  int done = 0;
  if constexpr (trace) {
    if (blockIdx.x == 0 && threadIdx.x < 8) g_trace[threadIdx.x] = 0;
    grid.sync();
    t_begin = now_ns();
  }
  for (int it = 0; it < num_iters; ++it) {
    if (threadIdx.x == 0) {
      int a = 0;
      for (int p = 0; p < P.num_problems; ++p) a |= P.state[p * kStateCols + kActive] != 0.0;
      any_active = a;
    }
    __syncthreads();
    if (!any_active) break;  // uniform over the grid (see above)
    const unsigned long long t0 = trace ? now_ns() : 0;
    const int parity = it & 1;
    clear_other_parity<kCluster>(P, parity);
    // A block that walks several point or vertex blocks reuses its shared memory: the
    // barrier after each body keeps the next one from overwriting what a slower thread of
    // this one still reads (stage 3's state row in the vertex body).
    for (int b = int(blockIdx.x); b < point_blocks; b += int(gridDim.x)) {
      const PointFixed fx = cached ? pcache.get() : load_fixed<kCluster>(P, b);
      points_body<kCluster, trace>(P, parity, b, false, psm, fx);
      __syncthreads();
    }
    const unsigned long long t1 = trace ? now_ns() : 0;
    grid.sync();
    const unsigned long long t2 = trace ? now_ns() : 0;
    for (int b = int(blockIdx.x); b < vertex_blocks; b += int(gridDim.x)) {
      const int2 entries = vcached ? ventries[threadIdx.x] : vertex_entries(P, b);
      vertex_body<kCluster, false, trace>(P, parity, b, vsm, entries);
      __syncthreads();
    }
    const unsigned long long t3 = trace ? now_ns() : 0;
    grid.sync();
    if constexpr (trace) {
      const unsigned long long t4 = now_ns();
      acc[0] += t1 - t0, acc[1] += t2 - t1, acc[2] += t3 - t2, acc[3] += t4 - t3;
      ++done;
    }
  }
  if constexpr (trace) {
    const unsigned long long total = now_ns() - t_begin;
    if (threadIdx.x == 0) {
      atomicMax(&g_trace[0], acc[0]);
      atomicMax(&g_trace[2], acc[2]);
      atomicAdd(&g_trace[4], acc[0]);
      atomicAdd(&g_trace[5], acc[2]);
    }
    grid.sync();
    if (blockIdx.x == 0 && threadIdx.x == 0 && done > 0) {
      const double n = done, nb = gridDim.x;
      printf("FLOXELS_SOLVER_TRACE %d iterations, %d blocks: per iteration %.2f us; points phase %.2f us (slowest "
             "block; mean %.2f), vertex phase %.2f us (slowest; mean %.2f); block 0: points %.2f, barrier %.2f, "
             "vertex %.2f, barrier %.2f us\n",
             done, int(gridDim.x), 1e-3 * total / n, 1e-3 * g_trace[0] / n, 1e-3 * g_trace[4] / n / nb,
             1e-3 * g_trace[2] / n, 1e-3 * g_trace[5] / n / nb, 1e-3 * acc[0] / n, 1e-3 * acc[1] / n,
             1e-3 * acc[2] / n, 1e-3 * acc[3] / n);
    }
  }
}

// Launches `kernel` with kThreads per block and, if given, one launch attribute.
template <typename... Params, typename... Args>
cudaError_t launch_ex(void (*kernel)(Params...), int blocks, cudaStream_t stream, const cudaLaunchAttribute* attr,
                      Args... args) {
  cudaLaunchConfig_t cfg{};
  cfg.gridDim = dim3(unsigned(blocks));
  cfg.blockDim = dim3(kThreads);
  cfg.stream = stream;
  cudaLaunchAttribute a[1];
  if (attr != nullptr) a[0] = *attr;
  cfg.attrs = a;
  cfg.numAttrs = attr != nullptr ? 1 : 0;
  return cudaLaunchKernelEx(&cfg, kernel, args...);
}

// Launch with programmatic stream serialisation (PDL) when `pdl`; see pdl_wait_previous.
cudaError_t launch(void (*kernel)(const KParams), int blocks, cudaStream_t stream, bool pdl, const KParams& P) {
  cudaLaunchAttribute attr{};
  attr.id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attr.val.programmaticStreamSerializationAllowed = 1;
  return launch_ex(kernel, blocks, stream, pdl ? &attr : nullptr, P);
}

// Runtime switches for measurements (read per call; "0" turns a feature off, "1" on).
bool env_flag(const char* name, bool dflt) {
  const char* v = std::getenv(name);
  return v == nullptr ? dflt : !(v[0] == '0' && v[1] == '\0');
}

// Blocks of the persistent loop kernel that can be resident at once, or 0 where it cannot
// be used: a stream being captured into a CUDA graph (a graph replays fixed chunks; the
// two-kernel iteration is the tested path there), or a device without cooperative launch.
int persistent_grid(bool cluster, cudaStream_t stream) {
  cudaStreamCaptureStatus cap = cudaStreamCaptureStatusNone;
  if (cudaStreamIsCapturing(stream, &cap) != cudaSuccess || cap != cudaStreamCaptureStatusNone) return 0;
  int dev = 0;
  if (cudaGetDevice(&dev) != cudaSuccess) return 0;
  // per device and variant; occupancy queries cost microseconds, a launch is ~10 us of work
  static thread_local int cached[64][2] = {};
  if (dev < 0 || dev >= 64) return 0;
  int& c = cached[dev][cluster ? 1 : 0];
  if (c == 0) {
    int coop = 0, sms = 0, per_sm = 0;
    cudaDeviceGetAttribute(&coop, cudaDevAttrCooperativeLaunch, dev);
    cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
    const cudaError_t e = cluster
        ? cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, loop_kernel<true>, kThreads, 0)
        : cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, loop_kernel<false>, kThreads, 0);
    c = (coop && e == cudaSuccess && per_sm > 0) ? sms * per_sm : -1;
    cudaGetLastError();  // a failed query leaves no sticky error behind
  }
  if (c <= 0) return 0;
  // FLOXELS_SOLVER_MAX_GRID caps the grid (tests: every block then walks many point and
  // vertex blocks, as with large batches)
  const char* cap_env = std::getenv("FLOXELS_SOLVER_MAX_GRID");
  const int cap_blocks = cap_env != nullptr ? std::atoi(cap_env) : 0;
  return cap_blocks > 0 ? std::min(c, cap_blocks) : c;
}

int64_t align256(int64_t bytes) { return (bytes + 255) / 256 * 256; }

int64_t blocks_for(int64_t n) { return (n + kThreads - 1) / kThreads; }
// Every problem gets at least one block of each kernel: stage 3 runs in vertex blocks and
// reads the state snapshot a point block takes, also for a problem without points.
int64_t point_blocks_for(int64_t n) { return n > 0 ? blocks_for(n) : 1; }
int64_t vertex_blocks_for(int64_t m) { return m > 0 ? (m + kVerticesPerBlock - 1) / kVerticesPerBlock : 1; }

bool use_cluster(const Args& a) { return a.labels != nullptr && a.num_clusters > 0; }

// Workspace pieces in order; offsets in bytes.
struct Layout {
  int64_t scans, rec, seg_corner, seg_label, seg_wsum, ent, pair, num_pairs, bias, seg_grad, mbuf, ubuf, loss,
      snap, total;
};

Layout layout(const Args& a) {
  const int64_t n = a.num_points, c = a.num_clusters, s = a.num_segments, m = a.num_vertices;
  Layout L{};
  int64_t off = 0;
  auto take = [&](int64_t bytes) {
    const int64_t at = off;
    off += align256(bytes);
    return at;
  };
  L.scans = take(int64_t(sizeof(ScanTable)));
  L.rec = take(16 * n);
  L.seg_corner = take(32 * s);
  L.seg_label = take(4 * s);
  L.seg_wsum = take(32 * s);
  L.ent = take(16 * 8 * s);
  L.pair = take(8 * 8 * s);
  L.num_pairs = take(4 * m);
  L.bias = take(16 * int64_t(a.hyper.max_iters));
  L.seg_grad = take(4 * kSegVals * s);
  L.mbuf = take(2 * 12 * c);
  L.ubuf = take(2 * 12 * c);
  L.loss = take(8 * 2 * kMaxProblems);
  L.snap = take(8 * kStateCols * int64_t(a.num_problems));
  L.total = off;
  return L;
}

// See solver_loop_blocks; pb / vb: point and vertex blocks of the call.
int loop_blocks(int64_t pb, int64_t vb, bool cluster, cudaStream_t stream) {
  const char* mode = std::getenv("FLOXELS_SOLVER_PERSISTENT");
  if (mode != nullptr && mode[0] == '0' && mode[1] == '\0') return 0;
  const bool force = mode != nullptr && mode[0] == '1' && mode[1] == '\0';
  const int grid = persistent_grid(cluster, stream);
  if (grid <= 0 || (!force && pb > grid)) return 0;
  return int(std::min<int64_t>(grid, std::max(pb, vb)));
}

}  // namespace

int solver_loop_blocks(const int64_t* point_ranges, const int64_t* vertex_ranges, int num_problems, bool cluster,
                       cudaStream_t stream) {
  int64_t pb = 0, vb = 0;
  for (int p = 0; p < num_problems; ++p) {
    pb += point_blocks_for(point_ranges[p + 1] - point_ranges[p]);
    vb += vertex_blocks_for(vertex_ranges[p + 1] - vertex_ranges[p]);
  }
  return loop_blocks(pb, vb, cluster, stream);
}

int64_t solver_workspace_bytes(const Args& a) { return layout(a).total; }

cudaError_t solver_launch(const Args& a, int num_iters, void* workspace, cudaStream_t stream) {
  if (a.num_problems < 1 || a.num_problems > kMaxProblems || a.num_dts > kMaxDts || num_iters < 0)
    return cudaErrorInvalidValue;
  if (num_iters == 0) return cudaSuccess;
  if (reinterpret_cast<uintptr_t>(a.corner_w) % 16 != 0) return cudaErrorMisalignedAddress;  // read as float4
  if (a.num_segments >= kSpansBit) return cudaErrorInvalidValue;  // segment ids share their int with a flag
  KParams P{};
  ScanTable T{};
  int pb = 0, vb = 0;
  for (int p = 0; p < a.num_problems; ++p) {
    const Problem& pr = a.problems[p];
    const int64_t n = pr.point_end - pr.point_begin;
    P.block_begin[p] = pb;
    P.vblock_begin[p] = vb;
    pb += int(point_blocks_for(n));
    vb += int(vertex_blocks_for(pr.vertex_end - pr.vertex_begin));
    P.point_begin[p] = int(pr.point_begin);
    P.point_end[p] = int(pr.point_end);
    P.vertex_begin[p] = int(pr.vertex_begin);
    P.vertex_end[p] = int(pr.vertex_end);
    const double inv_n = n > 0 ? 1.0 / double(n) : 0.0;
    P.flow_coef[p] = float(pr.reg_scale * inv_n);
    // the cluster term averages over all points, or over pr.cluster_n (clustered points)
    const double inv_c = pr.cluster_n < 0 ? inv_n : (pr.cluster_n > 0 ? 1.0 / pr.cluster_n : 0.0);
    P.cluster_coef[p] = float(pr.reg_scale * a.hyper.lambda_c * inv_c);
    if (pr.num_support < 0 || pr.num_support > kMaxSupport) return cudaErrorInvalidValue;
    P.num_support[p] = pr.num_support;
    for (int k = 0; k < pr.num_support; ++k) {
      const Support& s = pr.support[k];
      if (s.dt < 0 || s.dt >= a.num_dts) return cudaErrorInvalidValue;
      const DtDesc& d = a.dts[s.dt];
      T.scans[p][k] = Scan{d.data, int(d.nx), int(d.ny), int(d.nz), float(d.ox), float(d.oy), float(d.oz),
                           float(s.t), float(s.weight * inv_n)};
    }
  }
  P.block_begin[a.num_problems] = pb;
  P.vblock_begin[a.num_problems] = vb;
  P.num_problems = a.num_problems;
  const bool cl = use_cluster(a);
  P.num_clusters = cl ? int(a.num_clusters) : 0;
  P.num_vertices = int(a.num_vertices);
  P.num_points = int(a.num_points);
  P.num_segments = int(a.num_segments);
  P.hyper = a.hyper;
  P.points = a.points;
  P.corner_idx = a.corner_idx;
  P.corner_w = a.corner_w;
  P.seg_ptr = a.seg_ptr;
  P.vtx_ptr = a.vtx_ptr;
  P.vtx_entry = a.vtx_entry;
  P.labels = cl ? a.labels : nullptr;
  P.cluster_count = a.cluster_count;
  P.theta = a.theta;
  P.adam_m = a.adam_m;
  P.adam_v = a.adam_v;
  P.best = a.best;
  P.state = a.state;
  P.history = a.history;
  const Layout L = layout(a);
  char* w = static_cast<char*>(workspace);
  Scan* scans = reinterpret_cast<Scan*>(w + L.scans);
  P.scans = scans;
  P.rec = reinterpret_cast<float4*>(w + L.rec);
  P.seg_corner = reinterpret_cast<int32_t*>(w + L.seg_corner);
  P.seg_label = reinterpret_cast<int32_t*>(w + L.seg_label);
  P.seg_wsum = reinterpret_cast<float*>(w + L.seg_wsum);
  P.ent = reinterpret_cast<int4*>(w + L.ent);
  P.pair = reinterpret_cast<int2*>(w + L.pair);
  P.num_pairs = reinterpret_cast<int32_t*>(w + L.num_pairs);
  P.bias = reinterpret_cast<double*>(w + L.bias);
  P.seg_grad = reinterpret_cast<float*>(w + L.seg_grad);
  P.mbuf = reinterpret_cast<float*>(w + L.mbuf);
  P.ubuf = reinterpret_cast<float*>(w + L.ubuf);
  P.loss = reinterpret_cast<double*>(w + L.loss);
  P.snap = reinterpret_cast<double*>(w + L.snap);

  // Points outside every segment (invalid tables) read segment -1: fill the records with
  // ones first. The per-iteration tables start at zero.
  const int64_t S = a.num_segments, M = a.num_vertices;
  cudaError_t err = cudaMemsetAsync(P.rec, 0xff, 16 * a.num_points, stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(w + L.seg_grad, 0, L.snap - L.seg_grad, stream);  // seg_grad .. loss
  if (err == cudaSuccess && M > 0) err = cudaMemsetAsync(P.num_pairs, 0, 4 * M, stream);
  if (err != cudaSuccess) return err;
  scans_setup_kernel<<<1, kThreads, 0, stream>>>(T, scans);
  if (S > 0) {
    segment_setup_kernel<<<unsigned((S * 32 + kThreads - 1) / kThreads), kThreads, 0, stream>>>(P);
    entry_setup_kernel<<<unsigned(blocks_for(8 * S)), kThreads, 0, stream>>>(P);
    if (cl && M > 0) pair_setup_kernel<<<unsigned(blocks_for(M)), kThreads, 0, stream>>>(P);
  }
  bias_kernel<<<unsigned((a.hyper.max_iters + 127) / 128), 128, 0, stream>>>(P);
  if (cl) vertex_kernel<true, true><<<unsigned(vb), kThreads, 0, stream>>>(P);  // the first means
  if (const int grid = loop_blocks(pb, vb, cl, stream); grid > 0) {
    cudaLaunchAttribute coop{};
    coop.id = cudaLaunchAttributeCooperative;
    coop.val.cooperative = 1;
    // FLOXELS_SOLVER_SKIP (with the trace): bit mask of parts left out, to attribute time:
    // 1 DT look-ups, 2 segment sums, 4 cluster u sums, 8 loss reduction, 16 flow gather,
    // 32 vertex gradient gather, 64 next means
    const char* skip_env = std::getenv("FLOXELS_SOLVER_SKIP");
    P.debug_skip = skip_env != nullptr ? std::atoi(skip_env) : 0;
    const bool trace = env_flag("FLOXELS_SOLVER_TRACE", false);  // measurement only: the kernel prints phase times
    auto* kernel = cl ? (trace ? loop_kernel<true, true> : loop_kernel<true>)
                      : (trace ? loop_kernel<false, true> : loop_kernel<false>);
    err = launch_ex(kernel, grid, stream, &coop, P, num_iters, int(pb), int(vb));
    return err == cudaSuccess ? cudaGetLastError() : err;
  }
  const bool pdl = env_flag("FLOXELS_SOLVER_PDL", true);
  for (int it = 0; it < num_iters && err == cudaSuccess; ++it) {
    P.parity = it & 1;
    if (cl) {
      err = launch(points_kernel<true>, pb, stream, pdl, P);
      if (err == cudaSuccess) err = launch(vertex_kernel<true, false>, vb, stream, pdl, P);
    } else {
      err = launch(points_kernel<false>, pb, stream, pdl, P);
      if (err == cudaSuccess) err = launch(vertex_kernel<false, false>, vb, stream, pdl, P);
    }
  }
  return err == cudaSuccess ? cudaGetLastError() : err;
}

}  // namespace floxels::cuda
