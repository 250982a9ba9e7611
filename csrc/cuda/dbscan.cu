// CUDA exact DBSCAN with scikit-learn's labels (math in csrc/kernels/dbscan.h).
//
// Same stages as the CPU version: bounding box -> cell keys -> radix sort -> distinct
// cells + their 9 neighbour ranges -> core test -> lock-free union-find over core pairs
// (atomicCAS hooking of the larger root under the smaller, so no cycles) -> cluster ids
// ranked by each component's smallest original core index (scan over original order) ->
// border points take the smallest cluster id among their core neighbours.
#include <cuda_runtime.h>

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>

#include "cuda/dbscan_launch.h"
#include "kernels/dbscan.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;
using dbscan::Grid;

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
  keys[i] = dbscan::point_key(g, double(p[i * 3]), double(p[i * 3 + 1]), double(p[i * 3 + 2]));
  idx[i] = int32_t(i);
}

template <typename T>
__global__ void gather_kernel(const T* __restrict__ p, const uint64_t* __restrict__ keys,
                              const int32_t* __restrict__ orig, int64_t n, double* __restrict__ xs,
                              double* __restrict__ ys, double* __restrict__ zs, int32_t* __restrict__ flag) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int64_t o = orig[i];
  xs[i] = double(p[o * 3]);
  ys[i] = double(p[o * 3 + 1]);
  zs[i] = double(p[o * 3 + 2]);
  flag[i] = (i == 0 || keys[i] != keys[i - 1]) ? 1 : 0;
}

// cell_incl = inclusive scan of the new-cell flags: point i lies in cell cell_incl[i] - 1.
__global__ void cells_kernel(const uint64_t* __restrict__ keys, const int32_t* __restrict__ flag,
                             const int32_t* __restrict__ cell_incl, int64_t n, uint64_t* __restrict__ cell_keys,
                             int32_t* __restrict__ cell_start, int32_t* __restrict__ num_cells) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  if (flag[i]) {
    cell_keys[cell_incl[i] - 1] = keys[i];
    cell_start[cell_incl[i] - 1] = int32_t(i);
  }
  if (i == n - 1) {
    *num_cells = cell_incl[i];
    cell_start[cell_incl[i]] = int32_t(n);
  }
}

__global__ void ranges_kernel(Grid g, const uint64_t* __restrict__ cell_keys, const int32_t* __restrict__ cell_start,
                              const int32_t* __restrict__ num_cells, int32_t* __restrict__ ranges) {
  const int32_t c = int32_t(blockIdx.x) * blockDim.x + threadIdx.x;
  const int32_t m = *num_cells;
  if (c >= m) return;
  dbscan::neighbour_ranges(g, cell_keys, cell_start, m, cell_keys[c], ranges + int64_t(c) * 2 * dbscan::kRanges);
}

__global__ void count_kernel(const double* __restrict__ xs, const double* __restrict__ ys,
                             const double* __restrict__ zs, const int32_t* __restrict__ cell_incl,
                             const int32_t* __restrict__ ranges, int64_t n, double eps2, int32_t min_samples,
                             uint8_t* __restrict__ core, int32_t* __restrict__ parent, int32_t* __restrict__ min_orig) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * 2 * dbscan::kRanges;
  core[i] = dbscan::count_neighbours(xs, ys, zs, int32_t(i), rg, eps2, min_samples) >= min_samples;
  parent[i] = int32_t(i);
  min_orig[i] = INT_MAX;
}

// Reads go through volatile: other threads hook roots concurrently.
__device__ __forceinline__ int32_t find_root(int32_t* parent, int32_t x) {
  volatile int32_t* vp = parent;
  int32_t p = vp[x];
  while (p != x) {
    const int32_t gp = vp[p];
    if (gp != p) vp[x] = gp;  // path halving: only ever an ancestor
    x = p;
    p = gp;
  }
  return x;
}

__device__ __forceinline__ void unite(int32_t* parent, int32_t a, int32_t b) {
  while (true) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a == b) return;
    if (a < b) {
      const int32_t t = a;
      a = b;
      b = t;
    }
    if (atomicCAS(parent + a, a, b) == a) return;
  }
}

__global__ void hook_kernel(const double* __restrict__ xs, const double* __restrict__ ys,
                            const double* __restrict__ zs, const int32_t* __restrict__ cell_incl,
                            const int32_t* __restrict__ ranges, const uint8_t* __restrict__ core, int64_t n,
                            double eps2, int32_t* parent) {
  const int64_t ii = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (ii >= n || !core[ii]) return;
  const int32_t i = int32_t(ii);
  const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * 2 * dbscan::kRanges;
  const double px = xs[i], py = ys[i], pz = zs[i];
  // parent[j] == an ancestor of i proves j is already connected: no distance test.
  volatile const int32_t* vp = parent;
  int32_t ri = find_root(parent, i);
  for (int r = 0; r < dbscan::kRanges; ++r) {
    const int32_t end = min(rg[2 * r + 1], i);  // each unordered pair once
    for (int32_t j = rg[2 * r]; j < end; ++j) {
      if (!core[j] || vp[j] == ri) continue;
      if (dbscan::rdist(px, py, pz, xs[j], ys[j], zs[j]) > eps2) continue;
      unite(parent, i, j);
      ri = find_root(parent, i);
    }
  }
}

__global__ void root_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ orig, int64_t n,
                            int32_t* parent, int32_t* __restrict__ min_orig) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || !core[i]) return;
  const int32_t r = find_root(parent, int32_t(i));
  parent[i] = r;
  atomicMin(min_orig + r, orig[i]);
}

// first[o] = 1 where original point o is the smallest-index core of its component.
__global__ void first_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ orig,
                             const int32_t* __restrict__ parent, const int32_t* __restrict__ min_orig, int64_t n,
                             int32_t* __restrict__ first) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  first[orig[i]] = (core[i] && min_orig[parent[i]] == orig[i]) ? 1 : 0;
}

__global__ void core_label_kernel(const uint8_t* __restrict__ core, const int32_t* __restrict__ parent,
                                  const int32_t* __restrict__ min_orig, const int32_t* __restrict__ cid, int64_t n,
                                  int32_t* __restrict__ lab) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  lab[i] = core[i] ? cid[min_orig[parent[i]]] : -1;
}

__global__ void label_kernel(const double* __restrict__ xs, const double* __restrict__ ys,
                             const double* __restrict__ zs, const int32_t* __restrict__ cell_incl,
                             const int32_t* __restrict__ ranges, const uint8_t* __restrict__ core,
                             const int32_t* __restrict__ lab, const int32_t* __restrict__ orig, int64_t n,
                             double eps2, int64_t* __restrict__ labels) {
  const int64_t ii = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (ii >= n) return;
  const int32_t i = int32_t(ii);
  int32_t best = lab[i];
  if (!core[i]) {
    const int32_t* rg = ranges + int64_t(cell_incl[i] - 1) * 2 * dbscan::kRanges;
    const double px = xs[i], py = ys[i], pz = zs[i];
    best = INT_MAX;
    for (int r = 0; r < dbscan::kRanges; ++r)
      for (int32_t j = rg[2 * r]; j < rg[2 * r + 1]; ++j)
        if (core[j] && lab[j] < best && dbscan::rdist(px, py, pz, xs[j], ys[j], zs[j]) <= eps2) best = lab[j];
    if (best == INT_MAX) best = -1;
  }
  labels[orig[i]] = best;
}

// Workspace layout; every block 256-byte aligned.
struct Layout {
  size_t keys_in, keys_out, idx_in, idx_out, xs, ys, zs, flag, cell_incl, cell_keys, cell_start, num_cells,
      ranges, core, parent, min_orig, first, cid, lab, bbox, temp, temp_bytes, total;
};

inline size_t align_up(size_t v) { return (v + 255) & ~size_t(255); }

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
  L.keys_out = take(n * 8);
  L.idx_in = take(n * 4);
  L.idx_out = take(n * 4);
  L.xs = take(n * 8);
  L.ys = take(n * 8);
  L.zs = take(n * 8);
  L.flag = take(n * 4);
  L.cell_incl = take(n * 4);
  L.cell_keys = take(n * 8);
  L.cell_start = take((n + 1) * 4);
  L.num_cells = take(4);
  L.ranges = take(n * 2 * dbscan::kRanges * 4);
  L.core = take(n);
  L.parent = take(n * 4);
  L.min_orig = take(n * 4);
  L.first = take(n * 4);
  L.cid = take(n * 4);
  L.lab = take(n * 4);
  L.bbox = take(6 * 8);
  size_t sort_bytes = 0, scan_bytes = 0;
  cub::DeviceRadixSort::SortPairs(nullptr, sort_bytes, (const uint64_t*)nullptr, (uint64_t*)nullptr,
                                  (const int32_t*)nullptr, (int32_t*)nullptr, n_, 0, 64);
  cub::DeviceScan::InclusiveSum(nullptr, scan_bytes, (const int32_t*)nullptr, (int32_t*)nullptr, n_);
  size_t scan2 = 0;
  cub::DeviceScan::ExclusiveSum(nullptr, scan2, (const int32_t*)nullptr, (int32_t*)nullptr, n_);
  L.temp_bytes = align_up(std::max(sort_bytes, std::max(scan_bytes, scan2)));
  L.temp = take(L.temp_bytes);
  L.total = off;
  return L;
}

}  // namespace

size_t dbscan_workspace_bytes(int64_t n) { return n > 0 ? make_layout(n).total : 0; }

template <typename T>
int dbscan(const T* points, int64_t n, double eps, int32_t min_samples, int64_t* labels, void* workspace,
           size_t workspace_bytes, cudaStream_t stream) {
  if (n <= 0) return kDbscanOk;
  const Layout L = make_layout(n);
  if (workspace_bytes < L.total) return kDbscanCudaError;
  char* ws = static_cast<char*>(workspace);
  auto at = [&](size_t off) { return static_cast<void*>(ws + off); };
  auto* keys_in = static_cast<uint64_t*>(at(L.keys_in));
  auto* keys = static_cast<uint64_t*>(at(L.keys_out));
  auto* idx_in = static_cast<int32_t*>(at(L.idx_in));
  auto* orig = static_cast<int32_t*>(at(L.idx_out));
  auto* xs = static_cast<double*>(at(L.xs));
  auto* ys = static_cast<double*>(at(L.ys));
  auto* zs = static_cast<double*>(at(L.zs));
  auto* flag = static_cast<int32_t*>(at(L.flag));
  auto* cell_incl = static_cast<int32_t*>(at(L.cell_incl));
  auto* cell_keys = static_cast<uint64_t*>(at(L.cell_keys));
  auto* cell_start = static_cast<int32_t*>(at(L.cell_start));
  auto* num_cells = static_cast<int32_t*>(at(L.num_cells));
  auto* ranges = static_cast<int32_t*>(at(L.ranges));
  auto* core = static_cast<uint8_t*>(at(L.core));
  auto* parent = static_cast<int32_t*>(at(L.parent));
  auto* min_orig = static_cast<int32_t*>(at(L.min_orig));
  auto* first = static_cast<int32_t*>(at(L.first));
  auto* cid = static_cast<int32_t*>(at(L.cid));
  auto* lab = static_cast<int32_t*>(at(L.lab));
  auto* bbox = static_cast<unsigned long long*>(at(L.bbox));
  void* temp = at(L.temp);
  size_t temp_bytes = L.temp_bytes;
  const unsigned nb = blocks_for(n);

  // Bounding box, read back to size the grid and the sort.
  if (cudaMemsetAsync(bbox, 0xff, 3 * 8, stream) != cudaSuccess) return kDbscanCudaError;
  if (cudaMemsetAsync(bbox + 3, 0, 3 * 8, stream) != cudaSuccess) return kDbscanCudaError;
  const unsigned bb_blocks = nb < 1024u ? nb : 1024u;
  bbox_kernel<T><<<bb_blocks, kThreads, 0, stream>>>(points, n, bbox);
  unsigned long long bb_host[6];
  if (cudaMemcpyAsync(bb_host, bbox, sizeof(bb_host), cudaMemcpyDeviceToHost, stream) != cudaSuccess)
    return kDbscanCudaError;
  if (cudaStreamSynchronize(stream) != cudaSuccess) return kDbscanCudaError;
  double lo[3], hi[3];
  for (int a = 0; a < 3; ++a) {
    lo[a] = order_key_inverse(bb_host[a]);
    hi[a] = order_key_inverse(bb_host[3 + a]);
    if (!std::isfinite(lo[a]) || !std::isfinite(hi[a]) || !std::isfinite(hi[a] - lo[a])) return kDbscanNonFinite;
  }
  const Grid g = dbscan::make_grid(lo, hi, eps);
  const int key_bits = g.bits[0] + g.bits[1] + g.bits[2];
  const double eps2 = eps * eps;

  key_kernel<T><<<nb, kThreads, 0, stream>>>(points, n, g, keys_in, idx_in);
  if (cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys_in, keys, idx_in, orig, n, 0,
                                      key_bits > 0 ? key_bits : 1, stream) != cudaSuccess)
    return kDbscanCudaError;
  gather_kernel<T><<<nb, kThreads, 0, stream>>>(points, keys, orig, n, xs, ys, zs, flag);
  temp_bytes = L.temp_bytes;
  if (cub::DeviceScan::InclusiveSum(temp, temp_bytes, flag, cell_incl, n, stream) != cudaSuccess)
    return kDbscanCudaError;
  cells_kernel<<<nb, kThreads, 0, stream>>>(keys, flag, cell_incl, n, cell_keys, cell_start, num_cells);
  ranges_kernel<<<nb, kThreads, 0, stream>>>(g, cell_keys, cell_start, num_cells, ranges);
  count_kernel<<<nb, kThreads, 0, stream>>>(xs, ys, zs, cell_incl, ranges, n, eps2, min_samples, core, parent,
                                            min_orig);
  hook_kernel<<<nb, kThreads, 0, stream>>>(xs, ys, zs, cell_incl, ranges, core, n, eps2, parent);
  root_kernel<<<nb, kThreads, 0, stream>>>(core, orig, n, parent, min_orig);
  first_kernel<<<nb, kThreads, 0, stream>>>(core, orig, parent, min_orig, n, first);
  temp_bytes = L.temp_bytes;
  if (cub::DeviceScan::ExclusiveSum(temp, temp_bytes, first, cid, n, stream) != cudaSuccess)
    return kDbscanCudaError;
  core_label_kernel<<<nb, kThreads, 0, stream>>>(core, parent, min_orig, cid, n, lab);
  label_kernel<<<nb, kThreads, 0, stream>>>(xs, ys, zs, cell_incl, ranges, core, lab, orig, n, eps2, labels);
  return cudaGetLastError() == cudaSuccess ? kDbscanOk : kDbscanCudaError;
}

template int dbscan<float>(const float*, int64_t, double, int32_t, int64_t*, void*, size_t, cudaStream_t);
template int dbscan<double>(const double*, int64_t, double, int32_t, int64_t*, void*, size_t, cudaStream_t);

}  // namespace floxels::cuda
