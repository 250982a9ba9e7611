// CPU exact Euclidean distance transform and point-cloud occupancy (see kernels/edt.h).
//
// Memory plan: the float32 output doubles as the int32 squared-distance buffer (same size),
// always accessed as int32 (final floats are stored by bit pattern) so no type punning
// reaches the optimiser. Pass order keeps work in cache:
//   1+2. per Z slice (parallel over slices): X distances of each occupied row by sweeping
//        between consecutive occupied samples, then the Y envelope over blocks of
//        contiguous columns, using only the rows that had an occupied sample (the others
//        are all "infinite" and never enter an envelope, so they are not even written);
//   3.   per (y, block of x) (parallel): Z envelope over the non-empty slices only, then
//        sqrt * spacing written in place.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <string>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstring>
#include <vector>

#include "common/check.h"
#include "kernels/edt.h"

namespace floxels {
namespace {

using edt::kInf;

// Columns processed side by side: one cache line (or more) of int32 per row read.
constexpr int64_t kBlock = 32;
// Z pass: columns relaxed together by the search variant, and the largest Z it is used for.
constexpr int64_t kWide = 128;
constexpr int64_t kBruteMaxZ = 256;
// Y pass: average outward-search steps per row a block may use before it switches to the
// envelope.
constexpr int64_t kSearchBudget = 8;

// `lanes` independent lower envelopes (one per column of a block), each a stack of
// (apex, height) with capacity `cap`.
struct Envelopes {
  int64_t cap = 0;
  std::vector<int32_t> v, f;
  int32_t size[kBlock];

  void reset(int64_t capacity) {
    if (capacity > cap) {
      cap = capacity;
      v.resize(kBlock * cap);
      f.resize(kBlock * cap);
    }
    std::fill(size, size + kBlock, 0);
  }
  void push(int64_t b, int32_t q, int32_t fq) {
    int32_t* vb = v.data() + b * cap;
    int32_t* fb = f.data() + b * cap;
    int32_t k = size[b];
    while (k >= 2 && edt::middle_hidden(vb[k - 2], fb[k - 2], vb[k - 1], fb[k - 1], q, fq)) --k;
    vb[k] = q;
    fb[k] = fq;
    size[b] = k + 1;
  }
  // Writes the envelope minimum at x = 0..n-1 to out[x * stride] (as transformed by `op`),
  // one envelope member (a run of consecutive x) at a time, so the loop branches per
  // member instead of per sample. Needs size[b] > 0.
  template <class Op>
  void write(int64_t b, int32_t n, int32_t* out, int64_t stride, Op op) const {
    const int32_t* vb = v.data() + b * cap;
    const int32_t* fb = f.data() + b * cap;
    const int32_t m = size[b];
    int32_t start = 0;
    for (int32_t k = 0; k < m && start < n; ++k) {
      int32_t end = n;
      if (k + 1 < m) end = std::min(n, edt::segment_start(vb[k], fb[k], vb[k + 1], fb[k + 1]));
      for (int32_t x = start; x < end; ++x) out[x * stride] = op(edt::parabola(vb[k], fb[k], x));
      start = std::max(start, end);
    }
  }
};

// Squared distance along X of every sample of one row to the row's occupied samples;
// returns false (writing nothing) when the row has none.
bool row_pass(const uint8_t* occ, int32_t* out, int64_t X) {
  const void* hit = std::memchr(occ, 1, X);
  if (!hit) return false;
  int64_t prev = static_cast<const uint8_t*>(hit) - occ;
  for (int64_t x = 0; x < prev; ++x) out[x] = int32_t((prev - x) * (prev - x));
  out[prev] = 0;
  for (;;) {
    hit = prev + 1 < X ? std::memchr(occ + prev + 1, 1, X - prev - 1) : nullptr;
    if (!hit) {
      for (int64_t x = prev + 1; x < X; ++x) out[x] = int32_t((x - prev) * (x - prev));
      return true;
    }
    const int64_t next = static_cast<const uint8_t*>(hit) - occ;
    for (int64_t x = prev + 1; x < next; ++x) {
      const int64_t d = std::min(x - prev, next - x);
      out[x] = int32_t(d * d);
    }
    out[next] = 0;
    prev = next;
  }
}

// acc = min(acc, f + d2) elementwise; returns max(acc). The hot loop of the Z pass, built
// for AVX2 too (picked at load time) since the default x86-64 target has no int32 min.
__attribute__((target_clones("avx2", "default"))) int32_t relax_row(
    int32_t* __restrict acc, const int32_t* __restrict f, int32_t d2, int64_t n) {
  int32_t mx = 0;
  for (int64_t i = 0; i < n; ++i) {
    const int32_t a = std::min(acc[i], f[i] + d2);
    acc[i] = a;
    mx = std::max(mx, a);
  }
  return mx;
}

// Relaxes acc[0..n) with the candidate lines at sorted positions `lines` (values of line m at
// data + m * ld) in order of increasing distance from `pos`, stopping once d^2 reaches
// max(acc): no farther line can improve any column. `first` = index of the first line at
// or after pos. Returns the number of lines used, or -1 past max_steps (caller falls back).
int64_t search_outward(int32_t* acc, int64_t n, const int32_t* data, int64_t ld,
                       const std::vector<int32_t>& lines, int64_t first, int64_t pos, int64_t max_steps) {
  std::fill(acc, acc + n, kInf);
  const int64_t count = int64_t(lines.size());
  int32_t mx = kInf;
  int64_t lo = first - 1, hi = first, steps = 0;
  for (;;) {
    const int64_t dlo = lo >= 0 ? pos - lines[lo] : kInf;
    const int64_t dhi = hi < count ? lines[hi] - pos : kInf;
    const int64_t d = std::min(dlo, dhi);
    if (d == kInf || d * d >= mx) return steps;
    if (++steps > max_steps) return -1;
    const int64_t m = dlo <= dhi ? lo-- : hi++;
    mx = relax_row(acc, data + m * ld, int32_t(d * d), n);
  }
}

// first_ge[p] = index in `lines` of the first line at position >= p, for p in [0, n).
void first_at_or_after(const std::vector<int32_t>& lines, int64_t n, std::vector<int32_t>& first_ge) {
  first_ge.resize(n);
  for (int64_t p = 0, m = 0; p < n; ++p) {
    while (m < int64_t(lines.size()) && lines[m] < p) ++m;
    first_ge[p] = int32_t(m);
  }
}

// Per-thread buffers of the slice pass.
struct SliceScratch {
  std::vector<int32_t> rows, first_ge, local, acc;
  Envelopes env;
};

// Passes along X then Y for one (Y, X) slice; returns false (writing nothing) when the
// slice has no occupied sample.
bool slice_pass(const uint8_t* occ, int32_t* buf, int64_t Y, int64_t X, SliceScratch& sc) {
  auto& rows = sc.rows;
  rows.clear();
  for (int64_t y = 0; y < Y; ++y)
    if (row_pass(occ + y * X, buf + y * X, X)) rows.push_back(int32_t(y));
  if (rows.empty()) return false;
  const int64_t R = int64_t(rows.size());
  first_at_or_after(rows, Y, sc.first_ge);
  sc.local.resize(R * kWide);
  sc.acc.resize(kWide);
  for (int64_t x0 = 0; x0 < X; x0 += kWide) {
    const int64_t nb = std::min(kWide, X - x0);
    // Inputs of this block, copied: results overwrite them in place.
    for (int64_t m = 0; m < R; ++m)
      std::memcpy(sc.local.data() + m * kWide, buf + rows[m] * X + x0, nb * sizeof(int32_t));
    // Outward search first (cheap when distances are short); far-apart sparse rows make it
    // long, so past a budget the block is redone with the envelope (linear worst case).
    // The budget is a running average, so a hopeless block gives up after a few rows.
    int64_t used = 0;
    bool done = true;
    for (int64_t y = 0; y < Y && done; ++y) {
      const int64_t budget = kSearchBudget * (y + 1) + 4 * kSearchBudget - used;
      const int64_t steps = search_outward(sc.acc.data(), nb, sc.local.data(), kWide, rows, sc.first_ge[y], y, budget);
      if (steps < 0) {
        done = false;
      } else {
        used += steps;
        std::memcpy(buf + y * X + x0, sc.acc.data(), nb * sizeof(int32_t));
      }
    }
    if (done) continue;
    for (int64_t s0 = 0; s0 < nb; s0 += kBlock) {
      const int64_t sb = std::min(kBlock, nb - s0);
      sc.env.reset(R);
      for (int64_t m = 0; m < R; ++m) {
        const int32_t* r = sc.local.data() + m * kWide + s0;
        for (int64_t b = 0; b < sb; ++b) sc.env.push(b, rows[m], r[b]);
      }
      for (int64_t b = 0; b < sb; ++b)
        sc.env.write(b, int32_t(Y), buf + x0 + s0 + b, X, [](int32_t d2) { return d2; });
    }
  }
  return true;
}

int32_t as_output_bits(int32_t d2, double spacing) {
  return std::bit_cast<int32_t>(edt::to_distance(d2, spacing));
}

// out[i] = bits of the float distance of squared distance d2[i] (see edt::to_distance),
// vectorised: the double sqrt per sample is otherwise a large share of the last pass.
// no-math-errno lets sqrt vectorise; its inputs are never negative.
__attribute__((target_clones("avx2", "default"), optimize("no-math-errno"))) void to_distance_bits(
    const int32_t* __restrict d2, int32_t* __restrict out, int64_t n, double spacing) {
  for (int64_t i = 0; i < n; ++i) {
    const float dist = static_cast<float>(std::sqrt(static_cast<double>(d2[i])) * spacing);
    out[i] = std::bit_cast<int32_t>(d2[i] == kInf ? std::numeric_limits<float>::infinity() : dist);
  }
}

// Z pass for short Z (the usual lidar grid): for each output slice, relax a block of
// contiguous columns with the non-empty slices in order of increasing |dz|, stopping once
// dz^2 reaches the block's current maximum. SIMD-friendly and branch-predictable, unlike
// the envelope, whose pops mispredict. Worst case O(Z) vector steps per sample.
void z_pass_search(int32_t* buf, int64_t Z, int64_t Y, int64_t X, const std::vector<int32_t>& slices,
                   double spacing) {
  const int64_t plane = Y * X, nz = int64_t(slices.size());
  std::vector<int32_t> first_ge;
  first_at_or_after(slices, Z, first_ge);
  const int64_t xblocks = (X + kWide - 1) / kWide;
  const int64_t grain = std::max<int64_t>(1, 8192 / (Z * kWide));
  at::parallel_for(0, Y * xblocks, grain, [&](int64_t u0, int64_t u1) {
    std::vector<int32_t> local(nz * kWide), acc(kWide);
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t y = u / xblocks, x0 = (u % xblocks) * kWide;
      const int64_t nb = std::min(kWide, X - x0);
      int32_t* col = buf + y * X + x0;
      // Copy first: the results overwrite the inputs in place.
      for (int64_t m = 0; m < nz; ++m)
        std::memcpy(local.data() + m * kWide, col + slices[m] * plane, nb * sizeof(int32_t));
      for (int64_t z = 0; z < Z; ++z) {
        search_outward(acc.data(), nb, local.data(), kWide, slices, first_ge[z], z, INT64_MAX);
        to_distance_bits(acc.data(), col + z * plane, nb, spacing);
      }
    }
  });
}

// Z pass for long Z: lower envelope per column, blocks of contiguous columns.
void z_pass_envelope(int32_t* buf, int64_t Z, int64_t Y, int64_t X, const std::vector<int32_t>& slices,
                     double spacing) {
  const int64_t plane = Y * X;
  const int64_t xblocks = (X + kBlock - 1) / kBlock;
  const int64_t grain = std::max<int64_t>(1, 4096 / (Z * kBlock));
  at::parallel_for(0, Y * xblocks, grain, [&](int64_t u0, int64_t u1) {
    Envelopes env;
    for (int64_t u = u0; u < u1; ++u) {
      const int64_t y = u / xblocks, x0 = (u % xblocks) * kBlock;
      const int64_t nb = std::min(kBlock, X - x0);
      int32_t* col = buf + y * X + x0;
      env.reset(int64_t(slices.size()));
      for (int32_t z : slices) {
        const int32_t* r = col + z * plane;
        for (int64_t b = 0; b < nb; ++b) env.push(b, z, r[b]);
      }
      for (int64_t b = 0; b < nb; ++b)
        env.write(b, int32_t(Z), col + b, plane, [spacing](int32_t d2) { return as_output_bits(d2, spacing); });
    }
  });
}

at::Tensor edt_cpu(const at::Tensor& occupancy, double spacing) {
  // Integers go through std::to_string: streaming them into the message segfaulted in the
  // GPU machine's build (torch 2.11, g++ 13), see the edt family report.
  FLX_CHECK(occupancy.dim() == 3, "floxels: occupancy must be a (Z, Y, X) tensor, got ",
              std::to_string(occupancy.dim()), " dimensions");
  FLX_CHECK(occupancy.scalar_type() == at::kBool, "floxels: occupancy must be bool, got ",
              occupancy.scalar_type());
  check_spacing(spacing);
  const int64_t Z = occupancy.size(0), Y = occupancy.size(1), X = occupancy.size(2);
  auto out = at::empty({Z, Y, X}, occupancy.options().dtype(at::kFloat));
  if (out.numel() == 0) return out;
  FLX_CHECK(edt::max_squared_distance(Z, Y, X) < kInf,
              "floxels: edt grid (", std::to_string(Z), ", ", std::to_string(Y), ", ",
              std::to_string(X), ")",
              " is too large: squared distances would overflow int32");
  auto occ_c = occupancy.contiguous();
  const uint8_t* occ = reinterpret_cast<const uint8_t*>(occ_c.data_ptr<bool>());
  int32_t* buf = reinterpret_cast<int32_t*>(out.data_ptr<float>());
  const int64_t plane = Y * X;

  std::vector<uint8_t> slice_nonempty(Z, 0);
  at::parallel_for(0, Z, 1, [&](int64_t z0, int64_t z1) {
    SliceScratch scratch;
    for (int64_t z = z0; z < z1; ++z)
      slice_nonempty[z] = slice_pass(occ + z * plane, buf + z * plane, Y, X, scratch);
  });

  std::vector<int32_t> slices;
  for (int64_t z = 0; z < Z; ++z)
    if (slice_nonempty[z]) slices.push_back(int32_t(z));
  if (slices.empty()) return out.fill_(std::numeric_limits<float>::infinity());

  if (Z <= kBruteMaxZ)
    z_pass_search(buf, Z, Y, X, slices, spacing);
  else
    z_pass_envelope(buf, Z, Y, X, slices, spacing);
  return out;
}

at::Tensor points_to_occupancy_cpu(const at::Tensor& points, c10::ArrayRef<double> origin,
                                   double spacing, c10::ArrayRef<int64_t> grid_shape) {
  check_points(points);
  check_origin(origin);
  check_spacing(spacing);
  check_grid_shape(grid_shape);
  const int64_t Z = grid_shape[0], Y = grid_shape[1], X = grid_shape[2];
  auto out = at::zeros({Z, Y, X}, points.options().dtype(at::kBool));
  const int64_t N = points.size(0);
  if (N == 0) return out;
  auto pts = points.contiguous();
  uint8_t* occ = reinterpret_cast<uint8_t*>(out.data_ptr<bool>());
  AT_DISPATCH_FLOATING_TYPES(pts.scalar_type(), "points_to_occupancy_cpu", [&] {
    const scalar_t* p = pts.data_ptr<scalar_t>();
    const double ox = origin[0], oy = origin[1], oz = origin[2], s = spacing;
    at::parallel_for(0, N, 16384, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        const int64_t ix = edt::snap_index(p[3 * i], ox, s, X);
        const int64_t iy = edt::snap_index(p[3 * i + 1], oy, s, Y);
        const int64_t iz = edt::snap_index(p[3 * i + 2], oz, s, Z);
        if (ix < 0 || iy < 0 || iz < 0) continue;
        // Several points may mark one sample from different threads: relaxed atomic store.
        std::atomic_ref<uint8_t>(occ[(iz * Y + iy) * X + ix]).store(1, std::memory_order_relaxed);
      }
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("edt", &edt_cpu);
  m.impl("points_to_occupancy", &points_to_occupancy_cpu);
}

}  // namespace floxels
