// libFuzzer harness: transforms.json (io::parse_cameras_json_text, as load_transforms_json reads a file, then
// parse_transforms_json with an image size for every frame) on arbitrary bytes.
#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "flexsplat/io/transforms_json.hpp"

namespace fuzz_transforms_json {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  try {
    const nlohmann::json doc =
        io::parse_cameras_json_text(std::string(reinterpret_cast<const char*>(data), size), "fuzz transforms.json");
    const io::ImageSizeOf size_of = [](const std::string& f) -> std::optional<std::array<int, 2>> {
      if (f.empty()) return std::nullopt;
      return std::array<int, 2>{64, 48};
    };
    (void)io::parse_transforms_json(doc, "fuzz transforms.json", size_of);
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_transforms_json
