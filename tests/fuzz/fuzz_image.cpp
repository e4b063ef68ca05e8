// libFuzzer harness: the image decoder path (probe, then stb decode at the stored bit depth, as read_float and
// read_rgb do) on arbitrary bytes.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "flexsplat/image/image_io.hpp"

namespace fuzz_image {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const std::vector<unsigned char> bytes(data, data + size);
  const std::filesystem::path source = "fuzz.png";
  try {
    const image::ImageInfo info = image::detail::probe_bytes(source, bytes);
    if (info.bit_depth == 16) {
      (void)image::detail::decode<std::uint16_t>(source, bytes, 4);
      (void)image::detail::decode<std::uint16_t>(source, bytes, 0);
    } else {
      (void)image::detail::decode<std::uint8_t>(source, bytes, 4);
      (void)image::detail::decode<std::uint8_t>(source, bytes, 0);
    }
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_image
