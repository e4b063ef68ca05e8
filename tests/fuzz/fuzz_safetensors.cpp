// libFuzzer harness: safetensors::File validation and element conversion on arbitrary bytes.
// flexsplat::Error is the expected outcome for a bad file; anything else (crash, sanitizer report) is a finding.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "flexsplat/io/safetensors.hpp"

namespace fuzz_safetensors {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  try {
    const auto file = safetensors::File::from_bytes(data, size, "fuzz.safetensors");
    for (const auto& [key, value] : file.metadata()) (void)file.metadata(key);
    for (const auto& t : file.tensors()) {
      (void)file.info(t.name);
      std::vector<double> values(static_cast<std::size_t>(t.numel()));
      file.convert(t, values.data());
      if (t.dtype == safetensors::Dtype::I64 || t.dtype == safetensors::Dtype::I32 ||
          t.dtype == safetensors::Dtype::U8) {
        std::vector<std::int32_t> ints(static_cast<std::size_t>(t.numel()));
        try {
          file.convert(t, ints.data());
        } catch (const Error&) {
        }
      }
      if (t.dtype == safetensors::Dtype::F32 && t.shape.size() == 1) (void)file.view<float, 1>(t.name);
      if (t.shape.size() == 2) (void)file.get<float, 2>(t.name);
    }
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_safetensors
