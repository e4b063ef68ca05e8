#pragma once
// Per-pixel match descriptors as the geometry's consumers read them: scaled to unit length, so that a dot product is
// the cosine the match loss was trained on.
#include <cmath>

#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// out[0, D) = d / |d|, the length summed in double; false (out untouched) when |d| is zero or not finite, so that
// blank or broken pixels are left out rather than matched.
template <class T>
bool unit_descriptor(const T* d, index_t D, float* out) {
  double n2 = 0;
  for (index_t k = 0; k < D; ++k) n2 += static_cast<double>(d[k]) * static_cast<double>(d[k]);
  if (!(n2 > 0) || !std::isfinite(n2)) return false;
  const double inv = 1 / std::sqrt(n2);
  for (index_t k = 0; k < D; ++k) out[k] = static_cast<float>(static_cast<double>(d[k]) * inv);
  return true;
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
