// Warp-aggregated atomicAdd: the CUDA solver sums the shares of its cluster means with it, as
// 64-bit fixed-point integers (order-independent; use it with integers only: float atomics
// make the sums depend on the order in which threads arrive).
//
// Hot targets (voxels near the sensor, big clusters) make many lanes of a warp add to the same
// address; serialising those on one atomic is slow. The lanes first find their peers with
// __match_any_sync, one leader per distinct key sums its peers' values through shared memory,
// and only the leader issues the atomicAdd. When no two lanes share a key (the common case
// far from the sensor) every lane adds directly.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda_detail {

// Every lane of the warp must call this (convergent); a lane with nothing to add passes
// key < 0. Adds w * v[ch] to dst[key * kstride + ch * cstride] for ch < C. `scratch` is this
// warp's 32-element shared buffer.
template <typename T>
__device__ __forceinline__ T* base_of(T* dst, int64_t key, int64_t kstride) {
  return dst + key * kstride;
}

template <typename T>
__device__ __forceinline__ void warp_add(T* __restrict__ dst, int64_t key, int64_t kstride, int64_t cstride,
                                         const T* __restrict__ v, T w, int C, T* scratch) {
  const unsigned full = 0xffffffffu;
  const int lane = threadIdx.x & 31;
  const unsigned peers = __match_any_sync(full, static_cast<unsigned long long>(key));
  if (peers == full) {  // one key for the whole warp (sorted keys): butterfly sums, one atomic each
    if (key < 0) return;
    for (int ch = 0; ch < C; ++ch) {
      T s = w * v[ch];
      for (int o = 16; o > 0; o >>= 1) s += __shfl_xor_sync(full, s, o);
      if (lane == 0) atomicAdd(base_of(dst, key, kstride) + ch * cstride, s);
    }
    return;
  }
  const bool shared = __any_sync(full, peers != (1u << lane) && key >= 0);
  const bool leader = key >= 0 && (__ffs(peers) - 1) == lane;
  T* base = dst + key * kstride;
  if (!shared) {
    if (key >= 0)
      for (int ch = 0; ch < C; ++ch) atomicAdd(base + ch * cstride, w * v[ch]);
    return;
  }
  for (int ch = 0; ch < C; ++ch) {
    scratch[lane] = key >= 0 ? w * v[ch] : T(0);
    __syncwarp();
    if (leader) {
      T s = T(0);
      for (unsigned m = peers; m; m &= m - 1) s += scratch[__ffs(m) - 1];
      atomicAdd(base + ch * cstride, s);
    }
    __syncwarp();
  }
}

// Sum of x over the warp (every lane gets it).
template <typename T>
__device__ __forceinline__ T warp_sum(T x) {
  for (int o = 16; o > 0; o >>= 1) x += __shfl_xor_sync(0xffffffffu, x, o);
  return x;
}

}  // namespace floxels::cuda_detail
