#pragma once
// Ordering of points along a Morton (Z-order) curve: neighbouring positions in the order are (mostly) neighbours in
// space. The local self-attention uses it to form neighbourhoods, the deformable sampling to visit queries with
// overlapping footprints one after the other.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/radix_sort.hpp"
#include "flexsplat/core/tensor.hpp"

namespace flexsplat {
inline namespace v0 {
namespace decoder {

// A point's 30-bit Morton code and its index: the items the radix sort moves.
struct MortonKey {
  std::uint32_t code;
  std::uint32_t index;
};

// Morton order of points quantised to a 2^10 grid over their bounding box; ties keep the index order.
// order, keys, scratch: [n] caller buffers.
template <class T>
void morton_order(index_t* order, const T* centres, index_t n, MortonKey* keys, MortonKey* scratch) {
  if (!(n >= 0 && n <= index_t(std::numeric_limits<std::uint32_t>::max())))
    fail("morton_order: ", n, " points is outside [0, 2^32 - 1]");
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
    keys[i] = {c, static_cast<std::uint32_t>(i)};
  }
  const MortonKey* sorted = radix_sort(keys, n, scratch, keys, [](const MortonKey& k) { return k.code; });
  for (index_t i = 0; i < n; ++i) order[i] = sorted[i].index;
}

// Convenience form with its own (allocated) buffers.
template <class T>
void morton_order(std::vector<index_t>& order, const T* centres, index_t n) {
  order.resize(static_cast<std::size_t>(n));
  std::vector<MortonKey> keys(static_cast<std::size_t>(n)), scratch(static_cast<std::size_t>(n));
  morton_order(order.data(), centres, n, keys.data(), scratch.data());
}

}  // namespace decoder
}  // namespace v0
}  // namespace flexsplat
