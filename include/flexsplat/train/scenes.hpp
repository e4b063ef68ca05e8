#pragma once
// The scenes of a training run: which views each scene of a step has and where they come from (procedural objects
// made in process, or object folders), as pure functions of (seed, step, scene) so that resumed and multi-rank runs
// draw the same scenes. `flexsplat train` and bench/train_step share them.
#include <cstdint>
#include <span>
#include <vector>

#include "flexsplat/core/profile.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/train/run_config.hpp"
#include "flexsplat/optim/distributed.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

struct TrainData {
  bool procedural = true;
  data::GeneratorConfig generator;
  std::vector<data::ObjectRecord> objects;
};

// The input view count of scene `scene` of step `step`, in [inputs_min, inputs_max].
inline int scene_view_count(const model::TrainRunConfig& c, std::uint64_t step, index_t scene) {
  std::uint64_t x = c.seed ^ (step * 0x9E3779B97F4A7C15ull) ^ (static_cast<std::uint64_t>(scene) * 0xD1B54A32D192ED03ull);
  x ^= x >> 31, x *= 0xBF58476D1CE4E5B9ull, x ^= x >> 27, x *= 0x94D049BB133111EBull, x ^= x >> 31;
  return c.inputs_min + static_cast<int>(x % static_cast<std::uint64_t>(c.inputs_max - c.inputs_min + 1));
}

inline TrainExample<float> make_train_scene(const TrainData& d, const model::TrainRunConfig& c, std::uint64_t step,
                                            index_t scene) {
  const profile::Scope timed(profile::Op::data);
  data::BatchOptions o;
  o.inputs = scene_view_count(c, step, scene);
  o.targets = c.targets;
  o.structured_inputs = c.structured_inputs;
  const std::uint64_t index = step * static_cast<std::uint64_t>(c.batch) + static_cast<std::uint64_t>(scene);
  std::vector<data::SceneSample> s;
  if (d.procedural) {
    data::GeneratorConfig g = d.generator;
    g.orbit.max_baseline_deg = c.baseline_at(step);
    s = data::generate_batch(g, 1, c.seed, index, o);
  } else {
    o.crop = static_cast<int>(c.model.image_h);
    s = data::sample_batch(d.objects, 1, c.seed, index, o);
  }
  return make_train_example<float>(s[0], c.model, c.match_samples);
}

// Scenes `scenes` (global indices) of step `step`, made side by side as train_step runs them (run_scenes).
inline std::vector<TrainExample<float>> make_train_scenes(const TrainData& d, const model::TrainRunConfig& c,
                                                          std::uint64_t step, std::span<const index_t> scenes) {
  std::vector<TrainExample<float>> out(scenes.size());
  auto one = [&](index_t i, int) {
    out[static_cast<std::size_t>(i)] = make_train_scene(d, c, step, scenes[static_cast<std::size_t>(i)]);
  };
  run_scenes(static_cast<index_t>(scenes.size()), one);
  return out;
}

// Which rank makes and computes each scene of step `step`: balanced by input view count (every scene of a step
// renders the same targets), known before any scene is made.
inline train::ScenePlan train_scene_plan(const model::TrainRunConfig& c, std::uint64_t step, int ranks) {
  std::vector<index_t> views(static_cast<std::size_t>(c.batch));
  for (index_t s = 0; s < c.batch; ++s) views[static_cast<std::size_t>(s)] = scene_view_count(c, step, s);
  return train::balanced_plan(views, ranks);
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
