// Input checks shared by the CPU and CUDA bindings: every op validates dtype, shape and
// device up front so that bad input raises a RuntimeError naming the argument instead
// of reading out of bounds.
#pragma once
#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include <charconv>
#include <cmath>
#include <concepts>
#include <string>
#include <string_view>
#include <vector>

namespace floxels {

// Error messages are built here, never by streaming numbers into an ostream: with some
// torch wheels (seen with torch 2.11+cu130 on the GPU image) a second libstdc++ copy in
// the process makes `ostream << int` inside an extension segfault (pytorch#109923,
// #81543). Numbers are formatted with std::to_chars and TORCH_CHECK only receives the
// finished string.
namespace detail {
inline void append(std::string& s, std::string_view v) { s.append(v); }
inline void append(std::string& s, const char* v) { s.append(v); }
inline void append(std::string& s, const std::string& v) { s.append(v); }
inline void append(std::string& s, char v) { s.push_back(v); }
inline void append(std::string& s, bool v) { s.append(v ? "true" : "false"); }
template <typename T>
  requires(std::integral<T> || std::floating_point<T>)
inline void append(std::string& s, T v) {
  char buf[64];
  auto r = std::to_chars(buf, buf + sizeof(buf), v);
  s.append(buf, r.ptr);
}
template <typename T>
inline void append(std::string& s, c10::ArrayRef<T> v) {
  s.push_back('[');
  for (size_t i = 0; i < v.size(); ++i) {
    if (i) s.append(", ");
    append(s, v[i]);
  }
  s.push_back(']');
}
inline void append(std::string& s, c10::ScalarType t) { s.append(c10::toString(t)); }
inline void append(std::string& s, const c10::Device& d) {
  s.append(c10::DeviceTypeName(d.type(), /*lower_case=*/true));
  if (d.has_index()) {
    s.push_back(':');
    append(s, static_cast<int>(d.index()));
  }
}
}  // namespace detail

template <typename... Args>
std::string msg(const Args&... args) {
  std::string s;
  (detail::append(s, args), ...);
  return s;
}

}  // namespace floxels

// TORCH_CHECK with a message from floxels::msg (see above); evaluated only on failure.
#define FLX_CHECK(cond, ...) TORCH_CHECK((cond), ::floxels::msg(__VA_ARGS__))

namespace floxels {

inline void check_points(const at::Tensor& p, std::string_view name = "points") {
  FLX_CHECK(p.dim() == 2 && p.size(1) == 3, "floxels: ", name, " must have shape (N, 3), got ",
              p.sizes());
  FLX_CHECK(p.scalar_type() == at::kFloat || p.scalar_type() == at::kDouble, "floxels: ", name,
              " must be float32 or float64, got ", p.scalar_type());
}

inline void check_same_device(const at::Tensor& a, const at::Tensor& b, std::string_view na,
                              std::string_view nb) {
  FLX_CHECK(a.device() == b.device(), "floxels: ", na, " is on ", a.device(), " but ", nb,
              " is on ", b.device());
}

inline void check_same_dtype(const at::Tensor& a, const at::Tensor& b, std::string_view na,
                             std::string_view nb) {
  FLX_CHECK(a.scalar_type() == b.scalar_type(), "floxels: ", na, " is ", a.scalar_type(),
              " but ", nb, " is ", b.scalar_type());
}

inline void check_origin(c10::ArrayRef<double> origin, std::string_view name = "origin") {
  FLX_CHECK(origin.size() == 3, "floxels: ", name, " must have 3 values [x0, y0, z0], got ",
              origin.size());
  for (double v : origin) FLX_CHECK(std::isfinite(v), "floxels: ", name, " must be finite, got ", origin);
}

// Bounded away from 0 and inf so that 1 / spacing and (p - o) / spacing stay meaningful in
// float32 (a spacing that rounds to 0 in float32 would turn finite points into NaN).
inline void check_spacing(double spacing) {
  FLX_CHECK(spacing >= 1e-30 && spacing <= 1e30,
            "floxels: spacing must be positive and finite (1e-30 <= spacing <= 1e30), got ", spacing);
}

// Number of elements of `sizes` (entries >= 0), refusing a product above 2^60 (or one that
// overflows): a wrapped size would under-allocate and the kernels would write out of bounds.
inline int64_t checked_numel(c10::ArrayRef<int64_t> sizes, std::string_view name) {
  int64_t n = 1;
  for (auto s : sizes) {
    FLX_CHECK(s >= 0, "floxels: ", name, " has a negative size: ", sizes);
    FLX_CHECK(!__builtin_mul_overflow(n, s, &n) && n <= (int64_t(1) << 60), "floxels: ", name, " ", sizes,
              " has too many elements");
  }
  return n;
}

inline void check_grid_shape(c10::ArrayRef<int64_t> shape) {
  FLX_CHECK(shape.size() == 3, "floxels: grid_shape must be (Z, Y, X), got ", shape.size(),
              " values");
  for (auto s : shape) FLX_CHECK(s >= 1, "floxels: grid_shape entries must be >= 1, got ", shape);
  checked_numel(shape, "grid_shape");
}

}  // namespace floxels
