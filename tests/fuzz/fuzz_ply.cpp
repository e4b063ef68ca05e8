// libFuzzer harness: ply::decode_ply (binary little-endian and ASCII) on arbitrary bytes. A set the reader accepts
// must also survive encode_ply and decode again: an Error there is a reader/writer disagreement and aborts.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include "flexsplat/export/ply.hpp"

namespace fuzz_ply {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  decltype(ply::decode_ply(nullptr, 0, "")) set;
  try {
    set = ply::decode_ply(data, size, "fuzz.ply");
  } catch (const Error&) {
    return 0;
  }
  try {
    const std::vector<unsigned char> again = ply::encode_ply(set);
    (void)ply::decode_ply(again.data(), again.size(), "fuzz re-encoded.ply");
  } catch (const Error& e) {
    std::fprintf(stderr, "accepted PLY does not round-trip: %s\n", e.what());
    std::abort();
  }
  return 0;
}

}  // namespace fuzz_ply
