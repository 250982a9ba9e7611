// Lets the kernel-math headers in csrc/kernels/ be included by both g++ and nvcc.
#pragma once
#if defined(__CUDACC__)
#define FLX_HD __host__ __device__ __forceinline__
#else
#define FLX_HD inline
#endif
