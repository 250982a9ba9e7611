// CUDA kernels of the data-only distance-transform look-ups (math in kernels/dt_loss.h): one
// thread per point, each looping over the K scans, whose metadata travels by value in the
// kernel parameters (__grid_constant__, as in dt_loss.cu): one launch whatever K, no
// host-to-device copy.
//
// dt_evidence sums its groups (runs of points) without atomics: per point the prefix sums of
// the residuals in double (block scans in a fixed order plus a one-block scan of the block
// totals), and each group's sum is the difference of the prefix sums at its last point and
// before its first point (found by max / min scans of the run starts / ends). A point whose
// residual is not finite adds 0 and counts in a third "bad" channel, so that it makes its own
// group NaN and not every later one. Four kernels, same bits on every run.
#include <cuda_runtime.h>

#include <climits>
#include <cstdint>

#include "cuda/dt_query_launch.h"
#include "cuda/dt_scan.cuh"
#include "kernels/dt_loss.h"
#include "kernels/finite.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kScanThreads = 1024;

template <typename T>
struct Params {
  dt_loss::Scan<T, int> scans[dt_loss::kMaxScans];
  const T* points;
  const T* motion;
  const int32_t* observed;  // (n,) observed bits or nullptr (kernels/dt_loss.h counts)
  T* out;
  int n;
  int num_scans;
  T inv_spacing;
  T cap;
};

template <typename T>
Params<T> make_params(const T* points, const T* motion, int64_t n, const DtLossScanDesc* scans, int num_scans,
                      double spacing, double cap, T* out, const int32_t* observed = nullptr) {
  Params<T> p{};
  p.observed = observed;
  for (int k = 0; k < num_scans; ++k) p.scans[k] = device_scan<T>(scans[k], scans[k].weight);
  p.points = points;
  p.motion = motion;
  p.out = out;
  p.n = static_cast<int>(n);
  p.num_scans = num_scans;
  p.inv_spacing = T(1.0 / spacing);
  p.cap = T(cap);
  return p;
}

int num_blocks(int64_t n) { return static_cast<int>((n + kThreads - 1) / kThreads); }

// --- dt_residual / dt_sample ---

template <typename T, bool kSquared>
__global__ void __launch_bounds__(kThreads) residual_kernel(const __grid_constant__ Params<T> p) {
  const int i = blockIdx.x * kThreads + threadIdx.x;
  if (i >= p.n) return;
  const T* pi = p.points + 3 * static_cast<int64_t>(i);
  const T* mi = p.motion + 3 * static_cast<int64_t>(i);
  T r = dt_loss::point_residual<kSquared, T, int>(p.scans, p.num_scans, pi[0], pi[1], pi[2], mi[0], mi[1], mi[2],
                                                  p.inv_spacing, p.cap, dt_loss::point_bits(p.observed, i));
  if (!finite3(pi[0], pi[1], pi[2]) || !finite3(mi[0], mi[1], mi[2])) r = quiet_nan<T>();
  p.out[i] = r;
}

template <typename T>
__global__ void __launch_bounds__(kThreads) sample_kernel(const __grid_constant__ Params<T> p) {
  const int i = blockIdx.x * kThreads + threadIdx.x;
  if (i >= p.n) return;
  const T* pi = p.points + 3 * static_cast<int64_t>(i);
  const T* mi = p.motion + 3 * static_cast<int64_t>(i);
  const bool ok = finite3(pi[0], pi[1], pi[2]) && finite3(mi[0], mi[1], mi[2]);
#pragma unroll 4
  for (int k = 0; k < p.num_scans; ++k) {
    T g[3];
    const T v = dt_loss::scan_sample<true, T, int>(p.scans[k], pi[0], pi[1], pi[2], mi[0], mi[1], mi[2],
                                                   p.inv_spacing, g);
    T* o = p.out + 4 * (static_cast<int64_t>(k) * p.n + i);
    o[0] = ok ? v : quiet_nan<T>();
    o[1] = ok ? g[0] : T(0);
    o[2] = ok ? g[1] : T(0);
    o[3] = ok ? g[2] : T(0);
  }
}

// --- dt_evidence ---

struct Sum {
  __device__ double operator()(double a, double b) const { return a + b; }
};
struct Max {
  __device__ int operator()(int a, int b) const { return a > b ? a : b; }
};
struct Min {
  __device__ int operator()(int a, int b) const { return a < b ? a : b; }
};

// Inclusive scan over a block of kBlock threads (forward, or from the last thread backwards
// with kSuffix), in a fixed order. Every thread must call it; `smem` holds kBlock / 32 values.
template <int kBlock, bool kSuffix, typename V, typename Op>
__device__ V block_scan(V v, Op op, V identity, V* smem) {
  constexpr int kWarps = kBlock / 32;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  for (int off = 1; off < 32; off <<= 1) {
    const V y = kSuffix ? __shfl_down_sync(0xffffffffu, v, off) : __shfl_up_sync(0xffffffffu, v, off);
    if (kSuffix ? lane + off < 32 : lane >= off) v = op(v, y);
  }
  if (lane == (kSuffix ? 0 : 31)) smem[warp] = v;
  __syncthreads();
  if (warp == 0) {
    V w = lane < kWarps ? smem[lane] : identity;
    for (int off = 1; off < 32; off <<= 1) {
      const V y = kSuffix ? __shfl_down_sync(0xffffffffu, w, off) : __shfl_up_sync(0xffffffffu, w, off);
      if (kSuffix ? lane + off < 32 : lane >= off) w = op(w, y);
    }
    if (lane < kWarps) smem[lane] = w;
  }
  __syncthreads();
  if (kSuffix ? warp + 1 < kWarps : warp > 0) v = op(v, smem[kSuffix ? warp + 1 : warp - 1]);
  __syncthreads();  // smem free for the next scan
  return v;
}

template <typename T>
struct EvidenceParams {
  Params<T> q;
  GroupKeys labels, cells;
  double* vals;     // (n, 3): residual with flow, with zero flow, bad; then their prefix sums
  double* blk_sum;  // (B, 3) block totals
  double* blk_pre;  // (B, 3) exclusive prefix of the block totals
  int* blk_max;     // last run start in each block (-1: none)
  int* blk_min;     // first run end in each block (INT_MAX: none)
  int* blk_premax;  // max of blk_max over the earlier blocks
  int* blk_sufmin;  // min of blk_min over the later blocks
  int* first;       // (n) first point of each point's group
  int* last;        // (n) last point of each point's group
  T* score;
  bool* explained;
  T* res_flow;
  T* res_zero;
  int num_blocks;
  T margin, ratio;
};

__device__ __forceinline__ int64_t read_key(const GroupKeys& k, int i) {
  const int64_t j = static_cast<int64_t>(i) * k.stride;
  return k.is64 ? static_cast<const int64_t*>(k.data)[j] : static_cast<const int32_t*>(k.data)[j];
}

// Point i starts a group: the first point, or its label (or, unlabelled, its cell) differs.
template <typename T>
__device__ bool starts_group(const EvidenceParams<T>& p, int i) {
  if (i == 0) return true;
  const int64_t la = p.labels.data ? read_key(p.labels, i) : -1;
  const int64_t lb = p.labels.data ? read_key(p.labels, i - 1) : -1;
  return la != lb || (la < 0 && read_key(p.cells, i) != read_key(p.cells, i - 1));
}

// Run ends seen by point i (i < n): ``first`` = i where a group starts here, ``last`` = i where
// one ends here; the kernels' max / min scans carry them to every point of the group.
template <typename T>
__device__ void mark_run_ends(const EvidenceParams<T>& p, int i, int n, int& first, int& last) {
  if (starts_group(p, i)) first = i;
  if (i == n - 1 || starts_group(p, i + 1)) last = i;
}

template <typename T>
__global__ void __launch_bounds__(kThreads) evidence_values_kernel(const __grid_constant__ EvidenceParams<T> p) {
  __shared__ double sd[kThreads / 32];
  __shared__ int si[kThreads / 32];
  const int i = blockIdx.x * kThreads + threadIdx.x;
  const int n = p.q.n;
  double v[3] = {0.0, 0.0, 0.0};
  int smax = -1, emin = INT_MAX;
  if (i < n) {
    const T* pi = p.q.points + 3 * static_cast<int64_t>(i);
    const T* fi = p.q.motion + 3 * static_cast<int64_t>(i);
    T rf, rz;
    dt_loss::point_residual_pair<T, int>(p.q.scans, p.q.num_scans, pi[0], pi[1], pi[2], fi[0], fi[1], fi[2],
                                         p.q.inv_spacing, p.q.cap, rf, rz, dt_loss::point_bits(p.q.observed, i));
    const bool ok = finite3(pi[0], pi[1], pi[2]) && finite3(fi[0], fi[1], fi[2]) && is_finite(rf) && is_finite(rz);
    v[0] = ok ? static_cast<double>(rf) : 0.0;
    v[1] = ok ? static_cast<double>(rz) : 0.0;
    v[2] = ok ? 0.0 : 1.0;
    double* o = p.vals + 3 * static_cast<int64_t>(i);
    o[0] = v[0];
    o[1] = v[1];
    o[2] = v[2];
    mark_run_ends(p, i, n, smax, emin);
  }
  double tot[3];
  for (int c = 0; c < 3; ++c) tot[c] = block_scan<kThreads, false>(v[c], Sum{}, 0.0, sd);
  const int bmax = block_scan<kThreads, false>(smax, Max{}, -1, si);
  const int bmin = block_scan<kThreads, true>(emin, Min{}, INT_MAX, si);
  if (threadIdx.x == kThreads - 1) {
    for (int c = 0; c < 3; ++c) p.blk_sum[3 * blockIdx.x + c] = tot[c];
    p.blk_max[blockIdx.x] = bmax;
  }
  if (threadIdx.x == 0) p.blk_min[blockIdx.x] = bmin;
}

// One block: exclusive prefix sums / max and suffix min over the block totals, each thread
// walking a fixed run of consecutive blocks.
template <typename T>
__global__ void __launch_bounds__(kScanThreads) evidence_blocks_kernel(const __grid_constant__ EvidenceParams<T> p) {
  __shared__ double sd[kScanThreads / 32];
  __shared__ int si[kScanThreads / 32];
  const int B = p.num_blocks;
  const int per = (B + kScanThreads - 1) / kScanThreads;
  const int lo = min(B, static_cast<int>(threadIdx.x) * per), hi = min(B, lo + per);
  double s[3] = {0.0, 0.0, 0.0};
  int mx = -1, mn = INT_MAX;
  for (int j = lo; j < hi; ++j) {
    for (int c = 0; c < 3; ++c) s[c] += p.blk_sum[3 * j + c];
    mx = max(mx, p.blk_max[j]);
    mn = min(mn, p.blk_min[j]);
  }
  // inclusive scans over the threads; the exclusive values are the neighbouring thread's
  __shared__ double ex_sum[3][kScanThreads];
  __shared__ int ex_max[kScanThreads], ex_min[kScanThreads];
  for (int c = 0; c < 3; ++c) ex_sum[c][threadIdx.x] = block_scan<kScanThreads, false>(s[c], Sum{}, 0.0, sd);
  ex_max[threadIdx.x] = block_scan<kScanThreads, false>(mx, Max{}, -1, si);
  ex_min[threadIdx.x] = block_scan<kScanThreads, true>(mn, Min{}, INT_MAX, si);
  __syncthreads();
  double run[3];
  for (int c = 0; c < 3; ++c) run[c] = threadIdx.x > 0 ? ex_sum[c][threadIdx.x - 1] : 0.0;
  int rmax = threadIdx.x > 0 ? ex_max[threadIdx.x - 1] : -1;
  int rmin = threadIdx.x + 1 < kScanThreads ? ex_min[threadIdx.x + 1] : INT_MAX;
  for (int j = lo; j < hi; ++j) {
    for (int c = 0; c < 3; ++c) {
      p.blk_pre[3 * j + c] = run[c];
      run[c] += p.blk_sum[3 * j + c];
    }
    p.blk_premax[j] = rmax;
    rmax = max(rmax, p.blk_max[j]);
  }
  for (int j = hi - 1; j >= lo; --j) {
    p.blk_sufmin[j] = rmin;
    rmin = min(rmin, p.blk_min[j]);
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads) evidence_prefix_kernel(const __grid_constant__ EvidenceParams<T> p) {
  __shared__ double sd[kThreads / 32];
  __shared__ int si[kThreads / 32];
  const int i = blockIdx.x * kThreads + threadIdx.x;
  const int n = p.q.n;
  double v[3] = {0.0, 0.0, 0.0};
  int smax = -1, emin = INT_MAX;
  if (i < n) {
    const double* o = p.vals + 3 * static_cast<int64_t>(i);
    v[0] = o[0];
    v[1] = o[1];
    v[2] = o[2];
    mark_run_ends(p, i, n, smax, emin);
  }
  for (int c = 0; c < 3; ++c) v[c] = p.blk_pre[3 * blockIdx.x + c] + block_scan<kThreads, false>(v[c], Sum{}, 0.0, sd);
  smax = max(p.blk_premax[blockIdx.x], block_scan<kThreads, false>(smax, Max{}, -1, si));
  emin = min(p.blk_sufmin[blockIdx.x], block_scan<kThreads, true>(emin, Min{}, INT_MAX, si));
  if (i < n) {
    double* o = p.vals + 3 * static_cast<int64_t>(i);  // only this thread reads or writes row i
    o[0] = v[0];
    o[1] = v[1];
    o[2] = v[2];
    p.first[i] = smax;
    p.last[i] = emin;
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads) evidence_test_kernel(const __grid_constant__ EvidenceParams<T> p) {
  const int i = blockIdx.x * kThreads + threadIdx.x;
  if (i >= p.q.n) return;
  const int f = p.first[i], l = p.last[i];
  const double* hi = p.vals + 3 * static_cast<int64_t>(l);
  double s[3] = {hi[0], hi[1], hi[2]};
  if (f > 0) {
    const double* lo = p.vals + 3 * static_cast<int64_t>(f - 1);
    for (int c = 0; c < 3; ++c) s[c] -= lo[c];
  }
  T gain, rf, rz;
  bool e = dt_loss::evidence_test<T>(s[0], s[1], static_cast<double>(l - f + 1), p.margin, p.ratio, gain, rf, rz);
  if (s[2] > 0.5) {  // a non-finite residual in the group
    gain = rf = rz = quiet_nan<T>();
    e = false;
  }
  p.score[i] = gain;
  p.explained[i] = e;
  p.res_flow[i] = rf;
  p.res_zero[i] = rz;
}

// Workspace layout (byte offsets, each 16-byte aligned).
struct Layout {
  int64_t vals, blk_sum, blk_pre, blk_max, blk_min, blk_premax, blk_sufmin, first, last, total;
};

int64_t align16(int64_t b) { return (b + 15) / 16 * 16; }

Layout layout(int64_t n) {
  const int64_t B = num_blocks(n);
  Layout l{};
  int64_t at = 0;
  auto take = [&](int64_t bytes) {
    const int64_t o = at;
    at += align16(bytes);
    return o;
  };
  l.vals = take(3 * n * static_cast<int64_t>(sizeof(double)));
  l.blk_sum = take(3 * B * static_cast<int64_t>(sizeof(double)));
  l.blk_pre = take(3 * B * static_cast<int64_t>(sizeof(double)));
  l.blk_max = take(B * static_cast<int64_t>(sizeof(int)));
  l.blk_min = take(B * static_cast<int64_t>(sizeof(int)));
  l.blk_premax = take(B * static_cast<int64_t>(sizeof(int)));
  l.blk_sufmin = take(B * static_cast<int64_t>(sizeof(int)));
  l.first = take(n * static_cast<int64_t>(sizeof(int)));
  l.last = take(n * static_cast<int64_t>(sizeof(int)));
  l.total = at;
  return l;
}

bool bad_args(int64_t n, int num_scans) {
  return num_scans < 1 || num_scans > dt_loss::kMaxScans || n < 0 || n > INT32_MAX;
}

template <typename T>
cudaError_t residual_impl(const T* points, const T* motion, int64_t n, const DtLossScanDesc* scans, int num_scans,
                          double spacing, double cap, bool squared, const int32_t* observed, T* out, cudaStream_t stream) {
  if (bad_args(n, num_scans)) return cudaErrorInvalidValue;
  if (n == 0) return cudaSuccess;
  const Params<T> p = make_params<T>(points, motion, n, scans, num_scans, spacing, cap, out, observed);
  if (squared) {
    residual_kernel<T, true><<<num_blocks(n), kThreads, 0, stream>>>(p);
  } else {
    residual_kernel<T, false><<<num_blocks(n), kThreads, 0, stream>>>(p);
  }
  return cudaGetLastError();
}

template <typename T>
cudaError_t sample_impl(const T* points, const T* motion, int64_t n, const DtLossScanDesc* scans, int num_scans,
                        double spacing, T* out, cudaStream_t stream) {
  if (bad_args(n, num_scans)) return cudaErrorInvalidValue;
  if (n == 0) return cudaSuccess;
  const Params<T> p = make_params<T>(points, motion, n, scans, num_scans, spacing, 0.0, out);
  sample_kernel<T><<<num_blocks(n), kThreads, 0, stream>>>(p);
  return cudaGetLastError();
}

template <typename T>
cudaError_t evidence_impl(const T* points, const T* flow, int64_t n, GroupKeys labels, GroupKeys cells,
                          const DtLossScanDesc* scans, int num_scans, double spacing, double cap, double margin,
                          double ratio, const int32_t* observed, T* score, bool* explained, T* res_flow, T* res_zero,
                          void* workspace, cudaStream_t stream) {
  if (bad_args(n, num_scans) || cells.data == nullptr) return cudaErrorInvalidValue;
  if (n == 0) return cudaSuccess;
  const Layout l = layout(n);
  char* ws = static_cast<char*>(workspace);
  EvidenceParams<T> p{};
  p.q = make_params<T>(points, flow, n, scans, num_scans, spacing, cap, nullptr, observed);
  p.labels = labels;
  p.cells = cells;
  p.vals = reinterpret_cast<double*>(ws + l.vals);
  p.blk_sum = reinterpret_cast<double*>(ws + l.blk_sum);
  p.blk_pre = reinterpret_cast<double*>(ws + l.blk_pre);
  p.blk_max = reinterpret_cast<int*>(ws + l.blk_max);
  p.blk_min = reinterpret_cast<int*>(ws + l.blk_min);
  p.blk_premax = reinterpret_cast<int*>(ws + l.blk_premax);
  p.blk_sufmin = reinterpret_cast<int*>(ws + l.blk_sufmin);
  p.first = reinterpret_cast<int*>(ws + l.first);
  p.last = reinterpret_cast<int*>(ws + l.last);
  p.score = score;
  p.explained = explained;
  p.res_flow = res_flow;
  p.res_zero = res_zero;
  p.num_blocks = num_blocks(n);
  p.margin = T(margin);
  p.ratio = T(ratio);
  evidence_values_kernel<T><<<p.num_blocks, kThreads, 0, stream>>>(p);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  evidence_blocks_kernel<T><<<1, kScanThreads, 0, stream>>>(p);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  evidence_prefix_kernel<T><<<p.num_blocks, kThreads, 0, stream>>>(p);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  evidence_test_kernel<T><<<p.num_blocks, kThreads, 0, stream>>>(p);
  return cudaGetLastError();
}

}  // namespace

cudaError_t launch_dt_residual(const float* points, const float* motion, int64_t n, const DtLossScanDesc* scans,
                               int num_scans, double spacing, double cap, bool squared, const int32_t* observed, float* out,
                               cudaStream_t stream) {
  return residual_impl<float>(points, motion, n, scans, num_scans, spacing, cap, squared, observed, out, stream);
}

cudaError_t launch_dt_residual(const double* points, const double* motion, int64_t n, const DtLossScanDesc* scans,
                               int num_scans, double spacing, double cap, bool squared, const int32_t* observed, double* out,
                               cudaStream_t stream) {
  return residual_impl<double>(points, motion, n, scans, num_scans, spacing, cap, squared, observed, out, stream);
}

cudaError_t launch_dt_sample(const float* points, const float* motion, int64_t n, const DtLossScanDesc* scans,
                             int num_scans, double spacing, float* out, cudaStream_t stream) {
  return sample_impl<float>(points, motion, n, scans, num_scans, spacing, out, stream);
}

cudaError_t launch_dt_sample(const double* points, const double* motion, int64_t n, const DtLossScanDesc* scans,
                             int num_scans, double spacing, double* out, cudaStream_t stream) {
  return sample_impl<double>(points, motion, n, scans, num_scans, spacing, out, stream);
}

int64_t dt_evidence_workspace_bytes(int64_t n) { return n > 0 ? layout(n).total : 0; }

cudaError_t launch_dt_evidence(const float* points, const float* flow, int64_t n, GroupKeys labels,
                               GroupKeys cells, const DtLossScanDesc* scans, int num_scans, double spacing,
                               double cap, double margin, double ratio, const int32_t* observed, float* score, bool* explained,
                               float* res_flow, float* res_zero, void* workspace, cudaStream_t stream) {
  return evidence_impl<float>(points, flow, n, labels, cells, scans, num_scans, spacing, cap, margin, ratio, observed, score,
                              explained, res_flow, res_zero, workspace, stream);
}

cudaError_t launch_dt_evidence(const double* points, const double* flow, int64_t n, GroupKeys labels,
                               GroupKeys cells, const DtLossScanDesc* scans, int num_scans, double spacing,
                               double cap, double margin, double ratio, const int32_t* observed, double* score, bool* explained,
                               double* res_flow, double* res_zero, void* workspace, cudaStream_t stream) {
  return evidence_impl<double>(points, flow, n, labels, cells, scans, num_scans, spacing, cap, margin, ratio, observed, score,
                               explained, res_flow, res_zero, workspace, stream);
}

}  // namespace floxels::cuda
