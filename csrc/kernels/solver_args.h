// Plain description of one floxels::solver_run call (raw pointers and sizes, no torch
// types): filled by the torch bindings, read by the CPU loop and the CUDA launcher.
#pragma once
#include <cstdint>

#include "kernels/solver.h"

namespace floxels::solver {

struct DtDesc {
  const float* data;  // (nz, ny, nx) float32, contiguous
  int64_t nx, ny, nz;
  double ox, oy, oz;  // world position of sample (0, 0, 0)
};

struct Support {
  int dt;         // index into Args::dts
  double t;       // time offset of the scan: query = p + t * f
  double weight;  // lambda_d * w(t); the mean over the problem's points is applied inside
};

struct Problem {
  int64_t point_begin, point_end;    // rows of points / corner_idx / labels
  int64_t vertex_begin, vertex_end;  // rows of theta / adam state / vtx_ptr
  int num_support;
  Support support[kMaxSupport];
  double cluster_n;  // points the cluster term averages over (< 0: all points of the problem)
  double reg_scale;  // multiplies the cluster and flow-norm terms (number of support scans)
};

struct Args {
  // fixed data
  const float* points;         // (N, 3)
  const int32_t* corner_idx;   // (N, 8) global rows of theta
  const float* corner_w;       // (N, 8)
  // Segments: runs of consecutive points of one problem with identical corner_idx rows and
  // labels (the estimator sorts points by (label, voxel), so a segment is the part of one
  // cluster inside one flow-grid cell). The gradient of a vertex is a sum over the
  // (segment, corner) pairs that touch it: a fixed, small fan-in, however many points
  // crowd a cell near the sensor.
  const int32_t* seg_ptr;      // (S + 1) first point of each segment, then N
  const int32_t* vtx_ptr;      // (M + 1) CSR offsets into vtx_entry
  const int32_t* vtx_entry;    // (8S) entries segment * 8 + corner, grouped by vertex
  const int32_t* labels;       // (N) global cluster ids, -1 noise; null: no cluster term
  const float* cluster_count;  // (C) points per cluster
  int64_t num_points, num_vertices, num_clusters, num_segments;
  DtDesc dts[kMaxDts];
  int num_dts;
  Problem problems[kMaxProblems];
  int num_problems;
  Hyper hyper;
  // state, updated in place
  float* theta;     // (M, 3)
  float* adam_m;    // (M, 3)
  float* adam_v;    // (M, 3)
  float* best;      // (M, 3)
  double* state;    // (B, kStateCols)
  double* history;  // (B, max_iters)
};

}  // namespace floxels::solver
