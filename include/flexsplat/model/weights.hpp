#pragma once
// The parameters of a whole FlexSplat model in one train::ParamStore: segment "geometry" holds the VGGT tensors under
// VGGT's state_dict names (so the official checkpoint or any VGGT-layout file initialises it), segment "appearance"
// the UNet, fusion and decoder tensors in decoder::ModelParamLayout order (one contiguous block). The geometry weight
// structs point into the store's params block; gradients live at the same offsets of the grads block.
#include <cstdint>
#include <filesystem>
#include <memory>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "flexsplat/decoder/param_names.hpp"
#include "flexsplat/geometry/random_weights.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/optim/checkpoint.hpp"
#include "flexsplat/optim/params.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

inline constexpr const char* geometry_segment = "geometry";
inline constexpr const char* appearance_segment = "appearance";

// Every tensor of a model, in store order: geometry (VGGT names), then appearance ("appearance." + decoder names).
inline std::vector<io::TensorSpec> appearance_parameter_specs(const FlexSplatConfig& c) {
  std::vector<io::TensorSpec> specs;
  decoder::append_model_specs(specs, c.appearance, "appearance.");
  return specs;
}

template <class T>
class FlexSplatWeights {
public:
  // training: also allocate gradients and Adam moments. The object must stay where it is (the weights point into it),
  // hence create() returns it by pointer.
  static std::unique_ptr<FlexSplatWeights> create(const FlexSplatConfig& c, bool training) {
    c.validate();
    auto w = std::unique_ptr<FlexSplatWeights>(new FlexSplatWeights());
    w->config_ = c;
    w->store_.add_segment(geometry_segment, geometry::vggt_parameter_specs(c.geometry));
    w->store_.add_segment(appearance_segment, appearance_parameter_specs(c));
    require(w->store_.segment(appearance_segment).size == decoder::ModelParamLayout(c.appearance).size,
            "FlexSplat weights: appearance names cover ", w->store_.segment(appearance_segment).size,
            " values, the decoder layout has ", decoder::ModelParamLayout(c.appearance).size);
    w->store_.allocate(training);
    w->store_.bind_views(w->source_, geometry_segment);
    w->geometry_ = geometry::load_vggt_weights(w->source_, c.geometry);
    return w;
  }

  // Fresh initial values from one seed: geometry as geometry::random_parameter_values (LayerNorm 1, biases 0,
  // LayerScale 0.01, uniform matrices of variance 1/fan_in), appearance as decoder::model_init. The camera head's last
  // layer starts near a prior camera (identity rotation, zero translation, 45 degree field of view, reached after all
  // refinement iterations): random outputs would put the FoV through its ReLU at 0, a camera with no focal length.
  void init(std::uint64_t seed) {
    const auto& seg = store_.segment(geometry_segment);
    std::uint64_t stream = seed;
    for (std::size_t i = seg.first; i < seg.first + seg.count; ++i) {
      const auto& t = store_.tensors()[i];
      const io::TensorSpec spec{t.name, t.shape};
      const bool random = geometry::draws_random_values(spec);
      geometry::random_parameter_values(store_.params() + t.offset, spec, random ? stream++ : stream,
                                        config_.geometry.aggregator.init_values);
    }
    const double iterations = static_cast<double>(config_.geometry.camera.iterations);
    const double prior[geometry::pose_encoding_dim] = {0, 0, 0, 0, 0, 0, 1, camera_prior_fov, camera_prior_fov};
    auto bias = store_.param("camera_head.pose_branch.fc2.bias");
    for (std::size_t i = 0; i < bias.size(); ++i) bias[i] = static_cast<T>(prior[i] / iterations);
    for (T& v : store_.param("camera_head.pose_branch.fc2.weight")) v *= T(0.01);
    decoder::model_init(appearance(), config_.appearance, seed ^ 0x5851f42d4c957f2dull);
  }
  static constexpr double camera_prior_fov = 0.7853981633974483;  // 45 degrees, the renders' field of view

  // A flexsplat model or training-state file written by save(); the configuration must match.
  train::CheckpointInfo load(const std::filesystem::path& path, bool with_optimizer_state = true) {
    const nlohmann::json expected = to_json(config_);
    return train::load_checkpoint(path, store_, with_optimizer_state, &expected);
  }
  // Every weight of another flexsplat model or training state whose configuration differs from this one at most in
  // the input size and the self-attention choice (neither has parameters): a recipe that fine-tunes at a larger size.
  void init_from_model(const std::filesystem::path& path) {
    const auto file = safetensors::File::open(path);
    require(file.has_metadata(train::checkpoint_config_key), "model file '", path.string(),
            "' has no configuration in its metadata (not a flexsplat model)");
    FlexSplatConfig theirs = flexsplat_config_from_json(file.metadata(train::checkpoint_config_key));
    const FlexSplatConfig& ours = config_;
    theirs.image_h = ours.image_h, theirs.image_w = ours.image_w;
    theirs.appearance.decoder.local_attention = ours.appearance.decoder.local_attention;
    theirs.appearance.decoder.window = ours.appearance.decoder.window;
    require(to_json(theirs) == to_json(ours), "model file '", path.string(), "' has another architecture: ",
            to_json(theirs).dump(), ", expected ", to_json(ours).dump(), " (only the image size may differ)");
    train::load_checkpoint(path, store_, false);  // the configuration is checked above; the tensors are checked here
  }
  // VGGT's model.safetensors (or any VGGT-layout file): initialises the geometry segment only.
  void load_geometry(const std::filesystem::path& path, const std::string& file_prefix = {}) {
    train::load_vggt_geometry(path, store_, geometry_segment, file_prefix);
  }
  void save(const std::filesystem::path& path, std::uint64_t step = 0) const {
    train::save_model(path, store_, to_json(config_), step);
  }

  // The decoder's self-attention, full or local (Morton windows of `window` queries): it has no parameters of its own,
  // so a loaded model runs either way (eval --self-attention); save() then records the choice.
  void set_self_attention(bool local, index_t window) {
    FlexSplatConfig c = config_;
    c.appearance.decoder.local_attention = local;
    c.appearance.decoder.window = window;
    c.validate();
    config_ = c;
  }

  const FlexSplatConfig& config() const noexcept { return config_; }
  train::ParamStore<T>& store() noexcept { return store_; }
  const train::ParamStore<T>& store() const noexcept { return store_; }
  const geometry::VggtWeights<T>& geometry() const noexcept { return geometry_; }
  T* appearance() { return store_.segment_params(appearance_segment); }
  const T* appearance() const { return store_.params() + store_.segment(appearance_segment).offset; }
  T* appearance_grads() { return store_.segment_grads(appearance_segment); }

private:
  FlexSplatWeights() = default;
  FlexSplatConfig config_;
  train::ParamStore<T> store_;
  io::ParamSource<T> source_;
  geometry::VggtWeights<T> geometry_;
};

// Reads the configuration a model file was saved with (its __metadata__), creates the weights and loads them.
template <class T>
std::unique_ptr<FlexSplatWeights<T>> load_flexsplat(const std::filesystem::path& path, bool training = false) {
  const auto file = safetensors::File::open(path);
  require(file.has_metadata(train::checkpoint_config_key), "model file '", path.string(),
          "' has no configuration in its metadata (not a flexsplat model; a VGGT checkpoint goes to --init)");
  const FlexSplatConfig c = flexsplat_config_from_json(file.metadata(train::checkpoint_config_key));
  // The file must hold every tensor of that configuration, shape for shape, before the model is allocated: a few bytes
  // of metadata could otherwise ask for any size (absent keys mean VGGT-1B). Layer counts are bounded by the file's
  // tensor count first (each layer has tensors), so listing the names costs no more than the file.
  const auto& a = c.geometry.aggregator;
  const index_t layers = 2 * a.depth + a.dino.depth + c.geometry.camera.trunk_depth + c.appearance.decoder.layers +
                         c.appearance.unet.levels;
  require(layers <= static_cast<index_t>(file.tensors().size()), "model file '", path.string(), "' holds ",
          file.tensors().size(), " tensors; its configuration has ", layers, " layers");
  std::vector<io::TensorSpec> specs = geometry::vggt_parameter_specs(c.geometry);
  for (auto& s : appearance_parameter_specs(c)) specs.push_back(std::move(s));
  std::size_t absent = 0;
  std::string first;
  for (const auto& s : specs)
    if (!file.contains(s.name) || file.info(s.name).shape != s.shape) {
      if (absent++ == 0) first = s.name + " " + safetensors::shape_string(s.shape);
    }
  require(absent == 0, "model file '", path.string(), "' lacks ", absent, " of the ", specs.size(),
          " tensors its configuration names, or holds them with another shape (first: ", first, ")");
  auto w = FlexSplatWeights<T>::create(c, training);
  w->load(path, training);
  return w;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
