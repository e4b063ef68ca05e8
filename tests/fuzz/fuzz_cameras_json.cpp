// libFuzzer harness: cameras.json parsing (nlohmann without exceptions, as load_cameras_json reads it, then
// parse_cameras_json) on arbitrary bytes.
#include <cstddef>
#include <cstdint>

#include <nlohmann/json.hpp>

#include "flexsplat/export/cameras_json.hpp"

namespace fuzz_cameras_json {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const nlohmann::json doc = nlohmann::json::parse(data, data + size, nullptr, false);
  if (doc.is_discarded()) return 0;
  try {
    (void)gaussians::parse_cameras_json(doc, "fuzz cameras.json");
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_cameras_json
