// libFuzzer harness: the dataset-folder reader (data::load_objects, then data::sample_batch decoding the pixels) on
// an object folder written from the input. The input is split at "\n--8<--\n" into, in order, cameras.json,
// images/000.png, depth/000.png, images/001.png, depth/001.png (missing parts are absent files, extra parts ignored).
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <unistd.h>
#include <vector>

#include "flexsplat/data/dataset.hpp"

namespace fuzz_dataset {

namespace fs = std::filesystem;

constexpr std::string_view kSeparator = "\n--8<--\n";
constexpr const char* kFiles[] = {"cameras.json", "images/000.png", "depth/000.png", "images/001.png", "depth/001.png"};

// One folder per process (libFuzzer's -fork/-jobs run several), emptied before each input.
const fs::path& work_dir() {
  static const fs::path dir = fs::temp_directory_path() / ("flexsplat_fuzz_dataset_" + std::to_string(::getpid()));
  return dir;
}

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const fs::path obj = work_dir() / "obj";
  fs::remove_all(obj);
  fs::create_directories(obj / "images");
  fs::create_directories(obj / "depth");
  std::size_t at = 0;
  for (const char* name : kFiles) {
    if (at > input.size()) break;
    const std::size_t end = std::min(input.find(kSeparator, at), input.size());
    std::ofstream(obj / name, std::ios::binary).write(input.data() + at, static_cast<std::streamsize>(end - at));
    at = end + kSeparator.size();
  }
  try {
    const std::vector<data::ObjectRecord> objects = data::load_objects({work_dir()});
    const data::ObjectRecord& o = objects.at(0);
    data::BatchOptions options;
    options.inputs = 1;
    options.targets = o.frames.size() > 1 ? 1 : 0;
    options.crop = std::min({o.width, o.height, 32});
    (void)data::sample_batch(objects, 1, 7, 0, options);
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_dataset
