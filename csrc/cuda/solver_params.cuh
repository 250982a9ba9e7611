// Types and constants shared by the CUDA solver's translation units (csrc/cuda/solver*.cu):
// the kernel parameter block KParams, launch geometry, the launch helper, and the host
// functions each kernel file provides to the launcher (solver.cu). nvcc only.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "common/env_switches.h"
#include "kernels/dt_loss.h"
#include "kernels/solver.h"

namespace floxels::cuda::solver_detail {

using namespace floxels::solver;
using Scan = dt_loss::Scan<float, int>;
using env::kProfiling;

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
  int debug_skip;  // profiling builds, traced loop only (FLOXELS_SOLVER_SKIP): parts left out;
                   // always 0 otherwise (kept so that both builds pass the same block)
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
                        //      cluster, 1 if the segment spans two point tiles (its tiles' partial
                        //      rows are in span_part)
  int2* pair;           // (8S) per vertex, its clusters and summed coefficients A_cv (bits)
  int32_t* num_pairs;   // (M)
  double* bias;         // (max_iters, 2) Adam bias corrections (bias_corrections)
  // workspace, per iteration
  float* seg_grad;  // (S, 24) sum over the segment's points of w_k * g_i
  // Cluster means, unit-residual sums and losses, by parity, as fixed-point integers summed
  // by integer atomics in any order (cuda/fixed_point.cuh): deterministic.
  unsigned long long* mfx;      // (2, C, 3) cluster means
  unsigned long long* ufx;      // (2, C, 3) sums of the unit residuals per cluster
  unsigned long long* loss_fx;  // (2, kMaxProblems) each problem's loss (sum of its point blocks')
  int* loss_flag;               // (2, kMaxProblems) fixed::kLossNaN / kLossOver, or 0
  // (point tiles, 2, 24): the partial row sums of segments that span
  // point tiles (tables built elsewhere), per tile: slot 0 the run that holds the tile's
  // first point, slot 1 the run that holds its last; the vertex stage adds a segment's
  // partials tile by tile (fixed order) instead of float atomics.
  float* span_part;
  double* snap;     // (B, kStateCols) state rows as the point kernel saw them
};

// Points are summed per warp: a segment's sums are complete in one warp when its points lie
// in one tile of 32 points (tiles start at the problem's first point), which the segment
// tables built in Python guarantee (they split segments at tile boundaries). A segment that
// crosses a tile anyway (tables built elsewhere) is flagged in its point records (kSpansBit of
// the segment id) and vertex entries: its tiles' partial rows go to span_part, added by the
// vertex stage in tile order (span_sum).
constexpr int kTile = 32;
constexpr int kSpansBit = 1 << 30;
constexpr int kSegMask = kSpansBit - 1;

inline int64_t blocks_for(int64_t n) { return (n + kThreads - 1) / kThreads; }
// Every problem gets at least one block of each kernel: stage 3 runs in vertex blocks and
// reads the state snapshot a point block takes, also for a problem without points.
inline int64_t point_blocks_for(int64_t n) { return n > 0 ? blocks_for(n) : 1; }
inline int64_t vertex_blocks_for(int64_t m) { return m > 0 ? (m + kVerticesPerBlock - 1) / kVerticesPerBlock : 1; }

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

// --- What each kernel file provides to the launcher (solver.cu) ------------------------------
// Each kernel file launches its own kernels (templates are instantiated where they are
// launched; no relocatable device code). Errors of the <<<>>> launches are left for the
// launcher's final cudaGetLastError, as before the split.

// solver_setup.cu: the per-call setup kernels (support scans to `scans`, segment records,
// vertex entries, cluster pairs, Adam bias table), in that order. S, M: segments, vertices.
void launch_setup(const KParams& P, const ScanTable& T, Scan* scans, int64_t S, int64_t M, bool cluster,
                  cudaStream_t stream);

// solver_iteration.cu: the first cluster means (vertex kernel, means only; vb vertex blocks),
// once per call before the first iteration.
void launch_first_means(const KParams& P, int vb, cudaStream_t stream);
// solver_iteration.cu: `num_iters` iterations of two kernels (pb point blocks, vb vertex
// blocks), with programmatic dependent launch when `pdl`; P.parity is set per iteration.
cudaError_t launch_iterations(KParams P, int num_iters, int pb, int vb, bool cluster, bool pdl,
                              cudaStream_t stream);

// solver_loop.cu: blocks of the persistent loop kernel that can be resident at once on the
// current device (cached per device and variant), or 0 where it cannot be used (a stream
// being captured into a CUDA graph, no cooperative launch, a failed query).
int loop_capacity(bool cluster, cudaStream_t stream);
// solver_loop.cu: all `num_iters` iterations in one cooperative launch of `grid` blocks.
// `trace` (profiling builds only; must be false otherwise): the traced variant, which prints
// per-phase times and honours P.debug_skip.
cudaError_t launch_loop(const KParams& P, int grid, int num_iters, int pb, int vb, bool cluster, bool trace,
                        cudaStream_t stream);

}  // namespace floxels::cuda::solver_detail
