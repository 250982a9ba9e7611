// The distance transforms of a dt_loss-family op as the CPU kernels read them: contiguous
// tensors (kept alive by the caller) and one dt_loss::Scan per DT.
#pragma once
#include <ATen/core/Tensor.h>

#include <array>
#include <cstddef>
#include <vector>

#include "kernels/dt_loss.h"

namespace floxels {

template <typename T>
using CpuScan = dt_loss::Scan<T, int64_t>;

inline std::vector<at::Tensor> contiguous_dts(at::TensorList dts) {
  std::vector<at::Tensor> out;
  out.reserve(dts.size());
  for (const auto& d : dts) out.push_back(d.contiguous());  // no copy when already contiguous
  return out;
}

// Scan k's weight is ``scale * weights[k] / divisor`` in double, then T (dt_loss folds the
// upstream gradient and 1/N in); 0 when ``weights`` is empty (ops without weights).
template <typename T>
std::array<CpuScan<T>, dt_loss::kMaxScans> make_scans(const std::vector<at::Tensor>& dts,
                                                      c10::ArrayRef<double> origins,
                                                      c10::ArrayRef<double> time_offsets,
                                                      c10::ArrayRef<double> weights, double scale = 1.0,
                                                      double divisor = 1.0) {
  std::array<CpuScan<T>, dt_loss::kMaxScans> scans{};
  for (size_t k = 0; k < dts.size(); ++k) {
    const at::Tensor& d = dts[k];
    scans[k] = CpuScan<T>{d.data_ptr<float>(), d.size(2), d.size(1), d.size(0),
                          T(origins[3 * k]), T(origins[3 * k + 1]), T(origins[3 * k + 2]),
                          T(time_offsets[k]), weights.empty() ? T(0) : T(scale * weights[k] / divisor)};
  }
  return scans;
}

}  // namespace floxels
