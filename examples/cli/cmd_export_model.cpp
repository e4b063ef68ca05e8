// export-model: a training state (RUN/state.safetensors) as a model file: the parameters and the configuration, without
// the optimizer's moments (a third of the size), as the trainer writes model.safetensors at a run's end.
#include <cstdio>
#include <filesystem>
#include <string>

#include "flexsplat/model/weights.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/optim/checkpoint.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int export_model(Args args) {
  std::string out;
  require(take_option(args, "-o", out) || take_option(args, "--output", out), "export-model needs -o MODEL.safetensors");
  for (const auto& a : args) require(a.empty() || a[0] != '-', "export-model: unknown option '", a, "'");
  require(args.size() == 1, "export-model needs exactly one STATE.safetensors");
  require(std::filesystem::is_regular_file(args[0]), "export-model: '", args[0], "' does not exist");
  const auto w = model::load_flexsplat<float>(args[0]);
  const auto file = safetensors::File::open(args[0]);
  const std::uint64_t step = file.has_metadata(train::checkpoint_step_key)
                                 ? static_cast<std::uint64_t>(parse_integer(file.metadata(train::checkpoint_step_key),
                                                                            "the file's step", 0, 1LL << 62))
                                 : 0;
  w->save(out, step);
  std::printf("%s: the parameters of %s at step %llu\n", out.c_str(), args[0].c_str(),
              static_cast<unsigned long long>(step));
  return 0;
}

const RegisterCommand registered_cmd_export_model(
    "export-model", {"a training state as a model file (parameters and configuration, no optimizer state)",
                     "STATE.safetensors -o MODEL.safetensors", export_model});

}  // namespace
}  // namespace flexsplat::cli
