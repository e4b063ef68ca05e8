#pragma once
// The evaluation run of `flexsplat eval` (docs/app.md): per object folder, predict from the input views (optionally
// with the folder's own cameras, rotation noise on the predicted ones, test-time refinement), score the held-out
// targets (eval/evaluate.hpp), and optionally the posed-fit baseline; then the means, the JSON report and the picture
// grid. The command-line program only parses its arguments into EvalOptions and EvalExperiment and prints the tables.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/eval/evaluate.hpp"
#include "flexsplat/eval/refine.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"
#include "flexsplat/model/predict.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

// One row of the table: NaN stands for "not measured" (JSON null).
struct ObjectScores {
  double psnr = 0, ssim = 0, lpips = NAN, rotation_error_deg = NAN, center_error_rel = NAN, seconds = NAN;
};

// What eval does besides the protocol: test-time refinement, rotation noise, the posed-fit baseline.
struct EvalExperiment {
  bool native = true;             // score at the folder's image size (false: at the model's)
  double refine_seconds = 0;      // the refinement's time budget (0: none)
  std::int64_t refine_steps = 0;  // its step budget (0: none); neither: feed-forward only
  index_t refine_longer = 0;      // the refinement's longer side (0: the photos' own resolution)
  bool refine_validate = false;   // choose the refinement's step count on a held-out input view
  bool refine_cameras = true;     // refine the predicted cameras with the Gaussians
  bool refine_carve = true;       // carve the Gaussians to the input photos' silhouettes first
  index_t refine_grow = refine_grow_gaussians;  // Gaussians grown in the visual hull
  bool true_cameras = false;      // the folder's input cameras in place of the predicted ones
  double rotation_noise_deg = 0;  // 0: none
  std::uint64_t seed = 0;         // rotation noise and the posed fit's initialisation (per object: object_seed)
  bool posed_fit = false;
  index_t gaussians = 0;          // 0: the model's budget for the view count
  bool auto_budget = false;       // only the budget's queries on the object's outline (PredictWorkspace::auto_budget)
  double outline_margin = decoder::outline_margin_cells;  // within this many anchor spacings of it
  bool refining() const { return refine_seconds > 0 || refine_steps > 0; }
};

// The refinement's own numbers (steps, loss on the input views before and after, Gaussians pruned).
struct EvalRefineInfo {
  double steps = NAN, loss_initial = NAN, loss_final = NAN, pruned = NAN;
  double trial_steps = NAN, holdout_initial = NAN, holdout_best = NAN, carved = NAN, grown = NAN;
  index_t h = 0, w = 0;  // the size the input views were fitted at
};

struct ObjectEval {
  std::string name;
  ObjectScores model, white, posed_fit, feed_forward;  // feed_forward: the model before refinement (with refinement)
  EvalRefineInfo refine;
  std::vector<std::vector<float>> grid_gt, grid_render, grid_inputs;  // [h, w, 3] each
  std::vector<std::vector<float>> grid_feed_forward;                  // with refinement: the renders before it
  index_t score_h = 0, score_w = 0;  // the size targets were scored (and grid_gt / grid_render drawn) at
  index_t budget = 0, gaussians = 0;  // the Gaussian budget and the count predicted (fewer with auto_budget)
};

inline ObjectScores object_scores(const EvalResult& e, double seconds) {
  return {e.model.psnr, e.model.ssim, e.model.lpips, e.rotation_error_deg, e.center_error_rel, seconds};
}

namespace detail {
// The test-time refinement of a prediction on its input photos at fit_size; fills r.refine and r.feed_forward (the
// scores before it), adds its seconds to seconds and into spent, and returns the Gaussians it grew.
inline index_t eval_refine(ObjectEval& r, Prediction<float>& p, std::vector<float>& w2c, const data::ObjectRecord& rec,
                           const std::vector<int>& in, const std::vector<int>& targets,
                           const std::vector<Tensor<float, 3>>& rgba, const FlexSplatConfig& c, const EvalOptions& o,
                           EvalWorkspace& ews, const EvalExperiment& x, std::array<index_t, 2> fit_size,
                           std::uint64_t seed, index_t sh, index_t sw, double& seconds, double& spent) {
  auto since = [](auto t) { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count(); };
  EvalOptions before = o;
  before.white_baseline = false;
  EvalResult ff = score_prediction(rec, in, targets, w2c.data(), p.gaussians, sh, sw, before, ews);
  r.feed_forward = object_scores(ff, seconds);
  r.grid_feed_forward = std::move(ff.grid_render);
  const auto t1 = std::chrono::steady_clock::now();
  const PhotoTargets<float> photos = photo_targets<float>(rgba, c, p.geometry.K.data(), fit_size[0], fit_size[1]);
  const RefineViews<float> rv{p.views,         photos.h,   photos.w,           photos.images.data(),
                              photos.K.data(), w2c.data(), photos.alpha.data()};
  RefineConfig rc = prediction_refine_config(rv, x.refine_seconds, seed, x.refine_grow);
  rc.steps = x.refine_steps;
  rc.validate = x.refine_validate;
  rc.optimize_cameras = x.refine_cameras && !x.true_cameras;
  rc.carve = x.refine_carve;
  RefineWorkspace<float> rws;
  const RefineResult rr = refine(p.gaussians, rv, rc, rws);
  spent = since(t1);
  seconds += spent;
  r.refine = {static_cast<double>(rr.steps), rr.loss_initial, rr.loss_final, static_cast<double>(rr.pruned),
              static_cast<double>(rr.trial_steps), rr.holdout_initial, rr.holdout_best, static_cast<double>(rr.carved),
              static_cast<double>(rr.grown), photos.h, photos.w};
  return rr.grown;
}
}  // namespace detail

// One object folder under the protocol and the experiment: predict, refine (x.refining()), score, and the
// posed-fit baseline (x.posed_fit). seconds: reading and resizing the input views, the model's forward pass and the
// refinement (what reconstruct costs).
inline ObjectEval evaluate_object(const data::ObjectRecord& rec, const FlexSplatWeights<float>& w,
                                  PredictWorkspace<float>& ws, const EvalOptions& o, EvalWorkspace& ews,
                                  const EvalExperiment& x) {
  const FlexSplatConfig& c = w.config();
  std::vector<int> in, targets;
  eval_views(rec, o, in, targets);
  const std::uint64_t seed = object_seed(rec.name, x.seed);
  const auto t0 = std::chrono::steady_clock::now();
  auto since = [](auto t) { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count(); };
  std::vector<Tensor<float, 3>> rgba;
  for (int v : in) rgba.push_back(image::read_float<float>(rec.frames[static_cast<std::size_t>(v)].image, 4));
  ModelPhotos<float> photos = model_photos<float>(rgba, c);
  BeforeDecoder<float> noise;
  if (x.rotation_noise_deg > 0)
    noise = [&](GeometryResult<float>& g) { rotation_noise(g.extrinsics.data(), g.views, x.rotation_noise_deg, seed); };
  if (x.true_cameras) {
    // The folder's cameras given as reconstruct --cameras gives a capture's: the same frame and scale search.
    std::vector<Camera> cams;
    for (int v : in) cams.push_back(rec.frames[static_cast<std::size_t>(v)].camera);
    ws.given = given_cameras<float>(rgba, cams, c);
  }
  ws.silhouettes = std::move(photos.silhouettes);
  ws.auto_budget = x.auto_budget;
  ws.outline_margin = x.outline_margin;
  Prediction<float> p = predict<float>(ws, w, TensorView<const float, 4>(photos.images.view()), x.gaussians, noise);
  if (p.given) to_capture_world(p);  // the folder's world: the alignment below is then the identity
  double seconds = since(t0);
  const double predict_seconds = seconds;
  const index_t n_model = p.gaussians.size();
  const int degree = p.gaussians.sh_degree();
  ObjectEval r;
  r.name = rec.name;
  r.budget = p.budget, r.gaussians = n_model;
  // Native: the folder's whole image, a window model_view copies unchanged, K as stored.
  const index_t sh = x.native ? rec.height : c.image_h, sw = x.native ? rec.width : c.image_w;
  r.score_h = sh, r.score_w = sw;
  std::vector<float> w2c(p.geometry.extrinsics.begin(), p.geometry.extrinsics.end());
  // The refinement (and the posed fit beside it) fits the input photos at this size.
  const std::array<index_t, 2> fit_size =
      x.refining() ? refine_size(rgba, c, x.refine_longer) : std::array<index_t, 2>{c.image_h, c.image_w};
  index_t fit_gaussians = n_model;  // the posed fit's count: the refinement's start, before carving
  double refine_spent = 0;          // the refinement's seconds
  if (x.refining())
    fit_gaussians = n_model + detail::eval_refine(r, p, w2c, rec, in, targets, rgba, c, o, ews, x, fit_size, seed, sh,
                                                  sw, seconds, refine_spent);
  EvalResult e = score_prediction(rec, in, targets, w2c.data(), p.gaussians, sh, sw, o, ews);
  r.model = object_scores(e, seconds);
  r.white = {e.white.psnr, e.white.ssim, e.white.lpips, NAN, NAN, NAN};
  r.grid_gt = std::move(e.grid_gt), r.grid_render = std::move(e.grid_render);
  if (o.grid_targets > 0) {
    const std::vector<float> hwc = views_hwc(photos.images.data(), p.views, p.h, p.w);
    const std::size_t n = static_cast<std::size_t>(3 * p.h * p.w);
    for (index_t v = 0; v < p.views; ++v) r.grid_inputs.emplace_back(hwc.begin() + v * n, hwc.begin() + (v + 1) * n);
  }
  if (x.posed_fit) {
    // The same input views with their ground-truth cameras, fitted for the model's time: with refinement the
    // prediction's plus the whole refinement budget (the refinement may stop earlier when its trial says so; with a
    // step budget alone, the seconds it took), with as many Gaussians as the refinement started from (the
    // prediction's and the grown ones).
    const double budget =
        x.refining() ? predict_seconds + (x.refine_seconds > 0 ? x.refine_seconds : refine_spent) : seconds;
    const PosedFit f = posed_fit(rec, in, fit_size[0], fit_size[1], fit_gaussians, degree, budget, seed);
    EvalOptions po = o;
    po.white_baseline = false, po.grid_targets = 0;
    const EvalResult pe = score_prediction(rec, in, targets, f.w2c.data(), f.gaussians, sh, sw, po, ews);
    r.posed_fit = {pe.model.psnr, pe.model.ssim, pe.model.lpips, NAN, NAN, f.seconds};
  }
  return r;
}

// Every object in order with one workspace; progress(i) before object i; an object's error names its folder.
inline std::vector<ObjectEval> evaluate_objects(const std::vector<data::ObjectRecord>& objects,
                                                const FlexSplatWeights<float>& w, PredictWorkspace<float>& ws,
                                                const EvalOptions& o, const EvalExperiment& x,
                                                const std::function<void(std::size_t)>& progress = {}) {
  EvalWorkspace ews;
  std::vector<ObjectEval> results;
  for (std::size_t i = 0; i < objects.size(); ++i) {
    if (progress) progress(i);
    try {
      results.push_back(evaluate_object(objects[i], w, ws, o, ews, x));
    } catch (const Error& e) {
      fail("object '", objects[i].dir.string(), "': ", e.what());
    }
  }
  return results;
}

// The mean of each field over the rows (NaN, not measured, stays NaN).
inline ObjectScores mean_scores(const std::vector<ObjectScores>& all) {
  ObjectScores m;
  double ObjectScores::*fields[] = {&ObjectScores::psnr,         &ObjectScores::ssim,
                                    &ObjectScores::lpips,        &ObjectScores::rotation_error_deg,
                                    &ObjectScores::center_error_rel, &ObjectScores::seconds};
  for (auto f : fields) {
    double sum = 0;
    for (const ObjectScores& s : all) sum += s.*f;
    m.*f = sum / static_cast<double>(all.size());
  }
  return m;
}

// One field of every result: rows(results, &ObjectEval::model).
inline std::vector<ObjectScores> score_rows(const std::vector<ObjectEval>& results, ObjectScores ObjectEval::*field) {
  std::vector<ObjectScores> rows;
  for (const auto& r : results) rows.push_back(r.*field);
  return rows;
}

namespace detail {
inline nlohmann::json value_or_null(double v) { return std::isnan(v) ? nlohmann::json(nullptr) : nlohmann::json(v); }

inline nlohmann::json scores_json(const std::string& name, const ObjectScores& s) {
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

inline nlohmann::json refine_json(const EvalRefineInfo& r, const ObjectScores& refined, const ObjectScores& before) {
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
}  // namespace detail

// The report `flexsplat eval --json` writes: {model, refine_seconds, refine_steps, rotation_noise_deg, seed, resolution,
// self_attention, objects: [...], mean, baselines} (docs/app.md).
inline nlohmann::json eval_json(const std::string& model_path, const FlexSplatConfig& c, const EvalOptions& o,
                                const EvalExperiment& x, const std::vector<ObjectEval>& results) {
  const bool refined = x.refining();
  const std::vector<ObjectScores> rows = score_rows(results, &ObjectEval::model);
  const std::vector<ObjectScores> ff_rows = score_rows(results, &ObjectEval::feed_forward);
  nlohmann::json j;
  j["model"] = model_path;
  j["refine_seconds"] = x.refine_seconds;
  j["refine_steps"] = x.refine_steps;
  j["rotation_noise_deg"] = x.rotation_noise_deg;
  j["seed"] = x.seed;
  j["resolution"] = x.native ? "native" : "model";
  j["budget"] = x.auto_budget ? "auto" : "full";
  const auto& dc = c.appearance.decoder;
  j["self_attention"] = dc.local_attention ? "local:" + std::to_string(dc.window) : std::string("full");
  j["objects"] = nlohmann::json::array();
  for (std::size_t i = 0; i < rows.size(); ++i) {
    nlohmann::json obj = detail::scores_json(results[i].name, rows[i]);
    obj["resolution"] = {results[i].score_h, results[i].score_w};
    obj["budget"] = results[i].budget;
    obj["gaussians"] = results[i].gaussians;  // predicted, before refinement
    if (refined) {
      obj["feed_forward"] = detail::scores_json("", ff_rows[i]);
      obj["refine"] = detail::refine_json(results[i].refine, rows[i], ff_rows[i]);
    }
    j["objects"].push_back(obj);
  }
  j["mean"] = detail::scores_json("", mean_scores(rows));
  if (refined) {
    j["mean"]["feed_forward"] = detail::scores_json("", mean_scores(ff_rows));
    j["mean"]["psnr_change"] = detail::value_or_null(mean_scores(rows).psnr - mean_scores(ff_rows).psnr);
  }
  auto add_baseline = [&](const char* key, ObjectScores ObjectEval::*field) {
    const std::vector<ObjectScores> b_rows = score_rows(results, field);
    nlohmann::json b;
    b["objects"] = nlohmann::json::array();
    for (std::size_t i = 0; i < b_rows.size(); ++i) b["objects"].push_back(detail::scores_json(results[i].name, b_rows[i]));
    b["mean"] = detail::scores_json("", mean_scores(b_rows));
    j["baselines"][key] = b;
  };
  if (o.white_baseline) add_baseline("white", &ObjectEval::white);
  if (x.posed_fit) add_baseline("posed-fit", &ObjectEval::posed_fit);
  return j;
}

// The picture of a run: per object three rows, the input views the model saw (h x w, scaled up to the scoring size),
// its renders of the first targets (with refinement two rows: before and after) and their ground truth (at the
// scoring size).
inline void write_eval_grid(const std::filesystem::path& path, const std::vector<ObjectEval>& results, index_t h,
                            index_t w) {
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

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
