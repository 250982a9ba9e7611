// A host-described scan (DtLossScanDesc) in the kernels' types, for the dt_loss-family
// launchers (dt_loss.cu, dt_query.cu): sizes as int (the bindings check < 2^31 samples), the
// origin, time offset and ``weight`` as T.
#pragma once
#include "cuda/dt_loss_launch.h"
#include "kernels/dt_loss.h"

namespace floxels::cuda {

template <typename T>
inline dt_loss::Scan<T, int> device_scan(const DtLossScanDesc& d, double weight) {
  return dt_loss::Scan<T, int>{d.data,  static_cast<int>(d.nx), static_cast<int>(d.ny), static_cast<int>(d.nz),
                               T(d.ox), T(d.oy),                T(d.oz),                T(d.time_offset),
                               T(weight)};
}

}  // namespace floxels::cuda
