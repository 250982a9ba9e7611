// CUDA problem_setup kernels: a thread per point (or per entry). Every value is the ATen
// implementation's (csrc/cpu/problem_setup.cpp) bit for bit: the per-point arithmetic is
// kernels/problem_setup.h, and the rest is integer work whose results do not depend on the
// order threads run in (duplicate stores of one value, integer atomics).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/problem_setup_launch.h"
#include "kernels/finite.h"
#include "kernels/problem_setup.h"

namespace floxels::cuda {
namespace {

constexpr int kThreads = 256;

unsigned blocks(int64_t n) { return unsigned((n + kThreads - 1) / kThreads); }

template <typename T>
__global__ void keys_kernel(const T* __restrict__ points, const int64_t* __restrict__ labels, int64_t n,
                            SetupGrid<T> g, int64_t* __restrict__ key, int* __restrict__ bad) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const T* p = points + 3 * i;
  if (!finite3(p[0], p[1], p[2])) *bad = 1;
  const int64_t k = setup::cell_key(p, g.o, g.spacing, g.size);
  key[i] = labels ? (labels[i] + 1) * g.cells + k : k;
}

template <typename T>
__global__ void corners_kernel(const T* __restrict__ points, const int64_t* __restrict__ labels,
                               const int64_t* __restrict__ order, int64_t n, SetupGrid<T> g, T* __restrict__ points_s,
                               int64_t* __restrict__ labels_s, int64_t* __restrict__ lin, T* __restrict__ w,
                               int* __restrict__ mark, long long* __restrict__ max_label) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int64_t src = order[i];
  T p[3];
  for (int a = 0; a < 3; ++a) p[a] = points_s[3 * i + a] = points[3 * src + a];
  if (labels) {
    const int64_t l = labels[src];
    labels_s[i] = l;
    atomicMax(max_label, static_cast<long long>(l));
  }
  int64_t c[setup::kCorners];
  T cw[setup::kCorners];
  setup::corners(p, g.o, g.spacing, g.size, c, cw);
  for (int j = 0; j < setup::kCorners; ++j) {
    lin[setup::kCorners * i + j] = c[j];
    w[setup::kCorners * i + j] = cw[j];
    mark[c[j]] = 1;
  }
}

__global__ void segments_kernel(const int64_t* __restrict__ lin, const int* __restrict__ pos,
                                const int64_t* __restrict__ labels_s, int64_t n, int64_t tile, int* __restrict__ inverse,
                                int* __restrict__ is_new) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  bool fresh = i % tile == 0;
  for (int j = 0; j < setup::kCorners; ++j) {
    const int64_t c = lin[setup::kCorners * i + j];
    inverse[setup::kCorners * i + j] = pos[c] - 1;
    // the renumbering keeps distinct lattice indices distinct: equal rows <=> equal indices
    if (i > 0) fresh |= c != lin[setup::kCorners * (i - 1) + j];
  }
  if (i > 0 && labels_s) fresh |= labels_s[i] != labels_s[i - 1];
  is_new[i] = fresh ? 1 : 0;
}

__global__ void sizes_kernel(const int* __restrict__ pos, int64_t cells, const int64_t* __restrict__ seg_incl, int64_t n,
                             const long long* __restrict__ max_label, const int* __restrict__ bad,
                             int64_t* __restrict__ sizes) {
  sizes[0] = pos[cells - 1];
  sizes[1] = seg_incl[n - 1];
  const long long m = *max_label + 1;
  sizes[2] = m > 0 ? m : 0;
  sizes[3] = *bad ? 0 : 1;
}

__global__ void tables_kernel(const int64_t* __restrict__ lin, const int* __restrict__ inverse,
                              const int* __restrict__ is_new, const int64_t* __restrict__ seg_incl, int64_t n, int64_t S,
                              int64_t* __restrict__ vertices, int* __restrict__ seg_ptr, int* __restrict__ flat) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  for (int j = 0; j < setup::kCorners; ++j)
    vertices[inverse[setup::kCorners * i + j]] = lin[setup::kCorners * i + j];  // duplicates: the same value
  if (is_new[i]) {
    const int64_t s = seg_incl[i] - 1;
    seg_ptr[s] = int(i);
    for (int j = 0; j < setup::kCorners; ++j) flat[setup::kCorners * s + j] = inverse[setup::kCorners * i + j];
  }
  if (i == 0) seg_ptr[S] = int(n);
}

__global__ void counts_kernel(const int* __restrict__ flat, int64_t m, int* __restrict__ counts) {
  const int64_t k = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k < m) atomicAdd(counts + flat[k], 1);
}

}  // namespace

template <typename T>
void setup_keys(const T* points, const int64_t* labels, int64_t n, const SetupGrid<T>& g, int64_t* key, int* bad,
                cudaStream_t s) {
  if (n > 0) keys_kernel<T><<<blocks(n), kThreads, 0, s>>>(points, labels, n, g, key, bad);
}

template <typename T>
void setup_corners(const T* points, const int64_t* labels, const int64_t* order, int64_t n, const SetupGrid<T>& g,
                   T* points_s, int64_t* labels_s, int64_t* lin, T* w, int* mark, long long* max_label,
                   cudaStream_t s) {
  if (n > 0)
    corners_kernel<T><<<blocks(n), kThreads, 0, s>>>(points, labels, order, n, g, points_s, labels_s, lin, w, mark,
                                                      max_label);
}

void setup_segments(const int64_t* lin, const int* pos, const int64_t* labels_s, int64_t n, int64_t tile,
                    int* inverse, int* is_new, cudaStream_t s) {
  if (n > 0) segments_kernel<<<blocks(n), kThreads, 0, s>>>(lin, pos, labels_s, n, tile, inverse, is_new);
}

void setup_sizes(const int* pos, int64_t cells, const int64_t* seg_incl, int64_t n, const long long* max_label,
                 const int* bad, int64_t* sizes, cudaStream_t s) {
  sizes_kernel<<<1, 1, 0, s>>>(pos, cells, seg_incl, n, max_label, bad, sizes);
}

void setup_tables(const int64_t* lin, const int* inverse, const int* is_new, const int64_t* seg_incl, int64_t n,
                  int64_t S, int64_t* vertices, int* seg_ptr, int* flat, cudaStream_t s) {
  if (n > 0) tables_kernel<<<blocks(n), kThreads, 0, s>>>(lin, inverse, is_new, seg_incl, n, S, vertices, seg_ptr, flat);
}

void setup_counts(const int* flat, int64_t m, int* counts, cudaStream_t s) {
  if (m > 0) counts_kernel<<<blocks(m), kThreads, 0, s>>>(flat, m, counts);
}

template void setup_keys<float>(const float*, const int64_t*, int64_t, const SetupGrid<float>&, int64_t*, int*,
                                cudaStream_t);
template void setup_keys<double>(const double*, const int64_t*, int64_t, const SetupGrid<double>&, int64_t*, int*,
                                 cudaStream_t);
template void setup_corners<float>(const float*, const int64_t*, const int64_t*, int64_t, const SetupGrid<float>&,
                                   float*, int64_t*, int64_t*, float*, int*, long long*, cudaStream_t);
template void setup_corners<double>(const double*, const int64_t*, const int64_t*, int64_t, const SetupGrid<double>&,
                                    double*, int64_t*, int64_t*, double*, int*, long long*, cudaStream_t);

}  // namespace floxels::cuda
