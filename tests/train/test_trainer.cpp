#include <catch2/catch.hpp>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <numeric>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/train/trainer.hpp"
#include "flexsplat/optim/distributed.hpp"
#include "temp_dir.hpp"

using namespace flexsplat;
namespace fs = std::filesystem;

namespace {
const char* recipe_text = R"({
  "model": "tiny", "seed": 11, "batch": 2, "inputs": [1, 3], "targets": 1, "gaussians": 48,
  "checkpoint_every": 2, "log_every": 1,
  "stages": [
    {"name": "geometry", "steps": 2, "lr": 0.001, "warmup": 1, "appearance": false, "camera_weight": 1.0, "depth_weight": 0.1},
    {"name": "joint", "steps": 2, "lr": 0.001, "objective": {"rgb_head": 1.0, "render": 1.0, "depth": 0.1, "lpips": 0.0}}
  ]
})";

// The tiny recipe, its data and a scratch folder: what every run_training case starts from.
struct TinyRecipe {
  const nlohmann::json recipe = nlohmann::json::parse(recipe_text);
  const model::TrainRunConfig cfg = model::parse_train_config(recipe);
  const model::TrainData data = model::train_data_from({"procedural"}, cfg);
  train::SoloCommunicator solo;
  flexsplat_test::TempDir dirs;
  explicit TinyRecipe(const std::string& folder) : dirs(folder) {}
};

}  // namespace

TEST_CASE("run_training resumes exactly and reports its steps", "[model][trainer]") {
  TinyRecipe t("trainer");
  auto& [recipe, cfg, data, solo, dirs] = t;

  model::TrainerOptions straight;
  straight.run = dirs.path / "straight";
  std::vector<std::uint64_t> steps;
  std::vector<std::string> notes;
  straight.progress = [&](const model::TrainerProgress& p) {
    steps.push_back(p.step);
    CHECK(*p.stage == (p.step <= 2 ? "geometry" : "joint"));
    CHECK(p.total == 4);
  };
  straight.note = [&](const std::string& s) { notes.push_back(s); };
  const model::TrainerResult a = model::run_training(recipe, data, solo, straight);
  CHECK(a.first_step == 0);
  CHECK(a.step == 4);
  CHECK(steps == std::vector<std::uint64_t>{1, 2, 3, 4});
  REQUIRE(notes.size() == 1);
  CHECK(notes[0].find("steps 0 -> 4 of 4") != std::string::npos);

  // Stopped after step 3 (a checkpoint is written at the stop), then resumed to the end.
  model::TrainerOptions parts;
  parts.run = dirs.path / "parts";
  parts.stop_at = 3;
  CHECK(model::run_training(recipe, data, solo, parts).step == 3);
  parts.stop_at = 0;
  const model::TrainerResult b = model::run_training(recipe, data, solo, parts);
  CHECK(b.first_step == 3);
  CHECK(b.step == 4);
  CHECK(flexsplat_test::file_bytes(straight.run / "model.safetensors") == flexsplat_test::file_bytes(parts.run / "model.safetensors"));
  CHECK(flexsplat_test::file_bytes(straight.run / "state.safetensors") == flexsplat_test::file_bytes(parts.run / "state.safetensors"));
  for (const char* f : {"config.json", "log.jsonl", "curves.png"}) CHECK(fs::exists(parts.run / f));

  // A folder holding another recipe's run is refused before any compute.
  nlohmann::json other = recipe;
  other["seed"] = 12;
  CHECK_THROWS_WITH(model::run_training(other, data, solo, parts), Catch::Contains("holds a run with a different config"));
  CHECK_THROWS_WITH(model::train_data_from({}, cfg), Catch::Contains("no training data"));
  // The recipe's procedural family reaches the generator (training and validation scenes).
  model::TrainRunConfig organic = cfg;
  organic.procedural.blob_fraction = 0.25f;
  organic.procedural.attached = true;
  const model::TrainData organic_data = model::train_data_from({"procedural"}, organic);
  CHECK(organic_data.generator.object.blob_fraction == 0.25f);
  CHECK(organic_data.generator.object.attached);
}

TEST_CASE("train_scene_plan spreads a step's scenes over the ranks by their view counts", "[model][trainer]") {
  nlohmann::json recipe = nlohmann::json::parse(recipe_text);
  recipe["batch"] = 4, recipe["inputs"] = nlohmann::json::parse("[1, 3]");
  const model::TrainRunConfig cfg = model::parse_train_config(recipe);
  index_t uneven_contiguous = 0;
  for (std::uint64_t step = 0; step < 64; ++step) {
    std::vector<index_t> views;
    for (index_t s = 0; s < 4; ++s) views.push_back(model::scene_view_count(cfg, step, s));
    CHECK(model::train_scene_plan(cfg, step, 1).owner == std::vector<int>(4, 0));
    const train::ScenePlan p = model::train_scene_plan(cfg, step, 2);
    // The plan by hand (balanced_plan's rule): scenes by view count, most first (ties in scene order); the first to
    // rank 0, the second to rank 1, the third to the less loaded rank (ties: rank 0), the last to the rank with room.
    std::vector<std::size_t> by(4);
    std::iota(by.begin(), by.end(), std::size_t(0));
    std::stable_sort(by.begin(), by.end(), [&](std::size_t a, std::size_t b) { return views[a] > views[b]; });
    std::vector<int> expect(4, -1);
    expect[by[0]] = 0, expect[by[1]] = 1;
    expect[by[2]] = views[by[1]] < views[by[0]] ? 1 : 0;
    expect[by[3]] = 1 - expect[by[2]];
    CHECK(p.owner == expect);
    index_t load[2] = {0, 0}, count[2] = {0, 0};
    for (std::size_t s = 0; s < 4; ++s) load[p.owner[s]] += views[s], ++count[p.owner[s]];
    CHECK(count[0] == 2);
    CHECK(count[1] == 2);
    const index_t total = load[0] + load[1], pair = views[0] + views[1];
    // No better split into pairs exists; the contiguous one is often worse.
    for (std::size_t partner = 1; partner < 4; ++partner) {
      const index_t with = views[0] + views[partner];
      CHECK(std::max(load[0], load[1]) <= std::max(with, total - with));
    }
    if (std::max(pair, total - pair) > std::max(load[0], load[1])) ++uneven_contiguous;
  }
  CHECK(uneven_contiguous > 8);
}

TEST_CASE("run_training starts a fresh run from a model of another image size", "[model][trainer]") {
  TinyRecipe t("trainer_init");
  auto& [recipe, cfg, data, solo, dirs] = t;
  model::FlexSplatConfig smaller = cfg.model;
  smaller.image_h = smaller.image_w = 2 * smaller.geometry.aggregator.patch_size;
  REQUIRE(smaller.image_h != cfg.model.image_h);
  auto start = model::FlexSplatWeights<float>::create(smaller, false);
  start->init(5);
  start->save(dirs.path / "start.safetensors");

  model::TrainerOptions o;
  o.run = dirs.path / "fine";
  o.init = dirs.path / "start.safetensors";
  o.stop_at = 1;
  std::vector<std::string> notes;
  o.note = [&](const std::string& s) { notes.push_back(s); };
  CHECK(model::run_training(recipe, data, solo, o).step == 1);
  CHECK(std::any_of(notes.begin(), notes.end(),
                    [](const std::string& s) { return s.find("every weight initialised from") != std::string::npos; }));

  model::FlexSplatConfig other = smaller;
  other.gaussians += 16;
  auto different = model::FlexSplatWeights<float>::create(other, false);
  different->init(5);
  different->save(dirs.path / "other.safetensors");
  o.run = dirs.path / "refused";
  o.init = dirs.path / "other.safetensors";
  CHECK_THROWS_WITH(model::run_training(recipe, data, solo, o), Catch::Contains("has another architecture"));
}
