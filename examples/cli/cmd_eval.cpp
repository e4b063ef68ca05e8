// eval: the paper's evaluation protocol on object folders (docs/app.md): predict from the input views, align the
// predicted input cameras to the ground truth by a similarity (Umeyama), render every target view from its
// ground-truth camera mapped into the model's frame, and score PSNR / SSIM / LPIPS and the camera errors.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/model/evaluate.hpp"
#include "flexsplat/model/predict.hpp"
#include "flexsplat/model/refine.hpp"
#include "registry.hpp"

namespace flexsplat::cli::eval_cmd {

namespace fs = std::filesystem;

// One row of the table: NaN stands for "not measured" (JSON null).
struct Scores {
  double psnr = 0, ssim = 0, lpips = NAN, rotation_error_deg = NAN, center_error_rel = NAN, seconds = NAN;
};

// --views: "N" (a count) or "i,j,k" (frame indices).
struct ViewChoice {
  int count = 0;
  std::vector<int> list;
};

ViewChoice parse_views(const std::string& s) {
  ViewChoice c;
  std::stringstream in(s);
  std::string item;
  std::vector<int> values;
  while (std::getline(in, item, ',')) {
    std::size_t used = 0;
    int v = -1;
    try {
      v = std::stoi(item, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    require(used == item.size() && !item.empty() && v >= 0, "--views '", s,
            "': expected a view count or comma-separated frame indices");
    values.push_back(v);
  }
  require(!values.empty(), "--views '", s, "' is empty");
  if (values.size() == 1 && s.find(',') == std::string::npos) {
    require(values[0] >= 1, "--views ", values[0], ": need at least one input view");
    c.count = values[0];
  } else {
    c.list = values;
  }
  return c;
}

// What eval does besides the protocol: test-time refinement, rotation noise, the posed-fit baseline.
struct Experiment {
  bool native = true;             // score at the folder's image size (false: at the model's)
  double refine_seconds = 0;      // the refinement's time budget (0: none)
  std::int64_t refine_steps = 0;  // its step budget (0: none); neither: feed-forward only
  index_t refine_longer = 0;      // the refinement's longer side (0: the photos' own resolution)
  bool refine_validate = false;   // choose the refinement's step count on a held-out input view
  bool refine_cameras = true;     // refine the predicted cameras with the Gaussians
  bool refine_carve = true;       // carve the Gaussians to the input photos' silhouettes first
  index_t refine_grow = model::refine_grow_gaussians;  // Gaussians grown in the visual hull
  bool true_cameras = false;      // --cameras truth: the folder's input cameras in place of the predicted ones
  double rotation_noise_deg = 0;  // 0: none
  std::uint64_t seed = 0;         // rotation noise and the posed fit's initialisation (per object: model::object_seed)
  bool posed_fit = false;
  index_t gaussians = 0;          // 0: the model's budget for the view count
  bool refining() const { return refine_seconds > 0 || refine_steps > 0; }
};

// The refinement's own numbers (steps, loss on the input views before and after, Gaussians pruned).
struct RefineInfo {
  double steps = NAN, loss_initial = NAN, loss_final = NAN, pruned = NAN;
  double trial_steps = NAN, holdout_initial = NAN, holdout_best = NAN, carved = NAN, grown = NAN;
  index_t h = 0, w = 0;  // the size the input views were fitted at
};

struct ObjectResult {
  std::string name;
  Scores model, white, posed_fit, feed_forward;  // feed_forward: the model before refinement (with --refine)
  RefineInfo refine;
  std::vector<std::vector<float>> grid_gt, grid_render, grid_inputs;  // [h, w, 3] each
  std::vector<std::vector<float>> grid_feed_forward;                  // with --refine: the renders before it
  index_t score_h = 0, score_w = 0;  // the size targets were scored (and grid_gt / grid_render drawn) at
};

Scores row(const model::EvalResult& e, double seconds) {
  return {e.model.psnr, e.model.ssim, e.model.lpips, e.rotation_error_deg, e.center_error_rel, seconds};
}

ObjectResult evaluate_object(const data::ObjectRecord& rec, const model::FlexSplatWeights<float>& w,
                             model::PredictWorkspace<float>& ws, const model::EvalOptions& o,
                             model::EvalWorkspace& ews, const Experiment& x) {
  const model::FlexSplatConfig& c = w.config();
  std::vector<int> in, targets;
  model::eval_views(rec, o, in, targets);
  const std::uint64_t seed = model::object_seed(rec.name, x.seed);
  // seconds: reading and resizing the input views, the model's forward pass and the refinement (what reconstruct
  // costs).
  const auto t0 = std::chrono::steady_clock::now();
  auto since = [](auto t) { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count(); };
  std::vector<Tensor<float, 3>> rgba;
  for (int v : in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  const Tensor<float, 4> images = model::model_input<float>(rgba, c);
  model::BeforeDecoder<float> noise;
  if (x.rotation_noise_deg > 0)
    noise = [&](model::GeometryResult<float>& g) {
      model::rotation_noise(g.extrinsics.data(), g.views, x.rotation_noise_deg, seed);
    };
  if (x.true_cameras) {
    // The folder's cameras given as reconstruct --cameras gives a capture's: the same frame and scale search.
    std::vector<Camera> cams;
    for (int v : in) cams.push_back(rec.frames[static_cast<std::size_t>(v)].camera);
    ws.given = model::given_cameras<float>(rgba, cams, c);
  }
  ws.silhouettes = model::photo_silhouettes<float>(rgba, c);
  model::Prediction<float> p = model::predict<float>(ws, w, TensorView<const float, 4>(images.view()), x.gaussians, noise);
  if (p.given) model::to_capture_world(p);  // the folder's world: the alignment below is then the identity
  double seconds = since(t0);
  const double predict_seconds = seconds;
  const index_t n_model = p.gaussians.size();
  const int degree = p.gaussians.sh_degree();
  ObjectResult r;
  r.name = rec.name;
  // Native: the folder's whole image, a window model_view copies unchanged, K as stored.
  const index_t sh = x.native ? rec.height : c.image_h, sw = x.native ? rec.width : c.image_w;
  r.score_h = sh, r.score_w = sw;
  std::vector<float> w2c(p.geometry.extrinsics.begin(), p.geometry.extrinsics.end());
  // The refinement (and the posed fit beside it) fits the input photos at this size.
  const std::array<index_t, 2> fit_size =
      x.refining() ? model::refine_size(rgba, c, x.refine_longer) : std::array<index_t, 2>{c.image_h, c.image_w};
  index_t fit_gaussians = n_model;  // the posed fit's count: the refinement's start, before carving
  double refine_spent = 0;  // the refinement's seconds
  if (x.refining()) {
    model::EvalOptions before = o;
    before.white_baseline = false;
    model::EvalResult ff = model::score_prediction(rec, in, targets, w2c.data(), p.gaussians, sh, sw, before, ews);
    r.feed_forward = row(ff, seconds);
    r.grid_feed_forward = std::move(ff.grid_render);
    const auto t1 = std::chrono::steady_clock::now();
    const model::PhotoTargets<float> photos =
        model::photo_targets<float>(rgba, c, p.geometry.K.data(), fit_size[0], fit_size[1]);
    const model::RefineViews<float> rv{p.views,       photos.h,   photos.w,           photos.images.data(),
                                       photos.K.data(), w2c.data(), photos.alpha.data()};
    model::RefineConfig rc = model::prediction_refine_config(rv, x.refine_seconds, seed, x.refine_grow);
    rc.steps = x.refine_steps;
    rc.validate = x.refine_validate;
    rc.optimize_cameras = x.refine_cameras && !x.true_cameras;
    rc.carve = x.refine_carve;
    model::RefineWorkspace<float> rws;
    const model::RefineResult rr = model::refine(p.gaussians, rv, rc, rws);
    refine_spent = since(t1);
    seconds += refine_spent;
    r.refine = {static_cast<double>(rr.steps), rr.loss_initial, rr.loss_final, static_cast<double>(rr.pruned),
                static_cast<double>(rr.trial_steps), rr.holdout_initial, rr.holdout_best, static_cast<double>(rr.carved),
                static_cast<double>(rr.grown), photos.h, photos.w};
    fit_gaussians = n_model + rr.grown;
  }
  model::EvalResult e = model::score_prediction(rec, in, targets, w2c.data(), p.gaussians, sh, sw, o, ews);
  r.model = row(e, seconds);
  r.white = {e.white.psnr, e.white.ssim, e.white.lpips, NAN, NAN, NAN};
  r.grid_gt = std::move(e.grid_gt), r.grid_render = std::move(e.grid_render);
  if (o.grid_targets > 0) {
    const std::vector<float> hwc = model::views_hwc(images.data(), p.views, p.h, p.w);
    const std::size_t n = static_cast<std::size_t>(3 * p.h * p.w);
    for (index_t v = 0; v < p.views; ++v) r.grid_inputs.emplace_back(hwc.begin() + v * n, hwc.begin() + (v + 1) * n);
  }
  if (x.posed_fit) {
    // The same input views with their ground-truth cameras, fitted for the model's time: with --refine the
    // prediction's plus the whole refinement budget (the refinement may stop earlier when its trial says so; with
    // --refine-steps alone, the seconds it took), with as many Gaussians as the refinement started from (the
    // prediction's and the grown ones).
    const double budget =
        x.refining() ? predict_seconds + (x.refine_seconds > 0 ? x.refine_seconds : refine_spent) : seconds;
    const model::PosedFit f = model::posed_fit(rec, in, fit_size[0], fit_size[1], fit_gaussians, degree, budget, seed);
    model::EvalOptions po = o;
    po.white_baseline = false, po.grid_targets = 0;
    const model::EvalResult pe = model::score_prediction(rec, in, targets, f.w2c.data(), f.gaussians, sh, sw, po, ews);
    r.posed_fit = {pe.model.psnr, pe.model.ssim, pe.model.lpips, NAN, NAN, f.seconds};
  }
  return r;
}

nlohmann::json value_or_null(double v) { return std::isnan(v) ? nlohmann::json(nullptr) : nlohmann::json(v); }

nlohmann::json scores_json(const std::string& name, const Scores& s) {
  nlohmann::json j;
  if (!name.empty()) j["name"] = name;
  j["psnr"] = value_or_null(s.psnr);
  j["ssim"] = value_or_null(s.ssim);
  j["lpips"] = value_or_null(s.lpips);
  j["rotation_error_deg"] = value_or_null(s.rotation_error_deg);
  j["center_error_rel"] = value_or_null(s.center_error_rel);
  j["seconds"] = value_or_null(s.seconds);
  return j;
}

Scores mean_of(const std::vector<Scores>& all) {
  Scores m;
  double Scores::*fields[] = {&Scores::psnr, &Scores::ssim, &Scores::lpips, &Scores::rotation_error_deg,
                              &Scores::center_error_rel, &Scores::seconds};
  for (auto f : fields) {
    double sum = 0;
    for (const Scores& s : all) sum += s.*f;  // NaN (not measured) stays NaN
    m.*f = sum / static_cast<double>(all.size());
  }
  return m;
}

std::string cell(double v, const char* fmt) {
  if (std::isnan(v)) return "-";
  char buf[32];
  std::snprintf(buf, sizeof buf, fmt, v);
  return buf;
}

void print_table(const char* title, const std::vector<std::string>& names, const std::vector<Scores>& rows) {
  std::printf("%s\n%-20s %8s %7s %7s %9s %10s %8s\n", title, "object", "psnr", "ssim", "lpips", "rot_deg",
              "center_rel", "seconds");
  auto line = [](const std::string& name, const Scores& s) {
    std::printf("%-20s %8s %7s %7s %9s %10s %8s\n", name.c_str(), cell(s.psnr, "%.2f").c_str(),
                cell(s.ssim, "%.4f").c_str(), cell(s.lpips, "%.4f").c_str(), cell(s.rotation_error_deg, "%.2f").c_str(),
                cell(s.center_error_rel, "%.4f").c_str(), cell(s.seconds, "%.3f").c_str());
  };
  for (std::size_t i = 0; i < rows.size(); ++i) line(names[i], rows[i]);
  line("mean", mean_of(rows));
}

// Per object three rows: the input views the model saw (h x w, scaled up to the scoring size), its renders of the
// first targets (with --refine two rows: before and after) and their ground truth (at the scoring size).
void write_grid(const fs::path& path, const std::vector<ObjectResult>& results, index_t h, index_t w) {
  std::size_t cols = 0;
  for (const auto& r : results) cols = std::max({cols, r.grid_gt.size(), r.grid_inputs.size()});
  require(cols > 0, "eval --grid: no target was rendered");
  std::deque<std::vector<float>> upscaled;  // owns the scaled inputs the cells point at (a deque never moves them)
  std::vector<image::GridCell> cells;
  auto row = [&](const std::vector<const std::vector<float>*>& images, const std::string& label, index_t rh, index_t rw) {
    for (std::size_t i = 0; i < cols; ++i)
      cells.push_back(i < images.size() ? image::GridCell{TensorView<const float, 3>(images[i]->data(), Shape<3>{rh, rw, 3}),
                                                          label + " " + std::to_string(i + 1)}
                                        : image::GridCell{});
  };
  auto pointers = [](const std::vector<std::vector<float>>& v) {
    std::vector<const std::vector<float>*> p;
    for (const auto& x : v) p.push_back(&x);
    return p;
  };
  index_t cell = std::max(h, w);
  for (const auto& r : results) {
    cell = std::max({cell, r.score_h, r.score_w});
    std::vector<const std::vector<float>*> inputs;
    for (const auto& im : r.grid_inputs) {
      std::vector<float>& big = upscaled.emplace_back(static_cast<std::size_t>(3 * r.score_h * r.score_w));
      for (index_t y = 0; y < r.score_h; ++y)
        for (index_t x = 0; x < r.score_w; ++x)
          for (index_t k = 0; k < 3; ++k)
            big[static_cast<std::size_t>((y * r.score_w + x) * 3 + k)] =
                im[static_cast<std::size_t>(((y * h / r.score_h) * w + x * w / r.score_w) * 3 + k)];
      inputs.push_back(&big);
    }
    row(inputs, r.name + " in", r.score_h, r.score_w);
    if (!r.grid_feed_forward.empty()) row(pointers(r.grid_feed_forward), "feed-forward", r.score_h, r.score_w);
    row(pointers(r.grid_render), r.grid_feed_forward.empty() ? "render" : "refined", r.score_h, r.score_w);
    row(pointers(r.grid_gt), "truth", r.score_h, r.score_w);
  }
  image::write_png(path, image::image_grid(cells, static_cast<int>(cols), static_cast<int>(std::min<index_t>(cell, 512))));
}

nlohmann::json refine_json(const RefineInfo& r, const Scores& refined, const Scores& before) {
  nlohmann::json j;
  j["steps"] = value_or_null(r.steps);
  j["loss_initial"] = value_or_null(r.loss_initial);
  j["loss_final"] = value_or_null(r.loss_final);
  j["pruned"] = value_or_null(r.pruned);
  j["size"] = {r.h, r.w};
  j["carved"] = value_or_null(r.carved);
  j["grown"] = value_or_null(r.grown);
  j["trial_steps"] = value_or_null(r.trial_steps);
  j["holdout_loss_initial"] = value_or_null(r.holdout_initial);
  j["holdout_loss_best"] = value_or_null(r.holdout_best);
  j["psnr_change"] = value_or_null(refined.psnr - before.psnr);
  return j;
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
  if (!views_text.empty()) {
    const ViewChoice choice = parse_views(views_text);
    eo.view_count = choice.count, eo.view_list = choice.list;
  }
  eo.max_targets = parse_count(max_targets_text, "--max-targets", 0);
  eo.grid_targets = grid_path.empty() ? 0 : parse_count(grid_cols_text, "--grid-targets", 4);
  eo.white_baseline = has("white");
  Experiment x;
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
  model::EvalWorkspace ews;
  std::vector<ObjectResult> results;
  for (std::size_t i = 0; i < objects.size(); ++i) {
    if (!quiet) std::fprintf(stderr, "eval: %s (%zu/%zu)\n", objects[i].name.c_str(), i + 1, objects.size());
    try {
      results.push_back(evaluate_object(objects[i], *w, ws, eo, ews, x));
    } catch (const Error& e) {
      fail("object '", objects[i].dir.string(), "': ", e.what());
    }
  }

  const bool refined = x.refining();
  std::vector<std::string> names;
  std::vector<Scores> rows, white_rows, posed_rows, ff_rows;
  for (const auto& r : results) {
    names.push_back(r.name), rows.push_back(r.model), white_rows.push_back(r.white);
    posed_rows.push_back(r.posed_fit), ff_rows.push_back(r.feed_forward);
  }
  std::string title = "model " + model_path;
  title += x.native ? ", scored at the folders' image size" : ", scored at the model's size";
  char buf[96];
  if (attention) title += attention->first ? ", local self-attention (windows of " + std::to_string(attention->second) + ")"
                                           : std::string(", full self-attention");
  if (x.gaussians > 0) title += ", " + std::to_string(x.gaussians) + " Gaussians";
  if (x.true_cameras) title += ", the folders' input cameras";
  if (x.rotation_noise_deg > 0) {
    std::snprintf(buf, sizeof buf, ", rotation noise %g deg (seed %llu)", x.rotation_noise_deg,
                  static_cast<unsigned long long>(x.seed));
    title += buf;
  }
  if (refined) {
    print_table((title + ", feed-forward").c_str(), names, ff_rows);
    if (x.refine_steps > 0 && x.refine_seconds > 0)
      std::snprintf(buf, sizeof buf, ", refined %g s or %lld steps on the input views", x.refine_seconds,
                    static_cast<long long>(x.refine_steps));
    else if (x.refine_steps > 0)
      std::snprintf(buf, sizeof buf, ", refined %lld steps on the input views", static_cast<long long>(x.refine_steps));
    else
      std::snprintf(buf, sizeof buf, ", refined %g s on the input views", x.refine_seconds);
    title += buf;
  }
  print_table(title.c_str(), names, rows);
  if (refined) {
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
  if (eo.white_baseline) print_table("baseline white (a white image)", names, white_rows);
  if (x.posed_fit)
    print_table("baseline posed-fit (ground-truth input cameras, fitted for the model's seconds from as many Gaussians)",
                names, posed_rows);

  if (!json_path.empty()) {
    nlohmann::json j;
    j["model"] = model_path;
    j["refine_seconds"] = x.refine_seconds;
    j["refine_steps"] = x.refine_steps;
    j["rotation_noise_deg"] = x.rotation_noise_deg;
    j["seed"] = x.seed;
    j["resolution"] = resolution;
    const auto& dc = w->config().appearance.decoder;
    j["self_attention"] = dc.local_attention ? "local:" + std::to_string(dc.window) : std::string("full");
    j["objects"] = nlohmann::json::array();
    for (std::size_t i = 0; i < rows.size(); ++i) {
      nlohmann::json o = scores_json(names[i], rows[i]);
      o["resolution"] = {results[i].score_h, results[i].score_w};
      if (refined) {
        o["feed_forward"] = scores_json("", ff_rows[i]);
        o["refine"] = refine_json(results[i].refine, rows[i], ff_rows[i]);
      }
      j["objects"].push_back(o);
    }
    j["mean"] = scores_json("", mean_of(rows));
    if (refined) {
      j["mean"]["feed_forward"] = scores_json("", mean_of(ff_rows));
      j["mean"]["psnr_change"] = value_or_null(mean_of(rows).psnr - mean_of(ff_rows).psnr);
    }
    auto add_baseline = [&](const char* key, const std::vector<Scores>& b_rows) {
      nlohmann::json b;
      b["objects"] = nlohmann::json::array();
      for (std::size_t i = 0; i < b_rows.size(); ++i) b["objects"].push_back(scores_json(names[i], b_rows[i]));
      b["mean"] = scores_json("", mean_of(b_rows));
      j["baselines"][key] = b;
    };
    if (eo.white_baseline) add_baseline("white", white_rows);
    if (x.posed_fit) add_baseline("posed-fit", posed_rows);
    write_file_atomic(json_path, "eval --json", j.dump(1) + "\n");
  }
  if (!grid_path.empty()) write_grid(grid_path, results, w->config().image_h, w->config().image_w);
  return 0;
}

const RegisterCommand registered_cmd_eval(
    "eval", {"evaluate a model on object folders: predicted cameras aligned to the ground truth, held-out views scored",
             "OBJECT_DIR... [--model M.safetensors] [--views N|i,j,k] [--max-targets N]\n"
             "  [--baseline white|posed-fit|white,posed-fit] [--refine SECONDS] [--refine-steps N]\n"
             "  [--refine-size N|native]\n"
             "  [--refine-validate on|off] [--refine-cameras on|off] [--refine-carve on|off] [--refine-grow N]\n"
             "  [--rotation-noise DEG] [--seed N]\n"
             "  [--gaussians N] [--self-attention full|local[:WINDOW]] [--resolution native|model] [--lpips LPIPS.safetensors]\n"
             "  [--cameras model|orbit|turntable|truth] [--json out.json]\n"
             "  [--grid out.png [--grid-targets 4]] [--quiet]\n"
             "  OBJECT_DIR: a folder in the layout of ../shared/data/objects/<name> or a folder of them\n"
             "  inputs: the folder's input_views (--views N: those when it lists N, else N evenly spaced frames;\n"
             "  --views i,j,k: these frames); targets: every other frame (the first N with --max-targets)\n"
             "  views are resized to the model's size; predicted input cameras are aligned to the ground truth\n"
             "  with a similarity (Umeyama); targets are rendered on white and scored at the folders' own image size\n"
             "  (--resolution model: at the model's size, targets resized as the inputs); lpips is null without --lpips\n"
             "  center_error_rel: median camera-centre error / diagonal of the input views' depth-point box\n"
             "  --json: {model, resolution, objects: [{name, resolution [h, w], psnr, ssim, lpips, rotation_error_deg,\n"
             "  center_error_rel, seconds}],\n"
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
