// libFuzzer harness: gltf::decode_glb (tinygltf's GLB/JSON parsing and the KHR_gaussian_splatting reader) on
// arbitrary bytes. A set the reader accepts must also survive encode_glb and decode again.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include "flexsplat/export/gltf.hpp"

namespace fuzz_glb {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  decltype(gltf::decode_glb(nullptr, 0, "")) set;
  try {
    // Camera nodes are read only when asked for: ask, where the reader offers it.
    if constexpr (requires(std::vector<Camera> c) { gltf::decode_glb(data, size, "", &c); }) {
      std::vector<Camera> cameras;
      set = gltf::decode_glb(data, size, "fuzz.glb", &cameras);
    } else {
      set = gltf::decode_glb(data, size, "fuzz.glb");
    }
  } catch (const Error&) {
    return 0;
  }
  try {
    const std::vector<unsigned char> again = gltf::encode_glb(set);
    (void)gltf::decode_glb(again.data(), again.size(), "fuzz re-encoded.glb");
  } catch (const Error& e) {
    std::fprintf(stderr, "accepted glb does not round-trip: %s\n", e.what());
    std::abort();
  }
  return 0;
}

}  // namespace fuzz_glb
