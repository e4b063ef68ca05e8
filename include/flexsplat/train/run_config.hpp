#pragma once
// The configuration of a `flexsplat train` run from its JSON file: model ("tiny", "paper" or a FlexSplat config
// object), seed, global batch, views per scene, Gaussians, clipping, LPIPS weights, checkpoint/log periods and the
// stages (steps, learning rate, warmup, losses). Every key is checked before any compute; unknown keys are errors.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/error.hpp"
#include "flexsplat/data/procedural.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/optim/optimizer.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct TrainStage {
  std::string name;
  std::uint64_t steps = 1;
  double lr = 1e-3;
  std::uint64_t warmup = 0;
  model::StepConfig step;
};

// Held-out scoring during a run: procedural scenes from a seed stream the training batches never draw, and object
// folders (the layout of make-data and ../shared/data/objects) viewed whole at the model's size.
struct ValidationConfig {
  std::uint64_t every = 0;  // steps between validations; 0: none
  int scenes = 8;           // held-out procedural scenes
  int targets = 4;          // target views per scene
  std::vector<std::string> objects;

  bool enabled() const { return every > 0; }
};

// Where a global step is in a recipe: its stage and learning rate.
struct StepSchedule {
  std::size_t stage = 0;
  double lr = 0;
};

struct TrainRunConfig {
  model::FlexSplatConfig model;
  std::uint64_t seed = 0;
  index_t batch = 4;
  int inputs_min = 2, inputs_max = 4, targets = 2;
  // 4-view procedural scenes (training and validation) are the fixed evaluation rig; false: random orbit views in
  // random order for every scene, so that input order carries no pose.
  bool structured_inputs = true;
  index_t match_samples = model::match_samples;  // ground-truth correspondences per training scene (match head)
  // Procedural views' baseline (data::OrbitRanges::max_baseline_deg) grows linearly from baseline_deg[0] at step 0 to
  // baseline_deg[1] at baseline_steps, then stays; baseline_steps 0: no curriculum (independent views).
  std::array<double, 2> baseline_deg{0, 0};
  std::uint64_t baseline_steps = 0;
  double baseline_at(std::uint64_t step) const {
    if (baseline_steps == 0) return 0;
    const double f = std::min(1.0, static_cast<double>(step) / static_cast<double>(baseline_steps));
    return baseline_deg[0] + f * (baseline_deg[1] - baseline_deg[0]);
  }
  data::ObjectConfig procedural;  // the procedural objects' family (defaults: the loose unions of earlier recipes)
  index_t gaussians = 0;  // 0: tied to the view count (the model's budget)
  double max_grad_norm = 1.0;
  std::string lpips_weights;
  std::vector<TrainStage> stages;
  std::uint64_t checkpoint_every = 100, log_every = 10;
  ValidationConfig validation;

  std::uint64_t total_steps() const {
    std::uint64_t n = 0;
    for (const auto& s : stages) n += s.steps;
    return n;
  }
  // The stage running global step `step` and the step at which it started.
  std::size_t stage_at(std::uint64_t step, std::uint64_t& start) const {
    start = 0;
    for (std::size_t i = 0; i < stages.size(); ++i) {
      if (step < start + stages[i].steps || i + 1 == stages.size()) return i;
      start += stages[i].steps;
    }
    return 0;
  }
  // The stage of global step `step` and its learning rate (the stage's cosine schedule after its warm-up).
  StepSchedule schedule_at(std::uint64_t step) const {
    std::uint64_t start = 0;
    const std::size_t i = stage_at(step, start);
    return {i, train::CosineSchedule{stages[i].lr, 0.0, stages[i].warmup, stages[i].steps}.lr(step - start)};
  }
};

namespace detail {

// Reads one JSON object's keys with a path for error messages; unknown keys are errors.
class Keys {
public:
  Keys(const nlohmann::json& j, std::string where) : j_(j), where_(std::move(where)) {
    require(j.is_object(), "train config: ", where_.empty() ? "the file" : "'" + where_ + "'", " must be a JSON object");
  }
  std::string path(const std::string& key) const { return where_.empty() ? key : where_ + "." + key; }
  const nlohmann::json* find(const std::string& key) {
    seen_.insert(key);
    const auto it = j_.find(key);
    return it == j_.end() ? nullptr : &*it;
  }
  double number(const std::string& key, double fallback, double lo, double hi) {
    const nlohmann::json* v = find(key);
    if (!v) return fallback;
    require(v->is_number() && std::isfinite(v->get<double>()) && v->get<double>() >= lo && v->get<double>() <= hi,
            "train config: '", path(key), "' is ", v->dump(), ", expected a number in [", lo, ", ", hi, "]");
    return v->get<double>();
  }
  std::uint64_t integer(const std::string& key, std::uint64_t fallback, std::uint64_t lo, std::uint64_t hi) {
    const nlohmann::json* v = find(key);
    if (!v) return fallback;
    // A JSON built in C++ holds 12 as a signed integer, a parsed file as unsigned: both are the same count.
    const bool count = v->is_number_unsigned() || (v->is_number_integer() && v->get<std::int64_t>() >= 0);
    require(count && v->get<std::uint64_t>() >= lo && v->get<std::uint64_t>() <= hi, "train config: '",
            path(key), "' is ", v->dump(), ", expected an integer in [", lo, ", ", hi, "]");
    return v->get<std::uint64_t>();
  }
  bool boolean(const std::string& key, bool fallback) {
    const nlohmann::json* v = find(key);
    if (!v) return fallback;
    require(v->is_boolean(), "train config: '", path(key), "' is ", v->dump(), ", expected true or false");
    return v->get<bool>();
  }
  std::string string(const std::string& key, const std::string& fallback) {
    const nlohmann::json* v = find(key);
    if (!v) return fallback;
    require(v->is_string(), "train config: '", path(key), "' is ", v->dump(), ", expected a string");
    return v->get<std::string>();
  }
  void finish() const {
    for (const auto& [key, value] : j_.items())
      require(seen_.count(key), "train config: unknown key '", path(key), "'");
  }

private:
  const nlohmann::json& j_;
  std::string where_;
  std::set<std::string> seen_;
};

inline TrainStage parse_stage(const nlohmann::json& j, const std::string& where) {
  Keys k(j, where);
  TrainStage s;
  s.name = k.string("name", where);
  s.steps = k.integer("steps", 100, 1, 1000000000);
  s.lr = k.number("lr", 1e-3, 0, 10);
  s.warmup = k.integer("warmup", 0, 0, s.steps);
  s.step.appearance = k.boolean("appearance", true);
  s.step.train_geometry = k.boolean("train_geometry", true);
  s.step.decoder_true_cameras = k.boolean("decoder_true_cameras", false);
  s.step.camera_weight = k.number("camera_weight", 0.0, 0, 1e6);
  s.step.relative_camera_weight = k.number("relative_camera_weight", 0.0, 0, 1e6);
  s.step.depth_weight = k.number("depth_weight", 0.0, 0, 1e6);
  s.step.depth_shape_weight = k.number("depth_shape_weight", 0.0, 0, 1e6);
  s.step.point_weight = k.number("point_weight", 0.0, 0, 1e6);
  s.step.match_weight = k.number("match_weight", 0.0, 0, 1e6);
  if (const nlohmann::json* o = k.find("objective")) {
    Keys ok(*o, k.path("objective"));
    auto& w = s.step.objective;
    w.rgb_head = ok.number("rgb_head", w.rgb_head, 0, 1e6);
    w.render = ok.number("render", w.render, 0, 1e6);
    w.depth = ok.number("depth", w.depth, 0, 1e6);
    w.lpips = ok.number("lpips", w.lpips, 0, 1e6);
    ok.finish();
  }
  k.finish();
  require(s.step.appearance || s.step.camera_weight > 0 || s.step.relative_camera_weight > 0 || s.step.depth_weight > 0 ||
              s.step.depth_shape_weight > 0 || s.step.point_weight > 0 || s.step.match_weight > 0,
          "train config: '", where,
          "' has no loss (appearance is false and camera_weight, relative_camera_weight, depth_weight, depth_shape_weight, "
          "point_weight and match_weight are 0)");
  require(s.step.train_geometry || s.step.appearance, "train config: '", where,
          "' trains nothing (train_geometry and appearance are both false)");
  return s;
}

}  // namespace detail

// Checks every key and value before anything is computed; the error names the key path and the value.
inline TrainRunConfig parse_train_config(const nlohmann::json& j) {
  detail::Keys k(j, "");
  TrainRunConfig c;
  if (const nlohmann::json* m = k.find("model")) {
    if (m->is_string() && *m == "tiny") c.model = model::flexsplat_tiny_config();
    else if (m->is_string() && *m == "paper") c.model = model::flexsplat_paper_config();
    else {
      require(m->is_object(), "train config: 'model' is ", m->dump(), ", expected \"tiny\", \"paper\" or a FlexSplat config object");
      c.model = model::flexsplat_config_from_json(m->dump());
    }
  } else {
    c.model = model::flexsplat_tiny_config();
  }
  require(c.model.image_h == c.model.image_w, "train config: 'model' is ", c.model.image_w, " x ", c.model.image_h,
          "; training data is square, so image_h must equal image_w");
  c.seed = k.integer("seed", 0, 0, UINT64_MAX);
  c.batch = static_cast<index_t>(k.integer("batch", 4, 1, 1000000));
  const index_t max_views = c.model.appearance.decoder.max_views;
  if (const nlohmann::json* in = k.find("inputs")) {
    require(in->is_array() && in->size() == 2 && (*in)[0].is_number_unsigned() && (*in)[1].is_number_unsigned(),
            "train config: 'inputs' is ", in->dump(), ", expected [min, max] view counts");
    c.inputs_min = static_cast<int>(std::min<std::uint64_t>((*in)[0].get<std::uint64_t>(), 1 << 20));
    c.inputs_max = static_cast<int>(std::min<std::uint64_t>((*in)[1].get<std::uint64_t>(), 1 << 20));
  } else {
    c.inputs_min = static_cast<int>(std::min<index_t>(2, max_views)), c.inputs_max = static_cast<int>(max_views);
  }
  require(c.inputs_min >= 1 && c.inputs_min <= c.inputs_max && c.inputs_max <= max_views, "train config: 'inputs' is [",
          c.inputs_min, ", ", c.inputs_max, "], expected 1 <= min <= max <= ", max_views,
          " (the decoder's max_views)");
  c.targets = static_cast<int>(k.integer("targets", 2, 0, 64));
  c.structured_inputs = k.boolean("structured_inputs", true);
  c.match_samples = static_cast<index_t>(k.integer("match_samples", static_cast<std::uint64_t>(model::match_samples), 1, 1000000));
  if (const nlohmann::json* cu = k.find("curriculum")) {
    detail::Keys ck(*cu, "curriculum");
    c.baseline_steps = ck.integer("steps", 0, 1, UINT64_MAX);
    if (const nlohmann::json* b = ck.find("baseline_deg")) {
      require(b->is_array() && b->size() == 2 && (*b)[0].is_number() && (*b)[1].is_number(), "train config: ",
              "'curriculum.baseline_deg' is ", b->dump(), ", expected [start, end] in degrees");
      c.baseline_deg = {(*b)[0].get<double>(), (*b)[1].get<double>()};
    }
    ck.finish();
    require(c.baseline_steps > 0, "train config: 'curriculum' needs 'steps' (the step at which the baseline reaches its end)");
    for (double d : c.baseline_deg)
      require(d > 0 && d <= 360, "train config: 'curriculum.baseline_deg' entry ", d, " must be in (0, 360]");
    require(!c.structured_inputs, "train config: 'curriculum' needs structured_inputs false (the rig has fixed views)");
  }
  if (const nlohmann::json* pr = k.find("procedural")) {
    detail::Keys pk(*pr, "procedural");
    data::ObjectConfig& o = c.procedural;
    o.min_primitives = static_cast<int>(pk.integer("min_primitives", static_cast<std::uint64_t>(o.min_primitives), 1, 64));
    o.max_primitives = static_cast<int>(pk.integer("max_primitives", static_cast<std::uint64_t>(o.max_primitives), 1, 64));
    o.blob_fraction = static_cast<float>(pk.number("blob_fraction", o.blob_fraction, 0, 1));
    o.attached = pk.boolean("attached", o.attached);
    o.soft_textures = pk.boolean("soft_textures", o.soft_textures);
    pk.finish();
    require(o.min_primitives <= o.max_primitives, "train config: 'procedural.min_primitives' ", o.min_primitives,
            " exceeds 'procedural.max_primitives' ", o.max_primitives);
  }
  c.gaussians = static_cast<index_t>(k.integer("gaussians", 0, 0, 100000000));
  c.max_grad_norm = k.number("max_grad_norm", 1.0, 0, 1e12);
  c.lpips_weights = k.string("lpips_weights", "");
  c.checkpoint_every = k.integer("checkpoint_every", 100, 1, UINT64_MAX);
  c.log_every = k.integer("log_every", 10, 1, UINT64_MAX);
  if (const nlohmann::json* v = k.find("validation")) {
    detail::Keys vk(*v, "validation");
    c.validation.every = vk.integer("every", 0, 0, UINT64_MAX);
    c.validation.scenes = static_cast<int>(vk.integer("scenes", 8, 0, 100000));
    c.validation.targets = static_cast<int>(vk.integer("targets", 4, 1, 64));
    if (const nlohmann::json* o = vk.find("objects")) {
      require(o->is_array(), "train config: 'validation.objects' is ", o->dump().substr(0, 80),
              ", expected an array of object folder paths");
      for (std::size_t i = 0; i < o->size(); ++i) {
        require((*o)[i].is_string(), "train config: 'validation.objects[", i, "]' is ", (*o)[i].dump().substr(0, 80),
                ", expected a folder path");
        c.validation.objects.push_back((*o)[i].get<std::string>());
      }
    }
    vk.finish();
    require(!c.validation.enabled() || c.validation.scenes > 0 || !c.validation.objects.empty(),
            "train config: 'validation.every' is ", c.validation.every, " but there is nothing to validate on (scenes 0, no objects)");
  }
  if (const nlohmann::json* st = k.find("stages")) {
    require(st->is_array() && !st->empty(), "train config: 'stages' is ", st->dump().substr(0, 80),
            ", expected a non-empty array of stage objects");
    for (std::size_t i = 0; i < st->size(); ++i) c.stages.push_back(detail::parse_stage((*st)[i], concat("stages[", i, "]")));
  } else {
    c.stages.push_back(detail::parse_stage(nlohmann::json::object(), "stages[0]"));
  }
  k.finish();
  for (auto& s : c.stages) {
    require(s.step.point_weight == 0 || c.model.geometry.point_head, "train config: stage '", s.name, "' has point_weight ",
            s.step.point_weight, " but the model has no point head (model.geometry.point_head)");
    require(s.step.match_weight == 0 || c.model.geometry.match_dim > 0, "train config: stage '", s.name,
            "' has match_weight ", s.step.match_weight, " but the model has no match head (model.geometry.match_dim)");
    s.step.gaussians = c.gaussians;
    s.step.max_grad_norm = c.max_grad_norm;
    if (s.step.objective.lpips > 0)
      require(!c.lpips_weights.empty(), "train config: stage '", s.name,
              "' has objective.lpips > 0 but 'lpips_weights' (an LPIPS safetensors file) is not set");
  }
  if (!c.lpips_weights.empty())
    require(std::filesystem::is_regular_file(c.lpips_weights), "train config: 'lpips_weights' file '", c.lpips_weights, "' does not exist");
  return c;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
