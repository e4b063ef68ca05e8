// eval: the paper's evaluation protocol on object folders (docs/app.md): predict from the input views, align the
// predicted input cameras to the ground truth by a similarity (Umeyama), render every target view from its
// ground-truth camera mapped into the model's frame, and score PSNR / SSIM / LPIPS and the camera errors.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/image/image_io.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/model/evaluate.hpp"
#include "flexsplat/model/predict.hpp"
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

struct ObjectResult {
  std::string name;
  Scores model, white;
  std::vector<std::vector<float>> grid_gt, grid_render;
};

ObjectResult evaluate_object(const data::ObjectRecord& rec, const model::FlexSplatWeights<float>& w,
                             model::PredictWorkspace<float>& ws, const model::EvalOptions& o,
                             model::EvalWorkspace& ews) {
  const model::FlexSplatConfig& c = w.config();
  std::vector<int> in, targets;
  model::eval_views(rec, o, in, targets);
  // seconds: reading and resizing the input views and the model's forward pass (what reconstruct costs).
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<Tensor<float, 3>> rgba;
  for (int v : in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  const Tensor<float, 4> images = model::model_input<float>(rgba, c);
  const model::Prediction<float> p = model::predict<float>(ws, w, TensorView<const float, 4>(images.view()));
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  model::EvalResult e = model::score_prediction(rec, in, targets, p.geometry.extrinsics.data(), p.gaussians,
                                                c.image_h, c.image_w, o, ews);
  ObjectResult r;
  r.name = rec.name;
  r.model = {e.model.psnr, e.model.ssim, e.model.lpips, e.rotation_error_deg, e.center_error_rel, seconds};
  r.white = {e.white.psnr, e.white.ssim, e.white.lpips, NAN, NAN, NAN};
  r.grid_gt = std::move(e.grid_gt), r.grid_render = std::move(e.grid_render);
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

// Rows: per object, ground truth above the render; columns: the first targets. Gaps are white.
void write_grid(const fs::path& path, const std::vector<ObjectResult>& results, index_t h, index_t w) {
  std::size_t cols = 0;
  for (const auto& r : results) cols = std::max(cols, r.grid_gt.size());
  require(cols > 0, "eval --grid: no target was rendered");
  const index_t gap = 2, rows = static_cast<index_t>(2 * results.size());
  const index_t H = rows * h + (rows - 1) * gap, W = static_cast<index_t>(cols) * w + (static_cast<index_t>(cols) - 1) * gap;
  Tensor<float, 3> grid(Shape<3>{H, W, 3}, 1.0f);
  for (std::size_t o = 0; o < results.size(); ++o)
    for (int which = 0; which < 2; ++which) {
      const auto& images = which == 0 ? results[o].grid_gt : results[o].grid_render;
      const index_t y0 = static_cast<index_t>(2 * o + which) * (h + gap);
      for (std::size_t i = 0; i < images.size(); ++i) {
        const index_t x0 = static_cast<index_t>(i) * (w + gap);
        for (index_t y = 0; y < h; ++y)
          for (index_t x = 0; x < w; ++x)
            for (int c = 0; c < 3; ++c)
              grid(y0 + y, x0 + x, c) = std::clamp(images[i][static_cast<std::size_t>((y * w + x) * 3 + c)], 0.0f, 1.0f);
      }
    }
  image::write_png(path, grid);
}

int eval_command(Args args) {
  std::string model_path, views_text, baseline, json_path, grid_path, lpips_path, max_targets_text, grid_cols_text;
  take_option(args, "--model", model_path);
  take_option(args, "--views", views_text);
  take_option(args, "--baseline", baseline);
  take_option(args, "--json", json_path);
  take_option(args, "--grid", grid_path);
  take_option(args, "--grid-targets", grid_cols_text);
  take_option(args, "--lpips", lpips_path);
  take_option(args, "--max-targets", max_targets_text);
  const bool quiet = take_flag(args, "--quiet");
  for (const auto& a : args) require(a.empty() || a[0] != '-', "eval: unknown option '", a, "'");
  require(!args.empty(), "eval needs at least one OBJECT_DIR (a folder with cameras.json, or a folder of them)");
  require(baseline.empty() || baseline == "white", "eval: --baseline '", baseline,
          "' is not known (available: white)");
  auto parse_count = [](const std::string& text, const char* flag, int fallback) {
    if (text.empty()) return fallback;
    std::size_t used = 0;
    int v = -1;
    try {
      v = std::stoi(text, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    require(used == text.size() && v >= 1, flag, " '", text, "' must be a positive integer");
    return v;
  };
  model::EvalOptions eo;
  if (!views_text.empty()) {
    const ViewChoice choice = parse_views(views_text);
    eo.view_count = choice.count, eo.view_list = choice.list;
  }
  eo.max_targets = parse_count(max_targets_text, "--max-targets", 0);
  eo.grid_targets = grid_path.empty() ? 0 : parse_count(grid_cols_text, "--grid-targets", 4);
  eo.white_baseline = !baseline.empty();

  model_path = model_or_default(model_path);
  require(fs::is_regular_file(model_path), "eval: model file '", model_path, "' does not exist");
  const auto w = model::load_flexsplat<float>(model_path);
  std::optional<loss::LpipsWeights<float>> lpips;
  if (!lpips_path.empty()) lpips = loss::lpips_load_weights<float>(safetensors::File::open(lpips_path));

  std::vector<fs::path> dirs(args.begin(), args.end());
  const std::vector<data::ObjectRecord> objects = data::load_objects(dirs);
  eo.lpips = lpips ? &*lpips : nullptr;
  model::PredictWorkspace<float> ws;
  model::EvalWorkspace ews;
  std::vector<ObjectResult> results;
  for (std::size_t i = 0; i < objects.size(); ++i) {
    if (!quiet) std::fprintf(stderr, "eval: %s (%zu/%zu)\n", objects[i].name.c_str(), i + 1, objects.size());
    try {
      results.push_back(evaluate_object(objects[i], *w, ws, eo, ews));
    } catch (const Error& e) {
      fail("object '", objects[i].dir.string(), "': ", e.what());
    }
  }

  std::vector<std::string> names;
  std::vector<Scores> rows, white_rows;
  for (const auto& r : results) names.push_back(r.name), rows.push_back(r.model), white_rows.push_back(r.white);
  print_table(("model " + model_path).c_str(), names, rows);
  if (!baseline.empty()) print_table("baseline white (a white image)", names, white_rows);

  if (!json_path.empty()) {
    nlohmann::json j;
    j["model"] = model_path;
    j["objects"] = nlohmann::json::array();
    for (std::size_t i = 0; i < rows.size(); ++i) j["objects"].push_back(scores_json(names[i], rows[i]));
    j["mean"] = scores_json("", mean_of(rows));
    if (!baseline.empty()) {
      nlohmann::json b;
      b["objects"] = nlohmann::json::array();
      for (std::size_t i = 0; i < rows.size(); ++i) b["objects"].push_back(scores_json(names[i], white_rows[i]));
      b["mean"] = scores_json("", mean_of(white_rows));
      j["baselines"]["white"] = b;
    }
    std::ofstream f(json_path, std::ios::binary | std::ios::trunc);
    require(f.good(), "eval: cannot write '", json_path, "'");
    f << j.dump(1) << "\n";
    require(f.good(), "eval: writing '", json_path, "' failed");
  }
  if (!grid_path.empty()) write_grid(grid_path, results, w->config().image_h, w->config().image_w);
  return 0;
}

const RegisterCommand registered_cmd_eval(
    "eval", {"evaluate a model on object folders: predicted cameras aligned to the ground truth, held-out views scored",
             "OBJECT_DIR... [--model M.safetensors] [--views N|i,j,k] [--max-targets N] [--baseline white]\n"
             "  [--lpips LPIPS.safetensors] [--json out.json] [--grid out.png [--grid-targets 4]] [--quiet]\n"
             "  OBJECT_DIR: a folder in the layout of ../shared/data/objects/<name> or a folder of them\n"
             "  inputs: the folder's input_views (--views N: those when it lists N, else N evenly spaced frames;\n"
             "  --views i,j,k: these frames); targets: every other frame (the first N with --max-targets)\n"
             "  views are resized to the model's size; predicted input cameras are aligned to the ground truth\n"
             "  with a similarity (Umeyama); targets are rendered on white; lpips is null without --lpips\n"
             "  center_error_rel: median camera-centre error / diagonal of the input views' depth-point box\n"
             "  --json: {model, objects: [{name, psnr, ssim, lpips, rotation_error_deg, center_error_rel, seconds}],\n"
             "  mean, baselines}; --grid: ground truth above render, one row pair per object (docs/app.md)",
             eval_command});

}  // namespace flexsplat::cli::eval_cmd
