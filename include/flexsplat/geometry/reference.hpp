#pragma once
// Checker for reference bundles of kind `vggt`: builds the model from the bundle's `config` metadata and `param.*`
// tensors, runs every case<k>.images and compares DINO tokens, every aggregator output, the pose encoding of every
// refinement iteration, cameras and confidence within 1e-4 of the tensor's max abs value, depth element-wise within
// 1e-4 relative, and world points within 1e-4 of the reference depth of their pixel (per coordinate). A bundle tensor
// the checker does not know fails the check.
#include <cmath>
#include <string>
#include <vector>

#include "flexsplat/core/reference_check.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "flexsplat/io/safetensors.hpp"

namespace flexsplat {
inline namespace v0 {
namespace geometry {

inline constexpr double vggt_reference_tolerance = 1e-4;

// T = float is the check; T = double runs the same code in float64 (to separate float32 rounding from errors).
template <class T>
void check_vggt_reference_as(const safetensors::File& file, ReferenceReport& report) {
  require(file.has_metadata("config"), "vggt bundle '", file.path(), "' has no config metadata");
  const VggtConfig cfg = vggt_config_from_json(file.metadata("config"));
  io::ParamSource<T> src(file, "param.");
  const VggtWeights<T> weights = load_vggt_weights(src, cfg);
  VggtWorkspace<T> ws;
  VggtOptions options;
  options.keep_dino_tokens = true;
  options.keep_all_layers = true;
  const double tol = vggt_reference_tolerance;
  int cases = 0;
  for (int k = 0; file.contains("case" + std::to_string(k) + ".images"); ++k, ++cases) {
    const std::string p = "case" + std::to_string(k) + ".";
    const auto images = file.get<T, 5>(p + "images");
    require(images.shape(0) == 1 && images.shape(2) == 3, "vggt bundle: ", p, "images has shape ",
            shape_string(images.shape()), ", expected [1, S, 3, H, W]");
    const index_t S = images.shape(1), H = images.shape(3), W = images.shape(4);
    const auto out = vggt_forward<T>(images.data(), S, H, W, cfg, weights, ws, options);
    auto expected_of = [&](const std::string& name) {
      const auto& info = file.info(p + name);
      std::vector<double> expected(static_cast<std::size_t>(info.numel()));
      file.convert(info, expected.data());
      return expected;
    };
    auto compare = [&](const std::string& name, std::span<const T> actual) {
      if (!file.contains(p + name)) return;
      const auto expected = expected_of(name);
      report.compare<T, double>(p + name, actual, std::span<const double>(expected),
                                {ToleranceKind::relative_to_max_abs, tol});
    };
    compare("dino.x_norm_patchtokens", out.dino_tokens.span());
    for (auto& [index, tensor] : out.aggregator.layers) compare("aggregator.out." + std::to_string(index), tensor.span());
    for (index_t it = 0; it < cfg.camera.iterations; ++it)
      compare("camera_head.pose_enc." + std::to_string(it),
              std::span<const T>(out.pose_enc.data() + it * S * pose_encoding_dim, S * pose_encoding_dim));
    compare("extrinsics", out.extrinsics.span());
    compare("intrinsics", out.intrinsics.span());
    compare("depth_conf", out.depth_conf.span());
    // Depth relative per pixel; world points per coordinate relative to the reference depth of their pixel.
    std::vector<double> depth_scale;
    if (file.contains(p + "depth")) {
      const auto expected = expected_of("depth");
      depth_scale.resize(expected.size());
      for (std::size_t i = 0; i < expected.size(); ++i) depth_scale[i] = std::abs(expected[i]);
      report.compare_scaled<T, double>(p + "depth", out.depth.span(), std::span<const double>(expected), depth_scale, tol);
    }
    if (file.contains(p + "world_points")) {
      const auto expected = expected_of("world_points");
      require(!depth_scale.empty(), "vggt bundle: ", p, "world_points needs ", p, "depth (its per-pixel scale)");
      std::vector<double> scale(expected.size());
      for (std::size_t i = 0; i < scale.size(); ++i) scale[i] = depth_scale[std::min(i / 3, depth_scale.size() - 1)];
      if (depth_scale.size() * 3 != expected.size()) scale.clear();  // a size mismatch fails the row
      report.compare_scaled<T, double>(p + "world_points", out.world_points.span(), std::span<const double>(expected),
                                       scale, tol);
    }
  }
  require(cases > 0, "vggt bundle '", file.path(), "' holds no case0.images");
  std::vector<std::string> names;
  for (const auto& t : file.tensors()) names.push_back(t.name);
  report.fail_unknown(names, [&](const std::string& name) {
    if (name.rfind("param.", 0) == 0) return true;
    for (int k = 0; k < cases; ++k)
      if (name == "case" + std::to_string(k) + ".images") return true;
    return false;
  }, "vggt");
}

inline void check_vggt_reference(const safetensors::File& file, ReferenceReport& report) {
  check_vggt_reference_as<float>(file, report);
}

}  // namespace geometry
}  // namespace v0
}  // namespace flexsplat
