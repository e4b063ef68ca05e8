// libFuzzer harness: COLMAP binary models (io::parse_colmap_binary) on arbitrary bytes; the input is an 8-byte
// little-endian length n, then n bytes of cameras.bin, then images.bin.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "flexsplat/io/colmap.hpp"

namespace fuzz_colmap_binary {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  if (size < 8) return 0;
  std::uint64_t n = 0;
  std::memcpy(&n, data, 8);
  const std::string rest(reinterpret_cast<const char*>(data) + 8, size - 8);
  const std::size_t split = static_cast<std::size_t>(std::min<std::uint64_t>(n, rest.size()));
  try {
    (void)io::parse_colmap_binary(rest.substr(0, split), rest.substr(split), "fuzz cameras.bin", "fuzz images.bin");
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_colmap_binary
