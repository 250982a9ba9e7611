// CUDA exact DBSCAN with scikit-learn's labels (math in csrc/kernels/dbscan.h).
//
// Stages: bounding box -> sub-cell keys (cells of size ~eps, each split in 2 x 2 x 2 halves)
// -> radix sort -> distinct sub-cells and cells, each cell's 27-cell neighbourhood as 9
// contiguous RANGES OF SUB-CELLS -> core test -> union-find over core pairs within eps ->
// cluster ids ranked by each component's smallest original core index -> border points take
// the smallest cluster id among their core neighbours.
//
// Why sub-cells: a half cell's diagonal is < 0.96 eps (dbscan::subcells_within_eps), so all
// points of one sub-cell are neighbours of each other. Hence (the "dense" mode, used unless
// the grid had to be enlarged for a huge extent):
//  - a point whose sub-cell holds >= min_samples points is core with no distance test;
//  - all cores of one sub-cell are in one cluster: they start united (parent = the first
//    core of the sub-cell), the hook stage only needs ONE core pair within eps per pair of
//    sub-cells, skips a whole sub-cell already in its component with one root lookup, and a
//    border point needs one core within eps per sub-cell (all share a label);
//  - a sub-cell whose box is farther than eps from a point (rigorous bound with margin,
//    see far()) is skipped without touching its points.
// This removes the O(k^2) per dense cell of thousands of points near the sensor.
//
// Union-find: parent[x] <= x always (roots are only hooked under SMALLER roots with
// atomicCAS, path halving stores only ancestors), so there is no cycle and every stored value
// is a valid index, whatever the interleaving. Roots are then read with a read-only walk into
// a SEPARATE array (the old kernel stored them into parent while other threads were still
// path-halving through it, which could leave a non-root there and index min_orig/cid with
// garbage: the likely cause of the intermittent cudaErrorInvalidAddressSpace).
#include <cuda_runtime.h>

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>

#include "cuda/dbscan_launch.h"
#include "cuda/dbscan_stages.cuh"
#include "kernels/dbscan.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;
using dbscan::Grid;
using stages::kR2;
using stages::Params;

inline unsigned blocks_for(int64_t work) { return unsigned((work + kThreads - 1) / kThreads); }

// Order-preserving map double -> uint64 so that atomicMin/atomicMax on integers give the
// float min/max.
__device__ __forceinline__ unsigned long long order_key(double v) {
  const unsigned long long b = (unsigned long long)__double_as_longlong(v);
  return (b >> 63) ? ~b : (b | 0x8000000000000000ull);
}
inline double order_key_inverse(unsigned long long k) {
  const unsigned long long b = (k >> 63) ? (k & 0x7fffffffffffffffull) : ~k;
  double v;
  static_assert(sizeof(v) == sizeof(b));
  __builtin_memcpy(&v, &b, sizeof(v));
  return v;
}

// bb[0..2] = min, bb[3..5] = max (as order keys; initialised to ~0 and 0).
template <typename T>
__global__ void bbox_kernel(const T* __restrict__ p, int64_t n, unsigned long long* bb) {
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  bool nan = false;
  for (int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; i < n; i += int64_t(gridDim.x) * blockDim.x)
    for (int a = 0; a < 3; ++a) {
      const double v = double(p[i * 3 + a]);
      nan |= v != v;
      lo[a] = fmin(lo[a], v);
      hi[a] = fmax(hi[a], v);
    }
  // Every thread of the block reaches here (no early return): full-mask shuffles are valid.
  for (int off = 16; off > 0; off >>= 1)
    for (int a = 0; a < 3; ++a) {
      lo[a] = fmin(lo[a], __shfl_down_sync(0xffffffffu, lo[a], off));
      hi[a] = fmax(hi[a], __shfl_down_sync(0xffffffffu, hi[a], off));
    }
  nan = __any_sync(0xffffffffu, nan);
  if ((threadIdx.x & 31) == 0) {
    for (int a = 0; a < 3; ++a) {
      atomicMin(bb + a, order_key(lo[a]));
      // fmin/fmax skip NaN: report it as an infinite extent, which the host rejects.
      atomicMax(bb + 3 + a, order_key(nan ? INFINITY : hi[a]));
    }
  }
}

template <typename T>
__global__ void key_kernel(const T* __restrict__ p, int64_t n, Grid g, uint64_t* __restrict__ keys,
                           int32_t* __restrict__ idx) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  keys[i] = dbscan::point_sub_key(g, double(p[i * 3]), double(p[i * 3 + 1]), double(p[i * 3 + 2]));
  idx[i] = int32_t(i);
}

// Sorted coordinates (float64) and the flags "first point of its sub-cell / of its cell".
template <typename T>
__global__ void gather_kernel(const T* __restrict__ p, const uint64_t* __restrict__ keys,
                              const int32_t* __restrict__ orig, int64_t n, double* __restrict__ xs,
                              double* __restrict__ ys, double* __restrict__ zs, int32_t* __restrict__ sub_flag,
                              int32_t* __restrict__ cell_flag) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int64_t o = orig[i];
  xs[i] = double(p[o * 3]);
  ys[i] = double(p[o * 3 + 1]);
  zs[i] = double(p[o * 3 + 2]);
  sub_flag[i] = (i == 0 || keys[i] != keys[i - 1]) ? 1 : 0;
  cell_flag[i] = (i == 0 || (keys[i] >> dbscan::kSubBits) != (keys[i - 1] >> dbscan::kSubBits)) ? 1 : 0;
}

// sub_incl / cell_incl: inclusive scans of the flags, so point i lies in sub-cell
// sub_incl[i] - 1 and cell cell_incl[i] - 1. counts = {num_cells, num_subs}.
__global__ void segments_kernel(const uint64_t* __restrict__ keys, const int32_t* __restrict__ sub_incl,
                                const int32_t* __restrict__ cell_incl, int64_t n, int32_t* __restrict__ sub_start,
                                uint64_t* __restrict__ sub_key, uint64_t* __restrict__ cell_keys,
                                int32_t* __restrict__ cell_start, int32_t* __restrict__ counts) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  if (i == 0 || keys[i] != keys[i - 1]) {
    sub_start[sub_incl[i] - 1] = int32_t(i);
    sub_key[sub_incl[i] - 1] = keys[i];
  }
  if (i == 0 || (keys[i] >> dbscan::kSubBits) != (keys[i - 1] >> dbscan::kSubBits)) {
    cell_keys[cell_incl[i] - 1] = keys[i] >> dbscan::kSubBits;
    cell_start[cell_incl[i] - 1] = int32_t(i);
  }
  if (i == n - 1) {
    counts[0] = cell_incl[i];
    counts[1] = sub_incl[i];
    cell_start[cell_incl[i]] = int32_t(n);
    sub_start[sub_incl[i]] = int32_t(n);
  }
}

// The per-item logic lives in dbscan_stages.cuh (host+device functions); num_cells /
// num_subs are only known on the device (counts), so those kernels are launched with one
// thread per point and check the count.
__global__ void ranges_kernel(Grid g, const uint64_t* __restrict__ cell_keys, const int32_t* __restrict__ cell_start,
                              const int32_t* __restrict__ counts, const int32_t* __restrict__ sub_incl,
                              int32_t* __restrict__ ranges) {
  const int64_t c = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int32_t m = counts[0];
  if (c >= m) return;
  stages::cell_ranges(g, cell_keys, cell_start, m, sub_incl, c, ranges + c * kR2);
}

__global__ void core_kernel(Params P, const double* __restrict__ xs, const double* __restrict__ ys,
                            const double* __restrict__ zs, const int32_t* __restrict__ sub_incl,
                            const int32_t* __restrict__ cell_incl, const int32_t* __restrict__ sub_start,
                            const uint64_t* __restrict__ sub_key, const int32_t* __restrict__ ranges, int64_t n,
                            uint8_t* __restrict__ core) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  core[i] = stages::is_core(P, xs, ys, zs, sub_incl, cell_incl, sub_start, sub_key, ranges, int32_t(i));
}

__global__ void rep_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ sub_start,
                           const int32_t* __restrict__ counts, int32_t* __restrict__ rep) {
  const int64_t s = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (s >= counts[1]) return;
  rep[s] = stages::first_core(core, sub_start, s);
}

__global__ void init_kernel(Params P, const uint8_t* __restrict__ core, const int32_t* __restrict__ sub_incl,
                            const int32_t* __restrict__ rep, int64_t n, int32_t* __restrict__ parent,
                            int32_t* __restrict__ min_orig) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  parent[i] = stages::initial_parent(P, core, sub_incl, rep, int32_t(i));
  min_orig[i] = INT_MAX;
}

// parent is read and written concurrently (volatile loads, atomicCAS): not __restrict__.
__global__ void hook_kernel(Params P, const double* __restrict__ xs, const double* __restrict__ ys,
                            const double* __restrict__ zs, const int32_t* __restrict__ sub_incl,
                            const int32_t* __restrict__ cell_incl, const int32_t* __restrict__ sub_start,
                            const uint64_t* __restrict__ sub_key, const int32_t* __restrict__ rep,
                            const int32_t* __restrict__ ranges, const uint8_t* __restrict__ core, int64_t n,
                            int32_t* parent) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || !core[i]) return;
  stages::hook_point(P, xs, ys, zs, sub_incl, cell_incl, sub_start, sub_key, rep, ranges, core, parent, int32_t(i));
}

// After hook_kernel: roots into a SEPARATE array by a read-only walk (see file comment).
__global__ void root_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ orig,
                            const int32_t* __restrict__ parent, int64_t n, int32_t* __restrict__ root,
                            int32_t* __restrict__ min_orig) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || !core[i]) return;
  const int32_t r = stages::final_root(parent, int32_t(i));
  root[i] = r;
  atomicMin(min_orig + r, orig[i]);
}

// first[o] = 1 where original point o is the smallest-index core of its component.
__global__ void first_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ orig,
                             const int32_t* __restrict__ root, const int32_t* __restrict__ min_orig, int64_t n,
                             int32_t* __restrict__ first) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  first[orig[i]] = (core[i] && min_orig[root[i]] == orig[i]) ? 1 : 0;
}

__global__ void core_label_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ root,
                                  const int32_t* __restrict__ min_orig, const int32_t* __restrict__ cid, int64_t n,
                                  int32_t* __restrict__ lab) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  lab[i] = core[i] ? cid[min_orig[root[i]]] : -1;
}

__global__ void label_kernel(Params P, const double* __restrict__ xs, const double* __restrict__ ys,
                             const double* __restrict__ zs, const int32_t* __restrict__ cell_incl,
                             const int32_t* __restrict__ sub_start, const uint64_t* __restrict__ sub_key,
                             const int32_t* __restrict__ rep, const int32_t* __restrict__ ranges,
                             const uint8_t* __restrict__ core, const int32_t* __restrict__ lab,
                             const int32_t* __restrict__ orig, int64_t n, int64_t* __restrict__ labels) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  labels[orig[i]] = core[i] ? lab[i]
                            : stages::border_label(P, xs, ys, zs, cell_incl, sub_start, sub_key, rep, ranges, core,
                                                   lab, int32_t(i));
}

// Workspace layout; every block 256-byte aligned.
struct Layout {
  size_t keys_in, keys, idx_in, orig, xs, ys, zs, sub_flag, cell_flag, sub_incl, cell_incl, sub_start, sub_key,
      cell_keys, cell_start, counts, ranges, core, rep, parent, root, min_orig, first, cid, lab, bbox, temp,
      temp_bytes, total;
};

inline size_t align_up(size_t v) { return (v + 255) & ~size_t(255); }

// cub temporary storage for the sort over [0, end_bit) (typed exactly like the real call).
size_t sort_temp_bytes(int64_t n, int end_bit) {
  size_t bytes = 0;
  if (cub::DeviceRadixSort::SortPairs(nullptr, bytes, static_cast<const uint64_t*>(nullptr),
                                      static_cast<uint64_t*>(nullptr), static_cast<const int32_t*>(nullptr),
                                      static_cast<int32_t*>(nullptr), n, 0, end_bit) != cudaSuccess)
    return SIZE_MAX;
  return bytes;
}

size_t scan_temp_bytes(int64_t n) {
  size_t inc = 0, exc = 0;
  if (cub::DeviceScan::InclusiveSum(nullptr, inc, static_cast<const int32_t*>(nullptr), static_cast<int32_t*>(nullptr),
                                    n) != cudaSuccess ||
      cub::DeviceScan::ExclusiveSum(nullptr, exc, static_cast<const int32_t*>(nullptr), static_cast<int32_t*>(nullptr),
                                    n) != cudaSuccess)
    return SIZE_MAX;
  return std::max(inc, exc);
}

Layout make_layout(int64_t n_) {
  const size_t n = size_t(n_);
  Layout L{};
  size_t off = 0;
  auto take = [&](size_t bytes) {
    const size_t at = off;
    off = align_up(off + bytes);
    return at;
  };
  L.keys_in = take(n * 8);
  L.keys = take(n * 8);
  L.idx_in = take(n * 4);
  L.orig = take(n * 4);
  L.xs = take(n * 8);
  L.ys = take(n * 8);
  L.zs = take(n * 8);
  L.sub_flag = take(n * 4);
  L.cell_flag = take(n * 4);
  L.sub_incl = take(n * 4);
  L.cell_incl = take(n * 4);
  L.sub_start = take((n + 1) * 4);
  L.sub_key = take(n * 8);
  L.cell_keys = take(n * 8);
  L.cell_start = take((n + 1) * 4);
  L.counts = take(2 * 4);
  L.ranges = take(n * kR2 * 4);
  L.core = take(n);
  L.rep = take(n * 4);
  L.parent = take(n * 4);
  L.root = take(n * 4);
  L.min_orig = take(n * 4);
  L.first = take(n * 4);
  L.cid = take(n * 4);
  L.lab = take(n * 4);
  L.bbox = take(6 * 8);
  // The sort's key width is only known after the bounding box: size for all 64 bits (the
  // launcher re-queries with the real width and checks it fits).
  const size_t sort_bytes = sort_temp_bytes(n_, 64), scan_bytes = scan_temp_bytes(n_);
  if (sort_bytes == SIZE_MAX || scan_bytes == SIZE_MAX) return Layout{};  // total 0: reported as an error
  L.temp_bytes = align_up(std::max(sort_bytes, scan_bytes));
  L.temp = take(L.temp_bytes);
  L.total = off;
  return L;
}

inline bool launched() { return cudaPeekAtLastError() == cudaSuccess; }

}  // namespace

size_t dbscan_workspace_bytes(int64_t n) { return n > 0 ? make_layout(n).total : 0; }

template <typename T>
int dbscan(const T* points, int64_t n, double eps, int32_t min_samples, int64_t* labels, void* workspace,
           size_t workspace_bytes, cudaStream_t stream) {
  if (n <= 0) return kDbscanOk;
  if (n >= int64_t(INT32_MAX) || min_samples < 1 || !(eps > 0.0) || !std::isfinite(eps)) return kDbscanBadArgs;
  const Layout L = make_layout(n);
  if (L.total == 0 || workspace == nullptr || workspace_bytes < L.total) return kDbscanBadArgs;
  // Report only errors raised by this call's launches.
  if (cudaPeekAtLastError() != cudaSuccess) return kDbscanCudaError;
  char* ws = static_cast<char*>(workspace);
  auto at = [&](size_t off) { return static_cast<void*>(ws + off); };
  auto* keys_in = static_cast<uint64_t*>(at(L.keys_in));
  auto* keys = static_cast<uint64_t*>(at(L.keys));
  auto* idx_in = static_cast<int32_t*>(at(L.idx_in));
  auto* orig = static_cast<int32_t*>(at(L.orig));
  auto* xs = static_cast<double*>(at(L.xs));
  auto* ys = static_cast<double*>(at(L.ys));
  auto* zs = static_cast<double*>(at(L.zs));
  auto* sub_flag = static_cast<int32_t*>(at(L.sub_flag));
  auto* cell_flag = static_cast<int32_t*>(at(L.cell_flag));
  auto* sub_incl = static_cast<int32_t*>(at(L.sub_incl));
  auto* cell_incl = static_cast<int32_t*>(at(L.cell_incl));
  auto* sub_start = static_cast<int32_t*>(at(L.sub_start));
  auto* sub_key = static_cast<uint64_t*>(at(L.sub_key));
  auto* cell_keys = static_cast<uint64_t*>(at(L.cell_keys));
  auto* cell_start = static_cast<int32_t*>(at(L.cell_start));
  auto* counts = static_cast<int32_t*>(at(L.counts));
  auto* ranges = static_cast<int32_t*>(at(L.ranges));
  auto* core = static_cast<uint8_t*>(at(L.core));
  auto* rep = static_cast<int32_t*>(at(L.rep));
  auto* parent = static_cast<int32_t*>(at(L.parent));
  auto* root = static_cast<int32_t*>(at(L.root));
  auto* min_orig = static_cast<int32_t*>(at(L.min_orig));
  auto* first = static_cast<int32_t*>(at(L.first));
  auto* cid = static_cast<int32_t*>(at(L.cid));
  auto* lab = static_cast<int32_t*>(at(L.lab));
  auto* bbox = static_cast<unsigned long long*>(at(L.bbox));
  void* temp = at(L.temp);
  const unsigned nb = blocks_for(n);

  // Bounding box, read back (pinned-free: a pageable cudaMemcpy on the stream, then an
  // explicit stream sync before the host reads it) to size the grid and the sort.
  if (cudaMemsetAsync(bbox, 0xff, 3 * 8, stream) != cudaSuccess) return kDbscanCudaError;
  if (cudaMemsetAsync(bbox + 3, 0, 3 * 8, stream) != cudaSuccess) return kDbscanCudaError;
  const unsigned bb_blocks = nb < 1024u ? nb : 1024u;
  bbox_kernel<T><<<bb_blocks, kThreads, 0, stream>>>(points, n, bbox);
  if (!launched()) return kDbscanCudaError;
  unsigned long long bb_host[6] = {0, 0, 0, 0, 0, 0};
  if (cudaMemcpyAsync(bb_host, bbox, sizeof(bb_host), cudaMemcpyDeviceToHost, stream) != cudaSuccess)
    return kDbscanCudaError;
  if (cudaStreamSynchronize(stream) != cudaSuccess) return kDbscanCudaError;
  double lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    lo[a] = order_key_inverse(bb_host[a]);
    hi[a] = order_key_inverse(bb_host[3 + a]);
    if (!std::isfinite(lo[a]) || !std::isfinite(hi[a]) || !std::isfinite(hi[a] - lo[a])) return kDbscanNonFinite;
  }
  const Params P = stages::make_params(lo, hi, eps, min_samples);
  const int key_bits = P.g.bits[0] + P.g.bits[1] + P.g.bits[2] + dbscan::kSubBits;
  if (key_bits > 64) return kDbscanBadArgs;
  size_t temp_bytes = sort_temp_bytes(n, key_bits);
  if (temp_bytes > L.temp_bytes) return kDbscanBadArgs;

  key_kernel<T><<<nb, kThreads, 0, stream>>>(points, n, P.g, keys_in, idx_in);
  if (!launched()) return kDbscanCudaError;
  if (cub::DeviceRadixSort::SortPairs(temp, temp_bytes, static_cast<const uint64_t*>(keys_in), keys,
                                      static_cast<const int32_t*>(idx_in), orig, n, 0, key_bits,
                                      stream) != cudaSuccess)
    return kDbscanCudaError;
  gather_kernel<T><<<nb, kThreads, 0, stream>>>(points, keys, orig, n, xs, ys, zs, sub_flag, cell_flag);
  if (!launched()) return kDbscanCudaError;
  temp_bytes = L.temp_bytes;
  if (cub::DeviceScan::InclusiveSum(temp, temp_bytes, static_cast<const int32_t*>(sub_flag), sub_incl, n, stream) !=
      cudaSuccess)
    return kDbscanCudaError;
  temp_bytes = L.temp_bytes;
  if (cub::DeviceScan::InclusiveSum(temp, temp_bytes, static_cast<const int32_t*>(cell_flag), cell_incl, n,
                                    stream) != cudaSuccess)
    return kDbscanCudaError;
  segments_kernel<<<nb, kThreads, 0, stream>>>(keys, sub_incl, cell_incl, n, sub_start, sub_key, cell_keys, cell_start,
                                               counts);
  ranges_kernel<<<nb, kThreads, 0, stream>>>(P.g, cell_keys, cell_start, counts, sub_incl, ranges);
  core_kernel<<<nb, kThreads, 0, stream>>>(P, xs, ys, zs, sub_incl, cell_incl, sub_start, sub_key, ranges, n, core);
  rep_kernel<<<nb, kThreads, 0, stream>>>(core, sub_start, counts, rep);
  init_kernel<<<nb, kThreads, 0, stream>>>(P, core, sub_incl, rep, n, parent, min_orig);
  hook_kernel<<<nb, kThreads, 0, stream>>>(P, xs, ys, zs, sub_incl, cell_incl, sub_start, sub_key, rep, ranges, core, n,
                                           parent);
  root_kernel<<<nb, kThreads, 0, stream>>>(core, orig, parent, n, root, min_orig);
  first_kernel<<<nb, kThreads, 0, stream>>>(core, orig, root, min_orig, n, first);
  if (!launched()) return kDbscanCudaError;
  temp_bytes = L.temp_bytes;
  if (cub::DeviceScan::ExclusiveSum(temp, temp_bytes, static_cast<const int32_t*>(first), cid, n, stream) !=
      cudaSuccess)
    return kDbscanCudaError;
  core_label_kernel<<<nb, kThreads, 0, stream>>>(core, root, min_orig, cid, n, lab);
  label_kernel<<<nb, kThreads, 0, stream>>>(P, xs, ys, zs, cell_incl, sub_start, sub_key, rep, ranges, core, lab, orig,
                                            n, labels);
  return launched() ? kDbscanOk : kDbscanCudaError;
}

template int dbscan<float>(const float*, int64_t, double, int32_t, int64_t*, void*, size_t, cudaStream_t);
template int dbscan<double>(const double*, int64_t, double, int32_t, int64_t*, void*, size_t, cudaStream_t);

}  // namespace floxels::cuda
