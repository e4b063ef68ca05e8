#pragma once
// The architecture of a whole FlexSplat model: the VGGT geometry transformer, the appearance side (UNet, fusion,
// Gaussian decoder), the model's input resolution and the Gaussian budget. Serialises to the JSON stored in a
// checkpoint's __metadata__ ("config"), so a model file says what it is.
#include <cstdint>
#include <cstdlib>
#include <string>
#include <type_traits>
#include <utility>

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
    // Sizes the appearance side's parameter counts are taken from: positive, and the UNet's widest level (base <<
    // levels) within 2^20 so that no count overflows.
    const auto& u = appearance.unet;
    const auto& d = appearance.decoder;
    require(u.levels >= 0 && u.levels <= 20 && u.base >= 1 && u.base <= (index_t(1) << (20 - u.levels)),
            "FlexSplat config: UNet base ", u.base, " and levels ", u.levels, " must be >= 1 and >= 0 with base << levels <= 2^20");
    require(appearance.fusion.unet_channels >= 1 && appearance.fusion.out_channels >= 1 && appearance.fusion.depth_channels >= 1,
            "FlexSplat config: fusion channels ", appearance.fusion.depth_channels, ", ", appearance.fusion.unet_channels,
            ", ", appearance.fusion.out_channels, " must be positive");
    require(d.dim >= 1 && d.ffn >= 1 && d.heads >= 1 && d.dim % d.heads == 0 && d.layers >= 1 && d.points >= 1 &&
                d.max_views >= 1 && d.value_dim >= 1 && d.max_queries >= 1 && (!d.local_attention || d.window >= 1),
            "FlexSplat config: decoder dim ", d.dim, ", ffn ", d.ffn, ", heads ", d.heads, ", layers ", d.layers, ", points ",
            d.points, ", max_views ", d.max_views, ", value_dim ", d.value_dim, ", max_queries ", d.max_queries, ", window ",
            d.window, " must be positive, with dim divisible by heads");
    require(d.view_slots >= 0 && d.view_slots <= d.max_views, "FlexSplat config: decoder view_slots ", d.view_slots,
            " must be in [0, max_views = ", d.max_views, "] (0: one slot per view)");
    require(d.view_slots == 0 || gaussians * d.view_slots <= d.max_queries, "FlexSplat config: ", gaussians,
            " Gaussians of one view read ", gaussians * d.view_slots, " query embeddings with view_slots ",
            d.view_slots, ", max_queries is ", d.max_queries);
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
  nlohmann::json j = {{"img_size", a.dino.img_size},     {"patch_size", a.patch_size},
          {"embed_dim", a.embed_dim},        {"depth", a.depth},
          {"num_heads", a.num_heads},        {"mlp_ratio", a.mlp_ratio},
          {"num_register_tokens", a.num_register_tokens}, {"qk_norm", a.qk_norm},
          {"rope_freq", a.rope_freq},        {"init_values", a.init_values},
          {"aa_block_size", a.aa_block_size}, {"aa_order", a.aa_order},
          {"frame_tokens", a.frame_tokens},
          {"dino_depth", a.dino.depth},      {"dino_heads", a.dino.num_heads},
          {"dino_mlp_ratio", a.dino.mlp_ratio}, {"trunk_depth", c.camera.trunk_depth},
          {"cam_heads", c.camera.num_heads}, {"features", c.depth.features},
          {"out_channels", c.depth.out_channels}, {"intermediate_layer_idx", c.depth.intermediate_layer_idx}};
  if (c.point_head) j["point_head"] = true;  // absent in files made before the key existed
  if (c.match_dim > 0) j["match_dim"] = c.match_dim;
  if (c.match_image) j["match_image"] = true;
  if (c.match_image_convs > 0) {
    j["match_image_convs"] = c.match_image_convs;
    j["match_image_width"] = c.match_image_width;
  }
  if (c.depth.image_convs > 0) {
    j["depth_image_convs"] = c.depth.image_convs;
    j["depth_image_width"] = c.depth.image_width;
  }
  return j;
}

inline nlohmann::json to_json(const decoder::ModelConfig& c) {
  const auto& d = c.decoder;
  nlohmann::json j = {
      {"unet", {{"in_channels", c.unet.in_channels}, {"base", c.unet.base}, {"levels", c.unet.levels}}},
      {"fusion", {{"depth_channels", c.fusion.depth_channels}, {"unet_channels", c.fusion.unet_channels},
                  {"out_channels", c.fusion.out_channels}}},
      {"decoder", {{"dim", d.dim}, {"ffn", d.ffn}, {"heads", d.heads}, {"layers", d.layers}, {"points", d.points},
                   {"max_views", d.max_views}, {"value_dim", d.value_dim}, {"max_queries", d.max_queries},
                   {"local_attention", d.local_attention}, {"window", d.window}}}};
  if (d.view_slots > 0) j["decoder"]["view_slots"] = d.view_slots;  // absent in files made before the key existed
  return j;
}

inline nlohmann::json to_json(const FlexSplatConfig& c) {
  return {{"geometry", to_json(c.geometry)}, {"appearance", to_json(c.appearance)}, {"image_h", c.image_h},
          {"image_w", c.image_w}, {"gaussians", c.gaussians}};
}

namespace detail {
// Integer keys holding numbers are checked before nlohmann converts them (get<index_t> of 1e300 is undefined behaviour); sizes beyond
// 2^20 would overflow the parameter counts taken from them, as in geometry::check_vggt_config_numbers.
inline void check_config_integer(const nlohmann::json& o, const char* key) {
  constexpr std::int64_t max_size = std::int64_t(1) << 20;
  const nlohmann::json& v = o.at(key);
  if (!v.is_number()) return;  // nlohmann's type error names it
  const bool ok = v.is_number_unsigned() ? v.get<std::uint64_t>() <= std::uint64_t(max_size)
                  : v.is_number_integer() ? std::abs(v.get<std::int64_t>()) <= max_size
                                          : false;
  require(ok, "FlexSplat config: '", key, "' = ", v.dump(), " is not an integer in [-", max_size, ", ", max_size, "]");
}
}  // namespace detail

inline decoder::ModelConfig appearance_config_from_json(const nlohmann::json& j) {
  decoder::ModelConfig c;
  auto get = [](const nlohmann::json& o, const char* key, auto& v) {
    using V = std::remove_reference_t<decltype(v)>;
    if (!o.contains(key)) return;
    if constexpr (std::is_integral_v<V> && !std::is_same_v<V, bool>) detail::check_config_integer(o, key);
    v = o.at(key).get<V>();
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
    get(d, "view_slots", o.view_slots);
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
    for (auto [key, v] : {std::pair<const char*, index_t*>{"image_h", &c.image_h}, {"image_w", &c.image_w},
                          {"gaussians", &c.gaussians}})
      if (j.contains(key)) detail::check_config_integer(j, key), *v = j.at(key).get<index_t>();
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
