// libFuzzer harness: the `flexsplat train` configuration (model::parse_train_config, with the FlexSplat model config
// object it may hold) on arbitrary bytes parsed as JSON text the way cmd_train reads the file.
#include <cstddef>
#include <cstdint>

#include <nlohmann/json.hpp>

#include "flexsplat/train/run_config.hpp"

namespace fuzz_train_config {

int test_one_input(const std::uint8_t* data, std::size_t size) {
  using namespace flexsplat;
  const nlohmann::json doc = nlohmann::json::parse(data, data + size, nullptr, false);
  if (doc.is_discarded()) return 0;
  try {
    const model::TrainRunConfig c = model::parse_train_config(doc);
    std::uint64_t start = 0;
    (void)c.stage_at(c.total_steps(), start);
  } catch (const Error&) {
  }
  return 0;
}

}  // namespace fuzz_train_config
