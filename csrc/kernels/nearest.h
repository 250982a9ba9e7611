// Exact nearest neighbour (brute force): the distance rule shared by the CPU
// (cpu/nearest_cpu.cpp) and CUDA (cuda/nearest.cu) implementations of
// floxels::nearest_neighbor. Squared Euclidean distance computed directly from the
// coordinate differences (the |x|^2 + |y|^2 - 2 x.y form loses the ordering of near-ties on
// coordinates of tens of metres); a NaN distance counts as +inf; ties keep the lowest index.
#pragma once
#include <cmath>

#include "common/cuda_compat.h"

namespace floxels::nearest {

template <typename T>
FLX_HD T sq_dist(T ax, T ay, T az, T bx, T by, T bz) {
  const T dx = ax - bx, dy = ay - by, dz = az - bz;
  const T d = dx * dx + dy * dy + dz * dz;
  return d == d ? d : T(INFINITY);  // NaN -> +inf
}

}  // namespace floxels::nearest
