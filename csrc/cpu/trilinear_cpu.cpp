// CPU trilinear gather / gather-backward / scatter.
//
// The gather is embarrassingly parallel over points. The scatter (also the grid gradient of
// the gather) is made thread-safe and deterministic without atomics or per-thread grids:
//  1. a stable counting sort of the points by the (z, y) row of their lower corner
//     (per-chunk histograms, so it runs in parallel);
//  2. rows are cut into one contiguous range per thread, balanced by point count;
//  3. the 8 corners are written in 4 phases, one per (dz, dy) corner pair: in a phase, row
//     range [a, b) writes only rows [a, b) + (dz * Y + dy), so threads never collide.
// Each voxel therefore always receives its contributions in the same order whatever the
// thread count, and the sorted writes sweep the grid nearly sequentially (cache friendly).
// Points with a NaN/inf coordinate are ignored by the scatter and give NaN gather rows
// (kernels/trilinear.h).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/from_blob.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <memory>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include "common/op_args.h"
#include "kernels/trilinear.h"

namespace floxels {
namespace {

struct GridGeom {
  int64_t Z, Y, X;
  double ox, oy, oz, spacing;
  int64_t vol() const { return Z * Y * X; }
};

template <typename T>
tri::Cell<T> cell_of(const T* p, const GridGeom& g) {
  return tri::cell_setup<T>(p, T(g.ox), T(g.oy), T(g.oz), T(g.spacing), g.Z, g.Y, g.X);
}

// Writes the (dz, dy) corner pair of one point: out[ch][base+off], out[ch][base+off+sx].
template <typename T>
inline void splat_pair(T* out, int64_t C, int64_t vol, int64_t base, int64_t sx, T w, T tx, const T* v) {
  const T w0 = w * (T(1) - tx), w1 = w * tx;
  for (int64_t ch = 0; ch < C; ++ch) {
    T* o = out + ch * vol + base;
    o[0] += v[ch] * w0;
    o[sx] += v[ch] * w1;
  }
}

// Below this many points the sort costs more than it saves: splat serially in input order.
constexpr int64_t kSerialScatter = 4096;

template <typename T>
void scatter_into(T* out, const T* values, int64_t C, const T* pts, int64_t N, const GridGeom& g) {
  const int64_t vol = g.vol();
  const int64_t nthreads = std::max<int64_t>(1, at::get_num_threads());
  if (N < kSerialScatter || nthreads == 1) {
    for (int64_t i = 0; i < N; ++i) {
      const auto c = cell_of(pts + 3 * i, g);
      if (!c.ok) continue;  // non-finite point: ignored
      const T* v = values + i * C;
      for (int dz = 0; dz < 2; ++dz)
        for (int dy = 0; dy < 2; ++dy) {
          const T w = (dz ? c.tz : T(1) - c.tz) * (dy ? c.ty : T(1) - c.ty);
          splat_pair(out, C, vol, c.base + dz * c.sz + dy * c.sy, c.sx, w, c.tx, v);
        }
    }
    return;
  }
  const int64_t nrows = g.Z * g.Y;
  FLX_CHECK(nrows < (int64_t(1) << 31) && N < (int64_t(1) << 31),
              "floxels: trilinear_scatter supports < 2^31 points and rows");
  const int64_t P = nthreads;  // sort chunks
  auto chunk_lo = [&](int64_t p) { return N * p / P; };

  // 1. row key + per-chunk histogram
  std::unique_ptr<int32_t[]> key(new int32_t[N]);
  std::vector<int64_t> hist(P * nrows, 0);
  at::parallel_for(0, P, 1, [&](int64_t pb, int64_t pe) {
    for (int64_t p = pb; p < pe; ++p) {
      int64_t* h = hist.data() + p * nrows;
      for (int64_t i = chunk_lo(p); i < chunk_lo(p + 1); ++i) {
        const auto r = static_cast<int32_t>(cell_of(pts + 3 * i, g).row);
        key[i] = r;
        ++h[r];
      }
    }
  });
  // 2. stable offsets: row-major over (row, chunk)
  std::vector<int64_t> row_start(nrows + 1);
  int64_t run = 0;
  for (int64_t r = 0; r < nrows; ++r) {
    row_start[r] = run;
    for (int64_t p = 0; p < P; ++p) {
      const int64_t n = hist[p * nrows + r];
      hist[p * nrows + r] = run;
      run += n;
    }
  }
  row_start[nrows] = run;
  // 3. sorted per-point data: lower-corner index, fractions, values
  std::unique_ptr<int64_t[]> sbase(new int64_t[N]);
  std::unique_ptr<T[]> st(new T[3 * N]);
  std::unique_ptr<T[]> sval(new T[C * N + 1]);
  at::parallel_for(0, P, 1, [&](int64_t pb, int64_t pe) {
    for (int64_t p = pb; p < pe; ++p) {
      int64_t* h = hist.data() + p * nrows;
      for (int64_t i = chunk_lo(p); i < chunk_lo(p + 1); ++i) {
        const auto c = cell_of(pts + 3 * i, g);
        const int64_t pos = h[key[i]]++;
        sbase[pos] = c.base;
        st[3 * pos] = c.tx;
        st[3 * pos + 1] = c.ty;
        st[3 * pos + 2] = c.tz;
        // a non-finite point is ignored: it adds exact zeros (its clamped weights are finite)
        for (int64_t ch = 0; ch < C; ++ch) sval[pos * C + ch] = c.ok ? values[i * C + ch] : T(0);
      }
    }
  });
  // 4. balanced row ranges, one per thread
  std::vector<int64_t> cut(nthreads + 1);
  cut[0] = 0;
  cut[nthreads] = nrows;
  for (int64_t p = 1; p < nthreads; ++p) {
    const int64_t target = N * p / nthreads;
    cut[p] = std::lower_bound(row_start.begin(), row_start.end() - 1, target) - row_start.begin();
    cut[p] = std::max(cut[p], cut[p - 1]);
  }
  const int64_t sx = g.X >= 2 ? 1 : 0, sy = g.Y >= 2 ? g.X : 0, sz = g.Z >= 2 ? g.X * g.Y : 0;
  // 5. four collision-free phases
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy) {
      const int64_t off = dz * sz + dy * sy;
      at::parallel_for(0, nthreads, 1, [&](int64_t pb, int64_t pe) {
        for (int64_t p = pb; p < pe; ++p) {
          for (int64_t k = row_start[cut[p]]; k < row_start[cut[p + 1]]; ++k) {
            const T* t = st.get() + 3 * k;
            const T w = (dz ? t[2] : T(1) - t[2]) * (dy ? t[1] : T(1) - t[1]);
            splat_pair(out, C, vol, sbase[k] + off, sx, w, t[0], sval.get() + k * C);
          }
        }
      });
    }
}

// Zero-filled CPU output grids. at::zeros on a fresh large allocation faults in every 4 KiB
// page and memsets it: for a (3, 40, 400, 400) float grid that costs more than the scatter.
// Two tricks, in the spirit of torch's CUDA caching allocator:
//  * a small process-wide cache keeps the last freed big grids; reusing one costs a
//    (parallel) memset of memory that is already mapped, much cheaper than faulting it in;
//  * otherwise a fresh anonymous mapping (already zero: no memset) with transparent huge
//    pages, so the pages that do get touched fault in 2 MiB at a time.
// Small outputs use calloc.
class GridCache {
 public:
  struct Block {
    void* base = nullptr;
    size_t len = 0;
  };
  static GridCache& get() {
    static GridCache* c = new GridCache();  // leaked on purpose: outlives tensors freed at exit
    return *c;
  }
  bool take(size_t len, Block& out) {
    std::lock_guard<std::mutex> lock(mu_);
    for (size_t i = 0; i < n_; ++i)
      if (blocks_[i].len == len) {
        out = blocks_[i];
        blocks_[i] = blocks_[--n_];
        return true;
      }
    return false;
  }
  void give(Block b) {
    std::unique_lock<std::mutex> lock(mu_);
    if (n_ == kMax) {  // evict the oldest
      Block old = blocks_[0];
      for (size_t i = 1; i < n_; ++i) blocks_[i - 1] = blocks_[i];
      blocks_[n_ - 1] = b;
      lock.unlock();
      release(old);
      return;
    }
    blocks_[n_++] = b;
  }
  static void release(Block b);

 private:
  static constexpr size_t kMax = 2;
  std::mutex mu_;
  Block blocks_[kMax];
  size_t n_ = 0;
};

#if defined(__linux__)
void GridCache::release(Block b) { munmap(b.base, b.len); }
#else
void GridCache::release(Block b) { std::free(b.base); }
#endif

constexpr size_t kHugePage = size_t(2) << 20;

char* aligned_data(void* base) {
  const uintptr_t b = reinterpret_cast<uintptr_t>(base);
  return reinterpret_cast<char*>((b + kHugePage - 1) / kHugePage * kHugePage);
}

at::Tensor fresh_zeros(at::IntArrayRef sizes, const at::TensorOptions& opts) {
  const int64_t numel = checked_numel(sizes, "output grid");  // <= 2^60: nbytes cannot wrap
  const size_t nbytes = static_cast<size_t>(numel) * c10::elementSize(c10::typeMetaToScalarType(opts.dtype()));
  if (nbytes >= 2 * kHugePage) {
    const size_t len = (nbytes + kHugePage - 1) / kHugePage * kHugePage + kHugePage;  // + slack to align
    GridCache::Block blk;
    char* data;
    if (GridCache::get().take(len, blk)) {
      data = aligned_data(blk.base);
      at::parallel_for(0, static_cast<int64_t>(nbytes), int64_t(1) << 22, [&](int64_t b, int64_t e) {
        std::memset(data + b, 0, static_cast<size_t>(e - b));
      });
    } else {
#if defined(__linux__)
      blk.base = mmap(nullptr, len, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
      FLX_CHECK(blk.base != MAP_FAILED, "floxels: out of memory mapping ", nbytes, " bytes");
      data = aligned_data(blk.base);
      madvise(data, len - (data - static_cast<char*>(blk.base)), MADV_HUGEPAGE);  // a hint only
#else
      blk.base = std::calloc(len, 1);
      FLX_CHECK(blk.base != nullptr, "floxels: out of memory allocating ", nbytes, " bytes");
      data = aligned_data(blk.base);
#endif
      blk.len = len;
    }
    return at::from_blob(data, sizes, [blk](void*) { GridCache::get().give(blk); }, opts);
  }
  void* ptr = std::calloc(std::max<size_t>(nbytes, 1), 1);
  FLX_CHECK(ptr != nullptr, "floxels: out of memory allocating ", nbytes, " bytes");
  return at::from_blob(ptr, sizes, [](void* q) { std::free(q); }, opts);
}

GridGeom geom(c10::ArrayRef<double> origin, double spacing, int64_t Z, int64_t Y, int64_t X) {
  return GridGeom{Z, Y, X, origin[0], origin[1], origin[2], spacing};
}

at::Tensor gather_cpu(const at::Tensor& grid_in, const at::Tensor& points_in, c10::ArrayRef<double> origin,
                      double spacing) {
  args::gather(grid_in, points_in, origin, spacing);
  const auto grid = grid_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = grid.size(0);
  const auto g = geom(origin, spacing, grid.size(1), grid.size(2), grid.size(3));
  auto out = at::empty({N, C}, grid.options());
  if (N == 0 || C == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "trilinear_gather_cpu", [&] {
    const scalar_t* gp = grid.const_data_ptr<scalar_t>();
    const scalar_t* pp = points.const_data_ptr<scalar_t>();
    scalar_t* op = out.mutable_data_ptr<scalar_t>();
    at::parallel_for(0, N, 2048, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i)
        tri::gather_point(gp, C, g.vol(), cell_of(pp + 3 * i, g), op + i * C, int64_t(1));
    });
  });
  return out;
}

at::Tensor scatter_cpu(const at::Tensor& values_in, const at::Tensor& points_in, c10::ArrayRef<double> origin,
                       double spacing, c10::ArrayRef<int64_t> grid_shape) {
  args::scatter(values_in, points_in, origin, spacing, grid_shape);
  const auto values = values_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = values.size(1);
  const auto g = geom(origin, spacing, grid_shape[0], grid_shape[1], grid_shape[2]);
  auto out = fresh_zeros({C, g.Z, g.Y, g.X}, values.options());
  if (N == 0 || C == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(values.scalar_type(), "trilinear_scatter_cpu", [&] {
    scatter_into(out.mutable_data_ptr<scalar_t>(), values.const_data_ptr<scalar_t>(), C,
                 points.const_data_ptr<scalar_t>(), N, g);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> gather_backward_cpu(const at::Tensor& grad_in, const at::Tensor& grid_in,
                                                       const at::Tensor& points_in, c10::ArrayRef<double> origin,
                                                       double spacing, bool need_grid_grad, bool need_points_grad) {
  args::gather_backward(grad_in, grid_in, points_in, origin, spacing);
  const auto grad = grad_in.contiguous();
  const auto grid = grid_in.contiguous();
  const auto points = points_in.contiguous();
  const int64_t N = points.size(0), C = grid.size(0);
  const auto g = geom(origin, spacing, grid.size(1), grid.size(2), grid.size(3));
  at::Tensor gg = need_grid_grad ? fresh_zeros(grid.sizes(), grid.options()) : at::empty({0}, grid.options());
  at::Tensor gpts = need_points_grad ? at::empty_like(points) : at::empty({0}, points.options());
  if (N == 0) return {gg, gpts};
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "trilinear_gather_backward_cpu", [&] {
    const scalar_t* pp = points.const_data_ptr<scalar_t>();
    const scalar_t* gop = grad.const_data_ptr<scalar_t>();
    if (need_grid_grad && C > 0) scatter_into(gg.mutable_data_ptr<scalar_t>(), gop, C, pp, N, g);
    if (need_points_grad) {
      const scalar_t* gridp = grid.const_data_ptr<scalar_t>();
      scalar_t* out = gpts.mutable_data_ptr<scalar_t>();
      at::parallel_for(0, N, 2048, [&](int64_t b, int64_t e) {
        for (int64_t i = b; i < e; ++i)
          tri::gather_point_grad(gridp, C, g.vol(), cell_of(pp + 3 * i, g), gop + i * C, scalar_t(spacing),
                                 out + 3 * i);
      });
    }
  });
  return {gg, gpts};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("trilinear_gather", &gather_cpu);
  m.impl("trilinear_gather_backward", &gather_backward_cpu);
  m.impl("trilinear_scatter", &scatter_cpu);
}

}  // namespace floxels
