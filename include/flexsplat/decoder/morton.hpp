#pragma once
// Ordering of points along a Morton (Z-order) curve: neighbouring positions in the order are (mostly) neighbours in
// space. The local self-attention uses it to form neighbourhoods, the deformable sampling to visit queries with
// overlapping footprints one after the other.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "flexsplat/core/tensor.hpp"
#include "flexsplat/decoder/kernels.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// Morton order of points quantised to a 2^10 grid over their bounding box; ties keep the index order.
// order, codes, codes_tmp, order_tmp: [n] caller buffers.
template <class T>
void morton_order(index_t* order, const T* centres, index_t n, std::uint32_t* codes, std::uint32_t* codes_tmp,
                  index_t* order_tmp) {
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (index_t i = 0; i < n; ++i)
    for (int j = 0; j < 3; ++j) {
      const double x = static_cast<double>(centres[3 * i + j]);
      if (!std::isfinite(x)) continue;
      lo[j] = std::min(lo[j], x);
      hi[j] = std::max(hi[j], x);
    }
  for (index_t i = 0; i < n; ++i) {
    std::uint32_t c = 0;
    std::uint32_t cell[3];
    for (int j = 0; j < 3; ++j) {
      const double x = static_cast<double>(centres[3 * i + j]);
      const double extent = hi[j] - lo[j];
      const double t = std::isfinite(x) && extent > 0 ? (x - lo[j]) / extent : 0.0;
      cell[j] = static_cast<std::uint32_t>(std::clamp(t, 0.0, 1.0) * 1023.0);
    }
    for (int bit = 9; bit >= 0; --bit)
      for (int j = 0; j < 3; ++j) c = (c << 1) | ((cell[j] >> bit) & 1u);
    codes[i] = c;
  }
  kernels::radix_sort_30(order, codes, n, codes_tmp, order_tmp);
}

// Convenience form with its own (allocated) buffers.
template <class T>
void morton_order(std::vector<index_t>& order, const T* centres, index_t n) {
  order.resize(static_cast<std::size_t>(n));
  std::vector<std::uint32_t> codes(static_cast<std::size_t>(n)), tmp(static_cast<std::size_t>(n));
  std::vector<index_t> order_tmp(static_cast<std::size_t>(n));
  morton_order(order.data(), centres, n, codes.data(), tmp.data(), order_tmp.data());
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
