// CUDA exact Euclidean distance transform (math in kernels/edt.h).
//
// Three passes on int32 squared distances, each designed for coalesced access:
//   1. X (contiguous): one warp per row; __ballot_sync turns 32 samples into a bit mask, so
//      the nearest occupied sample to the left/right comes from clz/ffs plus a carry while
//      the warp walks the row forwards then backwards (reads/writes are 32 consecutive words).
//   2. Y and 3. Z: one thread per line; adjacent threads own adjacent X columns, so each
//      step of the lock-stepped scans reads/writes consecutive addresses. The lower envelope's
//      stack lives in a scratch buffer with the line's own layout (entry k at k*stride), so it
//      needs no shared memory and any line length works; the top two entries are cached in
//      registers, and entries hold the sample value too (the walk reads no input). The
//      output is written for x = 0..n-1 in lock step (coalesced); only the envelope
//      advances read divergently, and those hit L1/L2.
// Buffers: every pass reads and writes `out` in place (int32 squared distances viewed
// through the float buffer, float distances after pass 3); the envelope stacks of passes 2
// and 3, (q, f[q]) pairs, live in the scratch buffer (2N int32).
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/edt_launch.h"
#include "kernels/edt.h"

namespace floxels::cuda {
namespace {

using edt::kInf;

constexpr int kRowWarps = 8;      // warps per block of the X pass
constexpr int kLineThreads = 128;  // threads per block of the Y/Z passes

__global__ void edt_rows_kernel(const uint8_t* __restrict__ occ, int32_t* __restrict__ out, int64_t rows,
                                int32_t X) {
  const int64_t row = (int64_t(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const int lane = threadIdx.x & 31;
  if (row >= rows) return;  // uniform per warp
  const uint8_t* o = occ + row * X;
  int32_t* d = out + row * X;

  // Forward: index of the nearest occupied sample at or before x (-1: none), stored in d.
  int32_t last = -1;
  for (int32_t c = 0; c < X; c += 32) {
    const int32_t x = c + lane;
    const unsigned m = __ballot_sync(0xffffffffu, x < X && o[x] != 0);
    const unsigned upto = m & (0xffffffffu >> (31 - lane));
    if (x < X) d[x] = upto ? c + 31 - __clz(upto) : last;
    if (m) last = c + 31 - __clz(m);
  }
  if (last < 0) {  // empty row
    for (int32_t x = lane; x < X; x += 32) d[x] = kInf;
    return;
  }
  // Backward: nearest occupied at or after x, combined with the forward result.
  int32_t next = -1;
  for (int32_t c = ((X - 1) / 32) * 32; c >= 0; c -= 32) {
    const int32_t x = c + lane;
    const unsigned m = __ballot_sync(0xffffffffu, x < X && o[x] != 0);
    const unsigned from = m & (0xffffffffu << lane);
    const int32_t right = from ? c + __ffs(from) - 1 : next;
    if (x < X) {
      const int32_t left = d[x];
      int32_t dist = X;  // larger than any real distance
      if (left >= 0) dist = x - left;
      if (right >= 0 && right - x < dist) dist = right - x;
      d[x] = dist * dist;
    }
    if (m) next = c + __ffs(m) - 1;
  }
}

// Lower envelope of f[q*stride] + (x - q)^2 along one line per thread. Line `i` starts at
// (i / stride) * n * stride + i % stride, which covers both the Y pass (stride X) and the Z
// pass (stride Y*X) of a contiguous (Z, Y, X) array. The stack holds (q, f[q]) pairs, so
// the walk never re-reads the input and the output overwrites it in `buf` (int32 squared
// distances, or with kFinal float distances in the same memory): each line reads all its
// samples before it writes any. Latency hiding: the build loads kBatch samples at once, and
// the walk keeps one envelope member loaded ahead.
template <bool kFinal>
__global__ void edt_lines_kernel(int32_t* buf, int2* __restrict__ stack, int64_t lines, int32_t n, int64_t stride,
                                 double spacing) {
  constexpr int kBatch = 8;
  const int64_t line = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (line >= lines) return;
  const int64_t base = (line / stride) * n * stride + line % stride;
  const int32_t* f = buf + base;
  int32_t* out_d2 = buf;
  float* out_dist = reinterpret_cast<float*>(buf);
  int2* st = stack + base;

  int32_t cnt = 0, vt = 0, ft = 0, vp = 0, fp = 0;  // stack size, top and second entries
  for (int32_t q0 = 0; q0 < n; q0 += kBatch) {
    int32_t fb[kBatch];
#pragma unroll
    for (int j = 0; j < kBatch; ++j) fb[j] = q0 + j < n ? f[int64_t(q0 + j) * stride] : kInf;
#pragma unroll
    for (int j = 0; j < kBatch; ++j) {
      const int32_t q = q0 + j, fq = fb[j];
      if (fq == kInf) continue;
      while (cnt >= 2 && edt::middle_hidden(vp, fp, vt, ft, q, fq)) {
        --cnt;
        vt = vp;
        ft = fp;
        if (cnt >= 2) {
          const int2 e = st[int64_t(cnt - 2) * stride];
          vp = e.x;
          fp = e.y;
        }
      }
      st[int64_t(cnt) * stride] = make_int2(q, fq);
      ++cnt;
      vp = vt;
      fp = ft;
      vt = q;
      ft = fq;
    }
  }

  if (cnt == 0) {  // no occupied sample reaches this line
    for (int32_t x = 0; x < n; ++x) {
      if constexpr (kFinal)
        out_dist[base + int64_t(x) * stride] = edt::to_distance(kInf, spacing);
      else
        out_d2[base + int64_t(x) * stride] = kInf;
    }
    return;
  }
  // Walk the envelope: e0 the current member, e1 the next one, e2 the one after (loaded ahead).
  int32_t k = 0;
  int2 e0 = st[0], e1 = e0, e2 = e0;
  if (cnt > 1) e1 = st[stride];
  if (cnt > 2) e2 = st[2 * stride];
  for (int32_t x = 0; x < n; ++x) {
    while (k + 1 < cnt && edt::parabola(e1.x, e1.y, x) <= edt::parabola(e0.x, e0.y, x)) {
      ++k;
      e0 = e1;
      e1 = e2;
      if (k + 2 < cnt) e2 = st[int64_t(k + 2) * stride];
    }
    const int32_t d2 = edt::parabola(e0.x, e0.y, x);
    if constexpr (kFinal)
      out_dist[base + int64_t(x) * stride] = edt::to_distance(d2, spacing);
    else
      out_d2[base + int64_t(x) * stride] = d2;
  }
}

template <class T>
__global__ void points_to_occupancy_kernel(const T* __restrict__ p, int64_t n, double ox, double oy, double oz, double s,
                                           int64_t Z, int64_t Y, int64_t X, uint8_t* __restrict__ out) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int64_t ix = edt::snap_index(p[3 * i], ox, s, X);
  const int64_t iy = edt::snap_index(p[3 * i + 1], oy, s, Y);
  const int64_t iz = edt::snap_index(p[3 * i + 2], oz, s, Z);
  if (ix < 0 || iy < 0 || iz < 0) return;
  out[(iz * Y + iy) * X + ix] = 1;  // concurrent writers all store the same value
}

template <class T>
cudaError_t occupancy_impl(const T* points, int64_t n, const double* origin, double spacing, int64_t Z,
                           int64_t Y, int64_t X, uint8_t* out, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  const int threads = 256;
  const int64_t blocks = (n + threads - 1) / threads;
  points_to_occupancy_kernel<T><<<unsigned(blocks), threads, 0, stream>>>(
      points, n, origin[0], origin[1], origin[2], spacing, Z, Y, X, out);
  return cudaGetLastError();
}

}  // namespace

cudaError_t edt_launch(const uint8_t* occ, float* out, int32_t* scratch, int64_t Z, int64_t Y, int64_t X,
                       double spacing, cudaStream_t stream) {
  const int64_t N = Z * Y * X;
  if (N == 0) return cudaSuccess;
  // Every pass works in place in `out` (int32 squared distances, then float distances);
  // scratch holds the envelope stacks, (q, f) pairs with the line's layout.
  int32_t* d2 = reinterpret_cast<int32_t*>(out);
  int2* stack = reinterpret_cast<int2*>(scratch);

  const int64_t rows = Z * Y;
  const int64_t row_blocks = (rows + kRowWarps - 1) / kRowWarps;
  edt_rows_kernel<<<unsigned(row_blocks), kRowWarps * 32, 0, stream>>>(occ, d2, rows, int32_t(X));
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;

  const int64_t y_lines = Z * X;
  edt_lines_kernel<false><<<unsigned((y_lines + kLineThreads - 1) / kLineThreads), kLineThreads, 0, stream>>>(
      d2, stack, y_lines, int32_t(Y), X, spacing);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;

  const int64_t z_lines = Y * X;
  edt_lines_kernel<true><<<unsigned((z_lines + kLineThreads - 1) / kLineThreads), kLineThreads, 0, stream>>>(
      d2, stack, z_lines, int32_t(Z), Y * X, spacing);
  return cudaGetLastError();
}

cudaError_t points_to_occupancy_launch(const float* points, int64_t n, const double* origin, double spacing,
                                       int64_t Z, int64_t Y, int64_t X, uint8_t* out, cudaStream_t stream) {
  return occupancy_impl(points, n, origin, spacing, Z, Y, X, out, stream);
}

cudaError_t points_to_occupancy_launch(const double* points, int64_t n, const double* origin, double spacing,
                                       int64_t Z, int64_t Y, int64_t X, uint8_t* out, cudaStream_t stream) {
  return occupancy_impl(points, n, origin, spacing, Z, Y, X, out, stream);
}

}  // namespace floxels::cuda
