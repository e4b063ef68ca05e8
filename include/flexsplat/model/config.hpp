#pragma once
// The architecture of a whole FlexSplat model: the VGGT geometry transformer, the appearance side (UNet, fusion,
// Gaussian decoder), the model's input resolution and the Gaussian budget. Serialises to the JSON stored in a
// checkpoint's __metadata__ ("config"), so a model file says what it is.
#include <string>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/decoder/model.hpp"
#include "flexsplat/geometry/config.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct FlexSplatConfig {
  geometry::VggtConfig geometry;
  decoder::ModelConfig appearance;
  index_t image_h = 252, image_w = 252;  // model input; a multiple of the patch size
  index_t gaussians = 0;                 // 0: decoder::default_gaussian_budget(views)

  index_t gaussians_for(index_t views) const {
    return gaussians > 0 ? gaussians : decoder::default_gaussian_budget(views);
  }
  void validate() const {
    geometry.validate();
    decoder::validate_model_config(appearance);
    const index_t p = geometry.aggregator.patch_size;
    require(image_h >= p && image_w >= p && image_h % p == 0 && image_w % p == 0, "FlexSplat config: image size ",
            image_h, " x ", image_w, " must be a positive multiple of the patch size ", p);
    require(image_h <= geometry.aggregator.dino.img_size * 4 && image_w <= geometry.aggregator.dino.img_size * 4,
            "FlexSplat config: image size ", image_h, " x ", image_w, " is far beyond the position grid of img_size ",
            geometry.aggregator.dino.img_size);
    require(appearance.unet.in_channels == 3, "FlexSplat config: the UNet reads RGB (in_channels 3), got ",
            appearance.unet.in_channels);
    require(appearance.fusion.depth_channels == geometry.depth.head_features(), "FlexSplat config: fusion expects ",
            appearance.fusion.depth_channels, " depth-feature channels, the depth head gives ",
            geometry.depth.head_features(), " (features / 2)");
    require(gaussians >= 0 && gaussians <= appearance.decoder.max_queries, "FlexSplat config: gaussians ", gaussians,
            " outside [0, max_queries = ", appearance.decoder.max_queries, "]");
    require(gaussians > 0 || decoder::default_gaussian_budget(1) <= appearance.decoder.max_queries,
            "FlexSplat config: gaussians 0 picks the paper's budget (10K-20K), larger than max_queries ",
            appearance.decoder.max_queries, "; set gaussians explicitly");
  }
};

inline nlohmann::json to_json(const geometry::VggtConfig& c) {
  const auto& a = c.aggregator;
  return {{"img_size", a.dino.img_size},     {"patch_size", a.patch_size},
          {"embed_dim", a.embed_dim},        {"depth", a.depth},
          {"num_heads", a.num_heads},        {"mlp_ratio", a.mlp_ratio},
          {"num_register_tokens", a.num_register_tokens}, {"qk_norm", a.qk_norm},
          {"rope_freq", a.rope_freq},        {"init_values", a.init_values},
          {"aa_block_size", a.aa_block_size}, {"aa_order", a.aa_order},
          {"dino_depth", a.dino.depth},      {"dino_heads", a.dino.num_heads},
          {"dino_mlp_ratio", a.dino.mlp_ratio}, {"trunk_depth", c.camera.trunk_depth},
          {"cam_heads", c.camera.num_heads}, {"features", c.depth.features},
          {"out_channels", c.depth.out_channels}, {"intermediate_layer_idx", c.depth.intermediate_layer_idx}};
}

inline nlohmann::json to_json(const decoder::ModelConfig& c) {
  const auto& d = c.decoder;
  return {{"unet", {{"in_channels", c.unet.in_channels}, {"base", c.unet.base}, {"levels", c.unet.levels}}},
          {"fusion", {{"depth_channels", c.fusion.depth_channels}, {"unet_channels", c.fusion.unet_channels},
                      {"out_channels", c.fusion.out_channels}}},
          {"decoder", {{"dim", d.dim}, {"ffn", d.ffn}, {"heads", d.heads}, {"layers", d.layers}, {"points", d.points},
                       {"max_views", d.max_views}, {"value_dim", d.value_dim}, {"max_queries", d.max_queries},
                       {"local_attention", d.local_attention}, {"window", d.window}}}};
}

inline nlohmann::json to_json(const FlexSplatConfig& c) {
  return {{"geometry", to_json(c.geometry)}, {"appearance", to_json(c.appearance)}, {"image_h", c.image_h},
          {"image_w", c.image_w}, {"gaussians", c.gaussians}};
}

inline decoder::ModelConfig appearance_config_from_json(const nlohmann::json& j) {
  decoder::ModelConfig c;
  auto get = [](const nlohmann::json& o, const char* key, auto& v) {
    if (o.contains(key)) v = o.at(key).get<std::remove_reference_t<decltype(v)>>();
  };
  if (j.contains("unet")) {
    const auto& u = j.at("unet");
    get(u, "in_channels", c.unet.in_channels), get(u, "base", c.unet.base), get(u, "levels", c.unet.levels);
  }
  if (j.contains("fusion")) {
    const auto& f = j.at("fusion");
    get(f, "depth_channels", c.fusion.depth_channels), get(f, "unet_channels", c.fusion.unet_channels);
    get(f, "out_channels", c.fusion.out_channels);
  }
  if (j.contains("decoder")) {
    const auto& d = j.at("decoder");
    auto& o = c.decoder;
    get(d, "dim", o.dim), get(d, "ffn", o.ffn), get(d, "heads", o.heads), get(d, "layers", o.layers);
    get(d, "points", o.points), get(d, "max_views", o.max_views), get(d, "value_dim", o.value_dim);
    get(d, "max_queries", o.max_queries), get(d, "local_attention", o.local_attention), get(d, "window", o.window);
  }
  return c;
}

// Absent keys keep the defaults (VGGT-1B geometry, the paper's decoder); the result is validated.
inline FlexSplatConfig flexsplat_config_from_json(const std::string& text) {
  FlexSplatConfig c;
  try {
    const auto j = nlohmann::json::parse(text);
    require(j.is_object(), "FlexSplat config is not a JSON object");
    if (j.contains("geometry")) c.geometry = geometry::vggt_config_from_json(j.at("geometry").dump());
    if (j.contains("appearance")) c.appearance = appearance_config_from_json(j.at("appearance"));
    if (j.contains("image_h")) c.image_h = j.at("image_h").get<index_t>();
    if (j.contains("image_w")) c.image_w = j.at("image_w").get<index_t>();
    if (j.contains("gaussians")) c.gaussians = j.at("gaussians").get<index_t>();
  } catch (const nlohmann::json::exception& e) {
    fail("FlexSplat config JSON: ", e.what());
  }
  c.validate();
  return c;
}

// The paper's model: VGGT-1B geometry, UNet base 64, C_f 128, decoder width 256, L = 3, 20K queries, 518 input.
inline FlexSplatConfig flexsplat_paper_config() {
  FlexSplatConfig c;
  c.image_h = c.image_w = 518;
  c.appearance.fusion.depth_channels = c.geometry.depth.head_features();
  c.validate();
  return c;
}

// A configuration small enough for gradient checks and unit tests: every module present, tiny widths.
inline FlexSplatConfig flexsplat_tiny_config() {
  FlexSplatConfig c;
  auto& a = c.geometry.aggregator;
  a.patch_size = 7, a.embed_dim = 16, a.depth = 2, a.num_heads = 2, a.num_register_tokens = 2;
  a.dino.img_size = 28, a.dino.patch_size = 7, a.dino.embed_dim = 16, a.dino.depth = 1, a.dino.num_heads = 2;
  a.dino.num_register_tokens = 2;
  c.geometry.camera.dim = 32, c.geometry.camera.trunk_depth = 1, c.geometry.camera.num_heads = 2;
  auto& d = c.geometry.depth;
  d.dim_in = 32, d.patch_size = 7, d.features = 8, d.out_channels = {4, 8, 8, 8}, d.intermediate_layer_idx = {0, 1, 1, 1};
  c.appearance.unet = {3, 4, 1};
  c.appearance.fusion = {d.head_features(), 4, 6};
  auto& o = c.appearance.decoder;
  o.dim = 8, o.ffn = 16, o.heads = 2, o.layers = 2, o.points = 2, o.max_views = 4, o.value_dim = 6, o.max_queries = 64;
  c.image_h = c.image_w = 28;
  c.gaussians = 48;
  c.validate();
  return c;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
