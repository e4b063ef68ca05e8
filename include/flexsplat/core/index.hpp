#pragma once
// The signed index type of every extent, offset and loop bound (signed: differences and reverse loops stay plain).
#include <cstdint>

namespace flexsplat {
inline namespace v0 {

using index_t = std::int64_t;

}  // namespace v0
}  // namespace flexsplat
