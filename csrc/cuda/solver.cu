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
// Determinism (issue 31): every sum is order-independent, so the same input
// gives the same bytes run after run, in either launch mode, and whatever else is batched
// with a problem (tiles, blocks and their partial sums are relative to the problem's first
// point): warp and block partials in fixed order; segment rows with one writer (a segment
// that crosses tiles: per-tile partial rows added by the vertex stage in tile order); the
// cluster means, u sums and losses, which receive shares from many blocks, as fixed-point
// 64-bit integers (cuda/fixed_point.cuh: scales, ranges, overflow guards). Float atomics
// there (before issue 31) were 1.6 % faster per frame and 2.4 % on sequences on an H200
// (bench/RESULTS.md, "Determinism"): under the 3 % that would have kept them as an option.
//
// Files (no relocatable device code: each kernel file launches its own kernels):
//   solver.cu            this launcher: workspace layout, the kernel parameters, the choice
//                        between the persistent loop and the two-kernel iteration, the
//                        runtime switches (common/env_switches.h);
//   solver_params.cuh    KParams, launch geometry, launch_ex, the kernel files' entry points;
//   solver_device.cuh    device helpers (PDL, warp run sums, shared-memory layouts, fixed data);
//   solver_bodies.cuh    points_body and vertex_body, the two halves of an iteration;
//   solver_setup.cu      per-call setup kernels;
//   solver_iteration.cu  points_kernel + vertex_kernel (two kernels per iteration);
//   solver_loop.cu       loop_kernel (all iterations in one cooperative launch; the traced
//                        variant in FLOXELS_PROFILING builds only).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "common/env_switches.h"
#include "cuda/solver_launch.h"
#include "cuda/solver_params.cuh"

namespace floxels::cuda {
namespace {

using namespace solver_detail;

int64_t align256(int64_t bytes) { return (bytes + 255) / 256 * 256; }

bool use_cluster(const Args& a) { return a.labels != nullptr && a.num_clusters > 0; }

// Workspace pieces in order; offsets in bytes.
struct Layout {
  int64_t scans, rec, seg_corner, seg_label, seg_wsum, ent, pair, num_pairs, bias, span_part, seg_grad, mbuf, ubuf,
      loss, loss_flag, snap, total;
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
  int64_t tiles = 0;  // point tiles of the call (kWarps per point block)
  for (int p = 0; p < a.num_problems; ++p)
    tiles += kWarps * point_blocks_for(a.problems[p].point_end - a.problems[p].point_begin);
  L.span_part = take(4 * 2 * kSegVals * tiles);  // written before read: not cleared
  L.seg_grad = take(4 * kSegVals * s);
  L.mbuf = take(2 * 24 * c);  // (2, C, 3) 8-byte fixed point
  L.ubuf = take(2 * 24 * c);
  L.loss = take(8 * 2 * kMaxProblems);
  L.loss_flag = take(4 * 2 * kMaxProblems);
  L.snap = take(8 * kStateCols * int64_t(a.num_problems));
  L.total = off;
  return L;
}

// Blocks of the persistent loop kernel that can be resident at once, capped by
// FLOXELS_SOLVER_MAX_GRID (tests: every block then walks many point and vertex blocks, as
// with large batches), or 0 where the loop cannot be used (see loop_capacity).
int persistent_grid(bool cluster, cudaStream_t stream) {
  const int c = loop_capacity(cluster, stream);
  if (c <= 0) return 0;
  const int cap_blocks = env::solver_max_grid();
  return cap_blocks > 0 ? std::min(c, cap_blocks) : c;
}

// See solver_loop_blocks; pb / vb: point and vertex blocks of the call.
int loop_blocks(int64_t pb, int64_t vb, bool cluster, cudaStream_t stream) {
  const env::Persistent mode = env::solver_persistent();
  if (mode == env::Persistent::kOff) return 0;
  const bool force = mode == env::Persistent::kOn;
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
  P.mfx = reinterpret_cast<unsigned long long*>(w + L.mbuf);
  P.ufx = reinterpret_cast<unsigned long long*>(w + L.ubuf);
  P.loss_fx = reinterpret_cast<unsigned long long*>(w + L.loss);
  P.loss_flag = reinterpret_cast<int*>(w + L.loss_flag);
  P.span_part = reinterpret_cast<float*>(w + L.span_part);
  P.snap = reinterpret_cast<double*>(w + L.snap);

  // Points outside every segment (invalid tables) read segment -1: fill the records with
  // ones first. The per-iteration tables start at zero.
  const int64_t S = a.num_segments, M = a.num_vertices;
  cudaError_t err = cudaMemsetAsync(P.rec, 0xff, 16 * a.num_points, stream);
  if (err == cudaSuccess) err = cudaMemsetAsync(w + L.seg_grad, 0, L.snap - L.seg_grad, stream);  // seg_grad .. loss_flag
  if (err == cudaSuccess && M > 0) err = cudaMemsetAsync(P.num_pairs, 0, 4 * M, stream);
  if (err != cudaSuccess) return err;
  launch_setup(P, T, scans, S, M, cl, stream);
  if (cl) launch_first_means(P, vb, stream);
  if (const int grid = loop_blocks(pb, vb, cl, stream); grid > 0) {
    // Profiling builds only (constant false / 0 otherwise): the traced loop kernel, which
    // prints phase times, and FLOXELS_SOLVER_SKIP's parts left out (common/env_switches.h).
    const bool trace = env::solver_trace();
    P.debug_skip = env::solver_skip();
    err = launch_loop(P, grid, num_iters, pb, vb, cl, trace, stream);
    return err == cudaSuccess ? cudaGetLastError() : err;
  }
  err = launch_iterations(P, num_iters, pb, vb, cl, env::solver_pdl(), stream);
  return err == cudaSuccess ? cudaGetLastError() : err;
}

}  // namespace floxels::cuda
