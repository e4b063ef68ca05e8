// train: FlexSplat training runs from a JSON configuration, resumable exactly, data parallel over MPI when built with it.
#include <chrono>
#include <ctime>
#include <cmath>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "flexsplat/data/dataset.hpp"
#include "flexsplat/image/image_io.hpp"
#include "flexsplat/image/plot.hpp"
#include "flexsplat/loss/lpips.hpp"
#include "flexsplat/model/config.hpp"
#include "flexsplat/model/train.hpp"
#include "flexsplat/model/train_data.hpp"
#include "flexsplat/model/validate.hpp"
#include "flexsplat/model/weights.hpp"
#include "flexsplat/train/checkpoint.hpp"
#include "flexsplat/train/distributed.hpp"
#include "flexsplat/train/optimizer.hpp"
#include "flexsplat/model/run_config.hpp"
#include "registry.hpp"

namespace flexsplat::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

using model::parse_train_config;
using model::TrainRunConfig;
using model::TrainStage;

using model::TrainData;

std::string read_text(const fs::path& p);

// Held-out scenes, built once: procedural scenes from another seed, and each object folder viewed whole.
struct ValidationSet {
  std::string name;
  std::vector<std::string> scene_names;
  std::vector<model::TrainExample<float>> scenes;
};

std::vector<ValidationSet> make_validation_sets(const TrainData& d, const TrainRunConfig& c) {
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
      set.scenes.push_back(model::make_train_example<float>(s, c.model));
    }
    sets.push_back(std::move(set));
  }
  if (!v.objects.empty()) {
    ValidationSet set{"objects", {}, {}};
    for (const auto& rec : data::load_objects(std::vector<fs::path>(v.objects.begin(), v.objects.end()))) {
      require(rec.width == rec.height, "train: validation object '", rec.name, "' is ", rec.width, " x ", rec.height,
              "; validation views are whole square images");
      data::BatchOptions oo = o;
      oo.crop = static_cast<int>(c.model.image_h);
      oo.scale_min = oo.scale_max = static_cast<double>(c.model.image_h) / static_cast<double>(rec.width);
      // Off the rig, two draws of random views per object.
      for (std::uint64_t draw = 0; draw < (c.structured_inputs ? 1u : 2u); ++draw) {
        const auto s = data::sample_batch({rec}, 1, c.seed, draw, oo);
        set.scene_names.push_back(rec.name);
        set.scenes.push_back(model::make_train_example<float>(s[0], c.model));
      }
    }
    sets.push_back(std::move(set));
  }
  return sets;
}

// Scores every set, logs one line, and draws RUN_DIR/validation.png: per scene its inputs, then target and render.
nlohmann::json run_validation(const std::vector<ValidationSet>& sets, const model::FlexSplatWeights<float>& w,
                              const fs::path& picture) {
  model::ValidationWorkspace<float> ws;
  json result = json::object();
  std::deque<Tensor<float, 3>> keep;  // owns the renders the grid cells point at (a deque never moves them)
  std::vector<image::GridCell> cells;
  const int inputs_shown = 4, targets_shown = 2, cols = inputs_shown + 2 * targets_shown;
  for (const auto& set : sets) {
    double psnr = 0, ssim = 0, rot = 0, depth = 0, rra15 = 0, rra30 = 0, prot = 0, prra15 = 0, prra30 = 0, chance = 0, mrot = 0,
           mrra15 = 0, mrra30 = 0, macc = 0, mgt = 0;
    for (std::size_t i = 0; i < set.scenes.size(); ++i) {
      const auto& e = set.scenes[i];
      std::vector<Tensor<float, 3>> renders;
      const model::ValidationScore s = model::validate_scene(ws, w, e, &renders);
      psnr += s.psnr, ssim += s.ssim, rot += s.rotation_deg, depth += s.depth_rel, rra15 += s.rra15, rra30 += s.rra30;
      prot += s.points_rotation_deg, prra15 += s.points_rra15, prra30 += s.points_rra30, chance += s.chance_rotation_deg;
      mrot += s.matches_rotation_deg, mrra15 += s.matches_rra15, mrra30 += s.matches_rra30;
      macc += s.match_accuracy, mgt += s.matches_gt_depth_rotation_deg;
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
                        {"rra15", rra15 / n}, {"rra30", rra30 / n}, {"chance_rotation_deg", chance / n}};
    if (w.config().geometry.point_head)
      result[set.name].update({{"points_rotation_deg", prot / n}, {"points_rra15", prra15 / n}, {"points_rra30", prra30 / n}});
    if (w.config().geometry.match_dim > 0)
      result[set.name].update({{"matches_rotation_deg", mrot / n}, {"matches_rra15", mrra15 / n}, {"matches_rra30", mrra30 / n},
                               {"match_accuracy", macc / n}, {"matches_gt_depth_rotation_deg", mgt / n}});
  }
  if (!cells.empty()) image::write_png(picture, image::image_grid(cells, cols, 112));
  return result;
}

// RUN_DIR/curves.png from log.jsonl: training loss terms, PSNR and validation camera error against the step.
void write_curves(const fs::path& log_path, const fs::path& picture) {
  std::map<std::string, image::PlotSeries> loss, psnr, rot;
  const image::Rgb8 palette[] = {{31, 119, 180}, {214, 39, 40}, {44, 160, 44}, {148, 103, 189}, {255, 127, 14}, {23, 190, 207}};
  auto add = [&](std::map<std::string, image::PlotSeries>& m, const std::string& name, double x, double y) {
    auto it = m.find(name);
    if (it == m.end()) it = m.emplace(name, image::PlotSeries{name, {}, {}, palette[m.size() % 6]}).first;
    it->second.x.push_back(x), it->second.y.push_back(y);
  };
  std::istringstream lines(read_text(log_path));
  for (std::string line; std::getline(lines, line);) {
    json j;
    try {
      j = json::parse(line);
    } catch (const json::exception&) {
      continue;
    }
    if (!j.contains("step")) continue;
    const double step = j["step"].get<double>();
    if (j.contains("validation")) {
      for (const auto& [set, v] : j["validation"].items()) {
        add(psnr, "val " + set, step, v.value("psnr", 0.0));
        add(rot, "val " + set, step, v.value("rotation_deg", 0.0));
        if (v.contains("points_rotation_deg")) add(rot, "val " + set + " (points)", step, v.value("points_rotation_deg", 0.0));
        if (v.contains("matches_rotation_deg")) add(rot, "val " + set + " (matches)", step, v.value("matches_rotation_deg", 0.0));
      }
      continue;
    }
    add(loss, "total", step, j.value("loss", 0.0));
    for (const char* k : {"render", "camera", "depth", "points", "match", "rgb_head"})
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

std::string read_text(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  require(f.good(), "train: cannot read '", p.string(), "'");
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

void write_text_atomic(const fs::path& p, const std::string& text) {
  const fs::path tmp = p.string() + ".tmp";
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    f << text;
    f.flush();
    require(f.good(), "train: cannot write '", tmp.string(), "'");
  }
  fs::rename(tmp, p);
}

#if defined(FLEXSPLAT_WITH_MPI)
// Every rank starts from rank 0's parameters, optimizer moments and step (only rank 0 needs the run folder).
void share_start(train::ParamStore<float>& store, std::uint64_t& step) {
  for (float* block : {store.params(), store.adam_m(), store.adam_v()})
    for (index_t at = 0; at < store.size(); at += INT_MAX / 2) {
      const int n = static_cast<int>(std::min<index_t>(INT_MAX / 2, store.size() - at));
      require(MPI_Bcast(block + at, n, MPI_FLOAT, 0, MPI_COMM_WORLD) == MPI_SUCCESS, "train: MPI broadcast failed");
    }
  unsigned long long s = step;
  require(MPI_Bcast(&s, 1, MPI_UNSIGNED_LONG_LONG, 0, MPI_COMM_WORLD) == MPI_SUCCESS, "train: MPI broadcast failed");
  step = s;
}
#endif

int train_command(Args args) {
  std::string config_path, out, init, steps_text, seconds_text;
  std::vector<std::string> data_args;
  for (auto it = args.begin(); it != args.end(); ++it)
    if (*it == "--data") {
      auto end = std::next(it);
      while (end != args.end() && end->rfind("--", 0) != 0) data_args.push_back(*end++);
      args.erase(it, end);
      break;
    }
  const bool quiet = take_flag(args, "--quiet");
  require(take_option(args, "--config", config_path), "train needs --config CFG.json");
  require(take_option(args, "--out", out), "train needs --out RUN_DIR");
  take_option(args, "--init", init);
  const bool has_steps = take_option(args, "--steps", steps_text);
  const bool has_seconds = take_option(args, "--seconds", seconds_text);
  require(args.empty(), "train: unexpected argument '", args.empty() ? "" : args[0], "'");
  require(!data_args.empty(), "train needs --data procedural or --data DIR...");

  // Everything is checked before any compute.
  json raw;
  try {
    raw = json::parse(read_text(config_path));
  } catch (const json::exception& e) {
    fail("train config '", config_path, "' is not valid JSON: ", e.what());
  }
  const TrainRunConfig cfg = parse_train_config(raw);
  const std::uint64_t total = cfg.total_steps();
  std::uint64_t stop_at = total;
  if (has_steps) {
    const long long v = parse_integer(steps_text, "--steps", 1, std::numeric_limits<long long>::max());
    stop_at = std::min<std::uint64_t>(static_cast<std::uint64_t>(v), total);
  }
  double budget = 0;
  if (has_seconds) budget = parse_number(seconds_text, "--seconds", false);
  TrainData data;
  if (data_args.size() == 1 && data_args[0] == "procedural") {
    data.generator.size = static_cast<int>(cfg.model.image_h);
    data::check_generator(data.generator);
  } else {
    data.procedural = false;
    data.objects = data::load_objects(std::vector<fs::path>(data_args.begin(), data_args.end()));
    for (const auto& o : data.objects)
      require(static_cast<int>(o.frames.size()) >= cfg.inputs_max + cfg.targets, "train: object '", o.name, "' has ",
              o.frames.size(), " views, the config needs up to ", cfg.inputs_max, " inputs + ", cfg.targets, " targets");
  }
  std::unique_ptr<loss::LpipsWeights<float>> lpips;
  if (!cfg.lpips_weights.empty())
    lpips = std::make_unique<loss::LpipsWeights<float>>(
        loss::lpips_load_weights<float>(safetensors::File::open(cfg.lpips_weights)));

#if defined(FLEXSPLAT_WITH_MPI)
  train::MpiCommunicator comm;
#else
  train::SoloCommunicator comm;
#endif
  const bool root = comm.rank() == 0;
  const train::Share share = train::share_of(cfg.batch, comm.rank(), comm.size());
  const fs::path run(out), state_path = run / "state.safetensors", log_path = run / "log.jsonl";
  const json model_json = model::to_json(cfg.model);

  auto w = model::FlexSplatWeights<float>::create(cfg.model, true);
  w->init(cfg.seed);
  std::uint64_t step = 0;
  double cpu_offset = 0;
  if (root) {
    fs::create_directories(run);
    if (fs::exists(run / "config.json")) {
      json previous;
      try {
        previous = json::parse(read_text(run / "config.json"));
      } catch (const json::exception& e) {
        fail("train: '", (run / "config.json").string(), "' is not valid JSON: ", e.what());
      }
      require(previous == raw, "train: '", run.string(), "' holds a run with a different config (", (run / "config.json").string(),
              "); use a new --out or the same config");
    }
    if (fs::exists(state_path)) {
      const train::CheckpointInfo info = w->load(state_path, true);
      require(info.format == "training_state" && info.optimizer_state, "train: '", state_path.string(),
              "' is not a training state");
      step = info.state.step;
    } else if (!init.empty()) {
      w->load_geometry(init, train::vggt_name_prefix(safetensors::File::open(init)));
      if (root && !quiet) std::fprintf(stderr, "train: geometry initialised from %s\n", init.c_str());
    }
    write_text_atomic(run / "config.json", raw.dump(2) + "\n");
    // Log lines past the checkpoint belong to steps that will be redone.
    std::string kept;
    if (fs::exists(log_path)) {
      std::istringstream lines(read_text(log_path));
      for (std::string line; std::getline(lines, line);) {
        try {
          const json j = json::parse(line);
          if (j.at("step").get<std::uint64_t>() > step) continue;
          kept += line + "\n";
          // cpu_seconds counts across resumes: this invocation's CPU time adds to the last kept line's.
          if (j.contains("cpu_seconds")) cpu_offset = j.at("cpu_seconds").get<double>();
        } catch (const json::exception&) {
        }
      }
    }
    write_text_atomic(log_path, kept);
  }
#if defined(FLEXSPLAT_WITH_MPI)
  share_start(w->store(), step);
#endif
  const std::uint64_t first_step = step;
  if (root && !quiet)
    std::fprintf(stderr, "train: %s, %llu parameters, %d rank(s), steps %llu -> %llu of %llu\n", run.string().c_str(),
                 static_cast<unsigned long long>(w->store().size()), comm.size(), static_cast<unsigned long long>(step),
                 static_cast<unsigned long long>(stop_at), static_cast<unsigned long long>(total));

  std::vector<ValidationSet> validation;
  if (root && cfg.validation.enabled()) validation = make_validation_sets(data, cfg);
  std::ofstream log;
  if (root) log.open(log_path, std::ios::app);
  model::StepWorkspace<float> ws;
  const auto start = std::chrono::steady_clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); };
  double last_log_time = 0;
  std::uint64_t last_log_step = step;
  int last_width = 0;
  auto save_state = [&](std::uint64_t done) {
    if (!root) return;
    train::save_training_state(state_path, w->store(), model_json,
                               train::TrainingState{done, train::rng_state_string(std::mt19937_64(cfg.seed))});
  };
  while (step < stop_at) {
    std::uint64_t stage_start = 0;
    const std::size_t si = cfg.stage_at(step, stage_start);
    const TrainStage& stage = cfg.stages[si];
    train::CosineSchedule schedule{stage.lr, 0.0, stage.warmup, stage.steps};
    const double lr = schedule.lr(step - stage_start);
    std::vector<model::TrainExample<float>> local;
    for (index_t b = share.first; b < share.first + share.count; ++b) local.push_back(model::make_train_scene(data, cfg, step, b));
    const model::StepReport r = model::train_step<float>(ws, *w, local, cfg.batch, stage.step, lr, step, comm, lpips.get());
    require(std::isfinite(r.loss), "train: the loss is ", r.loss, " at step ", step, " (stage '", stage.name,
            "'); lower the learning rate");
    const std::uint64_t done = ++step;
    // The last rank's clock decides, so every rank stops after the same step.
    double out_of_time = has_seconds && elapsed() >= budget ? 1.0 : 0.0;
    comm.broadcast_from_last(&out_of_time, 1);
    if (out_of_time > 0) stop_at = done;
    if (!root) continue;
    const double now = elapsed();
    const double speed = static_cast<double>((done - last_log_step) * static_cast<std::uint64_t>(cfg.batch)) /
                         std::max(now - last_log_time, 1e-9);
    if (done % cfg.log_every == 0 || done == stop_at) {
      const json line = {{"step", done}, {"stage", stage.name}, {"lr", lr}, {"loss", r.loss}, {"camera", r.camera},
                         {"depth", r.depth}, {"points", r.points}, {"match", r.match}, {"rgb_head", r.rgb_head}, {"render", r.render},
                         {"render_depth", r.render_depth}, {"lpips", r.lpips}, {"psnr", r.psnr},
                         {"grad_norm", r.grad_norm}, {"seconds", now}, {"scenes_per_s", speed},
                         {"cpu_seconds", cpu_offset + static_cast<double>(std::clock()) / CLOCKS_PER_SEC}};
      log << line.dump() << "\n";
      log.flush();
      last_log_time = now, last_log_step = done;
    }
    if (cfg.validation.enabled() && (done % cfg.validation.every == 0 || done == stop_at)) {
      const double t0 = elapsed();
      const json v = run_validation(validation, *w, run / "validation.png");
      log << json{{"step", done}, {"validation", v}, {"seconds", now}, {"validation_seconds", elapsed() - t0}}.dump() << "\n";
      log.flush();
    }
    if (done % cfg.checkpoint_every == 0 || done == stop_at) {
      save_state(done);
      write_curves(log_path, run / "curves.png");
    }
    if (!quiet) {
      const int bar = 30,
                filled = static_cast<int>(static_cast<double>(bar) * static_cast<double>(done) / static_cast<double>(total));
      std::string text = "\r[" + std::string(static_cast<std::size_t>(filled), '#') +
                         std::string(static_cast<std::size_t>(bar - filled), ' ') + "] ";
      char tail[160];
      const double rate = static_cast<double>((done - first_step) * static_cast<std::uint64_t>(cfg.batch)) / std::max(now, 1e-9);
      std::snprintf(tail, sizeof tail, "step %llu/%llu %s loss %.4f psnr %.2f %.2f scenes/s %.1f s",
                    static_cast<unsigned long long>(done), static_cast<unsigned long long>(total), stage.name.c_str(),
                    r.loss, r.psnr, rate, now);
      text += tail;
      if (static_cast<int>(text.size()) < last_width) text += std::string(static_cast<std::size_t>(last_width) - text.size(), ' ');
      last_width = static_cast<int>(text.size());
      std::fputs(text.c_str(), stderr);
      std::fflush(stderr);
    }
  }
  if (root) {
    if (!quiet && last_width > 0) std::fputc('\n', stderr);
    if (step == first_step) save_state(step);
    w->save(run / "model.safetensors", step);
    const double secs = elapsed();
    std::printf("%s: step %llu of %llu, %.1f s, %.3f scenes/s on %d rank(s)%s\n", run.string().c_str(),
                static_cast<unsigned long long>(step), static_cast<unsigned long long>(total), secs,
                static_cast<double>((step - first_step) * static_cast<std::uint64_t>(cfg.batch)) / std::max(secs, 1e-9),
                comm.size(), step < total ? " (budget reached; rerun the same command to continue)" : "");
  }
  return 0;
}

const RegisterCommand registered_cmd_train(
    "train", {"train a FlexSplat model from a JSON config (resumable exactly; data parallel under mpirun)",
              "--config CFG.json --data procedural|DIR... --out RUN_DIR [--init VGGT.safetensors] [--steps N] "
              "[--seconds S] [--quiet]\n"
              "  CFG.json keys (all optional): model (\"tiny\" | \"paper\" | FlexSplat config object), seed, batch (global),\n"
              "  inputs [min, max] views per scene, structured_inputs (false: random views and order, no fixed rig),\n"
              "  curriculum {baseline_deg [start, end], steps}: procedural views within a growing angle of the first,\n"
              "  targets, gaussians (0: tied to the view count), max_grad_norm, lpips_weights, checkpoint_every,\n"
              "  log_every, validation, stages [{name, steps, lr, warmup, appearance, train_geometry, camera_weight,\n"
              "  depth_weight, point_weight (model.geometry.point_head), match_weight (model.geometry.match_dim),\n"
              "  objective {rgb_head, render, depth, lpips}}];\n"
              "  unknown keys are errors\n"
              "  validation {every, scenes, targets, objects [DIR...]}: held-out scores in log.jsonl and validation.png\n"
              "  RUN_DIR: config.json, log.jsonl, state.safetensors (resume point), model.safetensors (at the end),\n"
              "  curves.png (loss, PSNR, camera error against the step, redrawn at each checkpoint)\n"
              "  rerunning the same command resumes from state.safetensors; --steps N stops after global step N,\n"
              "  --seconds S after S seconds, both with a checkpoint; --init loads VGGT geometry weights on a fresh run",
              train_command});

}  // namespace
}  // namespace flexsplat::cli
