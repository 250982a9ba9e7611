// The two bodies of a Floxels iteration on CUDA (design: solver.cu's header), shared by the
// two-kernel iteration (solver_iteration.cu) and the persistent loop (solver_loop.cu):
//   points_body  stages 1-2 of one point block, a thread per point;
//   vertex_body  stage 3 then 4 of one vertex block, a group of 8 lanes per vertex, then the
//                vertices' shares of the next iteration's cluster means.
// Every sum is deterministic (issue 31): fixed-order warp and block sums, per-tile partial
// rows for tile-crossing segments, and fixed-point integer atomics for the cluster sums and
// the loss (cuda/fixed_point.cuh), so the same input gives the same bytes.
// kDebug (profiling builds only, the traced loop): P.debug_skip leaves parts out
// (FLOXELS_SOLVER_SKIP, common/env_switches.h); the results are then wrong. Release builds
// cannot instantiate it. nvcc only.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/fixed_point.cuh"
#include "cuda/solver_device.cuh"
#include "cuda/warp_aggregate.cuh"
#include "kernels/cluster.h"
#include "kernels/dt_loss.h"
#include "kernels/solver.h"

namespace floxels::cuda::solver_detail {

using cuda_detail::warp_add;
namespace fixed = cuda_detail::fixed;

// Stages 1-2 of point block `vb`, a thread per point, from its fixed data `fx` (load_fixed).
// `clear`: also run clear_other_parity (the per-iteration kernel; the persistent loop clears
// once per iteration instead).
template <bool kCluster, bool kDebug = false>
__device__ __forceinline__ void points_body(const KParams& P, int parity, int vb, bool clear, PointSmem& sm,
                                            const PointFixed& fx) {
  static_assert(!kDebug || kProfiling, "the traced variant exists in profiling builds only");
  const int skip = (kProfiling && kDebug) ? P.debug_skip : 0;
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
    sm.usum[threadIdx.x][0] = sm.usum[threadIdx.x][1] = sm.usum[threadIdx.x][2] = 0ull;
  }
  pdl_wait_previous();
  if (clear) clear_other_parity<kCluster>(P, parity);
  const int C3 = 3 * P.num_clusters;
  const double* st = P.state + p * kStateCols;
  if (vb == P.block_begin[p] && threadIdx.x < kStateCols)  // for stage 3 (vertex kernel)
    P.snap[p * kStateCols + threadIdx.x] = st[threadIdx.x];
  // read before the barrier, which hides its latency (no block writes the state row in this phase)
  const bool active = st[kActive] != 0.0;  // uniform per block
  __syncthreads();
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
        const unsigned long long* m = P.mfx + (parity ? C3 : 0) + 3 * label;
        for (int c = 0; c < 3; ++c) mean[c] = fixed::decode(m[c], fixed::kMeanScale);
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
    // one writer per segment), or, where the segment crosses tiles, its tile's partial row
    // (span_part, summed by the vertex stage in tile order).
    if (!(skip & 2)) {
      const WarpRuns runs = warp_runs(seg);
      float* dst = P.seg_grad + int64_t(kSegVals) * seg;  // (seg < 0: never written)
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
            const int slot = runs.start == 0 ? 0 : 1;  // see span_sum
            float* sp = P.span_part + ((int64_t(vb) * kWarps + (threadIdx.x >> 5)) * 2 + slot) * kSegVals + 12 * h;
            for (int j = 0; j < 12; ++j) sp[j] = wg[j];
          }
        }
      }
    }
    // Cluster u sums: per warp run, into the block's slot of the cluster (one atomic per
    // cluster and block below); a slot taken by another cluster (labels of one block more
    // than kThreads apart: not with sorted tables) adds to global memory directly.
    // Each point's u clamped to [-1, 1] (NaN to 0: its loss is NaN anyway), the run sums
    // (fixed order) converted to fixed point, integer atomics after (order-independent).
    if (kCluster && !(skip & 4)) {
      const int key = valid ? label : -1;
      for (int c = 0; c < 3; ++c) u[c] = fixed::clamp_finite(u[c], 1.0f);
      const WarpRuns runs = warp_runs(key);
      warp_run_sums(runs, u);
      if (runs.tail && key >= 0) {
        const int slot = key % kThreads;
        const int had = atomicCAS(&sm.ukey[slot], -1, key);
        unsigned long long q[3];
        for (int c = 0; c < 3; ++c) q[c] = fixed::encode(u[c], fixed::kUnitScale);
        unsigned long long* ub = (had == -1 || had == key) ? sm.usum[slot] : P.ufx + (parity ? C3 : 0) + 3 * key;
        for (int c = 0; c < 3; ++c) atomicAdd(ub + c, q[c]);
      }
    }
  }
  // Loss: per warp (fixed order), then one fixed-point atomic per block (fixed::add_loss). A
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
      unsigned long long* ub = P.ufx + (parity ? C3 : 0) + 3 * key;
      for (int c = 0; c < 3; ++c) atomicAdd(ub + c, sm.usum[threadIdx.x][c]);
    }
  }
  if (threadIdx.x == 0 && !(skip & 8)) {
    double total = 0.0;
    for (int k = 0; k < kWarps; ++k) total += sm.wloss[k];
    const int at = (parity ? kMaxProblems : 0) + p;
    fixed::add_loss(P.loss_fx + at, P.loss_flag + at, total, P.block_begin[p + 1] - P.block_begin[p]);
  }
}

// Stage 3 then 4, a group of 8 lanes per vertex, then the vertex's terms of the next
// iteration's cluster means. kInitMeans: only the means, of the current parameters (once
// per call, before the first iteration). `iter0`, if given: each problem's iteration count
// when the call began, so that iteration `it` of the call is iter0[p] + it for a problem
// still active (the persistent loop; stage 3 then reads Adam's bias pair ahead).
template <bool kCluster, bool kInitMeans, bool kDebug = false>
__device__ __forceinline__ void vertex_body(const KParams& P, int parity, int vb, VertexSmem& sm, int2 entries,
                                            const int* iter0 = nullptr, int it = 0) {
  static_assert(!kDebug || kProfiling, "the traced variant exists in profiling builds only");
  const int skip = (kProfiling && kDebug) ? P.debug_skip : 0;
  double* st = sm.st;
  const int p = problem_of(vb, P.vblock_begin, P.num_problems);
  const int sub = threadIdx.x & (kLanesPerVertex - 1), lane = threadIdx.x & 31;
  const int v = vertex_of(P, p, vb);
  const bool has_v = v < P.vertex_end[p];
  const int e_begin = entries.x, e_end = entries.y;
  pdl_wait_previous();
  const int C3 = 3 * P.num_clusters;
  const bool own = has_v && sub < 3;  // lanes 0-2 of a vertex's group own its x, y, z
  const int64_t pa = 3 * int64_t(v) + sub;
  float th = 0.0f;  // this lane's parameter
  int npairs = 0;   // the vertex's cluster pairs
  if constexpr (!kInitMeans) {
    if constexpr (kCluster) {  // the next means' slots, published by the stage-3 barrier below
      sm.mkey[threadIdx.x] = -1;
      for (int c = 0; c < 3; ++c) sm.msum[3 * threadIdx.x + c] = 0ull;
    }
    if (P.snap[p * kStateCols + kActive] == 0.0) return;  // stopped earlier: nothing changes (uniform)
    if (threadIdx.x == 0) {
      // Stage 3, by every block from the same loss and state snapshot (so all take the same
      // decision; the others gather gradients meanwhile); the problem's first block keeps
      // the record.
      // stage 3's bias pair, read beside the snapshot where the iteration is predicted
      // (control_update checks) rather than after it
      double ahead_it = -1.0, ahead_step = 0.0, ahead_bc2 = 0.0;
      if (iter0 != nullptr) {
        const int t = iter0[p] + it;
        if (t >= 0 && t < P.hyper.max_iters)
          ahead_it = t, ahead_step = P.bias[2 * int64_t(t)], ahead_bc2 = P.bias[2 * int64_t(t) + 1];
      }
      for (int c = 0; c < kStateCols; ++c) st[c] = P.snap[p * kStateCols + c];
      const int at = (parity ? kMaxProblems : 0) + p;
      const double loss = fixed::decode_loss(P.loss_fx[at], P.loss_flag[at]);
      const bool keeper = vb == P.vblock_begin[p];
      control_update(st, loss, keeper ? P.history + int64_t(p) * P.hyper.max_iters : nullptr, P.hyper, P.bias,
                     ahead_it, ahead_step, ahead_bc2);
      if (keeper)
        for (int c = 0; c < kStateCols; ++c) P.state[p * kStateCols + c] = st[c];
    }
    const unsigned long long* uq = P.ufx + (parity ? C3 : 0);
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
        if (r[u].x >= 0 && r[u].w) span_sum(P, r[u].x, gv[u]);  // tables built elsewhere only
      }
#pragma unroll
      for (int u = 0; u < kUnroll; ++u) {
        if (r[u].x < 0) continue;
        for (int k = 0; k < 3; ++k) G[k] += gv[u][k];
      }
    }
    if constexpr (kCluster) {
      // The cluster term, per (vertex, cluster) pair rather than per entry: the entries of one
      // cluster share its u sum U_c, and their coefficients summed are the pair's A_cv
      // (pair_setup_kernel), so sum_e ccoef * a_e * U_c = ccoef * A_cv * U_c: a vertex has one
      // or two clusters but up to hundreds of entries, and each U_c read is a fixed-point
      // decode.
      npairs = has_v ? min(P.num_pairs[v], e_end - e_begin) : 0;
      const int np = (skip & 32) ? 0 : npairs;
      for (int j = sub; j < np; j += kLanesPerVertex) {
        const int2 pr = P.pair[e_begin + j];
        if (unsigned(pr.x) >= unsigned(P.num_clusters)) continue;
        const float c = ccoef * __int_as_float(pr.y);
        for (int k = 0; k < 3; ++k) G[k] -= c * fixed::decode(uq[3 * pr.x + k], fixed::kUnitScale);
      }
    }
    // Adam's row of this lane, read before the barrier: the read overlaps the wait for stage 3
    // instead of following it (a memory round trip on the phase's critical path)
    float am = 0.0f, av = 0.0f;
    if (own) th = P.theta[pa], am = P.adam_m[pa], av = P.adam_v[pa];
    for (int c = 0; c < 3; ++c)
      for (int off = kLanesPerVertex / 2; off > 0; off >>= 1) G[c] += __shfl_xor_sync(0xffffffffu, G[c], off);
    __syncthreads();  // stage 3 done
    const bool step = st[kStep] != 0.0, copy = st[kCopyBest] != 0.0;
    if (!step && !copy) return;  // uniform per block
    if (own && copy) P.best[pa] = th;
    if (!step) return;  // uniform per block
    if (own) {
      adam_update(th, am, av, G[sub], P.hyper, float(st[kStepSize]), float(st[kBc2Sqrt]));
      P.theta[pa] = th, P.adam_m[pa] = am, P.adam_v[pa] = av;
    }
  }
  if constexpr (kCluster) {
    // this vertex's (updated) parameters to every lane of its group
    if constexpr (kInitMeans) {
      if (own) th = P.theta[pa];
      npairs = has_v ? min(P.num_pairs[v], e_end - e_begin) : 0;
    }
    const float mine = th;
    const int g0 = lane & ~(kLanesPerVertex - 1);
    const float t[3] = {__shfl_sync(0xffffffffu, mine, g0), __shfl_sync(0xffffffffu, mine, g0 + 1),
                        __shfl_sync(0xffffffffu, mine, g0 + 2)};
    const int next = (kInitMeans || parity) ? 0 : C3;  // the means of the next iteration
    const int np = npairs;
    const int mine_n = np > sub ? (np - sub + kLanesPerVertex - 1) / kLanesPerVertex : 0;
    const int rounds = (skip & 64) ? 0 : warp_max(mine_n);
    // Summed per block first: a vertex block (32 neighbouring vertices) meets few clusters,
    // while a big cluster's mean receives shares from hundreds of blocks, so one global
    // atomic per (block, cluster) instead of one per (warp, round, cluster) (those cost
    // 2.8 of 24.7 us per iteration at one frame on an H100). A slot taken by another
    // cluster adds to global memory directly. Every share is converted to fixed point first
    // (parameters clamped to +-fixed::kParamLimit), integer sums after: order-independent.
    if constexpr (kInitMeans) {  // (the iteration's path cleared them before stage 3's barrier)
      sm.mkey[threadIdx.x] = -1;
      for (int c = 0; c < 3; ++c) sm.msum[3 * threadIdx.x + c] = 0ull;
      __syncthreads();
    }
    const unsigned wbase = threadIdx.x & ~31u;
    for (int r = 0; r < rounds; ++r) {  // warp-uniform trip count: warp_add is collective
      int slot = -1, spill = -1;
      float val[3] = {0.0f, 0.0f, 0.0f};
      if (r < mine_n) {
        const int2 pr = P.pair[e_begin + sub + r * kLanesPerVertex];
        if (unsigned(pr.x) < unsigned(P.num_clusters)) {
          const float a = __int_as_float(pr.y);
          for (int c = 0; c < 3; ++c)
            val[c] = fixed::clamp_finite(a * fixed::clamp_finite(t[c], fixed::kParamLimit), fixed::kParamLimit);
          const int s = pr.x % kThreads;
          const int had = atomicCAS(&sm.mkey[s], -1, pr.x);
          if (had == -1 || had == pr.x) slot = s; else spill = pr.x;
        }
      }
      unsigned long long q[3];
      for (int c = 0; c < 3; ++c) q[c] = fixed::encode(val[c], fixed::kMeanScale);
      warp_add<unsigned long long>(sm.msum, slot, 3, 1, q, 1ull, 3, sm.scratch + wbase);
      warp_add<unsigned long long>(P.mfx + next, spill, 3, 1, q, 1ull, 3, sm.scratch + wbase);
    }
    __syncthreads();
    if (const int key = sm.mkey[threadIdx.x]; key >= 0)
      for (int c = 0; c < 3; ++c) atomicAdd(P.mfx + next + 3 * key + c, sm.msum[3 * threadIdx.x + c]);
  }
}

}  // namespace floxels::cuda::solver_detail
