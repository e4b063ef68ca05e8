// eval: the paper's evaluation protocol on object folders (docs/app.md): predict from the input views, align the
// predicted input cameras to the ground truth by a similarity (Umeyama), render every target view from its
// ground-truth camera mapped into the model's frame, and score PSNR / SSIM / LPIPS and the camera errors.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/eval/run.hpp"
#include "registry.hpp"

namespace flexsplat::cli::eval_cmd {

namespace fs = std::filesystem;

using model::ObjectScores;

std::string cell(double v, const char* fmt) {
  if (std::isnan(v)) return "-";
  char buf[32];
  std::snprintf(buf, sizeof buf, fmt, v);
  return buf;
}

void print_table(const char* title, const std::vector<model::ObjectEval>& results, ObjectScores model::ObjectEval::*field) {
  std::printf("%s\n%-20s %8s %7s %7s %9s %10s %8s\n", title, "object", "psnr", "ssim", "lpips", "rot_deg",
              "center_rel", "seconds");
  auto line = [](const std::string& name, const ObjectScores& s) {
    std::printf("%-20s %8s %7s %7s %9s %10s %8s\n", name.c_str(), cell(s.psnr, "%.2f").c_str(),
                cell(s.ssim, "%.4f").c_str(), cell(s.lpips, "%.4f").c_str(), cell(s.rotation_error_deg, "%.2f").c_str(),
                cell(s.center_error_rel, "%.4f").c_str(), cell(s.seconds, "%.3f").c_str());
  };
  for (const auto& r : results) line(r.name, r.*field);
  line("mean", model::mean_scores(model::score_rows(results, field)));
}

// The refinement's own table (with --refine).
void print_refinement(const std::vector<model::ObjectEval>& results) {
  std::printf("refinement (with --refine-validate on: trial_steps of the held-out trial, held_in and held_best the "
              "held-out view's loss)\n%-20s %6s %10s %10s %7s %11s %11s %9s %9s %7s %6s %9s\n",
              "object", "steps", "loss_in", "loss_out", "pruned", "psnr_change", "trial_steps", "held_in",
              "held_best", "carved", "grown", "size");
  for (const auto& r : results)
    std::printf("%-20s %6.0f %10.5f %10.5f %7.0f %+11.2f %11s %9s %9s %7.0f %6.0f %4lldx%-4lld\n", r.name.c_str(),
                r.refine.steps, r.refine.loss_initial, r.refine.loss_final, r.refine.pruned,
                r.model.psnr - r.feed_forward.psnr, cell(r.refine.trial_steps, "%.0f").c_str(),
                cell(r.refine.holdout_initial, "%.5f").c_str(), cell(r.refine.holdout_best, "%.5f").c_str(),
                r.refine.carved, r.refine.grown, static_cast<long long>(r.refine.w),
                static_cast<long long>(r.refine.h));
}

// The run's tables: the model's scores (with --refine also before it, and the refinement's own), the baselines.
void print_tables(const std::string& model_path, const std::optional<std::pair<bool, index_t>>& attention,
                  const model::EvalOptions& eo, const model::EvalExperiment& x,
                  const std::vector<model::ObjectEval>& results) {
  const bool refined = x.refining();
  std::string title = "model " + model_path;
  title += x.native ? ", scored at the folders' image size" : ", scored at the model's size";
  char buf[96];
  if (attention) title += attention->first ? ", local self-attention (windows of " + std::to_string(attention->second) + ")"
                                           : std::string(", full self-attention");
  if (x.gaussians > 0) title += ", " + std::to_string(x.gaussians) + " Gaussians";
  if (x.auto_budget) title += ", --budget auto (" + std::to_string(x.outline_margin) + " anchor spacings)";
  if (x.true_cameras) title += ", the folders' input cameras";
  if (x.rotation_noise_deg > 0) {
    std::snprintf(buf, sizeof buf, ", rotation noise %g deg (seed %llu)", x.rotation_noise_deg,
                  static_cast<unsigned long long>(x.seed));
    title += buf;
  }
  if (refined) {
    print_table((title + ", feed-forward").c_str(), results, &model::ObjectEval::feed_forward);
    if (x.refine_steps > 0 && x.refine_seconds > 0)
      std::snprintf(buf, sizeof buf, ", refined %g s or %lld steps on the input views", x.refine_seconds,
                    static_cast<long long>(x.refine_steps));
    else if (x.refine_steps > 0)
      std::snprintf(buf, sizeof buf, ", refined %lld steps on the input views", static_cast<long long>(x.refine_steps));
    else
      std::snprintf(buf, sizeof buf, ", refined %g s on the input views", x.refine_seconds);
    title += buf;
  }
  print_table(title.c_str(), results, &model::ObjectEval::model);
  if (refined) print_refinement(results);
  if (eo.white_baseline) print_table("baseline white (a white image)", results, &model::ObjectEval::white);
  if (x.posed_fit)
    print_table("baseline posed-fit (ground-truth input cameras, fitted for the model's seconds from as many Gaussians)",
                results, &model::ObjectEval::posed_fit);
}

int eval_command(Args args) {
  std::string model_path, views_text, json_path, grid_path, lpips_path, max_targets_text, grid_cols_text;
  std::string refine_text, refine_steps_text, noise_text, seed_text, baseline, gaussians_text, attention_text;
  std::vector<std::string> baselines;
  take_option(args, "--model", model_path);
  take_option(args, "--views", views_text);
  while (take_option(args, "--baseline", baseline)) {
    std::stringstream in(baseline);
    for (std::string item; std::getline(in, item, ',');) baselines.push_back(item);
  }
  take_option(args, "--json", json_path);
  take_option(args, "--grid", grid_path);
  take_option(args, "--grid-targets", grid_cols_text);
  take_option(args, "--lpips", lpips_path);
  take_option(args, "--max-targets", max_targets_text);
  take_option(args, "--refine", refine_text);
  take_option(args, "--refine-steps", refine_steps_text);
  std::string refine_size_text, refine_validate = "off", refine_cameras = "on", refine_carve = "on", refine_grow_text;
  bool refine_options = false;
  for (auto [flag, value] : {std::pair{"--refine-size", &refine_size_text}, {"--refine-validate", &refine_validate},
                             {"--refine-cameras", &refine_cameras}, {"--refine-carve", &refine_carve},
                             {"--refine-grow", &refine_grow_text}})
    if (take_option(args, flag, *value)) refine_options = true;
  take_option(args, "--rotation-noise", noise_text);
  take_option(args, "--seed", seed_text);
  take_option(args, "--gaussians", gaussians_text);
  std::string budget_text = "full";
  take_option(args, "--budget", budget_text);
  const bool auto_budget = budget_text == "auto" || budget_text.starts_with("auto:");
  std::string resolution = "native";
  take_option(args, "--resolution", resolution);
  require(resolution == "native" || resolution == "model", "eval: --resolution '", resolution,
          "' is neither 'native' (the folders' image size) nor 'model' (the model's input size)");
  take_option(args, "--self-attention", attention_text);
  std::string cameras_text = "model";
  take_option(args, "--cameras", cameras_text);
  // truth (eval only): the model's cameras replaced by the folder's before the decoder.
  const bool true_cameras = cameras_text == "truth";
  const model::CameraSource camera_source =
      true_cameras ? model::CameraSource::given : model::parse_camera_source(cameras_text);
  const bool quiet = take_flag(args, "--quiet");
  for (const auto& a : args) require(a.empty() || a[0] != '-', "eval: unknown option '", a, "'");
  require(!args.empty(), "eval needs at least one OBJECT_DIR (a folder with cameras.json, or a folder of them)");
  auto has = [&](const char* b) { return std::find(baselines.begin(), baselines.end(), b) != baselines.end(); };
  for (const auto& b : baselines)
    require(b == "white" || b == "posed-fit", "eval: --baseline '", b, "' is not known (available: white, posed-fit)");
  auto parse_count = [](const std::string& text, const char* flag, int fallback) {
    return text.empty() ? fallback : static_cast<int>(parse_integer(text, flag, 1, std::numeric_limits<int>::max()));
  };
  model::EvalOptions eo;
  if (!views_text.empty()) model::set_views(eo, views_text);
  eo.max_targets = parse_count(max_targets_text, "--max-targets", 0);
  eo.grid_targets = grid_path.empty() ? 0 : parse_count(grid_cols_text, "--grid-targets", 4);
  eo.white_baseline = has("white");
  model::EvalExperiment x;
  x.posed_fit = has("posed-fit");
  x.true_cameras = true_cameras;
  if (!refine_text.empty()) x.refine_seconds = parse_number(refine_text, "--refine", false);
  if (!refine_steps_text.empty()) x.refine_steps = parse_integer(refine_steps_text, "--refine-steps", 1, 100000000);
  if (!noise_text.empty()) {
    x.rotation_noise_deg = parse_number(noise_text, "--rotation-noise", true);
    require(x.rotation_noise_deg <= 180, "--rotation-noise ", x.rotation_noise_deg, " must be at most 180 degrees");
  }
  if (!seed_text.empty()) x.seed = parse_seed(seed_text, "--seed");
  x.native = resolution == "native";
  x.refine_longer = parse_longer_side(refine_size_text, "--refine-size");
  x.refine_validate = parse_on_off(refine_validate, "--refine-validate");
  x.refine_cameras = parse_on_off(refine_cameras, "--refine-cameras");
  x.refine_carve = parse_on_off(refine_carve, "--refine-carve");
  x.refine_grow = parse_gaussian_count(refine_grow_text, "--refine-grow", model::refine_grow_gaussians);
  require(!refine_options || x.refining(),
          "eval: --refine-size, --refine-validate, --refine-cameras, --refine-carve and --refine-grow need --refine "
          "SECONDS or --refine-steps N");

  if (!gaussians_text.empty()) x.gaussians = parse_count(gaussians_text, "--gaussians", 0);
  x.auto_budget = auto_budget;
  if (budget_text.starts_with("auto:")) x.outline_margin = parse_number(budget_text.substr(5), "--budget auto:", true);
  require(auto_budget || budget_text == "full", "eval: --budget '", budget_text, "': expected full, auto or auto:CELLS");
  // --self-attention full | local | local:WINDOW (the decoder's self-attention has no parameters of its own).
  std::optional<std::pair<bool, index_t>> attention;
  if (!attention_text.empty()) {
    const bool local = attention_text.rfind("local", 0) == 0;
    require(attention_text == "full" || attention_text == "local" || attention_text.rfind("local:", 0) == 0,
            "eval: --self-attention '", attention_text, "' must be full, local or local:WINDOW");
    const index_t window = attention_text.size() > 6 ? parse_count(attention_text.substr(6), "--self-attention local:", 0) : 512;
    attention = std::pair<bool, index_t>(local, window);
  }

  model_path = model_or_default(model_path, true_cameras);
  require(fs::is_regular_file(model_path), "eval: model file '", model_path, "' does not exist");
  const auto w = model::load_flexsplat<float>(model_path);
  if (attention) w->set_self_attention(attention->first, attention->second);
  std::optional<loss::LpipsWeights<float>> lpips;
  if (!lpips_path.empty()) lpips = loss::lpips_load_weights<float>(safetensors::File::open(lpips_path));

  std::vector<fs::path> dirs(args.begin(), args.end());
  const std::vector<data::ObjectRecord> objects = data::load_objects(dirs);
  eo.lpips = lpips ? &*lpips : nullptr;
  model::PredictWorkspace<float> ws;
  ws.cameras = camera_source;
  ws.keep_packed_weights = true;  // one fixed model for every object: under bf16, pack it once
  const std::vector<model::ObjectEval> results = model::evaluate_objects(objects, *w, ws, eo, x, [&](std::size_t i) {
    if (!quiet) std::fprintf(stderr, "eval: %s (%zu/%zu)\n", objects[i].name.c_str(), i + 1, objects.size());
  });

  print_tables(model_path, attention, eo, x, results);
  if (!json_path.empty())
    write_file_atomic(json_path, "eval --json", model::eval_json(model_path, w->config(), eo, x, results).dump(1) + "\n");
  if (!grid_path.empty()) model::write_eval_grid(grid_path, results, w->config().image_h, w->config().image_w);
  return 0;
}

const RegisterCommand registered_cmd_eval(
    "eval", {"evaluate a model on object folders: predicted cameras aligned to the ground truth, held-out views scored",
             "OBJECT_DIR... [--model M.safetensors] [--views N|i,j,k] [--max-targets N]\n"
             "  [--baseline white|posed-fit|white,posed-fit] [--refine SECONDS] [--refine-steps N]\n"
             "  [--refine-size N|native]\n"
             "  [--refine-validate on|off] [--refine-cameras on|off] [--refine-carve on|off] [--refine-grow N]\n"
             "  [--rotation-noise DEG] [--seed N]\n"
             "  [--gaussians N] [--budget full|auto[:CELLS]] [--self-attention full|local[:WINDOW]] [--resolution native|model]\n"
             "  [--lpips LPIPS.safetensors]\n"
             "  [--cameras model|orbit|turntable|truth] [--json out.json]\n"
             "  [--grid out.png [--grid-targets 4]] [--quiet]\n"
             "  OBJECT_DIR: a folder in the layout of ../shared/data/objects/<name> or a folder of them\n"
             "  inputs: the folder's input_views (--views N: those when it lists N, else N evenly spaced frames;\n"
             "  --views i,j,k: these frames); targets: every other frame (the first N with --max-targets)\n"
             "  views are resized to the model's size; predicted input cameras are aligned to the ground truth\n"
             "  with a similarity (Umeyama); targets are rendered on white and scored at the folders' own image size\n"
             "  (--resolution model: at the model's size, targets resized as the inputs); lpips is null without --lpips\n"
             "  center_error_rel: median camera-centre error / diagonal of the input views' depth-point box\n"
             "  --json: {model, resolution, budget, objects: [{name, resolution [h, w], budget, gaussians, psnr, ssim,\n"
             "  lpips, rotation_error_deg, center_error_rel, seconds}],\n"
             "  mean, baselines}; --grid: per object its inputs, renders and ground truth\n"
             "  --refine S: carve away the Gaussians seen on the input photos' background, add 4096 in the\n"
             "  silhouettes' visual hull, then optimise the Gaussians and predicted cameras on the input views for\n"
             "  about S seconds at the photos' own resolution (--refine-size N: N pixels on the longer side;\n"
             "  --refine-validate on: the step count chosen on the last input view held out of a trial fit;\n"
             "  --refine-cameras off: cameras fixed; --refine-carve off: no carving; --refine-grow N: N added);\n"
             "  --refine-steps N: at most N optimisation steps (the held-out trial's too), alone or with --refine S\n"
             "  (whichever ends first); alone, a budget that does not depend on the machine's speed;\n"
             "  the feed-forward scores and the PSNR change are reported too, and --baseline posed-fit then fits at\n"
             "  the refinement's size with its Gaussian count before carving; --rotation-noise DEG: each predicted\n"
             "  input camera turned by DEG degrees about a random axis before the decoder (seeded by --seed and the\n"
             "  object's name); --baseline posed-fit: a per-scene fit from the input views with their ground-truth\n"
             "  cameras for the model's seconds; --gaussians: default the model's budget for the view count;\n"
             "  --budget auto: only the budget's queries within CELLS anchor spacings (default 1) of the object's\n"
             "  outline run (reconstruct --budget auto);\n"
             "  --self-attention: the decoder's, whatever the model was trained with (local: windows of 512)\n"
             "  --cameras orbit: the input cameras searched on an orbit around the object from the predicted\n"
             "  silhouettes, depth and colours (models with a match head) instead of the model's own cameras;\n"
             "  --cameras turntable: the --views taken as photos in that order at equal azimuth steps around\n"
             "  the object, their elevation, direction and distance searched (reconstruct --cameras turntable);\n"
             "  --cameras truth: the folder's own input cameras (in the predicted depth's units) given to the\n"
             "  decoder, what the appearance side makes of exact cameras\n"
             "  (docs/app.md)",
             eval_command});

}  // namespace flexsplat::cli::eval_cmd
