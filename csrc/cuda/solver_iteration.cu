// The two-kernel iteration of the CUDA solver: points_kernel (stages 1-2) then vertex_kernel
// (stages 3-4 and the next cluster means), launched once each per iteration, with
// programmatic dependent launch by default; also the vertex kernel's means-only variant that
// forms the first cluster means of a call. The bodies are in solver_bodies.cuh; the launcher
// (solver.cu) chooses between this and the persistent loop (solver_loop.cu).
#include <cuda_runtime.h>

#include "cuda/solver_bodies.cuh"

namespace floxels::cuda {
namespace {

using namespace solver_detail;

template <bool kCluster>
__global__ void __launch_bounds__(kThreads) points_kernel(const __grid_constant__ KParams P) {
  __shared__ PointSmem sm;
  pdl_allow_next();
  // fixed per-call data first (overlaps the previous kernel's tail under PDL)
  const PointFixed fx = load_fixed<kCluster>(P, int(blockIdx.x));
  points_body<kCluster>(P, P.parity, int(blockIdx.x), true, sm, fx);
}

template <bool kCluster, bool kInitMeans>
__global__ void __launch_bounds__(kThreads, 5) vertex_kernel(const __grid_constant__ KParams P) {
  __shared__ VertexSmem sm;
  pdl_allow_next();
  vertex_body<kCluster, kInitMeans>(P, P.parity, int(blockIdx.x), sm, vertex_entries(P, int(blockIdx.x)));
}

// Launch with programmatic stream serialisation (PDL) when `pdl`; see pdl_wait_previous.
cudaError_t launch(void (*kernel)(const KParams), int blocks, cudaStream_t stream, bool pdl, const KParams& P) {
  cudaLaunchAttribute attr{};
  attr.id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attr.val.programmaticStreamSerializationAllowed = 1;
  return launch_ex(kernel, blocks, stream, pdl ? &attr : nullptr, P);
}

}  // namespace

namespace solver_detail {

void launch_first_means(const KParams& P, int vb, cudaStream_t stream) {
  vertex_kernel<true, true><<<unsigned(vb), kThreads, 0, stream>>>(P);
}

cudaError_t launch_iterations(KParams P, int num_iters, int pb, int vb, bool cluster, bool pdl,
                              cudaStream_t stream) {
  void (*pk)(const KParams) = cluster ? points_kernel<true> : points_kernel<false>;
  void (*vk)(const KParams) = cluster ? vertex_kernel<true, false> : vertex_kernel<false, false>;
  cudaError_t err = cudaSuccess;
  for (int it = 0; it < num_iters && err == cudaSuccess; ++it) {
    P.parity = it & 1;
    err = launch(pk, pb, stream, pdl, P);
    if (err == cudaSuccess) err = launch(vk, vb, stream, pdl, P);
  }
  return err;
}

}  // namespace solver_detail
}  // namespace floxels::cuda
