#pragma once
// The one radix sort: stable LSD radix sort of items by an unsigned integer key, 8-bit digits. Used by the
// rasterizer's per-tile depth sort and the decoder's Morton ordering.
#include <algorithm>
#include <bit>
#include <cstdint>
#include <limits>
#include <type_traits>

#include "flexsplat/core/error.hpp"

namespace flexsplat {
inline namespace v0 {

// Sorts count items by key_of(item) through buffers a and b (each count long; b may be the items' own memory, which
// only the first pass reads); returns the buffer that holds the result (items if no pass was needed). Ties keep
// their input order. Digits above the highest bit in which two keys differ, and digits every key shares, cost no pass.
template <class Item, class KeyOf>
Item* radix_sort(Item* items, std::int64_t count, Item* a, Item* b, KeyOf key_of) {
  using U = std::remove_cvref_t<decltype(key_of(*items))>;
  static_assert(std::is_unsigned_v<U>, "radix_sort needs an unsigned integer key");
  constexpr int max_digits = int(sizeof(U));
  if (count <= 1) return items;
  if (!(count <= std::int64_t(std::numeric_limits<std::uint32_t>::max())))
    fail("radix_sort: ", count, " items exceed the 2^32 - 1 limit of its counters");
  // Digits above the highest differing bit are the same in every key: no histogram, no pass (the depths of one tile
  // share their top byte, and counting it would be one long chain of increments).
  U differ = 0;
  const U first = key_of(items[0]);
  for (std::int64_t i = 0; i < count; ++i) differ |= key_of(items[i]) ^ first;
  const int digits = (int(std::bit_width(differ)) + 7) / 8;
  std::uint32_t counts[max_digits][256];
  for (int d = 0; d < digits; ++d) std::fill_n(counts[d], 256, 0u);
  for (std::int64_t i = 0; i < count; ++i) {
    const U key = key_of(items[i]);
    for (int d = 0; d < digits; ++d) ++counts[d][(key >> (8 * d)) & 0xff];
  }
  Item* from = items;
  Item* to = a;
  for (int d = 0; d < digits; ++d) {
    std::uint32_t* c = counts[d];
    if (*std::max_element(c, c + 256) == std::uint32_t(count)) continue;  // a digit shared by every key
    std::uint32_t sum = 0;
    for (int v = 0; v < 256; ++v) {
      const std::uint32_t k = c[v];
      c[v] = sum;
      sum += k;
    }
    const int shift = 8 * d;
    for (std::int64_t i = 0; i < count; ++i) to[c[(key_of(from[i]) >> shift) & 0xff]++] = from[i];
    from = to;
    to = to == a ? b : a;
  }
  return from;
}

}  // namespace v0
}  // namespace flexsplat
