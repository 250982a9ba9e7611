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
//      registers. The output is written for x = 0..n-1 in lock step (coalesced); only the
//      envelope advances read divergently, and those hit L1/L2.
// Buffers: pass 1 writes `out` viewed as int32; pass 2 reads it, stacks in scratch[0:N] and
// writes scratch[N:2N]; pass 3 reads that, stacks in scratch[0:N] and writes float `out`.
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
// pass (stride Y*X) of a contiguous (Z, Y, X) array.
template <bool kFinal>
__global__ void edt_lines_kernel(const int32_t* __restrict__ in, int32_t* __restrict__ stack,
                                 int32_t* __restrict__ out_d2, float* __restrict__ out_dist, int64_t lines,
                                 int32_t n, int64_t stride, double spacing) {
  const int64_t line = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (line >= lines) return;
  const int64_t base = (line / stride) * n * stride + line % stride;
  const int32_t* f = in + base;
  int32_t* st = stack + base;

  int32_t cnt = 0, vt = 0, ft = 0, vp = 0, fp = 0;  // stack size, top and second entries
  for (int32_t q = 0; q < n; ++q) {
    const int32_t fq = f[q * stride];
    if (fq == kInf) continue;
    while (cnt >= 2 && edt::middle_hidden(vp, fp, vt, ft, q, fq)) {
      --cnt;
      vt = vp;
      ft = fp;
      if (cnt >= 2) {
        vp = st[int64_t(cnt - 2) * stride];
        fp = f[int64_t(vp) * stride];
      }
    }
    st[int64_t(cnt) * stride] = q;
    ++cnt;
    vp = vt;
    fp = ft;
    vt = q;
    ft = fq;
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
  // Walk the envelope: (v0, f0) is the current member, (v1, f1) the next one.
  int32_t k = 0, v0 = st[0], f0, v1 = 0, f1 = 0;
  f0 = f[int64_t(v0) * stride];
  if (cnt > 1) {
    v1 = st[stride];
    f1 = f[int64_t(v1) * stride];
  }
  for (int32_t x = 0; x < n; ++x) {
    while (k + 1 < cnt && edt::parabola(v1, f1, x) <= edt::parabola(v0, f0, x)) {
      ++k;
      v0 = v1;
      f0 = f1;
      if (k + 1 < cnt) {
        v1 = st[int64_t(k + 1) * stride];
        f1 = f[int64_t(v1) * stride];
      }
    }
    const int32_t d2 = edt::parabola(v0, f0, x);
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
  int32_t* d2_x = reinterpret_cast<int32_t*>(out);
  int32_t* stack = scratch;
  int32_t* d2_xy = scratch + N;

  const int64_t rows = Z * Y;
  const int64_t row_blocks = (rows + kRowWarps - 1) / kRowWarps;
  edt_rows_kernel<<<unsigned(row_blocks), kRowWarps * 32, 0, stream>>>(occ, d2_x, rows, int32_t(X));
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;

  const int64_t y_lines = Z * X;
  edt_lines_kernel<false><<<unsigned((y_lines + kLineThreads - 1) / kLineThreads), kLineThreads, 0, stream>>>(
      d2_x, stack, d2_xy, nullptr, y_lines, int32_t(Y), X, spacing);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;

  const int64_t z_lines = Y * X;
  edt_lines_kernel<true><<<unsigned((z_lines + kLineThreads - 1) / kLineThreads), kLineThreads, 0, stream>>>(
      d2_xy, stack, nullptr, out, z_lines, int32_t(Z), Y * X, spacing);
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
