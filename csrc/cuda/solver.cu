// CUDA implementation of the device-resident Floxels optimiser (stages in kernels/solver.h).
//
// One iteration = four kernels: points (flow, DT loss, flow norm, cluster sums), cluster
// residuals, control (one block: losses, early stopping, Adam bias corrections) and
// vertices (best copy, gradient from the vertex's (point, corner) entries, Adam). The
// vertex gradient is a gather over a CSR list built once per frame, so no atomics touch
// the parameters; only the per-cluster sums use warp-aggregated atomics. Everything a
// kernel needs from the host is in the kernel parameters or in device memory, and
// nothing synchronises, so any number of iterations can be captured into a CUDA graph.
#include <cuda_runtime.h>

#include <cstdint>

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
constexpr int kVerticesPerBlock = kThreads / 32;  // stage 4: a warp per vertex
// Stage 1/2 cluster sums go through a per-block shared-memory table when the clusters fit:
// each block then issues one global atomic per cluster it touched instead of one per warp
// (big clusters made thousands of warps hit the same three addresses).
constexpr int kSmemClusters = 2048;

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
  int num_entries;  // 8 * number of points
  Hyper hyper;
  const float* points;
  const int32_t* corner_idx;
  const float* corner_w;
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
  float* f;     // (N, 3) flow of the iteration (cluster stage)
  float* g;     // (N, 3) d loss / d f_i
  float* csum;  // (C, 3) sums of f per cluster
  float* usum;  // (C, 3) sums of the unit residuals per cluster
  double* part_points;   // per point block: DT + flow-norm loss
  double* part_cluster;  // per point block: cluster loss
};

__device__ __forceinline__ int problem_of(int block, const int* begins, int num_problems) {
  int p = 0;
  while (p + 1 < num_problems && block >= begins[p + 1]) ++p;
  return p;
}

__device__ __forceinline__ void zero_strided(float* a, int64_t n) {
  for (int64_t j = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; j < n; j += int64_t(gridDim.x) * blockDim.x)
    a[j] = 0.0f;
}


// Adds v (3 values) to table[key] (global, (C, 3)), for every thread of the block (key < 0:
// nothing). With C <= kSmemClusters the block first sums into shared memory; otherwise
// warp-aggregated global atomics. Must be called by every thread of the block.
__device__ void cluster_accumulate(float* table, int64_t key, const float* v, int num_clusters, float* smem,
                                   float* scratch) {
  if (num_clusters <= kSmemClusters) {
    for (int j = threadIdx.x; j < 3 * num_clusters; j += blockDim.x) smem[j] = 0.0f;
    __syncthreads();
    warp_add<float>(smem, key, 3, 1, v, 1.0f, 3, scratch + (threadIdx.x & ~31u));
    __syncthreads();
    for (int j = threadIdx.x; j < 3 * num_clusters; j += blockDim.x)
      if (smem[j] != 0.0f) atomicAdd(table + j, smem[j]);
  } else {
    warp_add<float>(table, key, 3, 1, v, 1.0f, 3, scratch + (threadIdx.x & ~31u));
  }
}

// Stage 1. Also clears the u sums of the previous iteration (nothing reads them now).
template <bool kCluster>
__global__ void __launch_bounds__(kThreads) points_kernel(const __grid_constant__ KParams P) {
  __shared__ float scratch[kThreads];
  __shared__ float smem_table[kCluster ? 3 * kSmemClusters : 1];
  if constexpr (kCluster) zero_strided(P.usum, 3 * int64_t(P.num_clusters));
  const int p = problem_of(blockIdx.x, P.block_begin, P.num_problems);
  const double* st = P.state + p * kStateCols;
  if (st[kActive] == 0.0) return;  // uniform per block; this block's partials are not read
  const int i = P.point_begin[p] + (int(blockIdx.x) - P.block_begin[p]) * kThreads + int(threadIdx.x);
  const bool valid = i < P.point_end[p];
  float f[3] = {0.0f, 0.0f, 0.0f};
  float loss = 0.0f;
  if (valid) {
    const int32_t* idx = P.corner_idx + 8 * int64_t(i);
    const float* w = P.corner_w + 8 * int64_t(i);
    for (int j = 0; j < 8; ++j) {
      if (unsigned(idx[j]) >= unsigned(P.num_vertices)) continue;  // validated in Python; never read outside
      const float* row = P.theta + 3 * int64_t(idx[j]);
      for (int c = 0; c < 3; ++c) f[c] += w[j] * row[c];
    }
    const float* pi = P.points + 3 * int64_t(i);
    float g[3];
    loss = dt_loss::point_loss<true, float, int>(P.scans[p], P.num_support[p], pi[0], pi[1], pi[2], f[0], f[1],
                                                 f[2], P.hyper.inv_dt_cell, P.hyper.truncation, g);
    const float lam = float(lambda_g(P.hyper, st[kIter])) * P.flow_coef[p];
    float unit[3];
    loss += lam * norm_and_unit(f, unit);
    float* gi = P.g + 3 * int64_t(i);
    for (int c = 0; c < 3; ++c) gi[c] = g[c] + lam * unit[c];
    if constexpr (kCluster)
      for (int c = 0; c < 3; ++c) P.f[3 * int64_t(i) + c] = f[c];
  }
  if constexpr (kCluster) {
    const int64_t key = valid && unsigned(P.labels[i]) < unsigned(P.num_clusters) ? int64_t(P.labels[i]) : -1;
    cluster_accumulate(P.csum, key, f, P.num_clusters, smem_table, scratch);
  }
  const double total = block_sum<kThreads>(double(loss));
  if (threadIdx.x == 0) P.part_points[blockIdx.x] = total;
}

// Stage 2: residual to the cluster mean; adds cluster_coef * u_i to the point's gradient
// (stage 4 subtracts cluster_coef * mean(u) of the cluster).
__global__ void __launch_bounds__(kThreads) cluster_kernel(const __grid_constant__ KParams P) {
  __shared__ float scratch[kThreads];
  __shared__ float smem_table[3 * kSmemClusters];
  const int p = problem_of(blockIdx.x, P.block_begin, P.num_problems);
  if (P.state[p * kStateCols + kActive] == 0.0) return;
  const int i = P.point_begin[p] + (int(blockIdx.x) - P.block_begin[p]) * kThreads + int(threadIdx.x);
  const bool valid = i < P.point_end[p];
  const int64_t l = valid && unsigned(P.labels[i]) < unsigned(P.num_clusters) ? int64_t(P.labels[i]) : -1;
  float u[3] = {0.0f, 0.0f, 0.0f};
  float loss = 0.0f;
  if (l >= 0) {
    const float inv = 1.0f / P.cluster_count[l];
    const float mean[3] = {P.csum[3 * l] * inv, P.csum[3 * l + 1] * inv, P.csum[3 * l + 2] * inv};
    const float coef = P.cluster_coef[p];
    loss = coef * cluster::residual_unit<float>(P.f + 3 * int64_t(i), mean, 3, u);
    float* gi = P.g + 3 * int64_t(i);
    for (int c = 0; c < 3; ++c) gi[c] += coef * u[c];
  }
  cluster_accumulate(P.usum, l, u, P.num_clusters, smem_table, scratch);
  const double total = block_sum<kThreads>(double(loss));
  if (threadIdx.x == 0) P.part_cluster[blockIdx.x] = total;
}

// Stage 3: one warp per problem sums its blocks' partials in a fixed order.
template <bool kCluster>
__global__ void control_kernel(const __grid_constant__ KParams P) {
  const int p = threadIdx.x >> 5, lane = threadIdx.x & 31;
  if (p >= P.num_problems) return;
  double* st = P.state + p * kStateCols;
  if (st[kActive] == 0.0) {
    if (lane == 0) control_update(st, 0.0, P.history + int64_t(p) * P.hyper.max_iters, P.hyper);
    return;
  }
  double s = 0.0;
  for (int b = P.block_begin[p] + lane; b < P.block_begin[p + 1]; b += 32)
    s += P.part_points[b] + (kCluster ? P.part_cluster[b] : 0.0);
  for (int off = 16; off > 0; off >>= 1) s += __shfl_down_sync(0xffffffffu, s, off);
  if (lane == 0) control_update(st, s, P.history + int64_t(p) * P.hyper.max_iters, P.hyper);
}

// Stage 4, one warp per vertex: vertices near the sensor gather thousands of (point,
// corner) entries, so the lanes split the entry list and combine with shuffles. Also
// clears the cluster sums of f for the next iteration.
template <bool kCluster>
__global__ void __launch_bounds__(kThreads) vertex_kernel(const __grid_constant__ KParams P) {
  if constexpr (kCluster) zero_strided(P.csum, 3 * int64_t(P.num_clusters));
  const int p = problem_of(blockIdx.x, P.vblock_begin, P.num_problems);
  const double* st = P.state + p * kStateCols;
  const bool step = st[kStep] != 0.0, copy = st[kCopyBest] != 0.0;
  if (!step && !copy) return;
  const int lane = threadIdx.x & 31;
  const int v = P.vertex_begin[p] + (int(blockIdx.x) - P.vblock_begin[p]) * kVerticesPerBlock + int(threadIdx.x >> 5);
  if (v >= P.vertex_end[p]) return;  // uniform per warp
  float* th = P.theta + 3 * int64_t(v);
  if (copy && lane < 3) P.best[3 * int64_t(v) + lane] = th[lane];
  if (!step) return;
  float G[3] = {0.0f, 0.0f, 0.0f};
  const float ccoef = P.cluster_coef[p];
  const int e_end = min(P.vtx_ptr[v + 1], P.num_entries);
  for (int e = max(P.vtx_ptr[v], 0) + lane; e < e_end; e += 32) {
    const int ent = P.vtx_entry[e];
    if (unsigned(ent) >= unsigned(P.num_entries)) continue;  // validated in Python; never read outside
    const int i = ent >> 3;
    const float w = P.corner_w[ent];
    const float* gi = P.g + 3 * int64_t(i);
    float gx = gi[0], gy = gi[1], gz = gi[2];
    if constexpr (kCluster) {
      const int l = P.labels[i];
      if (unsigned(l) < unsigned(P.num_clusters)) {
        const float s = ccoef / P.cluster_count[l];
        gx -= s * P.usum[3 * l];
        gy -= s * P.usum[3 * l + 1];
        gz -= s * P.usum[3 * l + 2];
      }
    }
    G[0] += w * gx;
    G[1] += w * gy;
    G[2] += w * gz;
  }
  for (int c = 0; c < 3; ++c)
    for (int off = 16; off > 0; off >>= 1) G[c] += __shfl_xor_sync(0xffffffffu, G[c], off);
  if (lane < 3) {
    const float step_size = float(st[kStepSize]), bc2 = float(st[kBc2Sqrt]);
    adam_update(th[lane], P.adam_m[3 * int64_t(v) + lane], P.adam_v[3 * int64_t(v) + lane], G[lane], P.hyper,
                step_size, bc2);
  }
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

}  // namespace

int64_t solver_workspace_bytes(const Args& a) {
  const int64_t n = a.num_points, c = a.num_clusters, blocks = total_point_blocks(a);
  return 2 * align256(3 * n * 4) + 2 * align256(3 * c * 4) + 2 * align256(blocks * 8);
}

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
  P.num_entries = int(8 * a.num_points);
  P.hyper = a.hyper;
  P.points = a.points;
  P.corner_idx = a.corner_idx;
  P.corner_w = a.corner_w;
  P.vtx_ptr = a.vtx_ptr;
  P.vtx_entry = a.vtx_entry;
  P.labels = a.labels;
  P.cluster_count = a.cluster_count;
  P.theta = a.theta;
  P.adam_m = a.adam_m;
  P.adam_v = a.adam_v;
  P.best = a.best;
  P.state = a.state;
  P.history = a.history;
  char* w = static_cast<char*>(workspace);
  const int64_t n = a.num_points, c = a.num_clusters;
  P.f = reinterpret_cast<float*>(w);
  w += align256(3 * n * 4);
  P.g = reinterpret_cast<float*>(w);
  w += align256(3 * n * 4);
  P.csum = reinterpret_cast<float*>(w);
  w += align256(3 * c * 4);
  P.usum = reinterpret_cast<float*>(w);
  w += align256(3 * c * 4);
  P.part_points = reinterpret_cast<double*>(w);
  w += align256(int64_t(pb) * 8);
  P.part_cluster = reinterpret_cast<double*>(w);

  if (cl) {
    const cudaError_t err = cudaMemsetAsync(P.csum, 0, 3 * c * sizeof(float), stream);
    if (err != cudaSuccess) return err;
  }
  const int control_threads = 32 * a.num_problems;
  for (int it = 0; it < num_iters; ++it) {
    if (pb > 0) {
      if (cl) {
        points_kernel<true><<<pb, kThreads, 0, stream>>>(P);
        cluster_kernel<<<pb, kThreads, 0, stream>>>(P);
      } else {
        points_kernel<false><<<pb, kThreads, 0, stream>>>(P);
      }
    }
    if (cl)
      control_kernel<true><<<1, control_threads, 0, stream>>>(P);
    else
      control_kernel<false><<<1, control_threads, 0, stream>>>(P);
    if (vb > 0) {
      if (cl)
        vertex_kernel<true><<<vb, kThreads, 0, stream>>>(P);
      else
        vertex_kernel<false><<<vb, kThreads, 0, stream>>>(P);
    }
    const cudaError_t err = cudaGetLastError();
    if (err != cudaSuccess) return err;
  }
  return cudaSuccess;
}

}  // namespace floxels::cuda
