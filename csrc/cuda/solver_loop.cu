// The persistent loop of the CUDA solver: all iterations of a call in one cooperative launch
// (loop_kernel), the occupancy query that says how many of its blocks fit on the device, and
// its launch. Profiling builds (FLOXELS_PROFILING) also hold the traced variant, which times
// each phase (FLOXELS_SOLVER_TRACE) and can leave parts out (FLOXELS_SOLVER_SKIP); release
// builds compile none of it. The bodies are in solver_bodies.cuh; the launcher (solver.cu)
// chooses between this and the two-kernel iteration (solver_iteration.cu).
#include <cooperative_groups.h>
#include <cuda_runtime.h>

#include "cuda/solver_bodies.cuh"

namespace floxels::cuda {
namespace {

using namespace solver_detail;
namespace cg = cooperative_groups;

// Phase timer of the loop kernel. LoopTrace<false> (every build): no clock reads, no-ops.
// LoopTrace<true> (profiling builds only; FLOXELS_SOLVER_TRACE=1): per block, the time spent
// in each phase and at each barrier, summed over the iterations; block 0 prints the slowest
// block's phase times and its own barrier waits per iteration.
template <bool kOn>
struct LoopTrace;

template <>
struct LoopTrace<false> {
  __device__ __forceinline__ void begin(cg::grid_group&) {}
  __device__ __forceinline__ unsigned long long now() const { return 0; }
  __device__ __forceinline__ void iteration(unsigned long long, unsigned long long, unsigned long long,
                                            unsigned long long) {}
  __device__ __forceinline__ void report(cg::grid_group&) {}
};

#if FLOXELS_PROFILING
__device__ unsigned long long g_trace[8];  // the one __device__ global: this file only

template <>
struct LoopTrace<true> {
  unsigned long long acc[4] = {0, 0, 0, 0}, t_begin = 0;
  int done = 0;

  __device__ __forceinline__ unsigned long long now() const {
    unsigned long long t;
    asm volatile("mov.u64 %0, %globaltimer;" : "=l"(t));
    return t;
  }
  __device__ __forceinline__ void begin(cg::grid_group& grid) {
    if (blockIdx.x == 0 && threadIdx.x < 8) g_trace[threadIdx.x] = 0;
    grid.sync();
    t_begin = now();
  }
  // t0..t3: points phase start, its end, vertex phase start, its end; called after the
  // iteration's last barrier
  __device__ __forceinline__ void iteration(unsigned long long t0, unsigned long long t1, unsigned long long t2,
                                            unsigned long long t3) {
    const unsigned long long t4 = now();
    acc[0] += t1 - t0, acc[1] += t2 - t1, acc[2] += t3 - t2, acc[3] += t4 - t3;
    ++done;
  }
  __device__ __forceinline__ void report(cg::grid_group& grid) {
    const unsigned long long total = now() - t_begin;
    if (threadIdx.x == 0) {
      atomicMax(&g_trace[0], acc[0]);
      atomicMax(&g_trace[2], acc[2]);
      atomicAdd(&g_trace[4], acc[0]);
      atomicAdd(&g_trace[5], acc[2]);
    }
    grid.sync();
    if (blockIdx.x == 0 && threadIdx.x == 0 && done > 0) {
      const double n = done, nb = gridDim.x;
      printf("FLOXELS_SOLVER_TRACE %d iterations, %d blocks: per iteration %.2f us; points phase %.2f us (slowest "
             "block; mean %.2f), vertex phase %.2f us (slowest; mean %.2f); block 0: points %.2f, barrier %.2f, "
             "vertex %.2f, barrier %.2f us\n",
             done, int(gridDim.x), 1e-3 * total / n, 1e-3 * g_trace[0] / n, 1e-3 * g_trace[4] / n / nb,
             1e-3 * g_trace[2] / n, 1e-3 * g_trace[5] / n / nb, 1e-3 * acc[0] / n, 1e-3 * acc[1] / n,
             1e-3 * acc[2] / n, 1e-3 * acc[3] / n);
    }
  }
};
#endif  // FLOXELS_PROFILING

// All iterations in one cooperative launch: every block of a grid that fits on the GPU at
// once walks over the point blocks, the grid waits at a barrier, walks over the vertex
// blocks, and waits again; the barriers take the place of the kernel boundaries of the
// two-kernel iteration (same bodies, same buffers, same order of every write and read).
// This saves the launch and the fill/drain of two kernels per iteration, which dominate at
// one frame (~100k points fill the GPU less than once). The loop ends early once every
// problem has stopped: the state rows are only written before a barrier, so all blocks
// read the same rows after it and leave together.
// `trace`: the traced variant (profiling builds only; see LoopTrace).
template <bool kCluster, bool trace = false>
__global__ void __launch_bounds__(kThreads, 4) loop_kernel(const __grid_constant__ KParams P, int num_iters,
                                                        int point_blocks, int vertex_blocks) {
  static_assert(!trace || kProfiling, "the traced loop exists in profiling builds only");
  __shared__ PointSmem psm;
  __shared__ VertexSmem vsm;
  __shared__ PointCache pcache;
  cg::grid_group grid = cg::this_grid();
  // a block that owns one point block keeps its points' fixed data in shared memory (each
  // thread reads only its own slot: no barrier needed)
  const bool cached = point_blocks <= int(gridDim.x) && int(blockIdx.x) < point_blocks;
  if (cached) pcache.put(load_fixed<kCluster>(P, int(blockIdx.x)));
  __shared__ int2 ventries[kThreads];  // the same for the vertex block it owns, if one
  const bool vcached = vertex_blocks <= int(gridDim.x) && int(blockIdx.x) < vertex_blocks;
  if (vcached) ventries[threadIdx.x] = vertex_entries(P, int(blockIdx.x));
  // each problem's iteration count at the call's start (see vertex_body's iter0)
  __shared__ int iter0[kMaxProblems];
  if (int(threadIdx.x) < P.num_problems) iter0[threadIdx.x] = int(P.state[threadIdx.x * kStateCols + kIter]);
  __syncthreads();
  LoopTrace<trace> tr;
  tr.begin(grid);
  for (int it = 0; it < num_iters; ++it) {
    // Every thread reads the flags itself (the same rows after the same barrier): no thread-0
    // read and block barrier before the first body. The vote tells the compiler that the exit
    // is warp-uniform (a per-thread branch around the grid barriers cost registers: spills).
    bool any_active = false;
    for (int p = 0; p < P.num_problems; ++p) any_active |= P.state[p * kStateCols + kActive] != 0.0;
    if (!__any_sync(0xffffffffu, any_active)) break;  // uniform over the grid (see above)
    const unsigned long long t0 = tr.now();
    const int parity = it & 1;
    clear_other_parity<kCluster>(P, parity);
    // A block that walks several point or vertex blocks reuses its shared memory: the
    // barrier after each body keeps the next one from overwriting what a slower thread of
    // this one still reads (stage 3's state row in the vertex body).
    for (int b = int(blockIdx.x); b < point_blocks; b += int(gridDim.x)) {
      const PointFixed fx = cached ? pcache.get() : load_fixed<kCluster>(P, b);
      points_body<kCluster, trace>(P, parity, b, false, psm, fx);
      __syncthreads();
    }
    const unsigned long long t1 = tr.now();
    grid.sync();
    const unsigned long long t2 = tr.now();
    for (int b = int(blockIdx.x); b < vertex_blocks; b += int(gridDim.x)) {
      const int2 entries = vcached ? ventries[threadIdx.x] : vertex_entries(P, b);
      vertex_body<kCluster, false, trace>(P, parity, b, vsm, entries, iter0, it);
      __syncthreads();
    }
    const unsigned long long t3 = tr.now();
    grid.sync();
    tr.iteration(t0, t1, t2, t3);
  }
  tr.report(grid);
}

}  // namespace

namespace solver_detail {

// Blocks of the persistent loop kernel that can be resident at once, or 0 where it cannot
// be used: a stream being captured into a CUDA graph (a graph replays fixed chunks; the
// two-kernel iteration is the tested path there), or a device without cooperative launch.
// (The launcher applies FLOXELS_SOLVER_MAX_GRID on top.)
int loop_capacity(bool cluster, cudaStream_t stream) {
  cudaStreamCaptureStatus cap = cudaStreamCaptureStatusNone;
  if (cudaStreamIsCapturing(stream, &cap) != cudaSuccess || cap != cudaStreamCaptureStatusNone) return 0;
  int dev = 0;
  if (cudaGetDevice(&dev) != cudaSuccess) return 0;
  // per device and variant; occupancy queries cost microseconds, a launch is ~10 us of work
  static thread_local int cached[64][2] = {};
  if (dev < 0 || dev >= 64) return 0;
  int& c = cached[dev][cluster ? 1 : 0];
  if (c == 0) {
    int coop = 0, sms = 0, per_sm = 0;
    cudaDeviceGetAttribute(&coop, cudaDevAttrCooperativeLaunch, dev);
    cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
    const cudaError_t e = cluster
        ? cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, loop_kernel<true>, kThreads, 0)
        : cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, loop_kernel<false>, kThreads, 0);
    c = (coop && e == cudaSuccess && per_sm > 0) ? sms * per_sm : -1;
    cudaGetLastError();  // a failed query leaves no sticky error behind
  }
  return c > 0 ? c : 0;
}

cudaError_t launch_loop(const KParams& P, int grid, int num_iters, int pb, int vb, bool cluster, bool trace,
                        cudaStream_t stream) {
  cudaLaunchAttribute coop{};
  coop.id = cudaLaunchAttributeCooperative;
  coop.val.cooperative = 1;
#if FLOXELS_PROFILING
  auto* kernel = cluster ? (trace ? loop_kernel<true, true> : loop_kernel<true>)
                         : (trace ? loop_kernel<false, true> : loop_kernel<false>);
#else
  (void)trace;  // the launcher passes false: no traced variant in this build
  auto* kernel = cluster ? loop_kernel<true> : loop_kernel<false>;
#endif
  return launch_ex(kernel, grid, stream, &coop, P, num_iters, pb, vb);
}

}  // namespace solver_detail
}  // namespace floxels::cuda
