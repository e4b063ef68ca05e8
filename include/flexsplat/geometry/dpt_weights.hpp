#pragma once
// The configuration and weights of VGGT's DPT head (geometry/dpt_head.hpp): DptHeadConfig and its VGGT JSON, the
// weight views (projections, resize layers, layer_rn, fusion blocks, output convs, image convs), their tensor specs
// and their binding from a parameter source.
#include <algorithm>
#include <array>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/io/param_check.hpp"
#include "flexsplat/io/param_source.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

enum class DptActivation { exp, linear, relu, inv_log, sigmoid };
enum class DptConfActivation { expp1, expp0, sigmoid };

struct DptHeadConfig {
  index_t dim_in = 2048;  // channels of the aggregator outputs (2 x embed_dim: frame and global halves)
  index_t patch_size = 14;
  index_t output_dim = 2;  // output_dim - 1 prediction channels, then one confidence channel
  index_t features = 256;
  std::array<index_t, 4> out_channels{256, 512, 1024, 1024};
  std::array<index_t, 4> intermediate_layer_idx{4, 11, 17, 23};
  DptActivation activation = DptActivation::exp;
  DptConfActivation conf_activation = DptConfActivation::expp1;
  bool pos_embed = true;
  double pos_embed_ratio = 0.1;
  double pos_embed_omega = 100.0;
  double norm_eps = 1e-5;
  // > 0: the input image's channels join the full-resolution map entering output_conv2 (FlexSplat's match head: a
  // small model's patch tokens cannot place a descriptor within its patch, the pixels can). 0: VGGT's head.
  index_t image_channels = 0;
  // > 0: that many 3x3 convolutions + ReLU of image_width channels turn the pixels into local features before they join
  // (a descriptor has to tell a pixel by the texture around it, not by its colour alone). 0: the raw pixels join.
  index_t image_convs = 0;
  index_t image_width = 16;

  index_t head_features() const { return features / 2; }  // channels after output_conv1
  index_t image_out() const { return image_convs > 0 ? image_width : image_channels; }  // image channels that join
  index_t conv2_in() const { return head_features() + image_out(); }  // output_conv2.0's input channels
  static constexpr index_t head_hidden = 32;                // output_conv2's hidden channels
  void validate() const {
    require(dim_in > 0 && patch_size > 0 && features >= 2 && output_dim >= 2, "DPT head config: dim_in ", dim_in,
            ", patch_size ", patch_size, ", features ", features, ", output_dim ", output_dim,
            " (need positive sizes, features >= 2, output_dim >= 2)");
    for (index_t oc : out_channels) require(oc > 0, "DPT head config: out_channels entry ", oc, " must be positive");
    require(image_channels >= 0 && image_channels <= 4, "DPT head config: image_channels ", image_channels,
            " must be in [0, 4]");
    require(image_convs >= 0 && image_convs <= 4 && (image_convs == 0 || image_channels > 0),
            "DPT head config: image_convs ", image_convs, " must be in [0, 4] and needs image_channels > 0 (got ",
            image_channels, ")");
    require(image_width >= 1 && image_width <= 256, "DPT head config: image_width ", image_width,
            " must be in [1, 256]");
    for (index_t i : intermediate_layer_idx)
      require(i >= 0, "DPT head config: intermediate_layer_idx entry ", i, " must be non-negative");
    if (pos_embed) {
      for (index_t oc : out_channels)
        require(oc % 4 == 0, "DPT head config: positional embedding needs out_channels divisible by 4, got ", oc);
      require(head_features() % 4 == 0, "DPT head config: positional embedding needs features/2 divisible by 4, got ",
              head_features());
    }
  }
};

// The depth head of a VGGT whose config JSON uses the reference bundles' keys (embed_dim, patch_size, features,
// out_channels, intermediate_layer_idx); absent keys keep VGGT-1B's values.
inline DptHeadConfig dpt_head_config_from_vggt_json(const nlohmann::json& j) {
  DptHeadConfig c;
  try {
    if (j.contains("embed_dim")) c.dim_in = 2 * j.at("embed_dim").get<index_t>();
    if (j.contains("patch_size")) c.patch_size = j.at("patch_size").get<index_t>();
    if (j.contains("features")) c.features = j.at("features").get<index_t>();
    if (j.contains("out_channels")) c.out_channels = j.at("out_channels").get<std::array<index_t, 4>>();
    if (j.contains("intermediate_layer_idx"))
      c.intermediate_layer_idx = j.at("intermediate_layer_idx").get<std::array<index_t, 4>>();
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config ", j.dump(), ": bad DPT head entry: ", e.what());
  }
  c.validate();
  return c;
}

template <class T>
struct ConvWeights {
  const T* weight = nullptr;
  const T* bias = nullptr;
};

template <class T>
struct ResidualConvUnitWeights {
  ConvWeights<T> conv1, conv2;
};

template <class T>
struct FusionBlockWeights {
  ResidualConvUnitWeights<T> unit1;  // resConfUnit1: absent (null) in refinenet4, which has no skip input
  ResidualConvUnitWeights<T> unit2;
  ConvWeights<T> out_conv;
};

template <class T>
struct DptHeadWeights {
  const T *norm_weight = nullptr, *norm_bias = nullptr;
  std::array<ConvWeights<T>, 4> projects;
  std::array<ConvWeights<T>, 4> resize;  // [2] is the identity (no weights)
  std::array<const T*, 4> layer_rn{};    // bias-free 3x3 convs
  std::array<FusionBlockWeights<T>, 4> refinenet;  // [0] = refinenet1 (finest) .. [3] = refinenet4
  ConvWeights<T> output_conv1, output_conv2_0, output_conv2_2;
  std::array<ConvWeights<T>, 4> image_conv;  // the first image_convs are bound
};

// Parameter names and shapes as in VGGT's state_dict, each prefixed with `prefix`.
inline void append_dpt_head_specs(std::vector<io::TensorSpec>& out, const DptHeadConfig& c,
                                  const std::string& prefix = "depth_head.") {
  const index_t F = c.features;
  const auto& oc = c.out_channels;
  auto conv = [&](const std::string& name, std::vector<index_t> shape, bool bias = true) {
    const index_t o = shape[0];
    out.push_back({prefix + name + ".weight", std::move(shape)});
    if (bias) out.push_back({prefix + name + ".bias", {o}});
  };
  out.push_back({prefix + "norm.weight", {c.dim_in}});
  out.push_back({prefix + "norm.bias", {c.dim_in}});
  for (int i = 0; i < 4; ++i) conv("projects." + std::to_string(i), {oc[i], c.dim_in, 1, 1});
  conv("resize_layers.0", {oc[0], oc[0], 4, 4});
  conv("resize_layers.1", {oc[1], oc[1], 2, 2});
  conv("resize_layers.3", {oc[3], oc[3], 3, 3});
  for (int i = 0; i < 4; ++i) conv("scratch.layer" + std::to_string(i + 1) + "_rn", {F, oc[i], 3, 3}, false);
  for (int r = 1; r <= 4; ++r) {
    const std::string p = "scratch.refinenet" + std::to_string(r) + ".";
    conv(p + "out_conv", {F, F, 1, 1});
    for (int u = (r == 4 ? 2 : 1); u <= 2; ++u)
      for (int k = 1; k <= 2; ++k) conv(p + "resConfUnit" + std::to_string(u) + ".conv" + std::to_string(k), {F, F, 3, 3});
  }
  conv("scratch.output_conv1", {c.head_features(), F, 3, 3});
  for (index_t j = 0; j < c.image_convs; ++j)
    conv("scratch.image_conv." + std::to_string(j), {c.image_width, j == 0 ? c.image_channels : c.image_width, 3, 3});
  conv("scratch.output_conv2.0", {DptHeadConfig::head_hidden, c.conv2_in(), 3, 3});
  conv("scratch.output_conv2.2", {c.output_dim, DptHeadConfig::head_hidden, 1, 1});
}

// Binds every pointer through get(name, shape) -> const T* (the name relative to the head), in the order above.
template <class T, class Get>
DptHeadWeights<T> bind_dpt_head_weights(const DptHeadConfig& c, Get&& get) {
  c.validate();
  DptHeadWeights<T> w;
  auto conv = [&](ConvWeights<T>& cw, const std::string& p, std::vector<index_t> shape) {
    cw.weight = get(p + "weight", shape);
    cw.bias = get(p + "bias", std::vector<index_t>{shape[0]});
  };
  const index_t F = c.features;
  const auto& oc = c.out_channels;
  w.norm_weight = get("norm.weight", std::vector<index_t>{c.dim_in});
  w.norm_bias = get("norm.bias", std::vector<index_t>{c.dim_in});
  for (int i = 0; i < 4; ++i) conv(w.projects[i], "projects." + std::to_string(i) + ".", {oc[i], c.dim_in, 1, 1});
  conv(w.resize[0], "resize_layers.0.", {oc[0], oc[0], 4, 4});
  conv(w.resize[1], "resize_layers.1.", {oc[1], oc[1], 2, 2});
  conv(w.resize[3], "resize_layers.3.", {oc[3], oc[3], 3, 3});
  for (int i = 0; i < 4; ++i)
    w.layer_rn[i] = get("scratch.layer" + std::to_string(i + 1) + "_rn.weight", std::vector<index_t>{F, oc[i], 3, 3});
  for (int r = 1; r <= 4; ++r) {
    const std::string p = "scratch.refinenet" + std::to_string(r) + ".";
    auto& fb = w.refinenet[r - 1];
    conv(fb.out_conv, p + "out_conv.", {F, F, 1, 1});
    if (r != 4) {
      conv(fb.unit1.conv1, p + "resConfUnit1.conv1.", {F, F, 3, 3});
      conv(fb.unit1.conv2, p + "resConfUnit1.conv2.", {F, F, 3, 3});
    }
    conv(fb.unit2.conv1, p + "resConfUnit2.conv1.", {F, F, 3, 3});
    conv(fb.unit2.conv2, p + "resConfUnit2.conv2.", {F, F, 3, 3});
  }
  conv(w.output_conv1, "scratch.output_conv1.", {c.head_features(), F, 3, 3});
  for (index_t j = 0; j < c.image_convs; ++j)
    conv(w.image_conv[j], "scratch.image_conv." + std::to_string(j) + ".",
         {c.image_width, j == 0 ? c.image_channels : c.image_width, 3, 3});
  conv(w.output_conv2_0, "scratch.output_conv2.0.", {DptHeadConfig::head_hidden, c.conv2_in(), 3, 3});
  conv(w.output_conv2_2, "scratch.output_conv2.2.", {c.output_dim, DptHeadConfig::head_hidden, 1, 1});
  return w;
}

// Checks every parameter first (one error lists all missing, mis-shaped and unexpected `prefix` tensors), then binds.
template <class T>
DptHeadWeights<T> load_dpt_head_weights(io::ParamSource<T>& src, const DptHeadConfig& c,
                                        const std::string& prefix = "depth_head.") {
  c.validate();
  std::vector<io::TensorSpec> specs;
  append_dpt_head_specs(specs, c, prefix);
  io::check_parameters(src, specs, {prefix}, "DPT head");
  return bind_dpt_head_weights<T>(c, [&](const std::string& name, const std::vector<index_t>& shape) {
    return src.get(prefix + name, shape);
  });
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
