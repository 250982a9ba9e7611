// CUDA kernels of floxels::velocity_search (math in kernels/velocity_search.h), three launches:
//   1. axis_kernel: each cluster's horizontal principal axis (one thread, the CPU's order);
//   2. global_kernel: the global candidates' scores, kCandidates candidates per block and
//      kGroup threads per candidate summing interleaved rows, a grid of (cluster, candidate
//      chunk) blocks: a few moving clusters still fill the GPU (one block per cluster left
//      most SMs idle: the search of the accurate preset's refinement took ~5 ms a frame);
//   3. local_kernel: per cluster, the best global candidate and the pattern search, each of its
//      9 candidates summed by kLocalGroup threads.
// Each score is the partial sums of its threads added in a fixed order by one thread; ties go
// to the lowest candidate index: the same bits on every run.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/dt_scan.cuh"
#include "cuda/velocity_search_launch.h"
#include "kernels/dt_loss.h"
#include "kernels/rigid_lm.h"
#include "kernels/velocity_search.h"

namespace floxels::cuda {
namespace {

namespace vs = velocity_search;
constexpr int kCandidates = 16;                     // global candidates per block
constexpr int kGroup = 16;                          // threads per global candidate
constexpr int kGlobalThreads = kCandidates * kGroup;
constexpr int kLocalGroup = 64;                     // threads per pattern-search candidate
constexpr int kLocalThreads = vs::kLocal * kLocalGroup;

template <typename T>
struct Params {
  dt_loss::Scan<T, int> scans[dt_loss::kMaxScans];
  const T* points;
  const int64_t* segments;
  const int32_t* observed;
  T* axes;         // (C, 2) scratch: principal axes
  double* global;  // (C, nc) scratch: global candidates' scores
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

template <typename T>
__device__ double rows_of(const Params<T>& p, int64_t begin, int64_t end, int64_t first, int64_t stride, const T* v) {
  return vs::row_sum<T, int>(p.scans, p.num_scans, p.inv_spacing, p.tau, p.points, p.observed, begin, end, first,
                             stride, v);
}

template <typename T>
__global__ void axis_kernel(const __grid_constant__ Params<T> p, int64_t num_clusters) {
  const int64_t c = blockIdx.x * int64_t(blockDim.x) + threadIdx.x;
  if (c >= num_clusters) return;
  int64_t begin = 0, end = 0;
  rigid_lm::cluster_rows(p.segments, c, p.m, begin, end);
  vs::principal_axis<T>(p.points, begin, end, p.axes[2 * c], p.axes[2 * c + 1]);
}

template <typename T>
__global__ void __launch_bounds__(kGlobalThreads) global_kernel(const __grid_constant__ Params<T> p) {
  __shared__ double partial[kGlobalThreads];
  const int64_t c = blockIdx.x;
  const int nc = 1 + p.num_directions * p.num_speeds;
  const int t = threadIdx.x, j = blockIdx.y * kCandidates + t / kGroup, g = t % kGroup;
  int64_t begin = 0, end = 0;
  rigid_lm::cluster_rows(p.segments, c, p.m, begin, end);
  if (j < nc) {
    T v[3];
    vs::global_candidate<T>(j, p.num_directions, p.num_speeds, T(p.speed_step), p.axes[2 * c], p.axes[2 * c + 1], v);
    partial[t] = rows_of(p, begin, end, g, kGroup, v);
  }
  __syncthreads();
  if (g == 0 && j < nc) {
    double s = 0.0;
    for (int k = 0; k < kGroup; ++k) s += partial[t + k];
    p.global[c * nc + j] = s / (end > begin ? double(end - begin) : 1.0);
  }
}

template <typename T>
__global__ void __launch_bounds__(kLocalThreads) local_kernel(const __grid_constant__ Params<T> p) {
  __shared__ double partial[kLocalThreads];
  __shared__ double scores[vs::kLocal];
  __shared__ T best[3];
  __shared__ double best_s;
  __shared__ bool improved;
  const int64_t c = blockIdx.x;
  const int nc = 1 + p.num_directions * p.num_speeds;
  const int t = threadIdx.x, j = t / kLocalGroup, g = t % kLocalGroup;
  int64_t begin = 0, end = 0;
  rigid_lm::cluster_rows(p.segments, c, p.m, begin, end);
  const double n = end > begin ? double(end - begin) : 1.0;
  if (t == 0) {
    const double* s = p.global + c * nc;
    const int k = vs::first_min(s, nc);
    vs::global_candidate<T>(k, p.num_directions, p.num_speeds, T(p.speed_step), p.axes[2 * c], p.axes[2 * c + 1],
                            best);
    best_s = s[k];
    p.zero_score[c] = T(s[0]);
  }
  __syncthreads();
  double step = p.speed_step;
  for (int ls = 0; ls < p.local_steps; ++ls, step /= 2) {
    const T st = T(step);
    for (int r = 0; r < p.local_rounds; ++r) {
      T v[3];
      vs::local_candidate<T>(j, best, st, v);
      partial[t] = rows_of(p, begin, end, g, kLocalGroup, v);
      __syncthreads();
      if (g == 0) {
        double s = 0.0;
        for (int k = 0; k < kLocalGroup; ++k) s += partial[t + k];
        scores[j] = s / n;
      }
      __syncthreads();
      if (t == 0) {
        const int k = vs::first_min(scores, vs::kLocal);
        improved = scores[k] < best_s;
        if (improved) {
          vs::local_candidate<T>(k, best, st, v);
          for (int x = 0; x < 3; ++x) best[x] = v[x];
          best_s = scores[k];
        }
      }
      __syncthreads();
      if (!improved) break;  // (uniform over the block) the next round would be the same
    }
  }
  if (t == 0) {
    for (int x = 0; x < 3; ++x) p.best[3 * c + x] = best[x];
    p.best_score[c] = T(best_s);
  }
}

template <typename T>
cudaError_t search_impl(const T* points, const int64_t* segments, const int32_t* observed, int64_t m,
                        int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing, double tau,
                        int num_directions, double speed_step, int num_speeds, int local_steps, int local_rounds,
                        T* axes, double* global, T* best, T* best_score, T* zero_score, cudaStream_t stream) {
  if (num_clusters == 0) return cudaSuccess;
  Params<T> p{};
  for (int k = 0; k < num_scans; ++k) p.scans[k] = device_scan<T>(scans[k], scans[k].weight);
  p.points = points;
  p.segments = segments;
  p.observed = observed;
  p.axes = axes;
  p.global = global;
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
  const int nc = 1 + num_directions * num_speeds;
  const auto C = static_cast<unsigned>(num_clusters);
  axis_kernel<T><<<(C + 127) / 128, 128, 0, stream>>>(p, num_clusters);
  global_kernel<T><<<dim3(C, static_cast<unsigned>((nc + kCandidates - 1) / kCandidates)), kGlobalThreads, 0,
                     stream>>>(p);
  local_kernel<T><<<C, kLocalThreads, 0, stream>>>(p);
  return cudaGetLastError();
}

}  // namespace

cudaError_t launch_velocity_search(const float* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, float* axes, double* global, float* best,
                                   float* best_score, float* zero_score, cudaStream_t stream) {
  return search_impl<float>(points, segments, observed, m, num_clusters, scans, num_scans, spacing, tau,
                            num_directions, speed_step, num_speeds, local_steps, local_rounds, axes, global, best,
                            best_score, zero_score, stream);
}

cudaError_t launch_velocity_search(const double* points, const int64_t* segments, const int32_t* observed, int64_t m,
                                   int64_t num_clusters, const DtLossScanDesc* scans, int num_scans, double spacing,
                                   double tau, int num_directions, double speed_step, int num_speeds,
                                   int local_steps, int local_rounds, double* axes, double* global, double* best,
                                   double* best_score, double* zero_score, cudaStream_t stream) {
  return search_impl<double>(points, segments, observed, m, num_clusters, scans, num_scans, spacing, tau,
                             num_directions, speed_step, num_speeds, local_steps, local_rounds, axes, global, best,
                             best_score, zero_score, stream);
}

}  // namespace floxels::cuda
