// Torch binding of the CUDA distance transform and occupancy ops: checks inputs, allocates
// outputs and scratch, and launches on the current stream (no host synchronisation).
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include <string>

#include "common/check.h"
#include "cuda/edt_launch.h"
#include "kernels/edt.h"

namespace floxels {
namespace {

at::Tensor edt_cuda(const at::Tensor& occupancy, double spacing) {
  // Integers go through std::to_string: streaming them into the message segfaulted in the
  // GPU machine's build (torch 2.11, g++ 13), see the edt family report.
  FLX_CHECK(occupancy.dim() == 3, "floxels: occupancy must be a (Z, Y, X) tensor, got ",
              std::to_string(occupancy.dim()), " dimensions");
  FLX_CHECK(occupancy.scalar_type() == at::kBool, "floxels: occupancy must be bool, got ",
              occupancy.scalar_type());
  FLX_CHECK(occupancy.is_cuda(), "floxels: occupancy must be a CUDA tensor");
  check_spacing(spacing);
  const c10::cuda::CUDAGuard guard(occupancy.device());
  const int64_t Z = occupancy.size(0), Y = occupancy.size(1), X = occupancy.size(2);
  auto out = at::empty({Z, Y, X}, occupancy.options().dtype(at::kFloat));
  if (out.numel() == 0) return out;
  FLX_CHECK(edt::max_squared_distance(Z, Y, X) < edt::kInf, "floxels: edt grid (", std::to_string(Z), ", ", std::to_string(Y), ", ",
              std::to_string(X), ")",
              " is too large: squared distances would overflow int32");
  auto occ = occupancy.contiguous();
  auto scratch = at::empty({cuda::edt_scratch_elems(Z, Y, X)}, occupancy.options().dtype(at::kInt));
  const cudaError_t err = cuda::edt_launch(reinterpret_cast<const uint8_t*>(occ.data_ptr<bool>()),
                                           out.data_ptr<float>(), scratch.data_ptr<int32_t>(), Z, Y, X,
                                           spacing, at::cuda::getCurrentCUDAStream());
  FLX_CHECK(err == cudaSuccess, "floxels: edt CUDA launch failed: ", cudaGetErrorString(err));
  return out;
}

at::Tensor points_to_occupancy_cuda(const at::Tensor& points, c10::ArrayRef<double> origin, double spacing,
                                    c10::ArrayRef<int64_t> grid_shape) {
  check_points(points);
  check_origin(origin);
  check_spacing(spacing);
  check_grid_shape(grid_shape);
  FLX_CHECK(points.is_cuda(), "floxels: points must be a CUDA tensor");
  const c10::cuda::CUDAGuard guard(points.device());
  const int64_t Z = grid_shape[0], Y = grid_shape[1], X = grid_shape[2];
  auto out = at::zeros({Z, Y, X}, points.options().dtype(at::kBool));
  const int64_t n = points.size(0);
  if (n == 0) return out;
  auto pts = points.contiguous();
  uint8_t* occ = reinterpret_cast<uint8_t*>(out.data_ptr<bool>());
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  cudaError_t err;
  if (pts.scalar_type() == at::kFloat)
    err = cuda::points_to_occupancy_launch(pts.data_ptr<float>(), n, origin.data(), spacing, Z, Y, X, occ,
                                           stream);
  else
    err = cuda::points_to_occupancy_launch(pts.data_ptr<double>(), n, origin.data(), spacing, Z, Y, X, occ,
                                           stream);
  FLX_CHECK(err == cudaSuccess, "floxels: points_to_occupancy CUDA launch failed: ",
              cudaGetErrorString(err));
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(floxels, CUDA, m) {
  m.impl("edt", &edt_cuda);
  m.impl("points_to_occupancy", &points_to_occupancy_cuda);
}

}  // namespace floxels
