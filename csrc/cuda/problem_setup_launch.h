// Plain launchers of the CUDA problem_setup kernels (no torch types); the steps between them
// (the two stable sorts, the two prefix sums, the one host read of the sizes) are ATen calls in
// problem_setup_binding.cpp.
#pragma once
#include <cuda_runtime.h>

#include <cstdint>

namespace floxels::cuda {

// What the launchers share: the lattice (o in T, spacing, size = {X, Y, Z}, cells).
template <typename T>
struct SetupGrid {
  T o[3];
  T spacing;
  int64_t size[3];
  int64_t cells;
};

// key[i]: the cell of point i, plus (label + 1) * cells with labels; *bad set to 1 where a
// coordinate is not finite (zeroed beforehand).
template <typename T>
void setup_keys(const T* points, const int64_t* labels, int64_t n, const SetupGrid<T>& g, int64_t* key, int* bad,
                cudaStream_t s);

// The sorted points and labels (points[order], labels[order]), their corners (lin (n, 8)
// lattice indices, w (n, 8)), mark[lin] = 1 (zeroed beforehand, one int per lattice vertex),
// and *max_label the largest label (set to -1 beforehand; labels may be null).
template <typename T>
void setup_corners(const T* points, const int64_t* labels, const int64_t* order, int64_t n, const SetupGrid<T>& g,
                   T* points_s, int64_t* labels_s, int64_t* lin, T* w, int* mark, long long* max_label,
                   cudaStream_t s);

// inverse (n, 8) = pos[lin] - 1 (pos: the inclusive prefix sum of mark), and is_new[i] = 1
// where point i starts a segment: i % tile == 0, or its corners or label differ from point
// i - 1's.
void setup_segments(const int64_t* lin, const int* pos, const int64_t* labels_s, int64_t n, int64_t tile,
                    int* inverse, int* is_new, cudaStream_t s);

// sizes[0..3] = {vertices M = pos[cells - 1], segments S = seg_incl[n - 1], clusters
// (max_label + 1, at least 0), 1 if all points were finite}: one launch, for one host read.
void setup_sizes(const int* pos, int64_t cells, const int64_t* seg_incl, int64_t n, const long long* max_label,
                 const int* bad, int64_t* sizes, cudaStream_t s);

// vertices[inverse] = lin; for each segment start i (is_new): seg_ptr[seg_incl[i] - 1] = i and
// flat[8 s + j] = inverse[i][j]; seg_ptr[S] = n.
void setup_tables(const int64_t* lin, const int* inverse, const int* is_new, const int64_t* seg_incl, int64_t n,
                  int64_t S, int64_t* vertices, int* seg_ptr, int* flat, cudaStream_t s);

// counts[flat[k]] += 1 for k < m (integer atomics: the same counts in any order).
void setup_counts(const int* flat, int64_t m, int* counts, cudaStream_t s);

}  // namespace floxels::cuda
