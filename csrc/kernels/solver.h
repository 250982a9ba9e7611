// The Floxels optimiser as a device-resident loop: math and data layout shared by the CPU
// (cpu/solver_cpu.cpp) and CUDA (cuda/solver.cu) implementations of floxels::solver_run.
//
// Several independent problems (target frames) are optimised at once; their points,
// compact flow-grid vertices and clusters are concatenated. One iteration is four stages:
//   1. per point: flow f_i from its 8 compact vertices, multi-scan DT loss + gradient,
//      flow-norm term + gradient, cluster sums of f (for the cluster means);
//   2. per point: cluster-consistency residual ||f_i - mean_c||, its unit vector u_i and
//      the cluster sums of u (the gradient is c * (u_i - mean_c(u)));
//   3. per problem: the iteration's loss (deterministic sum of per-chunk partials), loss
//      history, lowest-loss tracking and early stopping (EarlyStopping in Python);
//   4. per vertex: copy to the best table if this iteration's loss is the lowest so far,
//      gradient = sum over the vertex's (segment, corner) entries of the segment's
//      corner-weighted gradient sum (segments: solver_args.h), Adam update.
// All state (iteration counters, best losses, flags) lives in a small float64 table, so
// iterations never need the host: the CUDA version enqueues a chunk of iterations per call
// (two kernels each, see cuda/solver.cu), which can also be captured into a CUDA graph.
#pragma once
#include <cmath>
#include <cstdint>

#include "common/cuda_compat.h"

namespace floxels::solver {

constexpr int kMaxProblems = 16;  // problems per call (metadata travels in kernel parameters)
constexpr int kMaxSupport = 12;   // support scans per problem (13-scan windows)
constexpr int kMaxDts = 32;       // distinct distance transforms per call
constexpr int kMaxMilestones = 4; // learning-rate milestones (FloxelsConfig.lr_milestones)

// Columns of the (B, kStateCols) float64 state table, one row per problem.
enum StateCol : int {
  kActive = 0,     // 1 while the problem still iterates
  kIter = 1,       // iterations recorded so far (= index of the next loss)
  kBestLoss = 2,   // lowest loss seen
  kRefLoss = 3,    // early stopping's reference (last loss that improved by min_delta)
  kStale = 4,      // iterations since kRefLoss improved
  kBestIter = 5,   // iteration of kBestLoss
  kStep = 6,       // stage 4 of this iteration applies an Adam step
  kCopyBest = 7,   // stage 4 of this iteration copies the parameters to the best table
  kStepSize = 8,   // lr / (1 - beta1^t) of this iteration's step
  kBc2Sqrt = 9,    // sqrt(1 - beta2^t)
  kStateCols = 10
};

// Hyperparameters shared by every problem of a call.
struct Hyper {
  float lr, beta1, beta2, eps;
  float lambda_c;                      // cluster weight before the per-problem scale
  float lambda_g_start, lambda_g_end;  // flow-norm weight schedule
  int lambda_g_decay_iters;
  int patience, max_iters;
  double min_delta;
  float truncation, inv_dt_cell;
  // Readings of the paper (FloxelsConfig, "faithfulness readings"): the DT value a truncated
  // sample counts as (0, or the truncation itself = clamped), and a step learning-rate
  // schedule: lr * lr_gamma^(number of milestones m <= it) at (0-based) iteration it.
  float trunc_above = 0.0f;
  float lr_gamma = 1.0f;
  int num_milestones = 0;
  int milestones[kMaxMilestones] = {0, 0, 0, 0};
};

// Learning rate of Adam step t (1-based; the step of iteration t - 1), like
// torch.optim.lr_scheduler.MultiStepLR stepped once per iteration.
FLX_HD double lr_at(const Hyper& h, double t) {
  double lr = h.lr;
  for (int k = 0; k < h.num_milestones; ++k)
    if (h.milestones[k] <= t - 1) lr *= h.lr_gamma;
  return lr;
}

// FloxelsConfig.lambda_g: linear decay over the first decay_iters iterations, then constant.
FLX_HD double lambda_g(const Hyper& h, double it) {
  if (h.lambda_g_decay_iters <= 0 || it >= h.lambda_g_decay_iters) return h.lambda_g_end;
  const double a = it / h.lambda_g_decay_iters;
  return h.lambda_g_start + a * (double(h.lambda_g_end) - h.lambda_g_start);
}

// Adam's bias corrections of step t (1-based), in double like torch.optim.Adam:
// step_size = lr / (1 - beta1^t) and sqrt(1 - beta2^t). The CUDA solver tabulates them once
// per call with this same function (pow in double is slow on the device's critical path).
FLX_HD void bias_corrections(const Hyper& h, double t, double* step_size, double* bc2_sqrt) {
  *step_size = lr_at(h, t) / (1.0 - pow(double(h.beta1), t));
  *bc2_sqrt = sqrt(1.0 - pow(double(h.beta2), t));
}

// Stage 3 for one problem: records `loss` and sets the flags that stage 4 reads. Same
// rules as floxels_ext.early_stopping.EarlyStopping and the Python loop: the flow of the
// lowest loss is kept; stop after `patience` iterations without an improvement of
// min_delta, or after max_iters; no Adam step after the last recorded loss. `history` may
// be null (no record kept); `bias`, if given, holds bias_corrections for t = 1..max_iters
// as (step_size, bc2_sqrt) pairs. (ahead_it, ahead_step, ahead_bc2): bias's pair of
// iteration ahead_it, read ahead by a caller that predicted the iteration (used only if it
// is this one; the CUDA loop thus takes the table's read off its critical path).
FLX_HD void control_update(double* st, double loss, double* history, const Hyper& h,
                           const double* bias = nullptr, double ahead_it = -1.0, double ahead_step = 0.0,
                           double ahead_bc2 = 0.0) {
  if (st[kActive] == 0.0) {
    st[kStep] = 0.0;
    st[kCopyBest] = 0.0;
    return;
  }
  const double it = st[kIter];
  if (history != nullptr) history[int64_t(it)] = loss;
  const bool is_best = loss < st[kBestLoss];
  if (is_best) {
    st[kBestLoss] = loss;
    st[kBestIter] = it;
  }
  if (loss < st[kRefLoss] - h.min_delta) {
    st[kRefLoss] = loss;
    st[kStale] = 0.0;
  } else {
    st[kStale] += 1.0;
  }
  const bool stop = st[kStale] >= h.patience || it + 1 >= h.max_iters;
  st[kCopyBest] = is_best ? 1.0 : 0.0;
  st[kStep] = stop ? 0.0 : 1.0;
  st[kIter] = it + 1;
  if (stop) st[kActive] = 0.0;
  // Adam's bias corrections for step t = it + 1 (no step follows the last iteration, so a
  // table of max_iters pairs covers every step)
  if (stop) return;
  if (ahead_it == it) {
    st[kStepSize] = ahead_step;
    st[kBc2Sqrt] = ahead_bc2;
  } else if (bias != nullptr) {
    st[kStepSize] = bias[2 * int64_t(it)];
    st[kBc2Sqrt] = bias[2 * int64_t(it) + 1];
  } else {
    bias_corrections(h, it + 1, &st[kStepSize], &st[kBc2Sqrt]);
  }
}

// Fresh state row: active, no loss recorded, best = inf.
FLX_HD void init_state(double* st) {
  for (int c = 0; c < kStateCols; ++c) st[c] = 0.0;
  st[kActive] = 1.0;
  st[kBestLoss] = INFINITY;
  st[kRefLoss] = INFINITY;
  st[kBestIter] = -1.0;
}

// torch.optim.Adam (no weight decay, no amsgrad) on one value, in the same operation order
// as torch's single-tensor implementation: m.lerp_(g, 1-b1); v.mul_(b2).addcmul_(g, g, 1-b2);
// denom = sqrt(v) / sqrt(1 - b2^t) + eps; p -= step_size * m / denom.
FLX_HD void adam_update(float& p, float& m, float& v, float g, const Hyper& h, float step_size, float bc2_sqrt) {
  m = m + (1.0f - h.beta1) * (g - m);
  v = v * h.beta2 + (1.0f - h.beta2) * g * g;
  const float denom = sqrtf(v) / bc2_sqrt + h.eps;
  p = p + (-step_size) * (m / denom);
}

// f / ||f|| (0 at f = 0, like the Python loop's clamp_min(1e-12)), the flow-norm gradient
// direction; returns ||f||.
FLX_HD float norm_and_unit(const float* f, float* unit) {
  const float n = sqrtf(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
  const float inv = 1.0f / fmaxf(n, 1e-12f);
  for (int c = 0; c < 3; ++c) unit[c] = f[c] * inv;
  return n;
}

}  // namespace floxels::solver
