// reconstruct: a few uncalibrated photos -> FlexSplat's feed-forward prediction (cameras, depth, Gaussians) -> a
// .glb (KHR_gaussian_splatting, with the predicted cameras as camera nodes) or .ply, and optionally a turntable.
#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

#include "flexsplat/export/file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/eval/reconstruct.hpp"
#include "flexsplat/io/capture_cameras.hpp"
#include "registry.hpp"

namespace flexsplat::cli::reconstruct_cmd {

namespace fs = std::filesystem;

int reconstruct_command(Args args) {
  std::string model_path, output, gaussians_text, turntable, refine_text, refine_size_text, turntable_size_text;
  std::string refine_validate = "off", refine_grow_text, compact_text = "on", budget_text = "full";
  take_option(args, "--model", model_path);
  require(take_option(args, "-o", output) || take_option(args, "--output", output),
          "reconstruct needs -o out.glb or -o out.ply");
  take_option(args, "--gaussians", gaussians_text);
  take_option(args, "--turntable", turntable);
  take_option(args, "--refine", refine_text);
  bool refine_options = take_option(args, "--refine-size", refine_size_text);
  if (take_option(args, "--refine-validate", refine_validate)) refine_options = true;
  if (take_option(args, "--refine-grow", refine_grow_text)) refine_options = true;
  take_option(args, "--turntable-size", turntable_size_text);
  take_option(args, "--compact", compact_text);
  take_option(args, "--budget", budget_text);
  require(budget_text == "full" || budget_text == "auto", "--budget '", budget_text, "': expected full or auto");
  const bool compact = parse_on_off(compact_text, "--compact");
  std::string cameras_text = "model";
  take_option(args, "--cameras", cameras_text);
  const bool given_cameras = cameras_text != "model" && cameras_text != "orbit" && cameras_text != "turntable";
  const model::CameraSource camera_source =
      given_cameras ? model::CameraSource::given : model::parse_camera_source(cameras_text);
  const bool verbose = take_flag(args, "--verbose");
  for (const auto& a : args) require(a.empty() || a[0] != '-', "reconstruct: unknown option '", a, "'");
  require(!args.empty(), "reconstruct needs at least one IMAGE (PNG or JPEG)");
  const gaussians::FileFormat format = gaussians::format_of(output);
  index_t n_gaussians = 0;
  if (!gaussians_text.empty()) {
    n_gaussians = static_cast<index_t>(parse_integer(gaussians_text, "--gaussians", 1, std::numeric_limits<int>::max()));
  }
  double refine_seconds = 0;
  if (!refine_text.empty()) refine_seconds = parse_number(refine_text, "--refine", false);
  const index_t refine_longer = parse_longer_side(refine_size_text, "--refine-size");
  const index_t turntable_longer = parse_longer_side(turntable_size_text, "--turntable-size");
  const bool validate = parse_on_off(refine_validate, "--refine-validate");
  const index_t refine_grow = parse_gaussian_count(refine_grow_text, "--refine-grow", model::refine_grow_gaussians);
  require(!refine_options || refine_seconds > 0,
          "reconstruct: --refine-size, --refine-validate and --refine-grow need --refine SECONDS");
  model_path = model_or_default(model_path, given_cameras);
  require(fs::is_regular_file(model_path), "reconstruct: model file '", model_path, "' does not exist");

  auto t0 = std::chrono::steady_clock::now();
  std::vector<std::pair<std::string, double>> stage_ms;
  auto lap = [&](const char* stage) {
    const auto now = std::chrono::steady_clock::now();
    stage_ms.emplace_back(stage, std::chrono::duration<double, std::milli>(now - t0).count());
    t0 = now;
  };
  std::fprintf(stderr, "reconstruct: loading %s\n", model_path.c_str());
  const auto w = model::load_flexsplat<float>(model_path);
  const model::FlexSplatConfig& c = w->config();
  require(static_cast<index_t>(args.size()) <= c.appearance.decoder.max_views, "reconstruct: ", args.size(),
          " images; the model takes 1 to ", c.appearance.decoder.max_views);
  lap("load model");
  std::fprintf(stderr, "reconstruct: reading %zu image(s)\n", args.size());
  std::vector<Tensor<float, 3>> rgba;
  for (const auto& a : args) rgba.push_back(image::read_float<float>(a, 4));
  model::ReconstructOptions o;
  o.cameras = camera_source;
  if (given_cameras) {
    std::vector<std::array<int, 2>> sizes;
    for (const auto& im : rgba) sizes.push_back({static_cast<int>(im.shape(1)), static_cast<int>(im.shape(0))});
    io::CameraFormat from{};
    o.given = io::cameras_for_photos(cameras_text, args, sizes, &from);
    std::fprintf(stderr, "reconstruct: %zu camera(s) from the %s %s\n", o.given.size(), io::camera_format_name(from),
                 cameras_text.c_str());
  }
  lap("decode images");
  o.gaussians = n_gaussians;
  o.auto_budget = budget_text == "auto";
  o.refine_seconds = refine_seconds;
  o.refine_longer = refine_longer;
  o.refine_validate = validate;
  o.refine_grow = refine_grow;
  o.compact = compact;
  for (const std::string& a : args) o.names.push_back(fs::path(a).filename().string());
  o.log = [](const std::string& line) { std::fprintf(stderr, "reconstruct: %s\n", line.c_str()); };
  const model::Reconstruction r = model::reconstruct(*w, rgba, o);
  stage_ms.insert(stage_ms.end(), r.stage_ms.begin(), r.stage_ms.end());
  t0 = std::chrono::steady_clock::now();
  gltf::WriteOptions wo;
  if (format == gaussians::FileFormat::Glb) wo.cameras = r.cameras;
  std::fprintf(stderr, "reconstruct: writing %s\n", output.c_str());
  const auto report = gaussians::write_gaussians(r.prediction.gaussians, output, wo);
  lap("export");
  if (!turntable.empty()) {
    std::fprintf(stderr, "reconstruct: rendering turntable %s\n", turntable.c_str());
    const std::array<index_t, 2> size = model::refine_size(rgba, c, turntable_longer);
    image::write_png(turntable, model::turntable_strip(r.prediction, 8, size[0], size[1]));
    lap("turntable");
  }
  std::printf("%s: %lld Gaussians, %zu camera(s), %zu bytes, from %zu image(s)\n", output.c_str(),
              static_cast<long long>(r.prediction.gaussians.size()), wo.cameras.size(), report.bytes, args.size());
  if (verbose) {
    double total = 0;
    for (const auto& [name, ms] : stage_ms) {
      std::printf("  %-18s %9.1f ms\n", name.c_str(), ms);
      total += ms;
    }
    std::printf("  %-18s %9.1f ms\n", "total", total);
  }
  return 0;
}

const RegisterCommand registered_cmd_reconstruct(
    "reconstruct", {"a Gaussian splat (.glb with the predicted cameras, or .ply) from a few uncalibrated images",
                    "IMAGE... -o out.glb|out.ply [--model M.safetensors] [--gaussians N] [--refine SECONDS]\n"
                    "  [--refine-size N|native] [--refine-validate on|off] [--refine-grow N] [--turntable out.png]\n"
                    "  [--turntable-size N|native] [--cameras model|orbit|turntable|PATH] [--compact on|off]\n"
                    "  [--budget full|auto] [--verbose]\n"
                    "  IMAGE: 1 to the model's max_views PNG/JPEG files of any size; RGBA is composited on white and\n"
                    "  each picture's centred window of the model's aspect ratio is resized to the model's size\n"
                    "  --model: default the shipped model (models/flexsplat-small.safetensors in the source tree)\n"
                    "  --gaussians: default the model's budget for the view count; --budget auto: of it, only the\n"
                    "  queries whose anchors lie on the object's outline (the photos' alpha, else the non-white pixels)\n"
                    "  run, the others would place Gaussians on the background; --turntable: 8 views around the\n"
                    "  object in one picture, each at the pictures' resolution (--turntable-size N: N pixels on the longer\n"
                    "  side); --verbose: time of each stage; --cameras orbit: the cameras searched on an orbit around the\n"
                    "  object from the predicted silhouettes, depth and colours (models with a match head)\n"
                    "  --cameras turntable: photos in order around the object at equal azimuth steps (a turntable\n"
                    "  or a walk around it): the cameras made from the count, elevation, direction and distance searched\n"
                    "  --cameras PATH: the photos' own cameras, matched by file name, from a COLMAP model folder\n"
                    "  (cameras.txt + images.txt or the .bin pair; pinhole models), a nerfstudio / instant-ngp\n"
                    "  transforms.json or a cameras.json; the splat and its cameras are written in that capture's world\n"
                    "  and units, refinement keeps the cameras; default model models/flexsplat-posed.safetensors\n"
                    "  --refine S: carve away the Gaussians seen on the pictures' background (RGBA) and add 4096 in\n"
                    "  their silhouettes' visual hull (--refine-grow N: N), then optimise the Gaussians and the\n"
                    "  predicted cameras (all but the first) on the input pictures for about S seconds before writing,\n"
                    "  at their own resolution (--refine-size N: N pixels on the longer side; --refine-validate on:\n"
                    "  the step count chosen on the last picture held out of a trial fit)\n"
                    "  --compact off: keep every Gaussian (default: drop those outside the photos' silhouettes and\n"
                    "  those no photo shows, model::compact_splat)\n"
                    "  (docs/app.md)",
                    reconstruct_command});

}  // namespace flexsplat::cli::reconstruct_cmd
