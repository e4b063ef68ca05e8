#pragma once
// The training run behind `flexsplat train`, as a library call: a run folder (config.json, log.jsonl,
// state.safetensors, model.safetensors, curves.png, validation.png), exact resume from its last checkpoint, the
// recipe's stages and learning rates, held-out validation, data parallel over any train::Communicator (the global
// batch split over ranks, every rank's result bit-identical to one process's). Usage:
//   const nlohmann::json recipe = nlohmann::json::parse(text);
//   const model::TrainRunConfig cfg = model::parse_train_config(recipe);
//   const model::TrainData data = model::train_data_from({"procedural"}, cfg);
//   train::SoloCommunicator comm;                        // or train::MpiCommunicator under mpirun
//   model::TrainerOptions o;  o.run = "runs/a";  o.stop_at = 1000;
//   model::TrainerResult r = model::run_training(recipe, data, comm, o);   // rerun: resumes where it stopped
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <ctime>
#include <deque>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/core/atomic_file.hpp"
#include "flexsplat/core/error.hpp"
#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"
#include "flexsplat/io/safetensors.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/train/run_config.hpp"
#include "flexsplat/train/step.hpp"
#include "flexsplat/train/scenes.hpp"
#include "flexsplat/train/validate.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/optim/checkpoint.hpp"
#include "flexsplat/optim/distributed.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

namespace trainer_detail {
inline std::string read_text(const std::filesystem::path& p) {
  std::ifstream f(p, std::ios::binary);
  require(f.good(), "train: cannot read '", p.string(), "'");
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}
}  // namespace trainer_detail

// A recipe file's JSON (run_training and parse_train_config take it); errors name the file.
inline nlohmann::json read_train_recipe(const std::filesystem::path& path) {
  const std::string text = trainer_detail::read_text(path);
  try {
    return nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    fail("train config '", path.string(), "' is not valid JSON: ", e.what());
  }
}

// The training scenes of `sources`: {"procedural"} (scenes generated at the model's size) or object folders, each
// with enough views for the recipe's inputs and targets.
inline TrainData train_data_from(const std::vector<std::string>& sources, const TrainRunConfig& cfg) {
  require(!sources.empty(), "train: no training data (procedural or object folders)");
  TrainData data;
  data.generator.object = cfg.procedural;  // also the validation's procedural scenes
  if (sources.size() == 1 && sources[0] == "procedural") {
    data.generator.size = static_cast<int>(cfg.model.image_h);
    data::check_generator(data.generator);
    return data;
  }
  data.procedural = false;
  data.objects = data::load_objects(std::vector<std::filesystem::path>(sources.begin(), sources.end()));
  for (const auto& o : data.objects)
    require(static_cast<int>(o.frames.size()) >= cfg.inputs_max + cfg.targets, "train: object '", o.name, "' has ",
            o.frames.size(), " views, the config needs up to ", cfg.inputs_max, " inputs + ", cfg.targets, " targets");
  return data;
}

// Held-out scenes, built once: procedural scenes from another seed, and each object folder viewed whole.
struct ValidationSet {
  std::string name;
  std::vector<std::string> scene_names;
  std::vector<TrainExample<float>> scenes;
};

inline std::vector<ValidationSet> make_validation_sets(const TrainData& d, const TrainRunConfig& c) {
  std::vector<ValidationSet> sets;
  const auto& v = c.validation;
  data::BatchOptions o;
  o.inputs = std::min(4, c.inputs_max);
  o.targets = v.targets;
  o.structured_inputs = c.structured_inputs;
  // Under a curriculum, also the first step's small baselines: where learning shows first.
  for (const double baseline : c.baseline_steps > 0 ? std::vector<double>{0.0, c.baseline_deg[0]} : std::vector<double>{0.0}) {
    if (v.scenes == 0) break;
    ValidationSet set{baseline > 0 ? "procedural-near" : "procedural", {}, {}};
    data::GeneratorConfig g = d.generator;
    g.size = static_cast<int>(c.model.image_h);
    g.orbit.max_baseline_deg = baseline;
    const std::uint64_t seed = data::child_seed(c.seed, 0x76616c6964ull);  // never a training batch's seed
    for (const auto& s : data::generate_batch(g, v.scenes, seed, 0, o)) {
      set.scene_names.push_back(s.name);
      set.scenes.push_back(make_train_example<float>(s, c.model));
    }
    sets.push_back(std::move(set));
  }
  if (!v.objects.empty()) {
    ValidationSet set{"objects", {}, {}};
    for (const auto& rec : data::load_objects(std::vector<std::filesystem::path>(v.objects.begin(), v.objects.end()))) {
      require(rec.width == rec.height, "train: validation object '", rec.name, "' is ", rec.width, " x ", rec.height,
              "; validation views are whole square images");
      data::BatchOptions oo = o;
      oo.crop = static_cast<int>(c.model.image_h);
      oo.scale_min = oo.scale_max = static_cast<double>(c.model.image_h) / static_cast<double>(rec.width);
      // Off the rig, two draws of random views per object.
      for (std::uint64_t draw = 0; draw < (c.structured_inputs ? 1u : 2u); ++draw) {
        const auto s = data::sample_batch({rec}, 1, c.seed, draw, oo);
        set.scene_names.push_back(rec.name);
        set.scenes.push_back(make_train_example<float>(s[0], c.model));
      }
    }
    sets.push_back(std::move(set));
  }
  return sets;
}

// Scores every set (the means of validate_scene's scores, one JSON object per set) and draws `picture`: per scene
// its inputs, then targets and renders. true_cameras: also psnr_true_cameras / ssim_true_cameras, the decoder given
// the ground-truth cameras (a decoder_true_cameras stage), whose renders the picture then shows.
inline nlohmann::json validate_sets(const std::vector<ValidationSet>& sets, const FlexSplatWeights<float>& w,
                                    const std::filesystem::path& picture, bool true_cameras = false) {
  std::vector<ValidationWorkspace<float>> ws(static_cast<std::size_t>(global_pool().size()));
  nlohmann::json result = nlohmann::json::object();
  std::deque<Tensor<float, 3>> keep;  // owns the renders the grid cells point at (a deque never moves them)
  std::vector<image::GridCell> cells;
  const int inputs_shown = 4, targets_shown = 2, cols = inputs_shown + 2 * targets_shown;
  for (const auto& set : sets) {
    double psnr = 0, ssim = 0, rot = 0, depth = 0, depth_shape = 0, rra15 = 0, rra30 = 0, prot = 0, prra15 = 0, prra30 = 0, chance = 0, mrot = 0,
           mrra15 = 0, mrra30 = 0, macc = 0, mgt = 0, morc = 0, morc15 = 0, macc4 = 0, hrot = 0, hrra30 = 0, tpsnr = 0, tssim = 0;
    std::array<double, 4> bin_hits{}, bin_count{}, bin_pairs{}, bin_pairs15{};
    // Scored side by side as training scenes run (run_scenes), summed below in scene order.
    const index_t count = static_cast<index_t>(set.scenes.size());
    std::vector<ValidationScore> scores(set.scenes.size());
    std::vector<std::vector<Tensor<float, 3>>> scene_renders(set.scenes.size());
    auto score = [&](index_t i, int worker) {
      const auto k = static_cast<std::size_t>(i);
      scores[k] = validate_scene(ws[static_cast<std::size_t>(worker)], w, set.scenes[k], &scene_renders[k], true_cameras);
    };
    run_scenes(count, score);
    for (std::size_t i = 0; i < set.scenes.size(); ++i) {
      const auto& e = set.scenes[i];
      const std::vector<Tensor<float, 3>>& renders = scene_renders[i];
      const ValidationScore& s = scores[i];
      psnr += s.psnr, ssim += s.ssim, rot += s.rotation_deg, depth += s.depth_rel, depth_shape += s.depth_shape_rel, rra15 += s.rra15, rra30 += s.rra30;
      prot += s.points_rotation_deg, prra15 += s.points_rra15, prra30 += s.points_rra30, chance += s.chance_rotation_deg;
      mrot += s.matches_rotation_deg, mrra15 += s.matches_rra15, mrra30 += s.matches_rra30;
      hrot += s.head_rotation_deg, hrra30 += s.head_rra30;
      if (true_cameras) tpsnr += s.psnr_true_cameras, tssim += s.ssim_true_cameras;
      macc += s.match_accuracy, mgt += s.matches_gt_depth_rotation_deg;
      morc += s.matches_oracle_rotation_deg, morc15 += s.matches_oracle_rra15, macc4 += s.match_accuracy_4px;
      for (std::size_t b = 0; b < bin_hits.size(); ++b) bin_hits[b] += s.match_hits_by_baseline[b], bin_count[b] += s.matches_by_baseline[b],
        bin_pairs[b] += s.pairs_by_baseline[b], bin_pairs15[b] += s.pairs_within15_by_baseline[b];
      if (i >= 4) continue;
      const Shape<3> shape{e.h, e.w, 3};
      for (int v = 0; v < inputs_shown; ++v)
        cells.push_back(v < e.views ? image::GridCell{TensorView<const float, 3>(e.inputs_hwc.data() + v * e.h * e.w * 3, shape),
                                                      v == 0 ? set.name.substr(0, 4) + " " + set.scene_names[i] : "input"}
                                    : image::GridCell{TensorView<const float, 3>(), ""});
      for (int t = 0; t < targets_shown; ++t) {
        if (t >= e.targets) {
          cells.push_back({TensorView<const float, 3>(), ""}), cells.push_back({TensorView<const float, 3>(), ""});
          continue;
        }
        keep.push_back(renders[static_cast<std::size_t>(t)]);
        cells.push_back({TensorView<const float, 3>(e.target_images.data() + t * e.h * e.w * 3, shape), "target"});
        cells.push_back({TensorView<const float, 3>(keep.back().view()), "render"});
      }
    }
    const double n = static_cast<double>(std::max<std::size_t>(set.scenes.size(), 1));
    result[set.name] = {{"psnr", psnr / n}, {"ssim", ssim / n}, {"rotation_deg", rot / n}, {"depth_rel", depth / n},
                        {"depth_shape_rel", depth_shape / n},
                        {"rra15", rra15 / n}, {"rra30", rra30 / n}, {"chance_rotation_deg", chance / n},
                        {"head_rotation_deg", hrot / n}, {"head_rra30", hrra30 / n}};
    if (true_cameras) result[set.name].update({{"psnr_true_cameras", tpsnr / n}, {"ssim_true_cameras", tssim / n}});
    if (w.config().geometry.point_head)
      result[set.name].update({{"points_rotation_deg", prot / n}, {"points_rra15", prra15 / n}, {"points_rra30", prra30 / n}});
    if (w.config().geometry.match_dim > 0)
      result[set.name].update({{"matches_rotation_deg", mrot / n}, {"matches_rra15", mrra15 / n}, {"matches_rra30", mrra30 / n},
                               {"match_accuracy", macc / n}, {"match_accuracy_4px", macc4 / n}, {"matches_gt_depth_rotation_deg", mgt / n},
                               {"matches_oracle_rotation_deg", morc / n}, {"matches_oracle_rra15", morc15 / n}});
    // By the pair's true baseline (absent when the set has no pair in the bin): match_accuracy over the bin's
    // correspondences, the number of view pairs and the fraction whose own fit is within 15 degrees.
    for (std::size_t b = 0; w.config().geometry.match_dim > 0 && b < bin_hits.size(); ++b) {
      const std::string bin = std::to_string(static_cast<int>(match_baseline_edges_deg[b])) + "_" +
                              std::to_string(static_cast<int>(match_baseline_edges_deg[b + 1]));
      if (bin_count[b] > 0) result[set.name]["match_accuracy_" + bin] = bin_hits[b] / bin_count[b];
      if (bin_pairs[b] > 0)
        result[set.name]["pairs_" + bin] = bin_pairs[b], result[set.name]["pairs_gt_depth_rra15_" + bin] = bin_pairs15[b] / bin_pairs[b];
    }
  }
  if (!cells.empty()) image::write_png(picture, image::image_grid(cells, cols, 112));
  return result;
}

// `picture` from a run's log.jsonl: training loss terms, PSNR and validation camera error against the step.
inline void write_training_curves(const std::filesystem::path& log_path, const std::filesystem::path& picture) {
  std::map<std::string, image::PlotSeries> loss, psnr, rot;
  const image::Rgb8 palette[] = {{31, 119, 180}, {214, 39, 40}, {44, 160, 44}, {148, 103, 189}, {255, 127, 14}, {23, 190, 207}};
  auto add = [&](std::map<std::string, image::PlotSeries>& m, const std::string& name, double x, double y) {
    auto it = m.find(name);
    if (it == m.end()) it = m.emplace(name, image::PlotSeries{name, {}, {}, palette[m.size() % 6]}).first;
    it->second.x.push_back(x), it->second.y.push_back(y);
  };
  std::istringstream lines(trainer_detail::read_text(log_path));
  for (std::string line; std::getline(lines, line);) {
    nlohmann::json j;
    try {
      j = nlohmann::json::parse(line);
    } catch (const nlohmann::json::exception&) {
      continue;
    }
    if (!j.contains("step")) continue;
    const double step = j["step"].get<double>();
    if (j.contains("validation")) {
      for (const auto& [set, v] : j["validation"].items()) {
        add(psnr, "val " + set, step, v.value("psnr", 0.0));
        if (v.contains("psnr_true_cameras")) add(psnr, "val " + set + " (true cameras)", step, v.value("psnr_true_cameras", 0.0));
        add(rot, "val " + set, step, v.value("rotation_deg", 0.0));
        if (v.contains("points_rotation_deg")) add(rot, "val " + set + " (points)", step, v.value("points_rotation_deg", 0.0));
        if (v.contains("matches_rotation_deg")) add(rot, "val " + set + " (matches)", step, v.value("matches_rotation_deg", 0.0));
      }
      continue;
    }
    add(loss, "total", step, j.value("loss", 0.0));
    for (const char* k : {"render", "camera", "depth", "depth_shape", "points", "match", "rgb_head"})
      if (j.value(k, 0.0) > 0) add(loss, k, step, j.value(k, 0.0));
    if (j.value("psnr", 0.0) > 0) add(psnr, "train", step, j.value("psnr", 0.0));
  }
  auto values = [](const std::map<std::string, image::PlotSeries>& m) {
    std::vector<image::PlotSeries> v;
    for (const auto& [k, s] : m) v.push_back(s);
    return v;
  };
  std::vector<Tensor<std::uint8_t, 3>> panels;
  image::PlotOptions o;
  o.width = 900, o.height = 320, o.x_label = "step";
  o.title = "training loss", o.log_y = true;
  panels.push_back(image::plot_lines(values(loss), o));
  o.title = "psnr (db) of the last decoder layer", o.log_y = false;
  panels.push_back(image::plot_lines(values(psnr), o));
  if (!rot.empty()) {
    o.title = "validation: rotation error of predicted cameras (deg)";
    panels.push_back(image::plot_lines(values(rot), o));
  }
  Tensor<std::uint8_t, 3> all(Shape<3>{static_cast<index_t>(panels.size()) * o.height, o.width, 3});
  for (std::size_t i = 0; i < panels.size(); ++i)
    std::copy(panels[i].data(), panels[i].data() + panels[i].size(), all.data() + static_cast<index_t>(i) * panels[i].size());
  image::write_png(picture, all);
}

// Rank 0 after every step.
struct TrainerProgress {
  std::uint64_t step = 0, first_step = 0, total = 0;  // the step just done, where this call started, the recipe's end
  const std::string* stage = nullptr;
  double loss = 0, psnr = 0;
  double seconds = 0;  // since this call started
  index_t batch = 0;   // global scenes per step
};

struct TrainerOptions {
  std::filesystem::path run;   // the run folder (created; a folder holding another recipe's run is refused)
  std::filesystem::path init;  // a fresh run's start: VGGT geometry weights or a flexsplat model; empty: none
  std::uint64_t stop_at = 0;   // stop after this global step; 0: the recipe's last
  double seconds = 0;          // > 0: stop after this much wall time (the last rank's clock decides)
  std::function<void(const std::string&)> note;             // rank 0's one-line messages (start, init)
  std::function<void(const TrainerProgress&)> progress;     // rank 0, after every step
};

struct TrainerResult {
  std::uint64_t first_step = 0, step = 0, total = 0;
  double seconds = 0;
};

// Trains the recipe `recipe` (parsed by parse_train_config) on `data` into o.run, from its last checkpoint if there
// is one, until o.stop_at or o.seconds; checkpoints every checkpoint_every steps and at the end, then writes
// model.safetensors. Every rank calls it with the same arguments; only rank 0 touches the run folder.
inline TrainerResult run_training(const nlohmann::json& recipe, const TrainData& data, train::Communicator& comm,
                                  const TrainerOptions& o) {
  namespace fs = std::filesystem;
  using nlohmann::json;
  const TrainRunConfig cfg = parse_train_config(recipe);
  const std::uint64_t total = cfg.total_steps();
  std::uint64_t stop_at = o.stop_at == 0 ? total : std::min(o.stop_at, total);
  std::unique_ptr<loss::LpipsWeights<float>> lpips;
  if (!cfg.lpips_weights.empty())
    lpips = std::make_unique<loss::LpipsWeights<float>>(
        loss::lpips_load_weights<float>(safetensors::File::open(cfg.lpips_weights)));
  const bool root = comm.rank() == 0;
  (void)train::contiguous_plan(cfg.batch, comm.size());  // a batch too small for the ranks fails before any work
  const fs::path state_path = o.run / "state.safetensors", log_path = o.run / "log.jsonl";
  const json model_json = to_json(cfg.model);
  auto note = [&](const std::string& s) {
    if (root && o.note) o.note(s);
  };

  auto w = FlexSplatWeights<float>::create(cfg.model, true);
  w->init(cfg.seed);
  std::uint64_t step = 0;
  double cpu_offset = 0;
  if (root) {
    fs::create_directories(o.run);
    if (fs::exists(o.run / "config.json")) {
      json previous;
      try {
        previous = json::parse(trainer_detail::read_text(o.run / "config.json"));
      } catch (const json::exception& e) {
        fail("train: '", (o.run / "config.json").string(), "' is not valid JSON: ", e.what());
      }
      require(previous == recipe, "train: '", o.run.string(), "' holds a run with a different config (",
              (o.run / "config.json").string(), "); use a new --out or the same config");
    }
    if (fs::exists(state_path)) {
      const train::CheckpointInfo info = w->load(state_path, true);
      require(info.format == "training_state" && info.optimizer_state, "train: '", state_path.string(),
              "' is not a training state");
      step = info.state.step;
    } else if (!o.init.empty()) {
      const auto init_file = safetensors::File::open(o.init);
      if (init_file.has_metadata(train::checkpoint_config_key)) {
        w->init_from_model(o.init);
        note("train: every weight initialised from " + o.init.string());
      } else {
        w->load_geometry(o.init, train::vggt_name_prefix(init_file));
        note("train: geometry initialised from " + o.init.string());
      }
    }
    write_file_atomic(o.run / "config.json", "train", recipe.dump(2) + "\n");
    // Log lines past the checkpoint belong to steps that will be redone.
    std::string kept;
    if (fs::exists(log_path)) {
      std::istringstream lines(trainer_detail::read_text(log_path));
      for (std::string line; std::getline(lines, line);) {
        try {
          const json j = json::parse(line);
          if (j.at("step").get<std::uint64_t>() > step) continue;
          kept += line + "\n";
          // cpu_seconds counts across resumes: this call's CPU time adds to the last kept line's.
          if (j.contains("cpu_seconds")) cpu_offset = j.at("cpu_seconds").get<double>();
        } catch (const json::exception&) {
        }
      }
    }
    write_file_atomic(log_path, "train", kept);
  }
  // Every rank starts from rank 0's parameters, optimizer moments and step.
  for (float* block : {w->store().params(), w->store().adam_m(), w->store().adam_v()})
    comm.broadcast(block, w->store().size(), 0);
  double step_value = static_cast<double>(step);  // exact: steps stay far below 2^53
  comm.broadcast(&step_value, 1, 0);
  step = static_cast<std::uint64_t>(step_value);
  const std::uint64_t first_step = step;
  note("train: " + o.run.string() + ", " + std::to_string(w->store().size()) + " parameters, " +
       std::to_string(comm.size()) + " rank(s), steps " + std::to_string(step) + " -> " + std::to_string(stop_at) +
       " of " + std::to_string(total));

  std::vector<ValidationSet> validation;
  if (root && cfg.validation.enabled()) validation = make_validation_sets(data, cfg);
  std::ofstream log;
  if (root) log.open(log_path, std::ios::app);
  StepWorkspace<float> ws;
  const auto start = std::chrono::steady_clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };
  double last_log_time = 0;
  std::uint64_t last_log_step = step;
  auto save_state = [&](std::uint64_t done) {
    if (!root) return;
    train::save_training_state(state_path, w->store(), model_json,
                               train::TrainingState{done, train::rng_state_string(std::mt19937_64(cfg.seed))});
  };
  // Each step also makes the next step's scenes, side by side in the time a thread would wait for the other's last.
  std::vector<TrainExample<float>> local, next;
  while (step < stop_at) {
    const StepSchedule at = cfg.schedule_at(step);
    const TrainStage& stage = cfg.stages[at.stage];
    const train::ScenePlan plan = train_scene_plan(cfg, step, comm.size());
    if (next.empty()) local = make_train_scenes(data, cfg, step, plan.scenes_of(comm.rank()));
    else local.swap(next);
    const std::uint64_t next_step = step + 1;
    std::vector<index_t> next_scenes;
    if (next_step < stop_at) next_scenes = train_scene_plan(cfg, next_step, comm.size()).scenes_of(comm.rank());
    next.assign(next_scenes.size(), TrainExample<float>{});
    const SideTasks prefetch{static_cast<index_t>(next.size()), [&](index_t i) {
                               next[static_cast<std::size_t>(i)] =
                                   make_train_scene(data, cfg, next_step, next_scenes[static_cast<std::size_t>(i)]);
                             }};
    const StepReport r = train_step<float>(ws, *w, std::span<const TrainExample<float>>(local), plan, stage.step,
                                           at.lr, step, comm, lpips.get(), nullptr, prefetch);
    require(std::isfinite(r.loss), "train: the loss is ", r.loss, " at step ", step, " (stage '", stage.name,
            "'); lower the learning rate");
    const std::uint64_t done = ++step;
    // The last rank's clock decides, so every rank stops after the same step.
    double out_of_time = o.seconds > 0 && elapsed() >= o.seconds ? 1.0 : 0.0;
    comm.broadcast(&out_of_time, 1, comm.size() - 1);
    if (out_of_time > 0) stop_at = done;
    if (!root) continue;
    const double now = elapsed();
    const double speed = static_cast<double>((done - last_log_step) * static_cast<std::uint64_t>(cfg.batch)) /
                         std::max(now - last_log_time, 1e-9);
    if (done % cfg.log_every == 0 || done == stop_at) {
      const json line = {{"step", done}, {"stage", stage.name}, {"lr", at.lr}, {"loss", r.loss}, {"camera", r.camera},
                         {"depth", r.depth}, {"depth_shape", r.depth_shape}, {"points", r.points}, {"match", r.match}, {"rgb_head", r.rgb_head}, {"render", r.render},
                         {"render_depth", r.render_depth}, {"lpips", r.lpips}, {"psnr", r.psnr},
                         {"grad_norm", r.grad_norm}, {"seconds", now}, {"scenes_per_s", speed},
                         {"cpu_seconds", cpu_offset + static_cast<double>(std::clock()) / CLOCKS_PER_SEC}};
      log << line.dump() << "\n";
      log.flush();
      last_log_time = now, last_log_step = done;
    }
    if (cfg.validation.enabled() && (done % cfg.validation.every == 0 || done == stop_at)) {
      const double t0 = elapsed();
      const json v = validate_sets(validation, *w, o.run / "validation.png", stage.step.decoder_true_cameras);
      log << json{{"step", done}, {"validation", v}, {"seconds", now}, {"validation_seconds", elapsed() - t0}}.dump() << "\n";
      log.flush();
    }
    if (done % cfg.checkpoint_every == 0 || done == stop_at) {
      save_state(done);
      write_training_curves(log_path, o.run / "curves.png");
    }
    if (o.progress) o.progress(TrainerProgress{done, first_step, total, &stage.name, r.loss, r.psnr, now, cfg.batch});
  }
  TrainerResult result{first_step, step, total, elapsed()};
  if (root) {
    if (step == first_step) save_state(step);
    w->save(o.run / "model.safetensors", step);
    result.seconds = elapsed();
  }
  return result;
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
