// CPU ops of the lidar pipeline, the per-frame host work of `floxels run`:
//  * lidar_keep_mask / lidar_point_classes: cropping, outliers and ground removal,
//    floxels_ext/lidar/preprocess/masks.py's numpy reference step for step (float64, same grid, same
//    block references, same filters, same trimmed plane);
//  * rigid_transform: a 4x4 transform of (N, 3) points in float64;
//  * lidar_select: the kept rows as an (M, 3) array and the rows with NaN/inf coordinates;
//  * frame_flow: a frame's optimised flow back into its file's rows and axes, plus the dynamic
//    flags.
// Why ops and not numpy: the run calls them from its reader and writer threads, and an op runs
// without the GIL from start to end, whereas numpy takes it back between every call; the
// thread driving the GPU waited for those threads (bench/RESULTS.md, floxels run). Each call is
// single-threaded: the pipeline's threads are the parallelism.
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <tuple>
#include <vector>

#include "common/check.h"
#include "kernels/finite.h"
#include "kernels/lidar.h"
#include "cpu/lidar_ground.h"
#include "cpu/lidar_plane.h"

namespace floxels {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// Class codes of lidar_point_classes (preprocess/settings.py's CROPPED, KEPT, GROUND, OUTLIER).
enum : uint8_t { kCropped = 0, kKept = 1, kGround = 2, kOutlier = 3 };

struct GroundGrid {
  int64_t H = 0, W = 0;
  std::vector<double> opened;   // the opened (and capped) lowest-point map, H x W
  std::vector<int64_t> cell;    // per point: its cell, -1 if it does not build the grid
  std::vector<char> outlier;    // per point (empty: none): step 0's outliers
};

struct OutlierRule {
  double below, above;  // NaN: no such test
};

// Step 0 of preprocess/masks.py's module docstring: flag the grid's outliers against the block
// references of preprocess/ground_outliers.py, then rebuild the lowest-point map without them.
template <typename T>
void drop_outliers(const lidar::Rows<T>& p, int64_t N, const OutlierRule& o, const double lo_c[2], double cell_size,
                   int64_t window_cells, GroundGrid& g, std::vector<double>& grid) {
  const bool below = lidar::has(o.below), above = lidar::has(o.above);
  if (!below && !above) return;
  int64_t Hb = 0, Wb = 0;
  std::vector<double> ref;
  if (below) ref = ground_reference(grid, g.H, g.W, lo_c, cell_size, window_cells, Hb, Wb);
  const int64_t b = ref_block_cells(window_cells);
  // the lowest z a point of each cell may have (its block's reference minus o.below), once per
  // cell: per point, the cell -> block lookup took four integer divisions (a fifth of the op)
  std::vector<double> floor_z;
  if (below) {
    floor_z.resize(g.H * g.W);
    for (int64_t a = 0; a < g.H; ++a)
      for (int64_t c = 0; c < g.W; ++c) floor_z[a * g.W + c] = ref[(a / b) * Wb + c / b] - o.below;
  }
  g.outlier.assign(N, 0);
  bool any = false;
  for (int64_t i = 0; i < N; ++i) {
    if (g.cell[i] < 0) continue;
    const double z = p.z(i);
    const bool bad = (above && z > o.above) || (below && z < floor_z[g.cell[i]]);
    g.outlier[i] = bad;
    any = any || bad;
  }
  if (!any) return;
  std::fill(grid.begin(), grid.end(), kInf);
  for (int64_t i = 0; i < N; ++i) {
    if (g.cell[i] < 0 || g.outlier[i]) continue;
    grid[g.cell[i]] = std::min(grid[g.cell[i]], p.z(i));  // no branch on it, as in build_ground
  }
}

// Steps 0-3 of preprocess/masks.py's module docstring: lowest z per cell, outliers, opening, plane cap.
template <typename T>
[[gnu::flatten]] void build_ground(const lidar::Rows<T>& p, int64_t N, double cell_size, int64_t window_cells, double max_rise,
                  double grid_distance, int64_t max_cells, const OutlierRule& orule, GroundGrid& g) {
  g.cell.assign(N, -1);
  double lo[2] = {kInf, kInf}, hi[2] = {-kInf, -kInf};
  bool any = false;
  for (int64_t i = 0; i < N; ++i) {
    const double x = p.x(i), y = p.y(i), z = p.z(i);
    if (!finite3(x, y, z) || lidar::compare_range(x, y, grid_distance) > 0) continue;
    g.cell[i] = 0;  // marks "builds the grid"; the index is set below
    any = true;
    lo[0] = std::min(lo[0], x), lo[1] = std::min(lo[1], y);
    hi[0] = std::max(hi[0], x), hi[1] = std::max(hi[1], y);
  }
  if (!any) return;
  double lo_c[2], size[2];
  for (int k = 0; k < 2; ++k) {
    lo_c[k] = std::floor(lo[k] / cell_size);
    size[k] = std::floor(hi[k] / cell_size) - lo_c[k] + 1;
  }
  FLX_CHECK(size[0] * size[1] <= double(max_cells), "floxels: lidar_keep_mask: points spread over ",
            std::llround(size[0] * cell_size), " x ", std::llround(size[1] * cell_size),
            " m: the ground grid would exceed ", max_cells, " cells; crop them (max_distance)");
  g.H = int64_t(size[0]), g.W = int64_t(size[1]);
  const int64_t H = g.H, W = g.W;
  std::vector<double> grid(H * W, kInf);
  // cell numbers far inside int64 (always, but for absurd direct calls): the cheap exact floor
  const bool small = std::max(std::fabs(lo_c[0]) + size[0], std::fabs(lo_c[1]) + size[1]) < 0x1p52;
  for (int64_t i = 0; i < N; ++i) {
    if (g.cell[i] < 0) continue;
    const double qa = p.x(i) / cell_size, qb = p.y(i) / cell_size;
    const int64_t a = int64_t((small ? lidar::floor_exact(qa) : std::floor(qa)) - lo_c[0]);
    const int64_t b = int64_t((small ? lidar::floor_exact(qb) : std::floor(qb)) - lo_c[1]);
    const int64_t c = a * W + b;
    g.cell[i] = c;
    // std::min (a minsd), stored every time: the branch it replaces mispredicted on real scans
    // (the KITTI sweeps: 4.6 -> 3.8 ms a scan with drop_outliers' loop alike; simulated scans
    // unchanged, bench/RESULTS.md); the same value (finite z, no NaN to order)
    grid[c] = std::min(grid[c], p.z(i));
  }
  drop_outliers(p, N, orule, lo_c, cell_size, window_cells, g, grid);
  // separable square filters (exact: min and max round nothing), constant border as scipy's
  const int64_t h = window_cells / 2;
  std::vector<double> buf(lidar::running_buffer(std::max(H, W), h)), tmp(H * W);
  auto filter = [&](std::vector<double>& v, double pad, auto less) {
    for (int64_t a = 0; a < H; ++a) lidar::running_extremum(&v[a * W], &tmp[a * W], W, 1, h, pad, buf.data(), less);
    for (int64_t b = 0; b < W; ++b) lidar::running_extremum(&tmp[b], &v[b], H, W, h, pad, buf.data(), less);
  };
  filter(grid, kInf, std::less<double>());
  for (auto& v : grid) v = is_finite(v) ? v : -kInf;  // empty windows must not raise the dilation
  filter(grid, -kInf, std::greater<double>());
  if (std::isfinite(max_rise)) cap_at_plane(grid, H, W, cell_size, max_rise);
  g.opened = std::move(grid);
}

// flatten: point_class and compare_range inlined into the loop (GCC kept them as calls: a
// tenth of the op's time)
template <typename T>
[[gnu::flatten]] void point_classes(const lidar::Rows<T>& p, int64_t N, const lidar::CropRule& rule, bool need_surface,
                   const GroundGrid& g, uint8_t* cls) {
  for (int64_t i = 0; i < N; ++i) {
    const double x = p.x(i), y = p.y(i), z = p.z(i);
    if (!finite3(x, y, z)) {
      cls[i] = kCropped;
      continue;
    }
    const double h = (need_surface && !g.cell.empty() && g.cell[i] >= 0) ? z - g.opened[g.cell[i]] : kNaN;
    cls[i] = uint8_t(lidar::point_class(rule, x, y, z, h, need_surface, !g.outlier.empty() && g.outlier[i]));
  }
}

template <typename T>
lidar::Rows<T> rows(const at::Tensor& points) {
  return {points.const_data_ptr<T>(), points.stride(0), points.stride(1)};
}

void check_host_points(const at::Tensor& points, const char* op) {
  check_points(points);
  FLX_CHECK(points.device().is_cpu(), "floxels: ", op, " runs on the CPU, got points on ", points.device());
}

double opt(const std::optional<double>& v, const char* name) {
  if (!v) return kNaN;
  FLX_CHECK(std::isfinite(*v) && *v >= 0, "floxels: lidar_keep_mask: ", name,
            " must be a finite number >= 0 or None, got ", *v);
  return *v;
}

// (N,) uint8 classes (kCropped, kKept, kGround, kOutlier) of one scan.
at::Tensor lidar_point_classes_cpu(const at::Tensor& points_in, std::optional<double> min_range,
                                   std::optional<double> max_range, std::optional<double> max_height,
                                   bool remove_ground, double ground_cell, int64_t window_cells,
                                   double ground_threshold, std::optional<double> ground_max_rise,
                                   double grid_distance, int64_t max_cells, std::optional<double> outlier_below,
                                   std::optional<double> outlier_above) {
  check_host_points(points_in, "lidar_keep_mask");
  FLX_CHECK(std::isfinite(ground_cell) && ground_cell > 0, "floxels: lidar_keep_mask: ground_cell must be > 0, got ",
            ground_cell);
  FLX_CHECK(window_cells >= 1 && window_cells % 2 == 1,
            "floxels: lidar_keep_mask: window_cells must be odd and >= 1, got ", window_cells);
  FLX_CHECK(std::isfinite(ground_threshold), "floxels: lidar_keep_mask: ground_threshold must be finite, got ",
            ground_threshold);
  FLX_CHECK(std::isfinite(grid_distance) && grid_distance > 0,
            "floxels: lidar_keep_mask: grid_distance must be a finite number > 0, got ", grid_distance);
  FLX_CHECK(max_cells >= 1, "floxels: lidar_keep_mask: max_cells must be >= 1, got ", max_cells);
  const lidar::CropRule rule{opt(min_range, "min_range"), opt(max_range, "max_range"),
                             opt(max_height, "max_height"), remove_ground, ground_threshold};
  const OutlierRule orule{opt(outlier_below, "outlier_below"), opt(outlier_above, "outlier_above")};
  const double max_rise = ground_max_rise ? *ground_max_rise : kInf;
  FLX_CHECK(!ground_max_rise || std::isfinite(*ground_max_rise),
            "floxels: lidar_keep_mask: ground_max_rise must be finite or None, got ", max_rise);
  const bool need_surface = remove_ground || lidar::has(rule.max_height);
  const auto& points = points_in;  // any strides: rows of a file read without a copy
  const int64_t N = points.size(0);
  auto out = at::empty({N}, points.options().dtype(at::kByte));
  uint8_t* cls = out.mutable_data_ptr<uint8_t>();
  // The per-point buffers (cell, outlier: ~9 bytes a point) keep their memory from call to call
  // on the calling thread: allocated afresh, a 200k-point scan's were page-faulted in every
  // call (~600 faults, ~1.2 ms of kernel time), glibc handing MB-sized blocks back to the kernel
  // when freed. Swapped in and out of a local GroundGrid, not used in place: a thread_local one
  // in the loops cost more than the faults (its members reloaded after every char store).
  // Kept up to kKeepPoints points (a larger scan's are freed).
  constexpr size_t kKeepPoints = size_t(1) << 22;
  thread_local std::vector<int64_t> keep_cell;
  thread_local std::vector<char> keep_outlier;
  GroundGrid g;
  g.cell.swap(keep_cell), g.outlier.swap(keep_outlier);
  g.cell.clear(), g.outlier.clear();
  auto run = [&](const auto& p) {
    if (need_surface) build_ground(p, N, ground_cell, window_cells, max_rise, grid_distance, max_cells, orule, g);
    point_classes(p, N, rule, need_surface, g, cls);
  };
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "lidar_keep_mask", [&] { run(rows<scalar_t>(points)); });
  if (g.cell.capacity() <= kKeepPoints) g.cell.swap(keep_cell), g.outlier.swap(keep_outlier);
  return out;
}

at::Tensor lidar_keep_mask_cpu(const at::Tensor& points_in, std::optional<double> min_range,
                               std::optional<double> max_range, std::optional<double> max_height,
                               bool remove_ground, double ground_cell, int64_t window_cells,
                               double ground_threshold, std::optional<double> ground_max_rise,
                               double grid_distance, int64_t max_cells, std::optional<double> outlier_below,
                               std::optional<double> outlier_above) {
  const auto cls = lidar_point_classes_cpu(points_in, min_range, max_range, max_height, remove_ground, ground_cell,
                                           window_cells, ground_threshold, ground_max_rise, grid_distance, max_cells,
                                           outlier_below, outlier_above);
  const int64_t N = cls.size(0);
  auto out = at::empty({N}, cls.options().dtype(at::kBool));
  const uint8_t* c = cls.const_data_ptr<uint8_t>();
  bool* keep = out.mutable_data_ptr<bool>();
  for (int64_t i = 0; i < N; ++i) keep[i] = c[i] == kKept;
  return out;
}

at::Tensor rigid_transform_cpu(const at::Tensor& points_in, const at::Tensor& transform_in) {
  check_host_points(points_in, "rigid_transform");
  FLX_CHECK(transform_in.dim() == 2 && transform_in.size(0) == 4 && transform_in.size(1) == 4,
            "floxels: rigid_transform: transform must be (4, 4), got ", transform_in.sizes());
  FLX_CHECK(transform_in.scalar_type() == at::kDouble && transform_in.device().is_cpu(),
            "floxels: rigid_transform: transform must be a float64 CPU tensor, got ", transform_in.scalar_type(),
            " on ", transform_in.device());
  const auto& points = points_in;
  const auto M = transform_in.contiguous();
  const double* m = M.const_data_ptr<double>();
  for (int k = 0; k < 16; ++k)
    FLX_CHECK(std::isfinite(m[k]), "floxels: rigid_transform: the transform has a NaN/inf entry");
  const int64_t N = points.size(0);
  auto out = at::empty({N, 3}, points.options());
  auto run = [&](const auto& p, auto* o) {
    for (int64_t i = 0; i < N; ++i) lidar::transform(m, p.at(i, 0), p.at(i, 1), p.at(i, 2), o + 3 * i);
  };
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "rigid_transform",
                             [&] { run(rows<scalar_t>(points), out.mutable_data_ptr<scalar_t>()); });
  return out;
}

std::tuple<at::Tensor, at::Tensor> lidar_select_cpu(const at::Tensor& points, const at::Tensor& mask_in) {
  check_host_points(points, "lidar_select");
  FLX_CHECK(mask_in.dim() == 1 && mask_in.scalar_type() == at::kBool && mask_in.device().is_cpu(),
            "floxels: lidar_select: mask must be a (N,) bool CPU tensor, got ", mask_in.sizes(), " ",
            mask_in.scalar_type(), " on ", mask_in.device());
  const int64_t N = points.size(0);
  FLX_CHECK(mask_in.size(0) == N, "floxels: lidar_select: mask has ", mask_in.size(0), " rows, points ", N);
  const auto mask = mask_in.contiguous();
  const bool* m = mask.const_data_ptr<bool>();
  // one pass over the points: the kept count from the mask alone, the (few) non-finite rows
  // gathered on the way (two passes over the strided rows cost twice the memory traffic)
  int64_t M = 0;
  for (int64_t i = 0; i < N; ++i) M += m[i];
  auto kept = at::empty({M, 3}, points.options());
  std::vector<int64_t> bad;
  auto fill = [&](const auto& p, auto* o) {
    for (int64_t i = 0; i < N; ++i) {
      const auto x = p.at(i, 0), y = p.at(i, 1), z = p.at(i, 2);
      if (!finite3(x, y, z)) bad.push_back(i);
      if (!m[i]) continue;
      o[0] = x, o[1] = y, o[2] = z;
      o += 3;
    }
  };
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "lidar_select",
                             [&] { fill(rows<scalar_t>(points), kept.mutable_data_ptr<scalar_t>()); });
  auto nonfinite = at::empty({int64_t(bad.size())}, points.options().dtype(at::kLong));
  std::copy(bad.begin(), bad.end(), nonfinite.mutable_data_ptr<int64_t>());
  return {kept, nonfinite};
}

std::tuple<at::Tensor, at::Tensor> frame_flow_cpu(const at::Tensor& flow_in, const at::Tensor& mask_in,
                                                  const at::Tensor& nonfinite_in, const at::Tensor& rotation_in,
                                                  double dynamic_threshold) {
  FLX_CHECK(flow_in.dim() == 2 && flow_in.size(1) == 3 && flow_in.scalar_type() == at::kFloat,
            "floxels: frame_flow: flow must be (M, 3) float32, got ", flow_in.sizes(), " ", flow_in.scalar_type());
  FLX_CHECK(mask_in.dim() == 1 && mask_in.scalar_type() == at::kBool, "floxels: frame_flow: mask must be (N,) bool");
  FLX_CHECK(nonfinite_in.dim() == 1 && nonfinite_in.scalar_type() == at::kLong,
            "floxels: frame_flow: nonfinite must be (K,) int64");
  FLX_CHECK(rotation_in.dim() == 2 && rotation_in.size(0) == 3 && rotation_in.size(1) == 3 &&
                rotation_in.scalar_type() == at::kFloat,
            "floxels: frame_flow: rotation must be (3, 3) float32");
  for (const auto* t : {&flow_in, &mask_in, &nonfinite_in, &rotation_in})
    FLX_CHECK(t->device().is_cpu(), "floxels: frame_flow runs on the CPU, got a tensor on ", t->device());
  FLX_CHECK(std::isfinite(dynamic_threshold) && dynamic_threshold >= 0,
            "floxels: frame_flow: dynamic_threshold must be a finite number >= 0, got ", dynamic_threshold);
  const auto flow = flow_in.contiguous();
  const auto mask = mask_in.contiguous();
  const auto nonfinite = nonfinite_in.contiguous();
  const auto R = rotation_in.contiguous();
  const int64_t N = mask.size(0), M = flow.size(0), K = nonfinite.size(0);
  const bool* m = mask.const_data_ptr<bool>();
  int64_t kept = 0;
  for (int64_t i = 0; i < N; ++i) kept += m[i];
  FLX_CHECK(kept == M, "floxels: frame_flow: mask selects ", kept, " rows but flow has ", M);
  // empty + serial fill, not at::zeros: zeros fills in parallel, and from the run's writer
  // threads that started an OpenMP team per thread (the pipeline's threads are the parallelism)
  auto full = at::empty({N, 3}, flow.options());
  auto dynamic = at::empty({N}, mask.options());
  float* o = full.mutable_data_ptr<float>();
  bool* d = dynamic.mutable_data_ptr<bool>();
  std::fill(o, o + 3 * N, 0.0f);
  std::fill(d, d + N, false);
  const int64_t* nf = nonfinite.const_data_ptr<int64_t>();
  for (int64_t k = 0; k < K; ++k) {
    FLX_CHECK(nf[k] >= 0 && nf[k] < N, "floxels: frame_flow: nonfinite index ", nf[k], " outside [0, ", N, ")");
    o[3 * nf[k]] = o[3 * nf[k] + 1] = o[3 * nf[k] + 2] = quiet_nan<float>();
  }
  const float* f = flow.const_data_ptr<float>();
  const float* r = R.const_data_ptr<float>();
  const float thr = float(dynamic_threshold), thr2 = thr * thr;
  for (int64_t i = 0, j = 0; i < N; ++i) {
    if (!m[i]) continue;
    const float fx = f[3 * j], fy = f[3 * j + 1], fz = f[3 * j + 2];
    ++j;
    float* q = o + 3 * i;
    for (int c = 0; c < 3; ++c) q[c] = fx * r[c] + fy * r[3 + c] + fz * r[6 + c];  // f @ R: world -> file axes
    d[i] = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] > thr2;
  }
  return {full, dynamic};
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CPU, m) {
  m.impl("lidar_keep_mask", &lidar_keep_mask_cpu);
  m.impl("lidar_point_classes", &lidar_point_classes_cpu);
  m.impl("rigid_transform", &rigid_transform_cpu);
  m.impl("lidar_select", &lidar_select_cpu);
  m.impl("frame_flow", &frame_flow_cpu);
}

}  // namespace floxels
