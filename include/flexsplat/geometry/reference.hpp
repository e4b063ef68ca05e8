#pragma once
// Checker for reference bundles of kind `vggt`: builds the model from the bundle's `config` metadata and `param.*`
// tensors, runs every case<k>.images and compares DINO tokens, every aggregator output, the pose encoding of every
// refinement iteration, cameras, depth, confidence and world points, each within 1e-4 of the tensor's max abs value.
#include <string>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

inline constexpr double vggt_reference_tolerance = 1e-4;

inline void check_vggt_reference(const safetensors::File& file, ReferenceReport& report) {
  require(file.has_metadata("config"), "vggt bundle '", file.path(), "' has no config metadata");
  const VggtConfig cfg = vggt_config_from_json(file.metadata("config"));
  ParamSource<float> src(file, "param.");
  const VggtWeights<float> weights = load_vggt_weights(src, cfg);
  VggtWorkspace<float> ws;
  VggtOptions options;
  options.keep_dino_tokens = true;
  options.keep_all_layers = true;
  const Tolerance tol{ToleranceKind::relative_to_max_abs, vggt_reference_tolerance};
  int cases = 0;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".images"); ++k, ++cases) {
    const std::string p = "case" + std::to_string(k) + ".";
    const auto images = file.get<float, 5>(p + "images");
    require(images.shape(0) == 1 && images.shape(2) == 3, "vggt bundle: ", p, "images has shape ",
            shape_string(images.shape()), ", expected [1, S, 3, H, W]");
    const index_t S = images.shape(1), H = images.shape(3), W = images.shape(4);
    const auto out = vggt_forward<float>(images.data(), S, H, W, cfg, weights, ws, options);
    auto compare = [&](const std::string& name, std::span<const float> actual) {
      if (!file.contains(p + name)) return;
      const auto& info = file.info(p + name);
      std::vector<float> expected(static_cast<std::size_t>(info.numel()));
      file.convert(info, expected.data());
      report.compare<float, float>(p + name, actual, std::span<const float>(expected), tol);
    };
    compare("dino.x_norm_patchtokens", out.dino_tokens.span());
    for (auto& [index, tensor] : out.aggregator.layers) compare("aggregator.out." + std::to_string(index), tensor.span());
    for (index_t it = 0; it < cfg.camera.iterations; ++it)
      compare("camera_head.pose_enc." + std::to_string(it),
              std::span<const float>(out.pose_enc.data() + it * S * pose_encoding_dim, S * pose_encoding_dim));
    compare("extrinsics", out.extrinsics.span());
    compare("intrinsics", out.intrinsics.span());
    compare("depth", out.depth.span());
    compare("depth_conf", out.depth_conf.span());
    compare("world_points", out.world_points.span());
  }
  require(cases > 0, "vggt bundle '", file.path(), "' holds no case0.images");
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
