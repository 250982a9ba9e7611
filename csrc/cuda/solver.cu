// CUDA implementation of the device-resident Floxels optimiser (stages in kernels/solver.h).
//
// One iteration = two kernels:
//   points   per point: flow f_i from its 8 vertices, multi-scan DT loss + gradient, flow
//            norm, residual to the cluster mean and its unit vector u_i (stages 1-2); per
//            block, the sums of w_k * g_i per segment and of u_i per cluster, and the loss
//            (one atomic into the problem's total);
//   vertices stage 3 (loss, early stopping: every block takes the same decision from the
//            problem's loss and a state snapshot, so no block waits for another), best copy, gradient = sum over the vertex's (segment, corner)
//            entries minus the cluster-mean term, Adam (stage 4); then the vertex's share of
//            the next iteration's cluster means.
// Cluster means need no pass over the points: m_c = (1/|c|) sum_{i in c} sum_k w_ik theta_{v_ik}
// is a fixed linear combination of vertex parameters (sum over the vertices v of c's points
// of A_cv theta_v, A_cv = weight of c's points at v / |c|). So the vertex kernel, right after
// its Adam step, adds A_cv theta_v into the next iteration's means, and the point kernel
// reads finished means instead of waiting for every point's flow: that is what makes one
// point kernel per iteration possible.
// Sums over points use sorted order: points are sorted by (cluster, voxel), so a block's
// points form runs of equal segment and label, which block_runs sums in a fixed order and
// stores with one plain write (or one atomic for runs that continue in another block). The
// means and the u sums alternate between two buffers by iteration parity (a kernel
// parameter): a point kernel reads one and clears the other, which the next kernel fills.
// Nothing synchronises with the host, so any number of iterations can be captured into a
// CUDA graph.
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>

#include "cuda/block_reduce.cuh"
#include "cuda/solver_launch.h"
#include "cuda/warp_aggregate.cuh"
#include "kernels/cluster.h"
#include "kernels/dt_loss.h"
#include "kernels/solver.h"

namespace floxels::cuda {
namespace {

using namespace floxels::solver;
using cuda_detail::block_sum;
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
                        //      cluster, 1 if the segment spans two point blocks (its row is summed
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

// Programmatic dependent launch (sm_90; off unless FLOXELS_SOLVER_PDL=1: measured slower
// here): a kernel lets the next one in the stream start early, and the next one reads
// nothing the previous kernel writes before wait. Without the launch attribute both are no-ops.
__device__ __forceinline__ void pdl_allow_next() { asm volatile("griddepcontrol.launch_dependents;" ::: "memory"); }
__device__ __forceinline__ void pdl_wait_previous() { asm volatile("griddepcontrol.wait;" ::: "memory"); }

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

// Sums K values per run of equal keys over the block's threads in thread order (a key's
// threads must be consecutive, as sorted points make them; key < 0 adds nothing) and calls
// emit(key, j, sum) once per run and column j < K. The summation order is fixed, so the
// result is deterministic. Each warp sums its 32 rows per run; a run that continues into
// later warps is completed by the warp where it starts, from the partials those warps left
// in `carry`. Every thread of the block must call it. Shared memory: rows (kThreads x
// row stride floats), keys (kThreads), carry (kWarps x K).
template <int K>
constexpr int row_stride() {
  return K % 2 == 0 ? K + 1 : K;  // odd: row writes and column reads are free of bank conflicts
}

template <int K, typename Emit>
__device__ __forceinline__ void block_runs(int key, const float* vals, float* rows, int* keys, float* carry,
                                           Emit emit) {
  constexpr int R = row_stride<K>();
  const int t = threadIdx.x, lane = t & 31, w = t >> 5;
  keys[t] = key;
  if (key >= 0)
    for (int j = 0; j < K; ++j) rows[t * R + j] = vals[j];
  __syncthreads();
  float pending = 0.0f;
  int pending_key = -1;
  if (lane < K) {
    const int r0 = 32 * w;
    const bool cont = w > 0 && keys[r0] >= 0 && keys[r0] == keys[r0 - 1];  // first run began in warp w - 1
    float acc = 0.0f;
    bool first = true;
    for (int r = r0; r < r0 + 32; ++r) {
      const int k = keys[r];
      if (k >= 0) acc += rows[r * R + lane];
      const bool last_row = r == r0 + 31;
      if (last_row || keys[r + 1] != k) {
        if (k >= 0) {
          if (first && cont) {
            carry[w * K + lane] = acc;  // completed by the warp where the run starts
          } else if (last_row && w + 1 < kWarps && keys[r + 1] == k) {
            pending = acc;  // continues in the next warps
            pending_key = k;
          } else {
            emit(k, lane, acc);
          }
        }
        acc = 0.0f;
        first = false;
      }
    }
  }
  __syncthreads();
  if (pending_key >= 0) {
    for (int w2 = w + 1; w2 < kWarps && keys[32 * w2] == pending_key; ++w2) {
      pending += carry[w2 * K + lane];
      if (keys[32 * w2 + 31] != pending_key) break;  // the run ends inside warp w2
    }
    emit(pending_key, lane, pending);
  }
  __syncthreads();  // rows, keys and carry are free again
}

// Per call, a warp per segment: corner rows, label, weight sums (fixed lane order, so
// deterministic) and the point records of its points.
__global__ void __launch_bounds__(kThreads) segment_setup_kernel(const __grid_constant__ KParams P) {
  const int s = int((int64_t(blockIdx.x) * kThreads + threadIdx.x) >> 5), lane = threadIdx.x & 31;
  if (s >= P.num_segments) return;
  const int b = max(P.seg_ptr[s], 0), e = min(P.seg_ptr[s + 1], P.num_points);
  float w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  for (int i = b + lane; i < e; i += 32) {
    P.rec[i] = make_float4(P.points[3 * int64_t(i)], P.points[3 * int64_t(i) + 1], P.points[3 * int64_t(i) + 2],
                           __int_as_float(s));
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

// Whether segment s spans two point blocks of its problem (then its row is summed by atomics).
__device__ bool segment_spans_blocks(const KParams& P, int s) {
  const int b = P.seg_ptr[s], e = P.seg_ptr[s + 1];
  int p = 0;
  while (p + 1 < P.num_problems && b >= P.point_end[p]) ++p;
  const int first = P.point_begin[p] + (b - P.point_begin[p]) / kThreads * kThreads;
  return b < P.point_begin[p] || e > first + kThreads;
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
                  segment_spans_blocks(P, s) ? 1 : 0);
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
  float rows[kThreads * row_stride<kSegVals>()];
  int keys[kThreads];
  float carry[kWarps * kSegVals];
};
struct VertexSmem {
  float scratch[kThreads];
  double st[kStateCols];
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
template <bool kCluster, bool kDebug = false>
__device__ __forceinline__ void points_body(const KParams& P, int parity, int vb, bool clear, PointSmem& sm) {
  const int skip = kDebug ? P.debug_skip : 0;
  float* rows = sm.rows;
  int* keys = sm.keys;
  float* carry = sm.carry;
  // Fixed per-call data first (overlaps the previous kernel's tail under PDL).
  const int p = problem_of(vb, P.block_begin, P.num_problems);
  const int first = block_first_point(P, p, vb);
  const int i = first + int(threadIdx.x);
  int seg = -1;
  float4 pt = make_float4(0.0f, 0.0f, 0.0f, 0.0f);
  float w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  if (i < P.point_end[p]) {
    pt = P.rec[i];
    const int s = __float_as_int(pt.w);
    seg = unsigned(s) < unsigned(P.num_segments) ? s : -1;
    const float4* wp = reinterpret_cast<const float4*>(P.corner_w + 8 * int64_t(i));
    const float4 w0 = wp[0], w1 = wp[1];
    w[0] = w0.x, w[1] = w0.y, w[2] = w0.z, w[3] = w0.w, w[4] = w1.x, w[5] = w1.y, w[6] = w1.z, w[7] = w1.w;
  }
  const bool valid = seg >= 0;
  int idx[8] = {-1, -1, -1, -1, -1, -1, -1, -1};
  int label = -1;
  if (valid) {
    const int4* cp = reinterpret_cast<const int4*>(P.seg_corner + 8 * int64_t(seg));
    const int4 c0 = cp[0], c1 = cp[1];
    idx[0] = c0.x, idx[1] = c0.y, idx[2] = c0.z, idx[3] = c0.w, idx[4] = c1.x, idx[5] = c1.y, idx[6] = c1.z,
    idx[7] = c1.w;
    if constexpr (kCluster) label = P.seg_label[seg];
  }
  pdl_wait_previous();
  if (clear) clear_other_parity<kCluster>(P, parity);
  const int C3 = 3 * P.num_clusters;
  const double* st = P.state + p * kStateCols;
  if (vb == P.block_begin[p] && threadIdx.x < kStateCols)  // for stage 3 (vertex kernel)
    P.snap[p * kStateCols + threadIdx.x] = st[threadIdx.x];
  float loss = 0.0f;
  if (st[kActive] != 0.0) {  // uniform per block
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
                                                   P.hyper.inv_dt_cell, P.hyper.truncation, g);
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
    // Segment sums of w_k * g_i: one writer per segment, unless it spans two blocks.
    float wg[kSegVals];
    for (int k = 0; k < 8; ++k)
      for (int c = 0; c < 3; ++c) wg[3 * k + c] = w[k] * g[c];
    if (!(skip & 2)) block_runs<kSegVals>(seg, wg, rows, keys, carry, [&](int s, int j, float sum) {
      float* dst = P.seg_grad + int64_t(kSegVals) * s + j;
      if (P.seg_ptr[s] >= first && P.seg_ptr[s + 1] <= first + kThreads)
        *dst = sum;
      else
        atomicAdd(dst, sum);  // cleared by its readers (entry flag)
    });
    if (kCluster && !(skip & 4)) {
      float* ub = P.ubuf + (parity ? C3 : 0);
      block_runs<3>(valid ? label : -1, u, rows, keys, carry,
                    [&](int l, int j, float sum) { atomicAdd(ub + 3 * l + j, sum); });
    }
  }
  // One double atomic per block: the sum order varies between runs (last bits of the loss),
  // like the float atomics of the other sums; a per-block table re-read by every vertex
  // block cost more than the whole vertex gradient with 16 problems.
  if (skip & 8) return;
  const double total = block_sum<kThreads>(double(loss));
  if (threadIdx.x == 0 && total != 0.0) atomicAdd(P.loss + (parity ? kMaxProblems : 0) + p, total);
}

template <bool kCluster>
__global__ void __launch_bounds__(kThreads) points_kernel(const __grid_constant__ KParams P) {
  __shared__ PointSmem sm;
  pdl_allow_next();
  points_body<kCluster>(P, P.parity, int(blockIdx.x), true, sm);
}

// Stage 3 then 4, a group of 8 lanes per vertex, then the vertex's terms of the next
// iteration's cluster means. kInitMeans: only the means, of the current parameters (once
// per call, before the first iteration).
template <bool kCluster, bool kInitMeans, bool kDebug = false>
__device__ __forceinline__ void vertex_body(const KParams& P, int parity, int vb, VertexSmem& sm) {
  const int skip = kDebug ? P.debug_skip : 0;
  float* scratch = sm.scratch;
  double* st = sm.st;
  const int p = problem_of(vb, P.vblock_begin, P.num_problems);
  const int sub = threadIdx.x & (kLanesPerVertex - 1), lane = threadIdx.x & 31;
  const int v = P.vertex_begin[p] + (vb - P.vblock_begin[p]) * kVerticesPerBlock +
                int(threadIdx.x / kLanesPerVertex);
  const bool has_v = v < P.vertex_end[p];
  int e_begin = 0, e_end = 0;
  if (has_v) {
    e_begin = max(P.vtx_ptr[v], 0);
    e_end = min(P.vtx_ptr[v + 1], 8 * P.num_segments);
  }
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
    for (int e = e_begin + sub; e < ((skip & 32) ? e_begin : e_end); e += kLanesPerVertex) {
      const int4 r = P.ent[e];
      if (r.x < 0) continue;  // invalid tables (validated in Python): never read outside
      float* sg = P.seg_grad + 3 * int64_t(r.x);
      float gx = sg[0], gy = sg[1], gz = sg[2];
      if (r.w) sg[0] = sg[1] = sg[2] = 0.0f;  // summed by atomics: clear for the next iteration
      if (kCluster && r.z >= 0) {
        const float c = ccoef * __int_as_float(r.y);
        gx -= c * ub[3 * r.z];
        gy -= c * ub[3 * r.z + 1];
        gz -= c * ub[3 * r.z + 2];
      }
      G[0] += gx;
      G[1] += gy;
      G[2] += gz;
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
    for (int r = 0; r < rounds; ++r) {  // warp-uniform trip count: warp_add is collective
      int key = -1;
      float val[3] = {0.0f, 0.0f, 0.0f};
      if (r < mine_n) {
        const int2 pr = P.pair[e_begin + sub + r * kLanesPerVertex];
        if (unsigned(pr.x) < unsigned(P.num_clusters)) {
          key = pr.x;
          const float a = __int_as_float(pr.y);
          for (int c = 0; c < 3; ++c) val[c] = a * t[c];
        }
      }
      warp_add<float>(mdst, key, 3, 1, val, 1.0f, 3, scratch + (threadIdx.x & ~31u));
    }
  }
}

template <bool kCluster, bool kInitMeans>
__global__ void __launch_bounds__(kThreads) vertex_kernel(const __grid_constant__ KParams P) {
  __shared__ VertexSmem sm;
  pdl_allow_next();
  vertex_body<kCluster, kInitMeans>(P, P.parity, int(blockIdx.x), sm);
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
  __shared__ int any_active;
  cg::grid_group grid = cg::this_grid();
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
      points_body<kCluster, trace>(P, parity, b, false, psm);
      __syncthreads();
    }
    const unsigned long long t1 = trace ? now_ns() : 0;
    grid.sync();
    const unsigned long long t2 = trace ? now_ns() : 0;
    for (int b = int(blockIdx.x); b < vertex_blocks; b += int(gridDim.x)) {
      vertex_body<kCluster, false, trace>(P, parity, b, vsm);
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
    P.cluster_coef[p] = float(pr.reg_scale * a.hyper.lambda_c * inv_n);
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
  const bool pdl = env_flag("FLOXELS_SOLVER_PDL", false);
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
