// Stress test of the CUDA exact DBSCAN (csrc/cuda/dbscan.cu) with no torch: lidar-like clouds
// (rings, objects, dense near-sensor blobs), float and double, several eps / min_samples,
// many calls, each checked for CUDA errors and compared label for label with an independent
// CPU DBSCAN written here (hash grid + scikit-learn's index-order BFS, dbscan_inner).
//
//   nvcc -std=c++20 -arch=sm_90 -O3 --expt-relaxed-constexpr -Xcompiler -ffp-contract=off \
//        -I csrc scripts/dbscan_stress.cu csrc/cuda/dbscan.cu -o /tmp/dbscan_stress
//   /tmp/dbscan_stress [--calls 200] [--max-n 200000] [--reps R] [--no-time] [-v]
//   /tmp/dbscan_stress --emulate [--max-n 20000]   (no GPU: same stage code run on the CPU)
//   /tmp/dbscan_stress --emulate --dump DIR        (also writes clouds + reference labels)
//
// Every configuration runs at least once (R times each with --reps, else about --calls calls
// in all); each cloud's reference labels are computed once.
//
// Prints one summary line ("dbscan_stress: OK ..." or "dbscan_stress: FAIL ...") and exits 1
// on any mismatch or CUDA error.
#include <cuda_runtime.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <unordered_map>
#include <vector>

#include "cuda/dbscan_launch.h"
#include "cuda/dbscan_stages.cuh"

namespace {

// ---------------------------------------------------------------- CPU reference (sklearn)
// Distances exactly like sklearn's KDTree rdist: float64, ((dx*dx + dy*dy) + dz*dz), no FMA
// (built with -ffp-contract=off), compared <= eps*eps.
struct Reference {
  const std::vector<double>& p;  // (n, 3)
  int64_t n;
  double eps2, cs, lo[3];
  std::unordered_map<uint64_t, std::vector<int32_t>> cells;

  Reference(const std::vector<double>& pts, double eps) : p(pts), n(int64_t(pts.size() / 3)), eps2(eps * eps) {
    double hi[3];
    for (int a = 0; a < 3; ++a) lo[a] = hi[a] = p[a];
    for (int64_t i = 0; i < n; ++i)
      for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], p[i * 3 + a]), hi[a] = std::max(hi[a], p[i * 3 + a]);
    double extent = 0;
    for (int a = 0; a < 3; ++a) extent = std::max(extent, hi[a] - lo[a]);
    // >= eps with a 1% margin over the rounding of the cell coordinates (<= 2^40 cells/axis).
    cs = std::max(eps * 1.01, extent * 0x1p-40);
    for (int64_t i = 0; i < n; ++i) cells[key(c(i, 0), c(i, 1), c(i, 2))].push_back(int32_t(i));
  }
  int64_t c(int64_t i, int a) const { return int64_t(std::floor((p[i * 3 + a] - lo[a]) / cs)); }
  // Hash of the cell coordinates. Two cells sharing a key only add candidates (distances are
  // always tested), so collisions cannot change the result.
  static uint64_t key(int64_t x, int64_t y, int64_t z) {
    uint64_t h = uint64_t(x) * 0x9E3779B97F4A7C15ull;
    h = (h ^ (h >> 29)) + uint64_t(y) * 0xBF58476D1CE4E5B9ull;
    h = (h ^ (h >> 31)) + uint64_t(z) * 0x94D049BB133111EBull;
    return h ^ (h >> 32);
  }
  bool within(int64_t i, int64_t j) const {
    const double dx = p[i * 3] - p[j * 3], dy = p[i * 3 + 1] - p[j * 3 + 1], dz = p[i * 3 + 2] - p[j * 3 + 2];
    return (dx * dx + dy * dy) + dz * dz <= eps2;
  }
  // f(j) for every j within eps of i; stops when f returns false.
  template <typename F>
  void neighbours(int64_t i, F&& f) const {
    const int64_t cx = c(i, 0), cy = c(i, 1), cz = c(i, 2);
    uint64_t seen[27];
    int num_seen = 0;
    for (int64_t dx = -1; dx <= 1; ++dx)
      for (int64_t dy = -1; dy <= 1; ++dy)
        for (int64_t dz = -1; dz <= 1; ++dz) {
          const uint64_t k = key(cx + dx, cy + dy, cz + dz);
          if (std::find(seen, seen + num_seen, k) != seen + num_seen) continue;  // colliding neighbours: once
          seen[num_seen++] = k;
          auto it = cells.find(k);
          if (it == cells.end()) continue;
          for (int32_t j : it->second)
            if (within(i, j) && !f(j)) return;
        }
  }
  std::vector<int64_t> labels(int32_t min_samples) const {
    std::vector<uint8_t> core(size_t(n), 0);
    for (int64_t i = 0; i < n; ++i) {
      int32_t count = 0;
      neighbours(i, [&](int32_t) { return ++count < min_samples; });
      core[size_t(i)] = count >= min_samples;
    }
    // sklearn.cluster._dbscan_inner.dbscan_inner, verbatim in structure.
    std::vector<int64_t> lab(size_t(n), -1);
    std::vector<int32_t> stack;
    int64_t label_num = 0;
    for (int64_t i0 = 0; i0 < n; ++i0) {
      if (lab[size_t(i0)] != -1 || !core[size_t(i0)]) continue;
      int64_t i = i0;
      while (true) {
        if (lab[size_t(i)] == -1) {
          lab[size_t(i)] = label_num;
          if (core[size_t(i)])
            neighbours(i, [&](int32_t v) {
              if (lab[size_t(v)] == -1) stack.push_back(v);
              return true;
            });
        }
        if (stack.empty()) break;
        i = stack.back();
        stack.pop_back();
      }
      ++label_num;
    }
    return lab;
  }
};

// ---------------------------------------------------------------- clouds
enum Kind { kLidar, kUniform, kDuplicates, kLattice, kFarOutliers, kTies, kNumKinds };
const char* kind_name(int k) {
  static const char* names[] = {"lidar", "uniform", "duplicates", "lattice", "far_outliers", "ties"};
  return names[k];
}

// Lidar-like sweep: ground rings, objects (boxes / pedestrians), dense blobs near the sensor
// (thousands of points per eps cell), walls, sparse noise. Shuffled.
std::vector<double> lidar(int64_t n, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::normal_distribution<double> N(0.0, 1.0);
  std::vector<double> p;
  p.reserve(size_t(n) * 3);
  auto put = [&](double x, double y, double z) { p.insert(p.end(), {x, y, z}); };
  const int blobs = 4 + int(rng() % 4), objects = 20 + int(rng() % 20);
  std::vector<double> ob(objects * 5);
  for (int o = 0; o < objects; ++o) {
    const double r = 5 + 40 * U(rng), t = 6.283185307179586 * U(rng);
    ob[o * 5] = r * std::cos(t), ob[o * 5 + 1] = r * std::sin(t), ob[o * 5 + 2] = 0.5 + 3.5 * U(rng);
    ob[o * 5 + 3] = 0.4 + 1.6 * U(rng), ob[o * 5 + 4] = 0.5 + 1.5 * U(rng);
  }
  std::vector<double> bl(blobs * 4);
  for (int b = 0; b < blobs; ++b) {
    const double r = 1.5 + 2.5 * U(rng), t = 6.283185307179586 * U(rng);
    bl[b * 4] = r * std::cos(t), bl[b * 4 + 1] = r * std::sin(t), bl[b * 4 + 2] = -1.0 + U(rng);
    bl[b * 4 + 3] = 0.05 + 0.25 * U(rng);
  }
  for (int64_t i = 0; i < n; ++i) {
    const double u = U(rng);
    if (u < 0.35) {  // ground rings, one per beam
      const int beam = int(rng() % 32);
      const double r = 2.5 + beam * beam * 0.06, t = 6.283185307179586 * U(rng);
      put(r * std::cos(t) + 0.02 * N(rng), r * std::sin(t) + 0.02 * N(rng), -1.7 + 0.03 * N(rng));
    } else if (u < 0.65) {  // objects: points on box surfaces
      const double* o = &ob[size_t(rng() % objects) * 5];
      double x = (U(rng) - 0.5) * o[2], y = (U(rng) - 0.5) * o[3], z = U(rng) * o[4];
      if (U(rng) < 0.5) x = (x < 0 ? -0.5 : 0.5) * o[2];
      else y = (y < 0 ? -0.5 : 0.5) * o[3];
      put(o[0] + x, o[1] + y, -1.7 + z);
    } else if (u < 0.9) {  // dense near-sensor blobs
      const double* b = &bl[size_t(rng() % blobs) * 4];
      put(b[0] + b[3] * N(rng), b[1] + b[3] * N(rng), b[2] + b[3] * N(rng));
    } else if (u < 0.97) {  // a wall
      put(-20.0 + 0.01 * N(rng), -30 + 60 * U(rng), -1.7 + 4 * U(rng));
    } else {  // sparse noise
      put(-60 + 120 * U(rng), -60 + 120 * U(rng), -2 + 6 * U(rng));
    }
  }
  return p;
}

std::vector<double> make_cloud(int kind, int64_t n, double eps, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::vector<double> p;
  switch (kind) {
    case kLidar:
      return lidar(n, rng);
    case kUniform:
      for (int64_t i = 0; i < 3 * n; ++i) p.push_back(4.0 * std::cbrt(double(n) / 5000.0) * U(rng));
      return p;
    case kDuplicates: {  // few distinct positions, many copies; one huge cell
      const int64_t distinct = std::max<int64_t>(1, n / 50);
      std::vector<double> base(size_t(distinct) * 3);
      for (auto& v : base) v = U(rng);
      for (int64_t i = 0; i < n; ++i) {
        const int64_t b = int64_t(rng() % uint64_t(distinct));
        p.insert(p.end(), {base[b * 3], base[b * 3 + 1], base[b * 3 + 2]});
      }
      return p;
    }
    case kLattice: {  // spacing exactly eps (a power of two): neighbours exactly at eps
      const int64_t side = std::max<int64_t>(1, int64_t(std::cbrt(double(n))));
      for (int64_t i = 0; i < n; ++i)
        p.insert(p.end(), {double(i % side) * eps, double((i / side) % side) * eps, double(i / (side * side)) * eps});
      return p;
    }
    case kFarOutliers: {  // lidar plus two points 1e6 away: enlarged cells (non-"dense" path)
      p = lidar(n, rng);
      if (n >= 3) {
        p[0] = 1e6, p[1] = -1e6, p[2] = 3.0;
        p[3] = -1e6, p[4] = 1e6, p[5] = -3.0;
      }
      return p;
    }
    case kTies: {  // pairs exactly eps apart in float32 -> float64, in a few rows
      for (int64_t i = 0; i < n; ++i) {
        const float x = float(3.0 * U(rng));
        const float xx = (i & 1) ? float(x + float(eps)) : x;
        p.insert(p.end(), {double(xx), double(int(rng() % 3) * 5), double(int(rng() % 2))});
      }
      return p;
    }
  }
  return p;
}

// ---------------------------------------------------------------- CPU emulation
// The launcher's pipeline run sequentially on the host with the SAME per-item stage functions
// as the kernels (csrc/cuda/dbscan_stages.cuh): checks the algorithm (sub-cells, pruning,
// hooking, labels) where there is no GPU. Concurrency is not exercised.
namespace st = floxels::cuda::stages;
std::vector<int64_t> emulate(const std::vector<double>& p, double eps, int32_t ms) {
  const int64_t n = int64_t(p.size() / 3);
  const size_t N = size_t(n);
  std::vector<int64_t> labels(N, -1);
  if (n == 0) return labels;
  ms = int32_t(std::min<int64_t>(ms, n + 1));
  double lo[3], hi[3];
  for (int a = 0; a < 3; ++a) lo[a] = hi[a] = p[a];
  for (int64_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], p[i * 3 + a]), hi[a] = std::max(hi[a], p[i * 3 + a]);
  const st::Params P = st::make_params(lo, hi, eps, ms);
  std::vector<std::pair<uint64_t, int32_t>> order(static_cast<size_t>(n));
  for (int64_t i = 0; i < n; ++i)
    order[size_t(i)] = {floxels::dbscan::point_sub_key(P.g, p[i * 3], p[i * 3 + 1], p[i * 3 + 2]), int32_t(i)};
  std::sort(order.begin(), order.end());  // == cub's stable radix sort of (key, index)
  std::vector<double> xs(N), ys(N), zs(N);
  std::vector<int32_t> orig(N), sub_incl(N), cell_incl(N), sub_start, cell_start;
  std::vector<uint64_t> sub_key, cell_keys;
  for (int64_t i = 0; i < n; ++i) {
    const uint64_t k = order[size_t(i)].first;
    const int32_t o = order[size_t(i)].second;
    orig[size_t(i)] = o;
    xs[size_t(i)] = p[o * 3], ys[size_t(i)] = p[o * 3 + 1], zs[size_t(i)] = p[o * 3 + 2];
    if (i == 0 || k != order[size_t(i - 1)].first) sub_start.push_back(int32_t(i)), sub_key.push_back(k);
    if (i == 0 || (k >> 3) != (order[size_t(i - 1)].first >> 3))
      cell_start.push_back(int32_t(i)), cell_keys.push_back(k >> 3);
    sub_incl[size_t(i)] = int32_t(sub_start.size());
    cell_incl[size_t(i)] = int32_t(cell_start.size());
  }
  const int32_t num_cells = int32_t(cell_keys.size()), num_subs = int32_t(sub_key.size());
  sub_start.push_back(int32_t(n));
  cell_start.push_back(int32_t(n));
  std::vector<int32_t> ranges(static_cast<size_t>(num_cells) * st::kR2);
  for (int64_t c = 0; c < num_cells; ++c)
    st::cell_ranges(P.g, cell_keys.data(), cell_start.data(), num_cells, sub_incl.data(), c, &ranges[size_t(c) * st::kR2]);
  std::vector<uint8_t> core(N);
  for (int32_t i = 0; i < n; ++i)
    core[size_t(i)] = st::is_core(P, xs.data(), ys.data(), zs.data(), sub_incl.data(), cell_incl.data(),
                                  sub_start.data(), sub_key.data(), ranges.data(), i);
  std::vector<int32_t> rep(static_cast<size_t>(num_subs)), parent(N), root(N, -1), min_orig(N, INT32_MAX);
  for (int32_t s = 0; s < num_subs; ++s) rep[size_t(s)] = st::first_core(core.data(), sub_start.data(), s);
  for (int32_t i = 0; i < n; ++i) parent[size_t(i)] = st::initial_parent(P, core.data(), sub_incl.data(), rep.data(), i);
  // Descending order: the opposite of index order, so hooking order differs from a naive pass.
  for (int32_t i = int32_t(n) - 1; i >= 0; --i)
    if (core[size_t(i)])
      st::hook_point(P, xs.data(), ys.data(), zs.data(), sub_incl.data(), cell_incl.data(), sub_start.data(),
                     sub_key.data(), rep.data(), ranges.data(), core.data(), parent.data(), i);
  for (int32_t i = 0; i < n; ++i)
    if (core[size_t(i)]) {
      root[size_t(i)] = st::final_root(parent.data(), i);
      min_orig[size_t(root[size_t(i)])] = std::min(min_orig[size_t(root[size_t(i)])], orig[size_t(i)]);
    }
  std::vector<int32_t> first(N, 0), cid(N, 0), lab(N, -1);
  for (int32_t i = 0; i < n; ++i)
    first[size_t(orig[size_t(i)])] = core[size_t(i)] && min_orig[size_t(root[size_t(i)])] == orig[size_t(i)];
  for (int64_t o = 1; o < n; ++o) cid[size_t(o)] = cid[size_t(o - 1)] + first[size_t(o - 1)];
  for (int32_t i = 0; i < n; ++i)
    if (core[size_t(i)]) lab[size_t(i)] = cid[size_t(min_orig[size_t(root[size_t(i)])])];
  for (int32_t i = 0; i < n; ++i)
    labels[size_t(orig[size_t(i)])] =
        core[size_t(i)] ? lab[size_t(i)]
                        : st::border_label(P, xs.data(), ys.data(), zs.data(), cell_incl.data(), sub_start.data(),
                                           sub_key.data(), rep.data(), ranges.data(), core.data(), lab.data(), i);
  return labels;
}

// ---------------------------------------------------------------- GPU runner
#define CK(call)                                                                                      \
  do {                                                                                                \
    const cudaError_t e_ = (call);                                                                    \
    if (e_ != cudaSuccess) {                                                                          \
      std::printf("dbscan_stress: FAIL CUDA error %s (%s) at %s:%d\n", cudaGetErrorName(e_),          \
                  cudaGetErrorString(e_), __FILE__, __LINE__);                                        \
      std::exit(1);                                                                                   \
    }                                                                                                 \
  } while (0)

struct Gpu {
  cudaStream_t stream{};
  void* ws = nullptr;
  size_t ws_bytes = 0;
  void* pts = nullptr;
  size_t pts_bytes = 0;
  int64_t* labels = nullptr;
  int64_t labels_n = 0;
  unsigned poison = 0;

  Gpu() { CK(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking)); }
  ~Gpu() {
    cudaFree(ws);
    cudaFree(pts);
    cudaFree(labels);
    cudaStreamDestroy(stream);
  }
  void reserve(void*& buf, size_t& have, size_t need) {
    if (need <= have) return;
    CK(cudaFree(buf));
    buf = nullptr;
    CK(cudaMalloc(&buf, need));
    have = need;
  }

  // One checked call; returns the status and fills `out`.
  template <typename T>
  int run(const std::vector<T>& host, double eps, int32_t ms, std::vector<int64_t>& out, float* ms_out = nullptr) {
    const int64_t n = int64_t(host.size() / 3);
    reserve(pts, pts_bytes, std::max<size_t>(1, host.size() * sizeof(T)));
    if (n > labels_n) {
      CK(cudaFree(labels));
      CK(cudaMalloc(&labels, size_t(n) * 8));
      labels_n = n;
    }
    const size_t need = floxels::cuda::dbscan_workspace_bytes(n);
    reserve(ws, ws_bytes, std::max<size_t>(need, 1));
    CK(cudaMemcpyAsync(pts, host.data(), host.size() * sizeof(T), cudaMemcpyHostToDevice, stream));
    // Garbage in the workspace and the output: results must not depend on it.
    const int fill[3] = {0x00, 0xff, 0xa5};
    CK(cudaMemsetAsync(ws, fill[poison % 3], ws_bytes, stream));
    if (n) CK(cudaMemsetAsync(labels, fill[(poison + 1) % 3], size_t(n) * 8, stream));
    ++poison;
    cudaEvent_t a, b;
    CK(cudaEventCreate(&a));
    CK(cudaEventCreate(&b));
    CK(cudaEventRecord(a, stream));
    const int status = floxels::cuda::dbscan<T>(static_cast<const T*>(pts), n, eps, ms, labels, ws, need, stream);
    CK(cudaEventRecord(b, stream));
    CK(cudaGetLastError());
    CK(cudaStreamSynchronize(stream));
    CK(cudaDeviceSynchronize());
    if (ms_out) CK(cudaEventElapsedTime(ms_out, a, b));
    CK(cudaEventDestroy(a));
    CK(cudaEventDestroy(b));
    out.assign(size_t(n), 0);
    if (n) CK(cudaMemcpy(out.data(), labels, size_t(n) * 8, cudaMemcpyDeviceToHost));
    return status;
  }
};

struct Config {
  int kind;
  int64_t n;
  double eps;
  int32_t ms;
  bool f32;
};

}  // namespace

int main(int argc, char** argv) {
  int64_t max_n = 200000;
  int calls_target = 200, reps = 0;  // reps 0: calls_target spread over the configurations
  bool timing = true, verbose = false, emulate_only = false;
  std::string dump;  // --dump DIR: write each cloud and its reference labels (to check them against sklearn)
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() { return i + 1 < argc ? std::atoll(argv[++i]) : 0; };
    if (a == "--max-n") max_n = next();
    else if (a == "--calls") calls_target = int(next());
    else if (a == "--reps") reps = std::max<int>(1, int(next()));
    else if (a == "--no-time") timing = false;
    else if (a == "-v") verbose = true;
    else if (a == "--emulate") emulate_only = true;
    else if (a == "--dump" && i + 1 < argc) dump = argv[++i];
    else {
      std::printf("usage: %s [--calls N] [--max-n N] [--reps R] [--no-time] [--emulate] [--dump DIR] [-v]\n", argv[0]);
      return 2;
    }
  }
  cudaDeviceProp prop{};
  if (emulate_only) std::snprintf(prop.name, sizeof prop.name, "CPU emulation");
  else CK(cudaGetDeviceProperties(&prop, 0));

  // Configurations: every kind at several sizes, dtypes, eps and min_samples.
  std::mt19937_64 pick(12345);
  std::vector<Config> configs;
  const int64_t sizes[] = {1, 2, 13, 1000, 5000, 20000, 60000, 120000, 150000, 200000};
  const double epss[] = {0.25, 0.3, 0.5, 1.0};
  const int32_t mss[] = {1, 2, 4, 4, 10};
  for (int64_t n : sizes) {
    if (n > max_n) continue;
    for (int kind = 0; kind < kNumKinds; ++kind) {
      if (kind != kLidar && kind != kFarOutliers && n > 20000) continue;  // keep the CPU reference quick
      for (int f = 0; f < 2; ++f) {
        const double eps = kind == kLattice ? 0.5 : epss[pick() % 4];
        configs.push_back({kind, n, eps, mss[pick() % 5], f == 0});
      }
    }
    if (n >= 100000) configs.push_back({kLidar, n, 0.5, 4, true});  // the production setting
  }

  Gpu* gpu_ptr = emulate_only ? nullptr : new Gpu();
  int calls = 0, mismatches = 0, bad_status = 0;
  double ref_s = 0;
  if (reps == 0) reps = std::max<int>(1, int((calls_target + configs.size() - 1) / configs.size()));
  {
    for (const Config& c : configs) {
      std::mt19937_64 rng(uint64_t(c.n) * 7919u + uint64_t(c.kind) * 104729u + uint64_t(c.ms) + (c.f32 ? 1u : 0u));
      std::vector<double> cloud = make_cloud(c.kind, c.n, c.eps, rng);
      std::vector<float> cloud_f(cloud.begin(), cloud.end());
      if (c.f32) cloud.assign(cloud_f.begin(), cloud_f.end());  // the reference sees the float values
      const auto t0 = std::chrono::steady_clock::now();
      const std::vector<int64_t> want = Reference(cloud, c.eps).labels(c.ms);
      ref_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      if (!dump.empty()) {  // <dir>/<k>_<n>_<f32>_<eps>_<ms>.{pts,lab}: raw float64 (n,3) / int64 (n,)
        char name[256];
        std::snprintf(name, sizeof name, "%s/%s_%lld_%d_%g_%d", dump.c_str(), kind_name(c.kind), (long long)c.n,
                      int(c.f32), c.eps, c.ms);
        FILE* f = std::fopen((std::string(name) + ".pts").c_str(), "wb");
        if (f) std::fwrite(cloud.data(), 8, cloud.size(), f), std::fclose(f);
        f = std::fopen((std::string(name) + ".lab").c_str(), "wb");
        if (f) std::fwrite(want.data(), 8, want.size(), f), std::fclose(f);
      }
      for (int r = 0; r < reps; ++r, ++calls) {
        std::vector<int64_t> got;
        int status = floxels::cuda::kDbscanOk;
        if (emulate_only) got = emulate(cloud, c.eps, c.ms);  // cloud holds the float values when f32
        else status = c.f32 ? gpu_ptr->run(cloud_f, c.eps, c.ms, got) : gpu_ptr->run(cloud, c.eps, c.ms, got);
        int64_t diff = 0, first = -1;
        for (size_t i = 0; i < want.size(); ++i)
          if (got[i] != want[i]) diff += 1, first = first < 0 ? int64_t(i) : first;
        if (status != floxels::cuda::kDbscanOk) ++bad_status;
        if (diff) ++mismatches;
        if (verbose || diff || status != floxels::cuda::kDbscanOk) {
          const int64_t clusters = want.empty() ? 0 : *std::max_element(want.begin(), want.end()) + 1;
          std::printf("  %-12s n=%-7lld %s eps=%.2f ms=%-3d clusters=%-5lld status=%d diff=%lld", kind_name(c.kind),
                      (long long)c.n, c.f32 ? "f32" : "f64", c.eps, c.ms, (long long)clusters, status,
                      (long long)diff);
          if (first >= 0)
            std::printf(" (first at %lld: got %lld want %lld)", (long long)first, (long long)got[size_t(first)],
                        (long long)want[size_t(first)]);
          std::printf("\n");
        }
      }
    }
  }

  // Timing of the production setting: 150k lidar float points, eps 0.5, min_samples 4.
  std::string timing_text = "";
  if (timing && !emulate_only && max_n >= 150000) {
    std::mt19937_64 rng(99);
    const std::vector<double> cloud = lidar(150000, rng);
    const std::vector<float> cloud_f(cloud.begin(), cloud.end());
    std::vector<int64_t> got;
    std::vector<float> ms;
    for (int r = 0; r < 25; ++r) {
      float t = 0;
      if (gpu_ptr->run(cloud_f, 0.5, 4, got, &t) != floxels::cuda::kDbscanOk) ++bad_status;
      if (r >= 5) ms.push_back(t);
    }
    std::sort(ms.begin(), ms.end());
    char buf[128];
    std::snprintf(buf, sizeof buf, " lidar150k_f32_eps0.5_ms4_median=%.3fms", ms[ms.size() / 2]);
    timing_text = buf;
  }
  delete gpu_ptr;
  const bool ok = mismatches == 0 && bad_status == 0;
  std::printf("dbscan_stress: %s device=\"%s\" calls=%d configs=%zu mismatches=%d bad_status=%d ref_cpu=%.1fs%s\n",
              ok ? "OK" : "FAIL", prop.name, calls, configs.size(), mismatches, bad_status, ref_s,
              timing_text.c_str());
  return ok ? 0 : 1;
}
