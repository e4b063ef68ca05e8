// libFuzzer harness: the checkpoint loader on a file written from the input: train::load_checkpoint into a small
// fixed parameter store (with and without optimizer state, with an expected configuration), then
// model::load_flexsplat, which builds the model the file's configuration describes and loads a training state into it.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <unistd.h>

#include <nlohmann/json.hpp>

#include "flexsplat/model/weights.hpp"
#include "flexsplat/optim/checkpoint.hpp"

namespace fuzz_checkpoint {

namespace fs = std::filesystem;

// The store of tests/fuzz/make_seeds.cpp's generic checkpoints: two segments, four tensors.
flexsplat::train::ParamStore<float>& small_store() {
  static flexsplat::train::ParamStore<float> store = [] {
    flexsplat::train::ParamStore<float> s;
    s.add_segment("a", {{"layer.weight", {2, 3}}, {"layer.bias", {3}}});
    s.add_segment("b", {{"norm.weight", {4}}, {"scalar", {}}});
    s.allocate(true);
    return s;
  }();
  return store;
}

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  static const fs::path path =
      fs::temp_directory_path() / ("flexsplat_fuzz_checkpoint_" + std::to_string(::getpid()) + ".safetensors");
  std::ofstream(path, std::ios::binary | std::ios::trunc).write(reinterpret_cast<const char*>(data),
                                                                static_cast<std::streamsize>(size));
  static const nlohmann::json expected = {{"kind", "fuzz"}};
  try {
    (void)train::load_checkpoint(path, small_store(), true, &expected);
  } catch (const Error&) {
  }
  try {
    (void)train::load_checkpoint(path, small_store(), false);
  } catch (const Error&) {
  }
  try {
    (void)model::load_flexsplat<float>(path, true);
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_checkpoint
