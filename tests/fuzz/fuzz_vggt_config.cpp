// libFuzzer harness: geometry::vggt_config_from_json (trunk, camera head and DPT head keys) on arbitrary bytes.
#include <cstddef>
#include <cstdint>
#include <string>

#include "flexsplat/geometry/config.hpp"

namespace fuzz_vggt_config {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    (void)geometry::vggt_config_from_json(text);
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_vggt_config
