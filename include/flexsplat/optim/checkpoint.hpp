#pragma once
// Checkpoints of a ParamStore as safetensors: a model (params) or a training state (params, Adam m and v under
// "optimizer.adam_m." / "optimizer.adam_v." + name, step and RNG state). __metadata__ holds the format, the model
// configuration as JSON and the step. Writes are atomic (temp file, fsync, rename; temp files of writers killed
// mid-write are removed by the next write). Loading validates everything first and
// raises one error listing every missing, mis-shaped, non-float and unexpected tensor. A VGGT-layout file (the official
// model.safetensors, F32/F16/BF16, with track/point heads that are ignored) initialises the geometry segment alone.
#include <signal.h>
#include <sys/types.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/io/param_check.hpp"
#include "flexsplat/io/param_source.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/optim/params.hpp"

namespace flexsplat {
inline namespace v0 {
namespace train {

inline constexpr const char* checkpoint_format_key = "flexsplat.format";  // "model" or "training_state"
inline constexpr const char* checkpoint_config_key = "flexsplat.config";  // JSON text
inline constexpr const char* checkpoint_step_key = "flexsplat.step";      // decimal
inline constexpr const char* checkpoint_rng_key = "flexsplat.rng_state";  // training_state only
inline constexpr const char* adam_m_prefix = "optimizer.adam_m.";
inline constexpr const char* adam_v_prefix = "optimizer.adam_v.";

struct TrainingState {
  std::uint64_t step = 0;  // updates done
  std::string rng_state;   // opaque (rng_state_string of the training loop's generator)
};

struct CheckpointInfo {
  std::string format;  // "model" or "training_state"
  nlohmann::json config;
  TrainingState state;
  bool optimizer_state = false;  // Adam m and v were loaded
};

inline std::string rng_state_string(const std::mt19937_64& rng) {
  std::ostringstream s;
  s << rng;
  return s.str();
}
inline void restore_rng_state(std::mt19937_64& rng, const std::string& state) {
  std::istringstream s(state);
  std::mt19937_64 r;
  s >> r;
  require(!s.fail(), "checkpoint: RNG state is not a std::mt19937_64 state (", state.size(), " characters)");
  rng = r;
}

namespace detail {
template <class T>
void add_block(safetensors::Writer& w, const ParamStore<T>& store, const T* block, const std::string& prefix) {
  for (const auto& t : store.tensors())
    w.add_raw(prefix + t.name, safetensors::dtype_of<T>(), t.shape, block + t.offset,
              static_cast<std::size_t>(t.numel) * sizeof(T));
}
template <class T>
void write_checkpoint(const std::filesystem::path& path, const ParamStore<T>& store, const nlohmann::json& config,
                      const TrainingState& state, bool training) {
  safetensors::Writer w;
  w.set_metadata(checkpoint_format_key, training ? "training_state" : "model");
  w.set_metadata(checkpoint_config_key, config.dump());
  w.set_metadata(checkpoint_step_key, std::to_string(state.step));
  if (training) w.set_metadata(checkpoint_rng_key, state.rng_state);
  add_block(w, store, store.params(), "");
  if (training) {
    add_block(w, store, store.adam_m(), adam_m_prefix);
    add_block(w, store, store.adam_v(), adam_v_prefix);
  }
  remove_stale_temp_files(path);
  w.write(path);
}
inline bool is_float_dtype(safetensors::Dtype d) {
  using safetensors::Dtype;
  return d == Dtype::F64 || d == Dtype::F32 || d == Dtype::F16 || d == Dtype::BF16;
}
}  // namespace detail

// Params only; step recorded in the metadata.
template <class T>
void save_model(const std::filesystem::path& path, const ParamStore<T>& store, const nlohmann::json& config,
                std::uint64_t step = 0) {
  detail::write_checkpoint(path, store, config, TrainingState{step, {}}, false);
}

// Params, Adam m and v, step and RNG state: resuming from it continues bit-exactly.
template <class T>
void save_training_state(const std::filesystem::path& path, const ParamStore<T>& store, const nlohmann::json& config,
                         const TrainingState& state) {
  detail::write_checkpoint(path, store, config, state, true);
}

// Loads a checkpoint written by save_model or save_training_state into `store` (allocated; any floating dtype is
// converted to T, equal dtypes are copied bit-exactly). Adam m and v are loaded when the file has them, the store is
// allocated for training and with_optimizer_state is set; otherwise they are left untouched and a training-state
// file's optimizer tensors are ignored. expected_config (may be null): the file's configuration must equal it.
// Nothing is written into the store unless every check passes.
template <class T>
CheckpointInfo load_checkpoint(const std::filesystem::path& path, ParamStore<T>& store, bool with_optimizer_state = true,
                               const nlohmann::json* expected_config = nullptr) {
  const auto file = safetensors::File::open(path);
  CheckpointInfo info;
  require(file.has_metadata(checkpoint_format_key), "checkpoint '", file.path(), "': no '", checkpoint_format_key,
          "' in __metadata__ (not a flexsplat checkpoint; a VGGT file initialises geometry with load_vggt_geometry)");
  info.format = file.metadata(checkpoint_format_key);
  require(info.format == "model" || info.format == "training_state", "checkpoint '", file.path(), "': format '",
          info.format, "' is neither 'model' nor 'training_state'");
  std::vector<std::string> problems;
  try {
    info.config = nlohmann::json::parse(file.metadata(checkpoint_config_key));
  } catch (const nlohmann::json::exception& e) {
    problems.push_back(concat("configuration metadata is not valid JSON: ", e.what()));
  }
  if (expected_config && !problems.size() && info.config != *expected_config)
    problems.push_back(concat("configuration differs: file ", info.config.dump(), ", expected ", expected_config->dump()));
  {
    const std::string s = file.metadata(checkpoint_step_key);
    char* end = nullptr;
    errno = 0;
    info.state.step = std::strtoull(s.c_str(), &end, 10);
    if (s.empty() || errno != 0 || *end != '\0' || s[0] == '-') problems.push_back("step '" + s + "' is not an unsigned integer");
  }
  const bool file_training = info.format == "training_state";
  if (file_training) info.state.rng_state = file.metadata(checkpoint_rng_key);
  info.optimizer_state = file_training && with_optimizer_state && store.training();

  io::ParamProblems found;
  found.general = std::move(problems);
  auto &missing = found.missing, &misshaped = found.misshaped, &unexpected = found.unexpected;
  std::set<std::string> expected;
  auto expect = [&](const std::string& name, const ParamInfo& t) {
    expected.insert(name);
    if (!file.contains(name)) {
      missing.push_back(name + " " + safetensors::shape_string(t.shape));
      return;
    }
    const auto& fi = file.info(name);
    if (fi.shape != t.shape)
      misshaped.push_back(name + " is " + safetensors::shape_string(fi.shape) + ", expected " +
                          safetensors::shape_string(t.shape));
    else if (!detail::is_float_dtype(fi.dtype))
      misshaped.push_back(name + " has dtype " + safetensors::dtype_name(fi.dtype) + ", expected a floating type");
  };
  for (const auto& t : store.tensors()) {
    expect(t.name, t);
    if (file_training) {
      // Always listed as expected so they are not "unexpected"; checked only when loaded.
      for (const char* prefix : {adam_m_prefix, adam_v_prefix}) {
        if (info.optimizer_state) expect(prefix + t.name, t);
        else expected.insert(prefix + t.name);
      }
    }
  }
  for (const auto& t : file.tensors())
    if (!expected.count(t.name)) unexpected.push_back(t.name + " " + safetensors::shape_string(t.shape));
  found.raise(concat("checkpoint '", file.path(), "' does not match the parameter store (", store.tensors().size(),
                     " tensors):"),
              "with the wrong shape or dtype");
  for (const auto& t : store.tensors()) {
    file.convert(file.info(t.name), store.params() + t.offset);
    if (info.optimizer_state) {
      file.convert(file.info(adam_m_prefix + t.name), store.adam_m() + t.offset);
      file.convert(file.info(adam_v_prefix + t.name), store.adam_v() + t.offset);
    }
  }
  return info;
}

// The prefix in front of VGGT's state_dict names in a file ("" for the model hub's file, "param." in reference
// bundles): whatever precedes the one tensor named *aggregator.camera_token.
inline std::string vggt_name_prefix(const safetensors::File& file) {
  const std::string key = "aggregator.camera_token";
  std::vector<std::string> found;
  for (const auto& t : file.tensors())
    if (t.name.size() >= key.size() && t.name.compare(t.name.size() - key.size(), key.size(), key) == 0 &&
        (t.name.size() == key.size() || t.name[t.name.size() - key.size() - 1] == '.'))
      found.push_back(t.name.substr(0, t.name.size() - key.size()));
  require(found.size() == 1, "VGGT file '", file.path(), "': ", found.size(), " tensors named *", key,
          found.empty() ? " (not a VGGT state dict)" : " (cannot tell which model to load)");
  return found[0];
}

// Initialises the tensors of segment `segment` (named as VGGT's state_dict: aggregator.*, camera_head.*,
// depth_head.*) from a VGGT-layout safetensors file, converting F16/BF16/F64 to T; file_prefix is prepended to every
// name looked up ("param." in reference bundles). Tensors outside the segment's top-level modules (track_head.*,
// point_head.*) are ignored; a missing or mis-shaped tensor, or a file tensor under one of those modules that the
// segment does not name, is listed in one error and nothing is written.
template <class T>
void load_vggt_geometry(const std::filesystem::path& path, ParamStore<T>& store, const std::string& segment = "geometry",
                        const std::string& file_prefix = {}) {
  const Segment& seg = store.segment(segment);
  std::vector<io::TensorSpec> specs;
  std::set<std::string> modules;
  for (std::size_t i = seg.first; i < seg.first + seg.count; ++i) {
    const auto& t = store.tensors()[i];
    specs.push_back({t.name, t.shape});
    const std::size_t dot = t.name.find('.');
    modules.insert(dot == std::string::npos ? t.name + "." : t.name.substr(0, dot + 1));
  }
  io::ParamSource<T> src(safetensors::File::open(path), file_prefix);
  io::check_parameters(src, specs, std::vector<std::string>(modules.begin(), modules.end()),
                             "geometry segment '" + segment + "'");
  for (std::size_t i = seg.first; i < seg.first + seg.count; ++i) {
    const auto& t = store.tensors()[i];
    const auto& fi = src.file().info(file_prefix + t.name);
    require(detail::is_float_dtype(fi.dtype), "VGGT file '", src.file().path(), "': tensor '", fi.name, "' has dtype ",
            safetensors::dtype_name(fi.dtype), ", expected a floating type");
  }
  for (std::size_t i = seg.first; i < seg.first + seg.count; ++i) {
    const auto& t = store.tensors()[i];
    src.file().convert(src.file().info(file_prefix + t.name), store.params() + t.offset);
  }
}

}  // namespace train
}  // namespace v0
}  // namespace flexsplat
