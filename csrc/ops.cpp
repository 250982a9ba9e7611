// Every schema of the `floxels` op namespace lives here; implementations register per
// device in cpu/*.cpp and cuda/*_binding.cpp (TORCH_LIBRARY_IMPL), fake/autograd
// registrations live in python/floxels_ext/ops/*.py. (Exception: has_profiling, which takes
// no tensor and has one device-independent kernel, registered with its schema below.)
//
// Conventions shared by all ops (see docs/ops.md):
//  * points are (N, 3) float32/float64 in (x, y, z) order;
//  * a grid is a regular lattice of SAMPLES: sample (iz, iy, ix) sits at
//    origin + (ix, iy, iz) * spacing; dense grids are stored (C, Z, Y, X) or (Z, Y, X);
//  * origin lists are [x0, y0, z0];
//  * non-finite points (a NaN/inf coordinate) give NaN gather rows and NaN losses, are ignored
//    by scatters and occupancy, and are refused by dbscan and problem_setup (docs/ops.md,
//    tests/ops/test_ops_nonfinite.py); bad host scalars are refused (common/check.h).
#include <Python.h>
#include <torch/library.h>

#include "common/env_switches.h"

extern "C" {
// `import floxels_ext._C` only needs a module object; the ops register through the
// static TORCH_LIBRARY initialisers below when the shared object is loaded.
PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", nullptr, -1, nullptr};
  return PyModule_Create(&module_def);
}
}

TORCH_LIBRARY(floxels, m) {
  // --- fixed-point sums by row (csrc/kernels/segment_sum.h) ---
  // out (rows, C [+1]) float64: per row r, the sum over the terms i with index[i] == r of
  // values[i] (M, C), each term clamped to +-limit and rounded to a multiple of 2^-24, summed as
  // int64: the same bits in any order and on any device. A non-finite term makes its row's
  // column NaN (void_row: the row's every value column); count appends the row's number of
  // terms. Terms whose index is outside [0, rows) are ignored. Data only (no autograd).
  m.def("fixed_segment_sum(Tensor values, Tensor index, int rows, float limit, bool void_row, bool count) -> Tensor");

  // --- trilinear family (csrc/kernels/trilinear.h) ---
  // out (N, C) = grid (C, Z, Y, X) interpolated at points; border clamping.
  m.def("trilinear_gather(Tensor grid, Tensor points, float[] origin, float spacing) -> Tensor");
  // Gradients of trilinear_gather: (grad_grid (C,Z,Y,X), grad_points (N,3)); an output not
  // requested is returned as an empty tensor.
  m.def("trilinear_gather_backward(Tensor grad_out, Tensor grid, Tensor points, float[] origin, "
        "float spacing, bool need_grid_grad, bool need_points_grad) -> (Tensor, Tensor)");
  // Adjoint of the gather: splats values (N, C) onto a zero grid of shape (C, *grid_shape).
  m.def("trilinear_scatter(Tensor values, Tensor points, float[] origin, float spacing, "
        "int[] grid_shape) -> Tensor");

  // --- compact voxel parameters (csrc/kernels/corners.h) ---
  // The optimiser keeps only the voxel corners touched by points, as rows of params (M, C);
  // corner_idx (N, 8) int32 and corner_w (N, 8) hold each point's 8 trilinear corners.
  // out (N, C) = sum_j corner_w[i, j] * params[corner_idx[i, j]].
  m.def("corner_gather(Tensor params, Tensor corner_idx, Tensor corner_w) -> Tensor");
  // Adjoint: out (num_params, C) = sum over (i, j) with corner_idx[i, j] = m of corner_w[i, j] * values[i].
  m.def("corner_scatter(Tensor values, Tensor corner_idx, Tensor corner_w, int num_params) -> Tensor");

  // --- exact Euclidean distance transform (csrc/kernels/edt.h) ---
  // occupancy (Z, Y, X) bool -> float32 distance (in units of `spacing`) from each sample to
  // the nearest True sample; +inf everywhere when nothing is occupied.
  m.def("edt(Tensor occupancy, float spacing) -> Tensor");
  // Marks the sample nearest to each point (round half up); points outside are ignored.
  m.def("points_to_occupancy(Tensor points, float[] origin, float spacing, int[] grid_shape) -> Tensor");

  // --- fused multi-scan distance-transform loss (csrc/kernels/dt_loss.h) ---
  // sum_k weights[k] * mean_i trunc(DT_k(points_i + time_offsets[k] * flow_i)); every DT is
  // (Z_k, Y_k, X_k) float32 with its own origin (origins = [x0,y0,z0] per DT, flattened),
  // all with sample spacing `spacing`. Values >= truncation count as 0 with zero gradient.
  m.def("dt_loss(Tensor points, Tensor flow, Tensor[] dts, float[] origins, float spacing, "
        "float[] time_offsets, float[] weights, float truncation) -> Tensor");
  m.def("dt_loss_backward(Tensor grad, Tensor points, Tensor flow, Tensor[] dts, float[] origins, "
        "float spacing, float[] time_offsets, float[] weights, float truncation) -> Tensor");
  // (loss, d loss / d flow) in one pass, for the optimiser's hot loop.
  m.def("dt_loss_fwd_bwd(Tensor points, Tensor flow, Tensor[] dts, float[] origins, float spacing, "
        "float[] time_offsets, float[] weights, float truncation) -> (Tensor, Tensor)");
  // Data-only look-ups of the same DTs (no autograd; csrc/cpu/dt_query_cpu.cpp, cuda/dt_query.cu),
  // query q_k = points + time_offsets[k] * motion, border clamping; a non-finite point or motion
  // row gives NaN. Per point (N,): sum_k weights[k] * c(min(DT_k(q_k), cap)), c = x or x^2.
  // observed (N,) int32 on the points' device, optional: bit k of row i set where scan k counts
  // for point i (it could see the point's unmoved position; FloxelsConfig.range_mask/visibility).
  m.def("dt_residual(Tensor points, Tensor motion, Tensor[] dts, float[] origins, float spacing, "
        "float[] time_offsets, float[] weights, float cap, bool squared, Tensor? observed=None) -> Tensor");
  // (K, N, 4): [DT_k(q_k), d DT_k / d q (x, y, z)] per scan and point (gradient 0 along a
  // clamped axis and for a non-finite row).
  m.def("dt_sample(Tensor points, Tensor motion, Tensor[] dts, float[] origins, float spacing, "
        "float[] time_offsets) -> Tensor");
  // Motion evidence per group of points (estimator/evidence.py): groups are runs of consecutive
  // points with equal labels, and for label < 0 (or no labels) equal cells. Per group, rf / rz =
  // mean over its points of dt_residual with flow / with zero flow (sums in double); per point
  // (score = rz - rf, explained = score > max(ratio * rz, margin), rf, rz); a group with a
  // non-finite residual gives NaN and False. Deterministic on every device. observed: as dt_residual.
  m.def("dt_evidence(Tensor points, Tensor flow, Tensor? labels, Tensor cells, Tensor[] dts, float[] origins, "
        "float spacing, float[] time_offsets, float[] weights, float cap, float margin, float ratio, "
        "Tensor? observed=None) -> (Tensor, Tensor, Tensor, Tensor)");
  // The rigid refinement's Levenberg-Marquardt loop (estimator/refine.py; kernels/rigid_lm.h has
  // the math, reference.rigid_lm the pure-PyTorch loop): points (m, 3) and their offsets rel
  // (m, 3) from their cluster's centroid, rows grouped by cluster (cluster c: rows
  // segments[c] .. segments[c + 1], int64 (C + 1,)); per cluster the start theta (C, 3) =
  // (vx, vy, yaw rate) and a fixed vertical velocity vz (C,); weights: the scans' w_k. Returns
  // (theta (C, 3), cost (C,)) after `iters` steps; data-only, deterministic on every device.
  m.def("rigid_lm(Tensor points, Tensor rel, Tensor segments, Tensor theta, Tensor vz, Tensor[] dts, "
        "float[] origins, float spacing, float[] time_offsets, float[] weights, float tau, int iters) "
        "-> (Tensor, Tensor)");
  // The per-cluster velocity search (estimator/refine.py cluster_velocity_search; math in
  // kernels/velocity_search.h, reference reference.velocity_search): rows grouped by cluster as
  // rigid_lm's (segments, int64 (C + 1,)); observed as dt_residual's; weights: w_k / sum w.
  // Scores zero flow and speeds (1..num_speeds) * speed_step along num_directions directions
  // from each cluster's principal axis, then a 3 x 3 pattern search (local_steps halving steps,
  // at most local_rounds moves each). Returns (best velocity (C, 3), its score (C,), zero flow's
  // score (C,)); data-only, deterministic on every device.
  m.def("velocity_search(Tensor points, Tensor segments, Tensor? observed, Tensor[] dts, float[] origins, "
        "float spacing, float[] time_offsets, float[] weights, float tau, int num_directions, float speed_step, "
        "int num_speeds, int local_steps, int local_rounds) -> (Tensor, Tensor, Tensor)");

  // --- cluster reductions (csrc/kernels/cluster.h) ---
  // Per-cluster mean (num_clusters, C) of values (N, C); labels (N,) int64 in [-1, num_clusters),
  // -1 (noise) ignored; empty clusters give 0.
  m.def("cluster_mean(Tensor values, Tensor labels, int num_clusters) -> Tensor");
  // mean over ALL N points of ||flow_i - mean flow of cluster(i)||; noise points add 0.
  m.def("cluster_consistency_loss(Tensor flow, Tensor labels, int num_clusters) -> Tensor");
  m.def("cluster_consistency_loss_backward(Tensor grad, Tensor flow, Tensor labels, "
        "int num_clusters) -> Tensor");
  m.def("cluster_consistency_fwd_bwd(Tensor flow, Tensor labels, int num_clusters) -> (Tensor, Tensor)");

  // --- exact nearest neighbours (csrc/kernels/nearest.h) ---
  // idx (N,) int64: index into y (M, 3) of the nearest row of each row of x (N, 3), by
  // squared Euclidean distance computed directly (no |x|^2 + |y|^2 - 2xy cancellation); ties
  // go to the lowest index; NaN distances count as +inf. M must be >= 1. (NSFP's Chamfer loss.)
  m.def("nearest_neighbor(Tensor x, Tensor y) -> Tensor");

  // --- exact DBSCAN (csrc/kernels/dbscan.h) ---
  // labels (N,) int64 identical to sklearn.cluster.DBSCAN(eps, min_samples).fit(points).labels_
  // (Euclidean, neighbourhood includes the point, -1 = noise).
  m.def("dbscan(Tensor points, float eps, int min_samples) -> Tensor");

  // --- device-resident optimiser (csrc/kernels/solver.h) ---
  // Runs num_iters Floxels iterations of B independent problems (target frames) whose
  // points / vertices / clusters are concatenated, updating theta, Adam's moments, the
  // lowest-loss table `best`, the (B, 10) float64 state and the (B, max_iters) float64 loss
  // history in place. point_ranges / vertex_ranges / support_ranges: B + 1 offsets;
  // support_dt / support_t / support_w: per support scan of each problem, the index into
  // dts, the time offset and lambda_d * w(t); reg_scale: B multipliers of the regularisers.
  // hyper = [dt_cell, truncation, lr, beta1, beta2, eps, lambda_c, lambda_g_start,
  // lambda_g_end, lambda_g_decay_iters, patience, max_iters, min_delta, truncation_mode
  // (0 zero / 1 clamp), lr_gamma, number of lr milestones (<= 4), 4 milestones,
  // cluster_n_given]; with cluster_n_given = 1, reg_scale holds 2B values, the second B
  // being each problem's cluster-term normaliser (its clustered points).
  // seg_ptr (S + 1): segments = runs of points with equal corner_idx rows and labels inside
  // one problem; vtx_ptr / vtx_entry: per vertex, its (segment * 8 + corner) entries
  // (python/floxels_ext/ops/solver.py builds all of this). No host synchronisation: the
  // CUDA version can be captured into a CUDA graph.
  m.def("solver_run(Tensor points, Tensor corner_idx, Tensor corner_w, Tensor seg_ptr, Tensor vtx_ptr, Tensor vtx_entry, "
        "Tensor? labels, Tensor? cluster_count, Tensor[] dts, float[] dt_origins, int[] point_ranges, "
        "int[] vertex_ranges, int[] support_ranges, int[] support_dt, float[] support_t, float[] support_w, "
        "float[] reg_scale, float[] hyper, Tensor(a!) theta, Tensor(b!) adam_m, Tensor(c!) adam_v, "
        "Tensor(d!) best, Tensor(e!) state, Tensor(f!) history, int num_iters) -> ()");
  // Blocks of the persistent loop kernel that solver_run would launch for problems with
  // these point / vertex ranges on `points`' device (0: two kernels per iteration, which
  // the caller enqueues in chunks; CPU: 0). FLOXELS_SOLVER_PERSISTENT=0/1 forces the choice.
  // Per-target preparation of solver_run in one call (one host synchronisation): points
  // sorted by (label, flow-grid cell) -> (order, sorted points, sorted labels (empty if
  // none), corner_idx (N, 8) int32, corner_w (N, 8), vertices (M,) int64 lattice index of
  // each compact row, seg_ptr (S + 1), vtx_ptr (M + 1), vtx_entry (8S) int32, number of
  // clusters). Segments are cut every `tile` points. csrc/cpu/problem_setup.cpp.
  m.def("problem_setup(Tensor points, Tensor? labels, float[] origin, float spacing, int[] grid_shape, "
        "int tile) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, int)");

  // --- host staging of scans (csrc/cpu/stage_cpu.cpp) ---
  // Copies each (N_k, 3) host scan into out[k] (N_k*3 float32, e.g. page-locked), a thread
  // per scan, and returns (K, 7) float64: per scan min xyz, max xyz of the float32 values,
  // and 1.0 if all are finite.
  m.def("stage_points(Tensor[] points, Tensor(a!)[] out) -> Tensor");
  m.def("solver_loop_blocks(Tensor points, int[] point_ranges, int[] vertex_ranges, bool cluster) -> int");

  // --- lidar pipeline, CPU (csrc/kernels/lidar.h, cpu/lidar_cpu.cpp) ---
  // The per-frame host work of `floxels run`, as ops so that the run's worker threads do it
  // without the GIL. keep (N,) bool: the points of one scan (sensor frame, z up) inside the
  // range crop [min_range, max_range] (horizontal), at most max_height above the local ground
  // surface, and (remove_ground) not within ground_threshold of it; the surface is built from
  // the finite points within grid_distance (horizontal): lowest z per ground_cell cell, opened
  // with a window_cells-wide square window, capped at a trimmed least-squares plane +
  // ground_max_rise (None: no cap); more than max_cells grid cells is an error. Before the
  // opening, points more than outlier_below under the block reference height
  // (floxels_ext/lidar/preprocess/ground_outliers.py) or above outlier_above (z) are outliers: they build
  // no cell and are never kept (None: no such test). Equal to
  // floxels_ext.lidar.preprocess.preprocess_mask_numpy (the reference). Non-finite rows: False.
  m.def("lidar_keep_mask(Tensor points, float? min_range, float? max_range, float? max_height, bool remove_ground, "
        "float ground_cell, int window_cells, float ground_threshold, float? ground_max_rise, float grid_distance, "
        "int max_cells, float? outlier_below, float? outlier_above) -> Tensor");
  // The same as (N,) uint8 classes: 0 cropped or non-finite, 1 kept, 2 ground, 3 outlier
  // (preprocess_classes_numpy, the reference).
  m.def("lidar_point_classes(Tensor points, float? min_range, float? max_range, float? max_height, "
        "bool remove_ground, float ground_cell, int window_cells, float ground_threshold, float? ground_max_rise, "
        "float grid_distance, int max_cells, float? outlier_below, float? outlier_above) -> Tensor");
  // out (N, 3), points' dtype = R p + t of a (4, 4) float64 rigid transform, computed in float64.
  m.def("rigid_transform(Tensor points, Tensor transform) -> Tensor");
  // kept (M, 3) contiguous, points' dtype: the rows of points where mask (N,) bool is set, in
  // order; nonfinite (K,) int64: the rows with a NaN/inf coordinate. These three ops take
  // points (N, 3) with any strides (the x y z columns of a file's rows, without a copy).
  m.def("lidar_select(Tensor points, Tensor mask) -> (Tensor, Tensor)");
  // A frame's flow in its file's rows and axes: flow (M, 3) float32 of the rows where mask
  // (N,) is set, in world axes, times rotation (3, 3) float32 (world <- file) from the left,
  // i.e. f @ R; other rows 0, rows listed in nonfinite (K,) int64 NaN. dynamic (N,) bool:
  // |flow| > dynamic_threshold (float32 arithmetic).
  m.def("frame_flow(Tensor flow, Tensor mask, Tensor nonfinite, Tensor rotation, float dynamic_threshold) "
        "-> (Tensor, Tensor)");
  // The .bin reader's scan-order score of points (N, 3), any strides (the x y z columns of a
  // reading of a file's rows): median over x, y, z of median |row step| / interquartile range,
  // on the finite rows; NaN under 16 of them (floxels_ext/lidar/io/readers.py, _disorder).
  m.def("scan_disorder(Tensor points) -> float");

  // --- build information ---
  // True when this library was built with FLOXELS_PROFILING=ON (CMakeLists.txt): only such a
  // build has the measurement-only solver code that FLOXELS_SOLVER_TRACE / FLOXELS_SOLVER_SKIP
  // switch on (csrc/common/env_switches.h); tools/profile_solver.py checks it. No tensor
  // arguments, so one catch-all kernel serves every device.
  m.def("has_profiling() -> bool", [] { return floxels::env::kProfiling; });
}
