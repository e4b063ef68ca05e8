// Every libFuzzer harness in one binary: one instrumented compile of the readers instead of one each. scripts/fuzz links
// build-fuzz/fuzz_<target> to it and the name it was started under (argv[0]) picks the harness.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string_view>

#include "fuzz_cameras_json.cpp"
#include "fuzz_colmap_binary.cpp"
#include "fuzz_colmap_text.cpp"
#include "fuzz_checkpoint.cpp"
#include "fuzz_dataset.cpp"
#include "fuzz_glb.cpp"
#include "fuzz_image.cpp"
#include "fuzz_ply.cpp"
#include "fuzz_safetensors.cpp"
#include "fuzz_train_config.cpp"
#include "fuzz_transforms_json.cpp"
#include "fuzz_vggt_config.cpp"

namespace {

using Harness = int (*)(const std::uint8_t*, std::size_t);

struct Target {
  std::string_view name;
  Harness run;
};

// The names scripts/fuzz's targets=(...) lists.
constexpr Target kTargets[] = {
    {"safetensors", fuzz_safetensors::test_one_input}, {"ply", fuzz_ply::test_one_input},
    {"glb", fuzz_glb::test_one_input},                 {"image", fuzz_image::test_one_input},
    {"cameras_json", fuzz_cameras_json::test_one_input}, {"vggt_config", fuzz_vggt_config::test_one_input},
    {"dataset", fuzz_dataset::test_one_input},         {"checkpoint", fuzz_checkpoint::test_one_input},
    {"train_config", fuzz_train_config::test_one_input}, {"colmap_text", fuzz_colmap_text::test_one_input},
    {"colmap_binary", fuzz_colmap_binary::test_one_input}, {"transforms_json", fuzz_transforms_json::test_one_input},
};

Harness g_harness = nullptr;

}  // namespace

extern "C" int LLVMFuzzerInitialize(int* argc, char*** argv) {
  std::string_view name = (*argc > 0 && (*argv)[0]) ? (*argv)[0] : "";
  name.remove_prefix(name.find_last_of('/') == std::string_view::npos ? 0 : name.find_last_of('/') + 1);
  if (name.starts_with("fuzz_")) name.remove_prefix(5);
  for (const Target& t : kTargets) {
    if (t.name == name) g_harness = t.run;
  }
  if (!g_harness) {
    std::fprintf(stderr, "fuzz_readers: started as '%.*s'; start it through a link named fuzz_<target>, target one of:",
                 static_cast<int>(name.size()), name.data());
    for (const Target& t : kTargets) std::fprintf(stderr, " %.*s", static_cast<int>(t.name.size()), t.name.data());
    std::fprintf(stderr, "\n");
    std::exit(2);
  }
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) { return g_harness(data, size); }
