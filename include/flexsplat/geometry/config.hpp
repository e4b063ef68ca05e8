#pragma once
// Hyper-parameters of the VGGT geometry trunk (DINOv2 patch embedder + alternating frame/global aggregator).
// Defaults are VGGT-1B; a reference bundle's `config` metadata JSON can be read into it.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/geometry/block.hpp"
#include "flexsplat/geometry/camera_head.hpp"
#include "flexsplat/geometry/dpt_head.hpp"
#include "flexsplat/geometry/pose_encoding.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

// DINOv2 ViT with register tokens as VGGT builds it (dinov2_vitl14_reg by default).
struct DinoConfig {
  index_t img_size = 518;           // pos_embed covers (img_size / patch_size)^2 patches
  index_t patch_size = 14;
  index_t embed_dim = 1024;
  index_t depth = 24;
  index_t num_heads = 16;
  double mlp_ratio = 4.0;
  index_t num_register_tokens = 4;
  double init_values = 1.0;         // LayerScale present when > 0
  double norm_eps = 1e-6;           // every LayerNorm of the DINOv2 model
  bool interpolate_antialias = true;
  double interpolate_offset = 0.0;  // 0: resize the position grid to an exact size

  index_t pos_grid() const { return img_size / patch_size; }
  BlockConfig block() const {
    return {.dim = embed_dim, .num_heads = num_heads, .mlp_ratio = mlp_ratio,
            .qk_norm = false, .layer_scale = init_values > 0, .norm_eps = norm_eps};
  }
  void validate() const {
    require(patch_size > 0 && img_size >= patch_size, "DINO config: img_size ", img_size, " and patch_size ",
            patch_size, " must be positive with img_size >= patch_size");
    require(depth >= 0 && num_register_tokens >= 0, "DINO config: depth ", depth, " and num_register_tokens ",
            num_register_tokens, " must be non-negative");
    block().validate("DINO config");
  }
};

// The alternating-attention trunk.
struct AggregatorConfig {
  index_t patch_size = 14;
  index_t embed_dim = 1024;
  index_t depth = 24;               // block pairs: aggregator outputs depth tensors of 2*embed_dim channels
  index_t num_heads = 16;
  double mlp_ratio = 4.0;
  index_t num_register_tokens = 4;
  bool qk_norm = true;
  double rope_freq = 100.0;         // <= 0 disables RoPE
  double init_values = 0.01;        // LayerScale present when > 0
  double norm_eps = 1e-5;
  index_t aa_block_size = 1;        // consecutive blocks of one kind before switching
  // Distinct camera/register token sets: frame s takes set min(s, frame_tokens - 1). VGGT's 2 (first frame, the
  // rest) keeps the model order-free apart from the reference frame; more makes it depend on the input order; 1 is
  // Pi3's reference-free design (every frame alike; the cameras are then re-expressed in the first view's frame).
  index_t frame_tokens = 2;
  std::vector<std::string> aa_order{"frame", "global"};
  DinoConfig dino;

  index_t patch_start_idx() const { return 1 + num_register_tokens; }
  index_t frame_token(index_t frame) const { return std::min(frame, frame_tokens - 1); }
  BlockConfig block() const {
    return {.dim = embed_dim, .num_heads = num_heads, .mlp_ratio = mlp_ratio,
            .qk_norm = qk_norm, .layer_scale = init_values > 0, .norm_eps = norm_eps};
  }
  void validate() const {
    block().validate("aggregator config");
    dino.validate();
    require(dino.embed_dim == embed_dim, "aggregator config: DINO embed_dim ", dino.embed_dim,
            " differs from the aggregator's ", embed_dim);
    require(dino.patch_size == patch_size, "aggregator config: DINO patch_size ", dino.patch_size,
            " differs from the aggregator's ", patch_size);
    require(depth >= 1 && aa_block_size >= 1 && depth % aa_block_size == 0, "aggregator config: depth ", depth,
            " must be a positive multiple of aa_block_size ", aa_block_size);
    require(rope_freq <= 0 || block().head_dim() % 4 == 0, "aggregator config: 2-D RoPE needs head_dim divisible by 4, got ",
            block().head_dim());
    require(frame_tokens >= 1 && frame_tokens <= 64, "aggregator config: frame_tokens ", frame_tokens,
            " must be in [1, 64]");
    require(!aa_order.empty(), "aggregator config: aa_order is empty");
    bool frame = false, global = false;
    for (auto& kind : aa_order) {
      require(kind == "frame" || kind == "global", "aggregator config: unknown aa_order entry '", kind, "'");
      frame = frame || kind == "frame";
      global = global || kind == "global";
    }
    require(frame && global && aa_order.size() == 2, "aggregator config: aa_order must hold 'frame' and 'global' once each");
  }
};

// Every number a VGGT config JSON may hold, checked before any is converted: nlohmann's get<index_t> of 1e300 is
// undefined behaviour, and sizes beyond 2^20 (or ratios beyond 2^10) would overflow the products taken from them.
inline void check_vggt_config_numbers(const nlohmann::json& j) {
  if (!j.is_object()) return;
  constexpr std::int64_t max_size = std::int64_t(1) << 20;
  auto check_integer = [&](const std::string& key, const nlohmann::json& v) {
    const bool ok = v.is_number_unsigned() ? v.get<std::uint64_t>() <= std::uint64_t(max_size)
                    : v.is_number_integer() ? std::abs(v.get<std::int64_t>()) <= max_size
                                            : false;
    require(ok, "VGGT config: '", key, "' = ", v.dump(), " is not an integer in [-", max_size, ", ", max_size, "]");
  };
  for (const char* key : {"img_size", "patch_size", "embed_dim", "depth", "num_heads", "num_register_tokens",
                          "aa_block_size", "frame_tokens", "dino_depth", "dino_heads", "trunk_depth", "cam_heads", "features"})
    if (j.contains(key)) check_integer(key, j.at(key));
  for (const char* key : {"out_channels", "intermediate_layer_idx"})
    if (j.contains(key) && j.at(key).is_array())
      for (const auto& v : j.at(key)) check_integer(key, v);
  for (const char* key : {"mlp_ratio", "dino_mlp_ratio", "rope_freq", "init_values"})
    if (j.contains(key)) {
      const auto& v = j.at(key);
      require(v.is_number() && std::abs(v.get<double>()) <= 1024.0, "VGGT config: '", key, "' = ", v.dump(),
              " is not a number in [-1024, 1024]");
    }
}

// Reads the trunk part of a bundle's config JSON (keys as in the reference README: img_size, patch_size, embed_dim,
// depth, num_heads, dino_depth, dino_heads; optional mlp_ratio, num_register_tokens, qk_norm, rope_freq,
// init_values, aa_block_size, aa_order). Absent keys keep VGGT-1B's values.
inline AggregatorConfig aggregator_config_from_json(const nlohmann::json& j) {
  AggregatorConfig c;
  check_vggt_config_numbers(j);
  try {
    require(j.is_object(), "config is not a JSON object");
    auto get_int = [&](const char* key, index_t& v) {
      if (j.contains(key)) v = j.at(key).get<index_t>();
    };
    auto get_double = [&](const char* key, double& v) {
      if (j.contains(key)) v = j.at(key).get<double>();
    };
    get_int("img_size", c.dino.img_size);
    get_int("patch_size", c.patch_size);
    get_int("embed_dim", c.embed_dim);
    get_int("depth", c.depth);
    get_int("num_heads", c.num_heads);
    get_double("mlp_ratio", c.mlp_ratio);
    get_int("num_register_tokens", c.num_register_tokens);
    if (j.contains("qk_norm")) c.qk_norm = j.at("qk_norm").get<bool>();
    get_double("rope_freq", c.rope_freq);
    get_double("init_values", c.init_values);
    get_int("aa_block_size", c.aa_block_size);
    get_int("frame_tokens", c.frame_tokens);
    if (j.contains("aa_order")) c.aa_order = j.at("aa_order").get<std::vector<std::string>>();
    c.dino.patch_size = c.patch_size;
    c.dino.embed_dim = c.embed_dim;
    c.dino.num_register_tokens = c.num_register_tokens;
    get_int("dino_depth", c.dino.depth);
    get_int("dino_heads", c.dino.num_heads);
    get_double("dino_mlp_ratio", c.dino.mlp_ratio);
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config JSON: ", e.what());
  }
  c.validate();
  return c;
}

inline AggregatorConfig aggregator_config_from_json(const std::string& text) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config is not valid JSON: ", e.what());
  }
  return aggregator_config_from_json(j);
}

// The whole VGGT as FlexSplat uses it: trunk, camera head, depth head and, when point_head is set, the point head
// (the track head is never computed). Defaults are VGGT-1B.
struct VggtConfig {
  AggregatorConfig aggregator;
  CameraHeadConfig camera;
  DptHeadConfig depth;
  PoseDecodeOptions pose_decode;  // what decoding does with FoV <= 0 or >= pi
  // VGGT's point head: per-pixel 3-D points in the first frame's camera frame with a confidence; its dense targets are
  // what makes the cameras learnable from scratch, and cameras can be solved from its output (solvers/procrustes.hpp).
  bool point_head = false;
  // > 0: the match head, FlexSplat's own (not in VGGT's checkpoint): per pixel a descriptor of match_dim channels that
  // finds the same surface point in another view, and the probability that the pixel shows the object. Cameras follow
  // from matched pixels' depths in closed form (solvers/procrustes.hpp), so pose is learnt as local matching.
  index_t match_dim = 0;
  // The match head also sees the image's pixels at full resolution (DptHeadConfig::image_channels 3).
  bool match_image = false;
  // > 0: the pixels pass that many 3x3 convolutions of match_image_width channels first (DptHeadConfig::image_convs).
  index_t match_image_convs = 0;
  index_t match_image_width = 16;
  // convs > 0: the depth head also reads the pixels through that many 3x3 convolutions of `width` channels
  // (DptHeadConfig::image_convs): a small model's 8 x 8 tokens leave the depth's shape within a patch to the pixels.
  // 0 is VGGT's head.
  void set_depth_image(index_t convs, index_t width) {
    depth.image_channels = convs > 0 ? 3 : 0;
    depth.image_convs = convs;
    depth.image_width = width;
  }

  // The point head is the depth head's architecture with 3 + 1 outputs and VGGT's inv_log activation.
  DptHeadConfig point() const {
    DptHeadConfig p = depth;
    p.image_channels = 0, p.image_convs = 0;  // VGGT's point head: no image path
    p.output_dim = 4;
    p.activation = DptActivation::inv_log;
    p.conf_activation = DptConfActivation::expp1;
    return p;
  }
  // The match head: the same architecture, match_dim linear channels and a sigmoid "confidence" (the object mask).
  DptHeadConfig match() const {
    DptHeadConfig p = depth;
    p.output_dim = match_dim + 1;
    p.activation = DptActivation::linear;
    p.conf_activation = DptConfActivation::sigmoid;
    p.image_channels = match_image ? 3 : 0;
    p.image_convs = match_image_convs;
    p.image_width = match_image_width;
    return p;
  }

  void validate() const {
    aggregator.validate();
    camera.validate();
    depth.validate();
    require(camera.dim == 2 * aggregator.embed_dim, "VGGT config: camera head dim ", camera.dim, " must be 2 x embed_dim ",
            aggregator.embed_dim);
    require(depth.dim_in == 2 * aggregator.embed_dim, "VGGT config: depth head dim_in ", depth.dim_in,
            " must be 2 x embed_dim ", aggregator.embed_dim);
    require(depth.patch_size == aggregator.patch_size, "VGGT config: depth head patch_size ", depth.patch_size,
            " differs from the aggregator's ", aggregator.patch_size);
    require(depth.output_dim == 2, "VGGT config: the depth head predicts depth + confidence (output_dim 2), got ",
            depth.output_dim);
    require(!point_head || aggregator.frame_tokens >= 2, "VGGT config: the point head predicts points in the first "
            "frame's camera frame, which frame_tokens 1 (every frame alike) cannot tell apart");
    require(match_dim >= 0 && match_dim <= 256, "VGGT config: match_dim ", match_dim, " must be in [0, 256]");
    require(!match_image || match_dim > 0, "VGGT config: match_image needs the match head (match_dim > 0)");
    require(match_image_convs == 0 || match_image, "VGGT config: match_image_convs ", match_image_convs,
            " needs match_image");
    require(depth.image_channels == (depth.image_convs > 0 ? 3 : 0),
            "VGGT config: the depth head reads the pixels only through its convolutions (", depth.image_channels,
            " channels, ", depth.image_convs, " convs; set both with set_depth_image)");
    if (match_dim > 0) match().validate();
    for (index_t i : depth.intermediate_layer_idx)
      require(i < aggregator.depth, "VGGT config: depth head reads aggregator output ", i, ", depth is ",
              aggregator.depth);
  }
};

inline VggtConfig vggt_config_from_json(const std::string& text) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    fail("VGGT config is not valid JSON: ", e.what());
  }
  VggtConfig c;
  c.aggregator = aggregator_config_from_json(j);
  c.camera = camera_head_config_from_vggt_json(j);
  c.depth = dpt_head_config_from_vggt_json(j);
  if (j.contains("point_head")) {
    require(j.at("point_head").is_boolean(), "VGGT config: 'point_head' = ", j.at("point_head").dump(),
            " is not true or false");
    c.point_head = j.at("point_head").get<bool>();
  }
  if (j.contains("match_dim")) {
    const auto& v = j.at("match_dim");
    require(v.is_number_integer() && v.get<std::int64_t>() >= 0 && v.get<std::int64_t>() <= 256,
            "VGGT config: 'match_dim' = ", v.dump(), " is not an integer in [0, 256]");
    c.match_dim = v.get<index_t>();
  }
  if (j.contains("match_image")) {
    require(j.at("match_image").is_boolean(), "VGGT config: 'match_image' = ", j.at("match_image").dump(),
            " is not true or false");
    c.match_image = j.at("match_image").get<bool>();
  }
  auto get_count = [&](const char* key, index_t lo, index_t hi, index_t& dst) {
    if (!j.contains(key)) return;
    const auto& v = j.at(key);
    require(v.is_number_integer() && v.get<std::int64_t>() >= lo && v.get<std::int64_t>() <= hi, "VGGT config: '",
            key, "' = ", v.dump(), " is not an integer in [", lo, ", ", hi, "]");
    dst = v.get<index_t>();
  };
  get_count("match_image_convs", 0, 4, c.match_image_convs);
  get_count("match_image_width", 1, 256, c.match_image_width);
  index_t depth_convs = 0, depth_width = 16;
  get_count("depth_image_convs", 0, 4, depth_convs);
  get_count("depth_image_width", 1, 256, depth_width);
  c.set_depth_image(depth_convs, depth_width);
  c.validate();
  return c;
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
