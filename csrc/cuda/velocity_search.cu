// CUDA kernel of floxels::velocity_search (math in kernels/velocity_search.h): one block per
// cluster runs the whole search. A set of candidates is scored by groups of threads: with at
// least as many candidates as threads, each thread sums whole candidates over the rows; with
// fewer, each candidate gets kThreads / count threads that sum interleaved rows, and one thread
// adds the group's partial sums in order. Thread 0 picks the best (the lowest index on ties);
// the block reads it from shared memory. Fixed orders throughout: the same bits on every run.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_scan.cuh"
#include "cuda/velocity_search_launch.h"
#include "kernels/dt_loss.h"
#include "kernels/rigid_lm.h"
#include "kernels/velocity_search.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;
namespace vs = velocity_search;

template <typename T>
struct Params {
  dt_loss::Scan<T, int> scans[dt_loss::kMaxScans];
  const T* points;
  const int64_t* segments;
  const int32_t* observed;
  T* best;
  T* best_score;
  T* zero_score;
  int64_t m;
  int num_scans;
  int num_directions;
  int num_speeds;
  int local_steps;
  int local_rounds;
  double speed_step;
  T inv_spacing;
  T tau;
};

// scores[j] = mean over rows of candidate j's residual, j < count; cand(j, v) writes candidate j.
template <typename T, typename Cand>
__device__ void score_all(const Params<T>& p, int64_t begin, int64_t end, double n, int count, Cand cand,
                          double* partial, double* scores) {
  const int t = threadIdx.x;
  T v[3];
  if (count >= kThreads) {
    for (int j = t; j < count; j += kThreads) {
      cand(j, v);
      scores[j] = vs::row_sum<T, int>(p.scans, p.num_scans, p.inv_spacing, p.tau, p.points, p.observed, begin, end,
                                      0, 1, v) / n;
    }
    __syncthreads();
    return;
  }
  const int group = kThreads / count;
  if (t < count * group) {
    const int j = t / group, g = t % group;
    cand(j, v);
    partial[t] = vs::row_sum<T, int>(p.scans, p.num_scans, p.inv_spacing, p.tau, p.points, p.observed, begin, end,
                                     g, group, v);
  }
  __syncthreads();
  if (t < count) {
    double s = 0.0;
    for (int g = 0; g < group; ++g) s += partial[t * group + g];
    scores[t] = s / n;
  }
  __syncthreads();
}

template <typename T>
__global__ void __launch_bounds__(kThreads) search_kernel(const __grid_constant__ Params<T> p) {
  __shared__ double partial[kThreads];
  __shared__ double scores[vs::kMaxCandidates];
  __shared__ T axis[2], best[3];
  __shared__ double best_s;
  __shared__ bool improved;
  const int64_t c = blockIdx.x;
  int64_t begin = 0, end = 0;
  rigid_lm::cluster_rows(p.segments, c, p.m, begin, end);
  const double n = end > begin ? double(end - begin) : 1.0;
  if (threadIdx.x == 0) vs::principal_axis<T>(p.points, begin, end, axis[0], axis[1]);
  __syncthreads();
  const T st0 = T(p.speed_step);
  const int nc = 1 + p.num_directions * p.num_speeds;
  const auto global = [&](int j, T* v) {
    vs::global_candidate<T>(j, p.num_directions, p.num_speeds, st0, axis[0], axis[1], v);
  };
  score_all<T>(p, begin, end, n, nc, global, partial, scores);
  if (threadIdx.x == 0) {
    const int k = vs::first_min(scores, nc);
    global(k, best);
    best_s = scores[k];
    p.zero_score[c] = T(scores[0]);
  }
  __syncthreads();
  double step = p.speed_step;
  for (int ls = 0; ls < p.local_steps; ++ls, step /= 2) {
    const T st = T(step);
    for (int r = 0; r < p.local_rounds; ++r) {
      const auto local = [&](int j, T* v) { vs::local_candidate<T>(j, best, st, v); };
      score_all<T>(p, begin, end, n, vs::kLocal, local, partial, scores);
      if (threadIdx.x == 0) {
        const int k = vs::first_min(scores, vs::kLocal);
        improved = scores[k] < best_s;
        if (improved) {
          T v[3];
          local(k, v);
          for (int x = 0; x < 3; ++x) best[x] = v[x];
          best_s = scores[k];
        }
      }
      __syncthreads();
      if (!improved) break;  // (uniform over the block) the next round would be the same
    }
  }
  if (threadIdx.x == 0) {
    for (int x = 0; x < 3; ++x) p.best[3 * c + x] = best[x];
    p.best_score[c] = T(best_s);
  }
}

template <typename T>
cudaError_t search_impl(const T* points, const int64_t* segments, const int32_t* observed, int64_t m,
                        int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing, double tau,
                        int num_directions, double speed_step, int num_speeds, int local_steps, int local_rounds,
                        T* best, T* best_score, T* zero_score, cudaStream_t stream) {
  if (num_clusters == 0) return cudaSuccess;
  Params<T> p{};
  for (int k = 0; k < num_scans; ++k) p.scans[k] = device_scan<T>(scans[k], scans[k].weight);
  p.points = points;
  p.segments = segments;
  p.observed = observed;
  p.best = best;
  p.best_score = best_score;
  p.zero_score = zero_score;
  p.m = m;
  p.num_scans = num_scans;
  p.num_directions = num_directions;
  p.num_speeds = num_speeds;
  p.local_steps = local_steps;
  p.local_rounds = local_rounds;
  p.speed_step = speed_step;
  p.inv_spacing = T(1.0 / spacing);
  p.tau = T(tau);
  search_kernel<T><<<static_cast<unsigned>(num_clusters), kThreads, 0, stream>>>(p);
  return cudaGetLastError();
}

}  // namespace

cudaError_t launch_velocity_search(const float* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, float* best, float* best_score,
                                   float* zero_score, cudaStream_t stream) {
  return search_impl<float>(points, segments, observed, m, num_clusters, scans, num_scans, spacing, tau,
                            num_directions, speed_step, num_speeds, local_steps, local_rounds, best, best_score,
                            zero_score, stream);
}

cudaError_t launch_velocity_search(const double* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, double* best, double* best_score,
                                   double* zero_score, cudaStream_t stream) {
  return search_impl<double>(points, segments, observed, m, num_clusters, scans, num_scans, spacing, tau,
                             num_directions, speed_step, num_speeds, local_steps, local_rounds, best, best_score,
                             zero_score, stream);
}

}  // namespace floxels::cuda
