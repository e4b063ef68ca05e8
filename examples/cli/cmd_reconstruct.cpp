// reconstruct: a few uncalibrated photos -> FlexSplat's feed-forward prediction (cameras, depth, Gaussians) -> a
// .glb (KHR_gaussian_splatting, with the predicted cameras as camera nodes) or .ply, and optionally a turntable.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <glm/glm.hpp>
#include <glm/gtc/matrix_transform.hpp>

#include "flexsplat/export/file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/io/capture_cameras.hpp"
#include "flexsplat/eval/compact.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/eval/refine.hpp"
#include "flexsplat/raster/render.hpp"
#include "registry.hpp"

namespace flexsplat::cli::reconstruct_cmd {

namespace fs = std::filesystem;

// Wall-clock stages, printed with --verbose.
struct Stages {
  std::vector<std::pair<std::string, double>> ms;
  std::chrono::steady_clock::time_point last = std::chrono::steady_clock::now();
  void lap(const std::string& name) {
    const auto now = std::chrono::steady_clock::now();
    ms.emplace_back(name, std::chrono::duration<double, std::milli>(now - last).count());
    last = now;
  }
};

// `frames` views orbiting the Gaussians' opacity-weighted centre about the first camera's up axis, at the first
// camera's distance, side by side in one picture (each h x w, the first camera's predicted K scaled to that size).
// Row-major K [V, 3, 3] of cameras, at their own image size.
std::vector<double> photo_intrinsics(const std::vector<Camera>& cameras) {
  std::vector<double> K(9 * cameras.size());
  for (std::size_t v = 0; v < cameras.size(); ++v) camera_arrays(cameras[v], K.data() + 9 * v, static_cast<double*>(nullptr));
  return K;
}

void write_turntable(const fs::path& path, const model::Prediction<float>& p, int frames, index_t h, index_t w) {
  const auto& s = p.gaussians;
  glm::dvec3 centre(0.0);
  double weight = 0;
  for (index_t i = 0; i < s.size(); ++i) {
    const double o = s.opacities(i);
    centre += o * glm::dvec3(s.means(i, 0), s.means(i, 1), s.means(i, 2));
    weight += o;
  }
  require(weight > 0, "turntable: every Gaussian is transparent");
  centre /= weight;
  Camera first = model::input_cameras(p)[0];
  const glm::dvec3 eye0 = first.centre();
  const glm::dvec3 up = -glm::transpose(first.R)[1];  // rows of R are the camera's axes; OpenCV y points down
  const double sx = static_cast<double>(w) / static_cast<double>(p.w), sy = static_cast<double>(h) / static_cast<double>(p.h);
  first.K[0][0] *= sx, first.K[1][0] *= sx, first.K[2][0] *= sx;  // column-major: fx, skew, cx
  first.K[1][1] *= sy, first.K[2][1] *= sy;
  const index_t gap = 2;
  Tensor<float, 3> strip(Shape<3>{h, frames * w + (frames - 1) * gap, 3}, 1.0f);
  raster::RenderOptions ro;
  ro.background = {1, 1, 1};
  raster::RenderWorkspace<float> ws;
  raster::RenderOutputs<float> out;
  for (int f = 0; f < frames; ++f) {
    const double angle = 2.0 * 3.14159265358979323846 * f / frames;
    const glm::dmat4 turn = glm::rotate(glm::dmat4(1.0), angle, glm::normalize(up));
    const glm::dvec3 eye = centre + glm::dvec3(turn * glm::dvec4(eye0 - centre, 0.0));
    raster::render_forward(
        s, raster::camera_view<float>(look_at(eye, centre, static_cast<int>(w), static_cast<int>(h), first.K, up)), ro,
        ws, out);
    for (index_t y = 0; y < h; ++y)
      for (index_t x = 0; x < w; ++x)
        for (int c = 0; c < 3; ++c) strip(y, f * (w + gap) + x, c) = std::clamp(out.image(y, x, c), 0.0f, 1.0f);
  }
  image::write_png(path, strip);
}

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

  Stages t;
  std::fprintf(stderr, "reconstruct: loading %s\n", model_path.c_str());
  const auto w = model::load_flexsplat<float>(model_path);
  const model::FlexSplatConfig& c = w->config();
  require(static_cast<index_t>(args.size()) <= c.appearance.decoder.max_views, "reconstruct: ", args.size(),
          " images; the model takes 1 to ", c.appearance.decoder.max_views);
  t.lap("load model");
  std::fprintf(stderr, "reconstruct: reading %zu image(s)\n", args.size());
  std::vector<Tensor<float, 3>> rgba;
  for (const auto& a : args) rgba.push_back(image::read_float<float>(a, 4));
  std::vector<Camera> cameras;  // with given cameras: the capture's camera of each photo, at the photo's size
  if (given_cameras) {
    std::vector<std::array<int, 2>> sizes;
    for (const auto& im : rgba) sizes.push_back({static_cast<int>(im.shape(1)), static_cast<int>(im.shape(0))});
    const io::ImageSizeOf size_of = [&](const std::string& file) -> std::optional<std::array<int, 2>> {
      for (std::size_t i = 0; i < args.size(); ++i)
        if (fs::path(args[i]).filename() == fs::path(file).filename() ||
            fs::path(args[i]).stem() == fs::path(file).filename())
          return sizes[i];
      return std::nullopt;
    };
    io::CameraFormat format{};
    cameras = io::cameras_for_images(io::load_capture_cameras(cameras_text, size_of, &format), args, sizes, cameras_text);
    std::fprintf(stderr, "reconstruct: %zu camera(s) from the %s %s\n", cameras.size(), io::camera_format_name(format),
                 cameras_text.c_str());
  }
  t.lap("decode images");
  std::fprintf(stderr, "reconstruct: predicting at %lld x %lld\n", static_cast<long long>(c.image_w),
               static_cast<long long>(c.image_h));
  model::PredictWorkspace<float> ws;
  ws.cameras = camera_source;
  ws.auto_budget = budget_text == "auto";
  model::Prediction<float> p;
  if (given_cameras) {
    p = model::predict_posed<float>(ws, *w, rgba, cameras, n_gaussians);
  } else {
    model::ModelPhotos<float> photos = model::model_photos<float>(rgba, c);
    ws.silhouettes = std::move(photos.silhouettes);
    t.lap("preprocess");
    p = model::predict<float>(ws, *w, TensorView<const float, 4>(photos.images.view()), n_gaussians);
  }
  if (ws.auto_budget)
    std::fprintf(stderr, "reconstruct: --budget auto: the decoder ran %lld of the budget's %lld queries (those on the "
                 "object's outline)\n", static_cast<long long>(p.budget_queries), static_cast<long long>(p.budget));
  t.ms.emplace_back("geometry (VGGT)", p.geometry_ms);
  t.ms.emplace_back("cameras", p.cameras_ms);
  t.ms.emplace_back("decoder", p.decoder_ms);
  if (camera_source == model::CameraSource::turntable)
    std::fprintf(stderr, "reconstruct: turntable at elevation %.1f deg, turning %s\n", ws.turntable.elevation_deg,
                 ws.turntable.direction > 0 ? "counter-clockwise seen from above" : "clockwise seen from above");
  if (p.given)
    std::fprintf(stderr, "reconstruct: the capture's scale %.6g world units per model unit (%s)\n", p.given->frame.scale,
                 p.given->from_views ? "the views' consistency" : "one view: the object at the world origin's distance");
  t.last = std::chrono::steady_clock::now();
  // The photos as targets at h x w in the prediction's cameras, made once for refinement and compaction alike (K is
  // neither refined nor moved to the capture's world).
  std::optional<model::PhotoTargets<float>> targets;
  auto targets_at = [&](std::array<index_t, 2> size) -> const model::PhotoTargets<float>& {
    if (!targets || targets->h != size[0] || targets->w != size[1])
      targets = given_cameras ? model::photo_targets<float>(rgba, photo_intrinsics(cameras), size[0], size[1])
                              : model::photo_targets<float>(rgba, c, p.geometry.K.data(), size[0], size[1]);
    return *targets;
  };
  if (refine_seconds > 0) {
    // Test-time refinement of the Gaussians and the predicted cameras on the input pictures (camera 0 stays fixed).
    const std::array<index_t, 2> size = model::refine_size(rgba, c, refine_longer);
    std::fprintf(stderr, "reconstruct: refining for %g s on the input views at %lld x %lld\n", refine_seconds,
                 static_cast<long long>(size[1]), static_cast<long long>(size[0]));
    const model::PhotoTargets<float>& photos = targets_at(size);
    const model::RefineViews<float> rv{p.views,         photos.h, photos.w, photos.images.data(),
                                       photos.K.data(), p.geometry.extrinsics.data(), photos.alpha.data()};
    model::RefineConfig rc = model::prediction_refine_config(rv, refine_seconds, 0, refine_grow);
    rc.validate = validate;
    rc.optimize_cameras = !given_cameras;  // given cameras are the capture's: kept as they are
    model::RefineWorkspace<float> rws;
    const model::RefineResult rr = model::refine(p.gaussians, rv, rc, rws);
    if (rr.chosen_steps >= 0)
      std::fprintf(stderr, "reconstruct: held-out trial of %lld steps on all views but the last: its loss %.5f -> "
                   "%.5f at step %lld\n", static_cast<long long>(rr.trial_steps), rr.holdout_initial,
                   rr.holdout_best, static_cast<long long>(rr.chosen_steps));
    std::fprintf(stderr, "reconstruct: %lld refinement steps, loss on the inputs %.5f -> %.5f, %lld Gaussians carved "
                 "away (seen on a photo's background), %lld grown in the silhouettes, %lld pruned\n",
                 static_cast<long long>(rr.steps), rr.loss_initial, rr.loss_final, static_cast<long long>(rr.carved),
                 static_cast<long long>(rr.grown), static_cast<long long>(rr.pruned));
    t.lap("refine");
  }

  if (p.given) model::to_capture_world(p);  // the splat in the capture's world and units
  if (compact) {
    // The input views at the photos' resolution in the prediction's frame, with their alpha.
    const std::array<index_t, 2> size = model::refine_size(rgba, c);
    const model::PhotoTargets<float>& photos = targets_at(size);
    std::vector<Camera> views;
    for (index_t v = 0; v < p.views; ++v)
      views.push_back(camera_from_arrays(photos.K.data() + 9 * v, p.geometry.extrinsics.data() + 12 * v,
                                         static_cast<int>(size[1]), static_cast<int>(size[0])));
    const model::CompactReport cr = model::compact_splat(p.gaussians, views, photos.alpha.data());
    std::fprintf(stderr, "reconstruct: compact: %lld of %lld Gaussians kept (%lld outside the silhouettes, %lld unseen, "
                 "%lld degenerate)\n", static_cast<long long>(cr.after), static_cast<long long>(cr.before),
                 static_cast<long long>(cr.outside), static_cast<long long>(cr.unseen),
                 static_cast<long long>(cr.degenerate));
    t.lap("compact");
  }
  gltf::WriteOptions wo;
  if (format == gaussians::FileFormat::Glb && given_cameras) {
    wo.cameras = cameras;
  } else if (format == gaussians::FileFormat::Glb) {
    std::vector<std::string> names;
    for (const std::string& a : args) names.push_back(fs::path(a).filename().string());
    wo.cameras = model::input_cameras(p, names);
  }
  std::fprintf(stderr, "reconstruct: writing %s\n", output.c_str());
  const auto report = gaussians::write_gaussians(p.gaussians, output, wo);
  t.lap("export");
  if (!turntable.empty()) {
    std::fprintf(stderr, "reconstruct: rendering turntable %s\n", turntable.c_str());
    const std::array<index_t, 2> size = model::refine_size(rgba, c, turntable_longer);
    write_turntable(turntable, p, 8, size[0], size[1]);
    t.lap("turntable");
  }
  std::printf("%s: %lld Gaussians, %zu camera(s), %zu bytes, from %zu image(s)\n", output.c_str(),
              static_cast<long long>(p.gaussians.size()), wo.cameras.size(), report.bytes, args.size());
  if (verbose) {
    double total = 0;
    for (const auto& [name, ms] : t.ms) {
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
