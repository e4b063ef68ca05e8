// libFuzzer harness: cameras.json parsing (io::parse_cameras_json_text, as load_cameras_json reads a file, then
// parse_cameras_json) on arbitrary bytes.
#include <cstddef>
#include <cstdint>
#include <string>

#include <nlohmann/json.hpp>

#include "flexsplat/io/cameras_json.hpp"

namespace fuzz_cameras_json {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  try {
    const nlohmann::json doc =
        io::parse_cameras_json_text(std::string(reinterpret_cast<const char*>(data), size), "fuzz cameras.json");
    (void)io::parse_cameras_json(doc, "fuzz cameras.json");
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_cameras_json
