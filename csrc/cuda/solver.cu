// CUDA implementation of the device-resident Floxels optimiser (stages in kernels/solver.h).
//
// One iteration = three kernels:
//   points   flow, DT loss, flow norm, cluster sums of f;
//   cluster  residual to the cluster mean and cluster sums of u, then each warp folds its
//            points' corner-weighted gradients into their segment's 8x3 table (segments:
//            kernels/solver_args.h); the last block to finish runs stage 3 (losses, early
//            stopping, Adam's bias corrections) for every problem;
//   vertices best copy, gradient = sum over the vertex's (segment, corner) entries, Adam.
// Segments give every vertex a small fixed fan-in (at most 8 cells times the labels in
// them), so the vertices near the sensor, which thousands of points touch, cost the same
// as any other. Cluster sums go through a per-block shared table over the block's label
// range (points are sorted by label, so a block sees a handful of clusters) and one global
// atomic per (block, cluster). Nothing synchronises with the host, so any number of
// iterations can be captured into a CUDA graph.
#include <cuda_runtime.h>

#include <climits>
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

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kLanesPerVertex = 8;  // stage 4: a group of 8 lanes per vertex
constexpr int kVerticesPerBlock = kThreads / kLanesPerVertex;
constexpr int kSegVals = 24;      // 8 corners x 3 components per segment
constexpr int kSmemClusters = 512;  // label range a block sums in shared memory

struct KParams {
  Scan scans[kMaxProblems][kMaxSupport];
  int num_support[kMaxProblems];
  int block_begin[kMaxProblems + 1];   // point blocks of each problem
  int vblock_begin[kMaxProblems + 1];  // vertex blocks of each problem
  int point_begin[kMaxProblems], point_end[kMaxProblems];
  int vertex_begin[kMaxProblems], vertex_end[kMaxProblems];
  float flow_coef[kMaxProblems];     // reg_scale / n: multiplies lambda_g(it) * ||f_i||
  float cluster_coef[kMaxProblems];  // reg_scale * lambda_c / n
  int num_problems;
  int num_clusters;
  int num_vertices;
  int num_points;
  int num_segments;
  bool smem_tables;  // cluster sums through per-block shared tables (else warp atomics)
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
  // workspace
  float* f;          // (N, 3) flow of the iteration (cluster stage)
  float* g;          // (N, 3) d loss / d f_i without the cluster-mean term
  float* csum;       // (C, 3) sums of f per cluster
  float* usum;       // (C, 3) sums of the unit residuals per cluster
  float* seg_grad;   // (S, 24) sum over the segment's points of w_k * g_i
  float* seg_wsum;   // (S, 8) sum over the segment's points of w_k (fixed)
  int32_t* seg_label;  // (S) cluster of the segment's points (fixed)
  int32_t* point_seg;  // (N) segment of each point (fixed)
  double* part_points;   // per point block: DT + flow-norm loss
  double* part_cluster;  // per point block: cluster loss
  unsigned* done;        // blocks of the cluster kernel finished this iteration
};

// Programmatic dependent launch (sm_90): a kernel lets the next one in the stream start
// once all its blocks run (launch_dependents), and the next one reads nothing the previous
// kernel writes before wait, which returns once that kernel has finished and its writes
// are visible. This hides the launch gap and each kernel's fixed-data loads behind the
// tail of the previous kernel. Without the launch attribute both are no-ops.
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

// Per call: each segment's label, weight sums and points' segment ids (a warp per segment,
// fixed lane order, so deterministic).
__global__ void __launch_bounds__(kThreads) segment_setup_kernel(const __grid_constant__ KParams P) {
  const int s = int((int64_t(blockIdx.x) * kThreads + threadIdx.x) >> 5), lane = threadIdx.x & 31;
  if (s >= P.num_segments) return;
  const int b = max(P.seg_ptr[s], 0), e = min(P.seg_ptr[s + 1], P.num_points);
  float w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  for (int i = b + lane; i < e; i += 32) {
    P.point_seg[i] = s;
    for (int k = 0; k < 8; ++k) w[k] += P.corner_w[8 * int64_t(i) + k];
  }
  for (int k = 0; k < 8; ++k)
    for (int off = 16; off > 0; off >>= 1) w[k] += __shfl_xor_sync(0xffffffffu, w[k], off);
  if (lane < 8) P.seg_wsum[8 * int64_t(s) + lane] = w[lane];
  if (lane == 0) {
    const int l = (P.labels != nullptr && b < e) ? P.labels[b] : -1;
    P.seg_label[s] = unsigned(l) < unsigned(P.num_clusters) ? l : -1;
  }
}

// Adds v (3 values) to table[key] (global, (C, 3)) for every thread of the block (key < 0:
// nothing). Labels are sorted, so the block's keys span a short range [lo, hi]: when it
// fits, the block sums in shared memory first and issues one atomic per (cluster,
// component); otherwise warp-aggregated global atomics. Every thread must call it.
__device__ void cluster_accumulate(float* table, int key, const float* v, float* smem, float* scratch,
                                   bool smem_tables) {
  if (!smem_tables) {  // warp-aggregated global atomics (one per warp and cluster)
    warp_add<float>(table, key, 3, 1, v, 1.0f, 3, scratch + (threadIdx.x & ~31u));
    return;
  }
  __shared__ int range[2];
  if (threadIdx.x == 0) {
    range[0] = INT_MAX;
    range[1] = -1;
  }
  __syncthreads();
  if (key >= 0) {
    atomicMin(range, key);
    atomicMax(range + 1, key);
  }
  __syncthreads();
  const int lo = range[0], hi = range[1];
  if (hi < lo) return;  // no labelled point in the block (uniform)
  const int width = hi - lo + 1;
  if (width <= kSmemClusters) {
    for (int j = threadIdx.x; j < 3 * width; j += blockDim.x) smem[j] = 0.0f;
    __syncthreads();
    warp_add<float>(smem, key >= 0 ? key - lo : -1, 3, 1, v, 1.0f, 3, scratch + (threadIdx.x & ~31u));
    __syncthreads();
    for (int j = threadIdx.x; j < 3 * width; j += blockDim.x)
      if (smem[j] != 0.0f) atomicAdd(table + 3 * int64_t(lo) + j, smem[j]);
  } else {
    warp_add<float>(table, key, 3, 1, v, 1.0f, 3, scratch + (threadIdx.x & ~31u));
  }
  __syncthreads();  // the caller may reuse smem / range
}

// Stage 1. Also clears the segment tables and the u sums of the previous iteration
// (stage 4 has read them).
template <bool kCluster>
__global__ void __launch_bounds__(kThreads) points_kernel(const __grid_constant__ KParams P) {
  __shared__ float scratch[kThreads];
  __shared__ float smem_table[kCluster ? 3 * kSmemClusters : 1];
  pdl_allow_next();
  // Fixed per-frame data first (overlaps the previous kernel's tail under PDL).
  const int p = problem_of(blockIdx.x, P.block_begin, P.num_problems);
  const int i = P.point_begin[p] + (int(blockIdx.x) - P.block_begin[p]) * kThreads + int(threadIdx.x);
  const bool valid = i < P.point_end[p];
  int32_t idx[8];
  float w[8], px = 0.0f, py = 0.0f, pz = 0.0f;
  int key = -1;
  if (valid) {
    for (int j = 0; j < 8; ++j) {
      idx[j] = P.corner_idx[8 * int64_t(i) + j];
      w[j] = P.corner_w[8 * int64_t(i) + j];
    }
    px = P.points[3 * int64_t(i)];
    py = P.points[3 * int64_t(i) + 1];
    pz = P.points[3 * int64_t(i) + 2];
    if constexpr (kCluster) key = unsigned(P.labels[i]) < unsigned(P.num_clusters) ? P.labels[i] : -1;
  }
  pdl_wait_previous();
  zero_strided(P.seg_grad, int64_t(kSegVals) * P.num_segments);
  if constexpr (kCluster) zero_strided(P.usum, 3 * int64_t(P.num_clusters));
  const double* st = P.state + p * kStateCols;
  if (st[kActive] == 0.0) return;  // uniform per block; this block's partials are not read
  float f[3] = {0.0f, 0.0f, 0.0f};
  float loss = 0.0f;
  if (valid) {
    for (int j = 0; j < 8; ++j) {
      if (unsigned(idx[j]) >= unsigned(P.num_vertices)) continue;  // validated in Python; never read outside
      const float* row = P.theta + 3 * int64_t(idx[j]);
      for (int c = 0; c < 3; ++c) f[c] += w[j] * row[c];
    }
    float g[3];
    loss = dt_loss::point_loss<true, float, int>(P.scans[p], P.num_support[p], px, py, pz, f[0], f[1], f[2],
                                                 P.hyper.inv_dt_cell, P.hyper.truncation, g);
    const float lam = float(lambda_g(P.hyper, st[kIter])) * P.flow_coef[p];
    float unit[3];
    loss += lam * norm_and_unit(f, unit);
    float* gi = P.g + 3 * int64_t(i);
    for (int c = 0; c < 3; ++c) gi[c] = g[c] + lam * unit[c];
    if constexpr (kCluster)
      for (int c = 0; c < 3; ++c) P.f[3 * int64_t(i) + c] = f[c];
  }
  if constexpr (kCluster) {
    cluster_accumulate(P.csum, key, f, smem_table, scratch, P.smem_tables);
  }
  const double total = block_sum<kThreads>(double(loss));
  if (threadIdx.x == 0) P.part_points[blockIdx.x] = total;
}

// Each warp adds w_k * g_i of its points to their segments' (S, 24) rows: the values go
// through shared memory transposed, and lane j < 24 walks the 32 points summing component
// j of each run of equal segment ids, with one atomic per run. Runs are long (a segment is
// one cluster inside one cell), so this is a handful of atomics per warp.
__device__ void segment_accumulate(const KParams& P, int seg, const float* w, const float* g,
                                   float (*buf)[kSegVals + 1], int* segs) {
  const int lane = threadIdx.x & 31;
  if (seg >= 0)
    for (int k = 0; k < 8; ++k)
      for (int c = 0; c < 3; ++c) buf[lane][3 * k + c] = w[k] * g[c];
  segs[lane] = seg;
  __syncwarp();
  // Common case: the whole warp lies in one segment (long segments near the sensor):
  // an unrolled, branch-free column sum and one atomic per value.
  if (__all_sync(0xffffffffu, seg == segs[0]) && seg >= 0) {
    if (lane < kSegVals) {
      float acc = 0.0f;
#pragma unroll
      for (int r = 0; r < 32; ++r) acc += buf[r][lane];
      atomicAdd(P.seg_grad + int64_t(kSegVals) * seg + lane, acc);
    }
    __syncwarp();
    return;
  }
  if (lane < kSegVals) {
    float acc = 0.0f;
    for (int r = 0; r < 32; ++r) {
      const int s = segs[r];
      if (s >= 0) acc += buf[r][lane];
      if (r == 31 || segs[r + 1] != s) {
        if (s >= 0) atomicAdd(P.seg_grad + int64_t(kSegVals) * s + lane, acc);
        acc = 0.0f;
      }
    }
  }
  __syncwarp();
}

// Stage 3 for every problem, by the last block of the cluster kernel: a warp per problem
// sums its blocks' partials in a fixed order.
template <bool kCluster>
__device__ void control_all(const KParams& P) {
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  for (int p = warp; p < P.num_problems; p += kWarps) {
    double* st = P.state + p * kStateCols;
    double* hist = P.history + int64_t(p) * P.hyper.max_iters;
    if (st[kActive] == 0.0) {
      if (lane == 0) control_update(st, 0.0, hist, P.hyper);
      continue;
    }
    // Unrolled so that several partials are in flight per lane (this runs on the
    // critical path of every iteration); the summation order stays fixed.
    double s = 0.0;
#pragma unroll 8
    for (int b = P.block_begin[p] + lane; b < P.block_begin[p + 1]; b += 32)
      s += __ldcg(P.part_points + b) + (kCluster ? __ldcg(P.part_cluster + b) : 0.0);
    for (int off = 16; off > 0; off >>= 1) s += __shfl_down_sync(0xffffffffu, s, off);
    if (lane == 0) control_update(st, s, hist, P.hyper);
  }
}

// Stage 2 (+ stage 3 in the last block). Adds cluster_coef * u_i to the point's gradient;
// stage 4 subtracts cluster_coef * mean(u) of the cluster through the segment weight sums.
template <bool kCluster>
__global__ void __launch_bounds__(kThreads) cluster_kernel(const __grid_constant__ KParams P) {
  __shared__ float scratch[kThreads];
  __shared__ float smem_table[kCluster ? 3 * kSmemClusters : 1];
  __shared__ float seg_buf[kWarps][32][kSegVals + 1];
  __shared__ int seg_ids[kWarps][32];
  __shared__ bool is_last;
  pdl_allow_next();
  const int p = problem_of(blockIdx.x, P.block_begin, P.num_problems);
  const int i = P.point_begin[p] + (int(blockIdx.x) - P.block_begin[p]) * kThreads + int(threadIdx.x);
  const bool valid = i < P.point_end[p];
  // Fixed data first (overlaps the previous kernel under PDL), then, after the wait,
  // every read that depends on stage 1 before the first barrier so their latencies overlap.
  float w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int seg = -1, l = -1;
  if (valid) {
    for (int k = 0; k < 8; ++k) w[k] = P.corner_w[8 * int64_t(i) + k];
    seg = unsigned(P.point_seg[i]) < unsigned(P.num_segments) ? P.point_seg[i] : -1;
    if constexpr (kCluster) l = unsigned(P.labels[i]) < unsigned(P.num_clusters) ? P.labels[i] : -1;
  }
  pdl_wait_previous();
  if (P.state[p * kStateCols + kActive] != 0.0) {  // uniform per block
    float g[3] = {0.0f, 0.0f, 0.0f};
    if (valid)
      for (int c = 0; c < 3; ++c) g[c] = P.g[3 * int64_t(i) + c];
    float loss = 0.0f;
    if constexpr (kCluster) {
      float u[3] = {0.0f, 0.0f, 0.0f};
      if (l >= 0) {
        const float inv = 1.0f / P.cluster_count[l];
        const float mean[3] = {P.csum[3 * l] * inv, P.csum[3 * l + 1] * inv, P.csum[3 * l + 2] * inv};
        const float coef = P.cluster_coef[p];
        loss = coef * cluster::residual_unit<float>(P.f + 3 * int64_t(i), mean, 3, u);
        for (int c = 0; c < 3; ++c) g[c] += coef * u[c];
      }
      cluster_accumulate(P.usum, l, u, smem_table, scratch, P.smem_tables);
    }
    segment_accumulate(P, seg, w, g, seg_buf[threadIdx.x >> 5], seg_ids[threadIdx.x >> 5]);
    const double total = block_sum<kThreads>(double(loss));
    if (threadIdx.x == 0) P.part_cluster[blockIdx.x] = total;
  }
  // Last block: every partial of this iteration is written (threadfence before the ticket).
  if (threadIdx.x == 0) {
    __threadfence();
    is_last = atomicAdd(P.done, 1u) == gridDim.x - 1;
  }
  __syncthreads();
  if (!is_last) return;
  __threadfence();
  control_all<kCluster>(P);
  if (threadIdx.x == 0) *P.done = 0u;
}

// Stage 4, a group of 8 lanes per vertex. Also clears the cluster sums of f for the next
// iteration (stage 2 has read them).
template <bool kCluster>
__global__ void __launch_bounds__(kThreads) vertex_kernel(const __grid_constant__ KParams P) {
  pdl_allow_next();
  pdl_wait_previous();
  if constexpr (kCluster) zero_strided(P.csum, 3 * int64_t(P.num_clusters));
  const int p = problem_of(blockIdx.x, P.vblock_begin, P.num_problems);
  const double* st = P.state + p * kStateCols;
  const bool step = st[kStep] != 0.0, copy = st[kCopyBest] != 0.0;
  if (!step && !copy) return;  // uniform per block
  const int sub = threadIdx.x & (kLanesPerVertex - 1);
  const int v = P.vertex_begin[p] + (int(blockIdx.x) - P.vblock_begin[p]) * kVerticesPerBlock +
                int(threadIdx.x / kLanesPerVertex);
  const bool has_v = v < P.vertex_end[p];
  float* th = P.theta + 3 * int64_t(v);
  if (has_v && copy && sub < 3) P.best[3 * int64_t(v) + sub] = th[sub];
  if (!step) return;  // uniform per block
  float G[3] = {0.0f, 0.0f, 0.0f};
  if (has_v) {
    const float ccoef = P.cluster_coef[p];
    const int e_end = min(P.vtx_ptr[v + 1], 8 * P.num_segments);
    for (int e = max(P.vtx_ptr[v], 0) + sub; e < e_end; e += kLanesPerVertex) {
      const int ent = P.vtx_entry[e];
      const int s = ent >> 3, k = ent & 7;
      if (unsigned(s) >= unsigned(P.num_segments)) continue;  // validated in Python; never read outside
      const float* sg = P.seg_grad + int64_t(kSegVals) * s + 3 * k;
      float gx = sg[0], gy = sg[1], gz = sg[2];
      if constexpr (kCluster) {
        const int l = P.seg_label[s];
        if (l >= 0) {
          const float c = ccoef * P.seg_wsum[8 * int64_t(s) + k] / P.cluster_count[l];
          gx -= c * P.usum[3 * l];
          gy -= c * P.usum[3 * l + 1];
          gz -= c * P.usum[3 * l + 2];
        }
      }
      G[0] += gx;
      G[1] += gy;
      G[2] += gz;
    }
  }
  for (int c = 0; c < 3; ++c)
    for (int off = kLanesPerVertex / 2; off > 0; off >>= 1) G[c] += __shfl_xor_sync(0xffffffffu, G[c], off);
  if (has_v && sub < 3) {
    const float step_size = float(st[kStepSize]), bc2 = float(st[kBc2Sqrt]);
    adam_update(th[sub], P.adam_m[3 * int64_t(v) + sub], P.adam_v[3 * int64_t(v) + sub], G[sub], P.hyper,
                step_size, bc2);
  }
}

// Launch with programmatic stream serialisation (PDL) when `pdl`; see pdl_wait_previous.
cudaError_t launch(void (*kernel)(const KParams), int blocks, cudaStream_t stream, bool pdl, const KParams& P) {
  cudaLaunchConfig_t cfg{};
  cfg.gridDim = dim3(unsigned(blocks));
  cfg.blockDim = dim3(kThreads);
  cfg.stream = stream;
  cudaLaunchAttribute attr[1];
  attr[0].id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attr[0].val.programmaticStreamSerializationAllowed = 1;
  cfg.attrs = attr;
  cfg.numAttrs = pdl ? 1 : 0;
  return cudaLaunchKernelEx(&cfg, kernel, P);
}

// Runtime switches for measurements (read per call; "0" turns a feature off).
bool env_flag(const char* name, bool dflt) {
  const char* v = std::getenv(name);
  return v == nullptr ? dflt : !(v[0] == '0' && v[1] == '\0');
}

int64_t align256(int64_t bytes) { return (bytes + 255) / 256 * 256; }

int64_t blocks_for(int64_t n) { return (n + kThreads - 1) / kThreads; }
int64_t vertex_blocks_for(int64_t m) { return (m + kVerticesPerBlock - 1) / kVerticesPerBlock; }

int64_t total_point_blocks(const Args& a) {
  int64_t b = 0;
  for (int p = 0; p < a.num_problems; ++p) b += blocks_for(a.problems[p].point_end - a.problems[p].point_begin);
  return b;
}

bool use_cluster(const Args& a) { return a.labels != nullptr && a.num_clusters > 0; }

// Workspace pieces in order; sizes in bytes.
struct Layout {
  int64_t f, g, csum, usum, seg_grad, seg_wsum, seg_label, point_seg, part_points, part_cluster, done, total;
};

Layout layout(const Args& a) {
  const int64_t n = a.num_points, c = a.num_clusters, s = a.num_segments;
  const int64_t blocks = total_point_blocks(a) > 0 ? total_point_blocks(a) : 1;  // the cluster kernel runs >= 1
  Layout L{};
  int64_t off = 0;
  auto take = [&](int64_t bytes) {
    const int64_t at = off;
    off += align256(bytes);
    return at;
  };
  L.f = take(3 * n * 4);
  L.g = take(3 * n * 4);
  L.csum = take(3 * c * 4);
  L.usum = take(3 * c * 4);
  L.seg_grad = take(kSegVals * s * 4);
  L.seg_wsum = take(8 * s * 4);
  L.seg_label = take(s * 4);
  L.point_seg = take(n * 4);
  L.part_points = take(blocks * 8);
  L.part_cluster = take(blocks * 8);
  L.done = take(4);
  L.total = off;
  return L;
}

}  // namespace

int64_t solver_workspace_bytes(const Args& a) { return layout(a).total; }

cudaError_t solver_launch(const Args& a, int num_iters, void* workspace, cudaStream_t stream) {
  if (a.num_problems < 1 || a.num_problems > kMaxProblems || a.num_dts > kMaxDts || num_iters < 0)
    return cudaErrorInvalidValue;
  if (num_iters == 0) return cudaSuccess;
  KParams P{};
  int pb = 0, vb = 0;
  for (int p = 0; p < a.num_problems; ++p) {
    const Problem& pr = a.problems[p];
    const int64_t n = pr.point_end - pr.point_begin;
    P.block_begin[p] = pb;
    P.vblock_begin[p] = vb;
    pb += int(blocks_for(n));
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
      P.scans[p][k] = Scan{d.data, int(d.nx), int(d.ny), int(d.nz), float(d.ox), float(d.oy), float(d.oz),
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
  P.smem_tables = env_flag("FLOXELS_SOLVER_SMEM_TABLES", true);
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
  P.f = reinterpret_cast<float*>(w + L.f);
  P.g = reinterpret_cast<float*>(w + L.g);
  P.csum = reinterpret_cast<float*>(w + L.csum);
  P.usum = reinterpret_cast<float*>(w + L.usum);
  P.seg_grad = reinterpret_cast<float*>(w + L.seg_grad);
  P.seg_wsum = reinterpret_cast<float*>(w + L.seg_wsum);
  P.seg_label = reinterpret_cast<int32_t*>(w + L.seg_label);
  P.point_seg = reinterpret_cast<int32_t*>(w + L.point_seg);
  P.part_points = reinterpret_cast<double*>(w + L.part_points);
  P.part_cluster = reinterpret_cast<double*>(w + L.part_cluster);
  P.done = reinterpret_cast<unsigned*>(w + L.done);

  // Points outside every segment (invalid tables) read segment -1: fill with -1 first.
  cudaError_t err = cudaMemsetAsync(P.point_seg, 0xff, a.num_points * sizeof(int32_t), stream);
  if (err == cudaSuccess && cl) err = cudaMemsetAsync(P.csum, 0, 3 * a.num_clusters * sizeof(float), stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(P.done, 0, sizeof(unsigned), stream);
  if (err != cudaSuccess) return err;
  if (a.num_segments > 0)
    segment_setup_kernel<<<unsigned((a.num_segments * 32 + kThreads - 1) / kThreads), kThreads, 0, stream>>>(P);
  // The cluster kernel always runs: it folds gradients into segments and its last block
  // runs stage 3, so it needs at least one block even without points.
  const int cb = pb > 0 ? pb : 1;
  const bool pdl = env_flag("FLOXELS_SOLVER_PDL", true);
  for (int it = 0; it < num_iters && err == cudaSuccess; ++it) {
    if (cl) {
      if (pb > 0) err = launch(points_kernel<true>, pb, stream, pdl, P);
      if (err == cudaSuccess) err = launch(cluster_kernel<true>, cb, stream, pdl, P);
      if (err == cudaSuccess && vb > 0) err = launch(vertex_kernel<true>, vb, stream, pdl, P);
    } else {
      if (pb > 0) err = launch(points_kernel<false>, pb, stream, pdl, P);
      if (err == cudaSuccess) err = launch(cluster_kernel<false>, cb, stream, pdl, P);
      if (err == cudaSuccess && vb > 0) err = launch(vertex_kernel<false>, vb, stream, pdl, P);
    }
  }
  return err == cudaSuccess ? cudaGetLastError() : err;
}

}  // namespace floxels::cuda
