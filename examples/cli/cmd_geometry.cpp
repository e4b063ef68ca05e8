// geometry: VGGT cameras and depth for a set of images with a real checkpoint (VGGT-1B model.safetensors).
#include <chrono>
#include <cstdio>

#include "flexsplat/geometry/preprocess.hpp"
#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/geometry/weights.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

int run_geometry(const Args& input) {
  Args args = input;
  std::string weights_path, out_path, mode_name = "crop", config_json, prefix;
  const bool have_weights = take_option(args, "--weights", weights_path);
  const bool have_out = take_option(args, "--out", out_path);
  take_option(args, "--mode", mode_name);
  take_option(args, "--config", config_json);  // JSON with the reference-bundle keys; VGGT-1B when absent
  take_option(args, "--prefix", prefix);       // e.g. "param." for a reference bundle
  std::string fov_policy = "error";
  take_option(args, "--fov-policy", fov_policy);
  require(fov_policy == "error" || fov_policy == "clamp", "geometry: --fov-policy must be 'error' or 'clamp', got '",
          fov_policy, "'");
  require(have_weights, "geometry: --weights model.safetensors is required");
  require(have_out, "geometry: --out pred.safetensors is required");
  require(!args.empty(), "geometry: no input images given");
  for (const auto& a : args) require(a.rfind("--", 0) != 0, "geometry: unknown option '", a, "'");
  const auto mode = parse_vggt_preprocess_mode(mode_name);
  geometry::VggtConfig cfg = config_json.empty() ? geometry::VggtConfig{} : geometry::vggt_config_from_json(config_json);
  cfg.pose_decode.policy =
      fov_policy == "clamp" ? geometry::DegeneratePosePolicy::clamp : geometry::DegeneratePosePolicy::error;

  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(Clock::now() - start).count(); };
  std::fprintf(stderr, "[geometry %7.1fs] loading %zu images (%s mode)\n", elapsed(), args.size(), mode_name.c_str());
  const Tensor<float, 4> images = vggt_load_and_preprocess_images(args, mode);
  const index_t S = images.shape(0), H = images.shape(2), W = images.shape(3);
  std::fprintf(stderr, "[geometry %7.1fs] images preprocessed to %lld x 3 x %lld x %lld\n", elapsed(), (long long)S,
               (long long)H, (long long)W);
  std::fprintf(stderr, "[geometry %7.1fs] mapping weights %s\n", elapsed(), weights_path.c_str());
  const auto checkpoint = geometry::VggtCheckpoint<float>::open(weights_path, cfg, prefix);
  std::fprintf(stderr, "[geometry %7.1fs] weights ready (%.2f GB converted from F16/BF16)\n", elapsed(),
               checkpoint->source.converted_bytes() / 1e9);

  geometry::VggtWorkspace<float> ws;
  geometry::VggtOptions options;
  options.progress = [&](const std::string& stage, index_t step, index_t steps) {
    std::fprintf(stderr, "[geometry %7.1fs] %s %lld/%lld\n", elapsed(), stage.c_str(), (long long)step, (long long)steps);
  };
  const auto out = geometry::vggt_forward<float>(images.data(), S, H, W, cfg, checkpoint->weights, ws, options);

  safetensors::Writer writer;
  writer.set_metadata("kind", "vggt_prediction");
  writer.set_metadata("conventions",
                      "extrinsics: world-to-camera [R|t], OpenCV axes; intrinsics: pixels, principal point at the "
                      "image centre; pose_enc: absT_quaR_FoV (quaternion xyzw) per refinement iteration");
  writer.set_metadata("mode", mode_name);
  writer.add("images", images);
  writer.add("extrinsics", out.extrinsics);
  writer.add("intrinsics", out.intrinsics);
  writer.add("depth", out.depth);
  writer.add("depth_conf", out.depth_conf);
  writer.add("pose_enc", out.pose_enc);
  writer.add("world_points", out.world_points);
  writer.write(out_path);
  std::fprintf(stderr, "[geometry %7.1fs] wrote %s\n", elapsed(), out_path.c_str());
  return 0;
}

const RegisterCommand registered_cmd_geometry(
    "geometry",
    {"VGGT cameras (K, world-to-camera), depth and confidence for images",
     "--weights model.safetensors [--mode crop|pad] [--fov-policy error|clamp] [--config JSON] [--prefix P] IMAGES... "
     "--out pred.safetensors",
     run_geometry});

}  // namespace
}  // namespace flexsplat::cli
