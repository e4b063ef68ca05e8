// libFuzzer harness: COLMAP text models (io::parse_colmap_text) on arbitrary bytes; the input is cameras.txt, a form
// feed, then images.txt (no form feed: all of it is both).
#include <cstddef>
#include <cstdint>
#include <string>

#include "flexsplat/io/colmap.hpp"

namespace fuzz_colmap_text {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const std::string all(reinterpret_cast<const char*>(data), size);
  const std::size_t split = all.find('\f');
  try {
    (void)io::parse_colmap_text(all.substr(0, split), split == std::string::npos ? all : all.substr(split + 1),
                                "fuzz cameras.txt", "fuzz images.txt");
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_colmap_text
